"""``zenrl export``: the greedy policy as a TorchScript file that loads without zenrl."""

from __future__ import annotations

import json
import os
import warnings
from typing import Any, Dict, Mapping, Sequence

import gymnasium as gym
import numpy as np
import torch

from zenrl.common.errors import ZenrlError
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.tools.loading import env_config_for, is_exported, is_match_env, load_policy_env, resolve_checkpoint

class ExportedPolicy(torch.nn.Module):
    """Greedy policy for TorchScript: one observation (no batch dim) -> int64 scalar action.

    Dict observation space: ``forward({"lidar": float[360], "pose": float[4], ...})`` keyed like
    the env's observation space; plain Box space: ``forward(tensor)``. Preprocessing is inside
    (uint8 camera images are scaled by 1/255, other inputs cast to float32).
    """

    def __init__(self, net: torch.nn.Module, keys: Sequence[str], dict_obs: bool) -> None:
        super().__init__()
        self.net = net
        self.keys = list(keys)
        self.dict_obs = dict_obs

    def forward(self, obs: Any) -> torch.Tensor:
        if self.dict_obs:
            flat = {f"obs/{k}": obs[k].unsqueeze(0) for k in self.keys}
        else:
            flat = {"obs": obs.unsqueeze(0)}
        out = self.net(flat)
        if isinstance(out, tuple):
            out = out[0]
        return out.argmax(1)[0]


class _MixtureOfDicts(torch.nn.Module):
    """A mixture of exported policies (dict observations): ``pick(i)`` seats member ``i``
    (call it when a match begins; member 0 until then), ``forward`` is that member's action."""

    def __init__(self, members: Sequence[torch.nn.Module]) -> None:
        super().__init__()
        self.members = torch.nn.ModuleList(members)
        self.n_members = len(members)
        self.current = 0

    @torch.jit.export
    def pick(self, i: int) -> int:
        if i < 0 or i >= self.n_members:
            raise ValueError("member index out of range")
        self.current = i
        return i

    def forward(self, obs: Dict[str, torch.Tensor]) -> torch.Tensor:
        out = torch.zeros((), dtype=torch.int64)
        for i, m in enumerate(self.members):
            if i == self.current:
                out = m(obs)
        return out


class _MixtureOfTensors(_MixtureOfDicts):
    """:class:`_MixtureOfDicts` for a plain Box observation."""

    def forward(self, obs: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        out = torch.zeros((), dtype=torch.int64)
        for i, m in enumerate(self.members):
            if i == self.current:
                out = m(obs)
        return out


def _example_obs(space: gym.Space, seed: int = 0) -> Any:
    space.seed(seed)
    return space.sample()


def export(checkpoint: str, out: str | os.PathLike[str], env_id: str | None = None,
           env_kwargs: Mapping[str, Any] | None = None, members: Sequence[str] = ()) -> dict[str, Any]:
    """Write the greedy policy of ``checkpoint`` as TorchScript (``torch.jit.trace``) to ``out``,
    with a ``zenrl.json`` extra file describing the inputs and the action set. Load it with
    ``torch.jit.load(out)`` (no zenrl needed). ``checkpoint``: a file, or a folder's newest.

    ``members``: more checkpoints of the same env: the file is then a mixed policy over
    ``checkpoint`` and them, one of which plays each match (``pick(i)`` seats member ``i``;
    zenrl draws one uniformly as each match begins; ``zenrl.json`` says ``"members": K``)."""
    checkpoint = str(resolve_checkpoint(checkpoint))
    paths = [checkpoint, *(str(resolve_checkpoint(m)) for m in members)]
    for p in paths:
        if is_exported(p):
            raise ZenrlError(f"{p} is already an exported policy; export takes checkpoints")
    policy, env, cfg = load_policy_env(checkpoint, env_id, env_kwargs)
    try:
        nets = [policy.net]
        for p in paths[1:]:
            other, env2, cfg2 = load_policy_env(p, env_id, env_kwargs)
            env2.close()
            if (cfg2.env.id != cfg.env.id or env2.observation_space != env.observation_space
                    or env2.action_space != env.action_space):
                raise ZenrlError(f"{p}: a policy for {cfg2.env.id} {env2.observation_space}, {checkpoint} is for "
                                 f"{cfg.env.id} {env.observation_space}: a mixture plays one env")
            nets.append(other.net)
        for p, net in zip(paths, nets):
            if isinstance(net, RecurrentQNetwork):
                raise ZenrlError(f"{p}: a recurrent ({cfg.algo}) policy cannot be exported yet: the exported "
                                 "call takes one observation and would have to carry the LSTM state between calls")
        space = env.observation_space
        dict_obs = isinstance(space, gym.spaces.Dict)
        keys = list(space.spaces) if dict_obs else ["obs"]
        ex = _example_obs(space)
        example = {k: torch.as_tensor(np.asarray(ex[k])) for k in keys} if dict_obs else torch.as_tensor(np.asarray(ex))
        with torch.no_grad(), warnings.catch_warnings():
            # torch 2.13 deprecates TorchScript in favour of torch.export, but a TorchScript file
            # is what loads with a bare `torch.jit.load` (and from C++ libtorch) on a robot
            warnings.simplefilter("ignore", DeprecationWarning)
            traced = [torch.jit.trace(ExportedPolicy(net, keys, dict_obs).eval(), (example,), strict=False,
                                      check_trace=False) for net in nets]
            if len(traced) == 1:
                traced = traced[0]
            else:
                traced = torch.jit.script((_MixtureOfDicts if dict_obs else _MixtureOfTensors)(traced).eval())
        inputs = {}
        for k in keys:
            sub = space.spaces[k] if dict_obs else space
            inputs[k] = {"shape": list(sub.shape), "dtype": str(sub.dtype)}
        meta = {"format": 1, "env": env.spec.id if env.spec else cfg.env.id, "env_kwargs": _jsonable(env_config_for(cfg, env_id, env_kwargs).kwargs),
                "algo": cfg.algo, "inputs": inputs, "n_actions": int(env.action_space.n),
                "call": ("policy({key: tensor}) " if dict_obs else "policy(tensor) ") +
                        "-> int64 scalar tensor (one observation, no batch dim)"}
        if len(paths) > 1:
            meta["members"] = len(paths)
            meta["call"] += f"; a mixed policy of {len(paths)} members: policy.pick(i) seats member i as a match begins"
        if is_match_env(env):
            from zenrl.games.burgerwar.env import RICH_ACTIONS, USERS_ACTIONS

            table = {"users": USERS_ACTIONS, "rich": RICH_ACTIONS}.get(env.unwrapped.action_set)
            meta["actions_v_w"] = np.asarray(table).tolist() if table is not None else None
    finally:
        env.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(traced, str(out), _extra_files={"zenrl.json": json.dumps(meta)})
    return {"out": str(out), **meta}


def _jsonable(x: Any) -> Any:
    try:
        json.dumps(x)
        return x
    except TypeError:
        return {k: v for k, v in x.items() if _is_json(v)} if isinstance(x, dict) else str(x)


def _is_json(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except TypeError:
        return False

