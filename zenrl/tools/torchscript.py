"""``zenrl export``: the greedy policy as a TorchScript file that loads without zenrl."""

from __future__ import annotations

import json
import os
import warnings
from typing import Any, Mapping, Sequence

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


def _example_obs(space: gym.Space, seed: int = 0) -> Any:
    space.seed(seed)
    return space.sample()


def export(checkpoint: str, out: str | os.PathLike[str], env_id: str | None = None,
           env_kwargs: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write the greedy policy of ``checkpoint`` as TorchScript (``torch.jit.trace``) to ``out``,
    with a ``zenrl.json`` extra file describing the inputs and the action set. Load it with
    ``torch.jit.load(out)`` (no zenrl needed). ``checkpoint``: a file, or a folder's newest."""
    checkpoint = str(resolve_checkpoint(checkpoint))
    if is_exported(checkpoint):
        raise ZenrlError(f"{checkpoint} is already an exported policy; export takes a checkpoint")
    policy, env, cfg = load_policy_env(checkpoint, env_id, env_kwargs)
    try:
        if isinstance(policy.net, RecurrentQNetwork):
            raise ZenrlError(f"{checkpoint}: a recurrent ({cfg.algo}) policy cannot be exported yet: the exported "
                             "call takes one observation and would have to carry the LSTM state between calls")
        space = env.observation_space
        dict_obs = isinstance(space, gym.spaces.Dict)
        keys = list(space.spaces) if dict_obs else ["obs"]
        module = ExportedPolicy(policy.net, keys, dict_obs).eval()
        ex = _example_obs(space)
        example = {k: torch.as_tensor(np.asarray(ex[k])) for k in keys} if dict_obs else torch.as_tensor(np.asarray(ex))
        with torch.no_grad(), warnings.catch_warnings():
            # torch 2.13 deprecates TorchScript in favour of torch.export, but a TorchScript file
            # is what loads with a bare `torch.jit.load` (and from C++ libtorch) on a robot
            warnings.simplefilter("ignore", DeprecationWarning)
            traced = torch.jit.trace(module, (example,), strict=False, check_trace=False)
        inputs = {}
        for k in keys:
            sub = space.spaces[k] if dict_obs else space
            inputs[k] = {"shape": list(sub.shape), "dtype": str(sub.dtype)}
        meta = {"format": 1, "env": env.spec.id if env.spec else cfg.env.id, "env_kwargs": _jsonable(env_config_for(cfg, env_id, env_kwargs).kwargs),
                "algo": cfg.algo, "inputs": inputs, "n_actions": int(env.action_space.n),
                "call": ("policy({key: tensor}) " if dict_obs else "policy(tensor) ") +
                        "-> int64 scalar tensor (one observation, no batch dim)"}
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

