"""``zenrl export``: the greedy policy as a TorchScript file that loads without zenrl."""

from __future__ import annotations

import json
import math
import os
import warnings
from typing import Any, Dict, Mapping, Sequence

import gymnasium as gym
import numpy as np
import torch

from zenrl.common.env_factory import NormalisedActions, ShiftedActions
from zenrl.common.errors import ZenrlError
from zenrl.games.burgerwar import geometry as geo
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.specs import flatten
from zenrl.tools.loading import (ExportedPlayer, env_config_for, is_exported, is_match_env, load_policy_env,
                                 resolve_checkpoint)

class ExportedPolicy(torch.nn.Module):
    """Greedy policy for TorchScript: one observation (no batch dim) -> int64 scalar action.

    Dict observation space: ``forward({"lidar": float[360], "pose": float[4], ...})`` keyed like
    the env's observation space (a Dict inside it by path: ``{"arm/joints": ...}``); plain Box space: ``forward(tensor)``. Preprocessing is inside
    (uint8 camera images are scaled by 1/255, other inputs cast to float32).

    A Gaussian actor-critic (continuous actions) with ``bounds`` = the env's ``(low, high)``:
    float32[d], its mean action mapped from [-1, 1] onto the env's bounds (what the robot takes).
    A discrete policy for an env whose actions are ``Discrete(n, start)`` returns the env's action,
    ``start`` + the greedy index (``start`` 0 for the rest).
    """

    def __init__(self, net: torch.nn.Module, keys: Sequence[str], dict_obs: bool,
                 bounds: tuple[np.ndarray, np.ndarray] | None = None, start: int = 0) -> None:
        super().__init__()
        self.net = net
        self.keys = list(keys)
        self.dict_obs = dict_obs
        self.continuous = bounds is not None
        self.start = int(start)
        if bounds is not None:
            self.register_buffer("low", torch.as_tensor(np.asarray(bounds[0], np.float32)))
            self.register_buffer("span", torch.as_tensor(np.asarray(bounds[1], np.float32) - np.asarray(bounds[0], np.float32)))

    def forward(self, obs: Any) -> torch.Tensor:
        if self.dict_obs:
            flat = {f"obs/{k}": obs[k].unsqueeze(0) for k in self.keys}
        else:
            flat = {"obs": obs.unsqueeze(0)}
        out = self.net(flat)
        if isinstance(out, tuple):
            out = out[0]
        if self.continuous:
            return self.low + (out[0].clamp(-1.0, 1.0) + 1.0) * 0.5 * self.span
        return out.argmax(1)[0] + self.start


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


#: the guard's defaults (``zenrl export --guard``), the same rule the env's ``facing`` reward pays on
GUARD_RADIUS_M, GUARD_ANGLE_DEG = geo.GUARD_RADIUS_M, geo.GUARD_ANGLE_DEG


class _Guarded(torch.nn.Module):
    """A guard around an exported policy of a match env with the enemy detector: when
    ``obs["enemy_seen"]`` (seen, x forward, y left; metres, the robot's own frame) shows the other
    robot nearer than ``radius`` and more than ``angle`` off the heading, turn towards it on the
    spot (action ``turn_left`` if it is on the left, else ``turn_right``); otherwise the inner
    policy acts. Its markers are on the robot's sides and back: facing the other robot keeps them
    out of its camera's reach and keeps its markers in front of ours."""

    def __init__(self, inner: torch.nn.Module, radius_m: float, angle_deg: float, turn_left: int,
                 turn_right: int) -> None:
        super().__init__()
        self.inner = inner
        self.radius = float(radius_m)
        self.cos_angle = math.cos(math.radians(angle_deg))
        self.turn_left = int(turn_left)
        self.turn_right = int(turn_right)

    def forward(self, obs: Dict[str, torch.Tensor]) -> torch.Tensor:
        e = obs["enemy_seen"]
        if float(e[0]) > 0.5:
            x = float(e[1])
            y = float(e[2])
            r = math.sqrt(x * x + y * y)
            if r > 0.0 and r < self.radius and x < r * self.cos_angle:
                return torch.tensor(self.turn_left if y > 0.0 else self.turn_right, dtype=torch.int64)
        return self.inner(obs)


class _GuardedMixture(_Guarded):
    """:class:`_Guarded` around a mixed policy: ``pick(i)`` seats the inner mixture's member ``i``."""

    @torch.jit.export
    def pick(self, i: int) -> int:
        return self.inner.pick(i)


def guard_turns(table: Sequence[Sequence[float]]) -> tuple[int, int]:
    """``(left, right)``: the fastest turns on the spot (v = 0) of an action table of ``(v, w)``
    rows, w > 0 turning left. :class:`ZenrlError` where the table has none in either direction."""
    from zenrl.games.burgerwar.env import spot_turns

    try:
        return spot_turns(table)
    except ValueError as e:
        raise ZenrlError(str(e)) from None


def _guard_meta(meta: Mapping[str, Any], radius_m: float, angle_deg: float) -> dict[str, Any]:
    """The ``guard`` entry of ``zenrl.json`` for a policy described by ``meta``; ZenrlError where
    the policy cannot be guarded (no ``enemy_seen`` input, no action table, a bad number)."""
    if not (isinstance(radius_m, (int, float)) and 0.0 < radius_m <= 5.0):
        raise ZenrlError(f"--guard-radius must be in (0, 5] m, got {radius_m!r}")
    if not (isinstance(angle_deg, (int, float)) and 0.0 <= angle_deg < 180.0):
        raise ZenrlError(f"--guard-angle must be in [0, 180) degrees, got {angle_deg!r}")
    if "enemy_seen" not in meta.get("inputs", {}):
        raise ZenrlError("the guard reads obs['enemy_seen']: export a policy of a match env with enemy_detector: true")
    if meta.get("guard"):
        raise ZenrlError("this policy is already guarded")
    table = meta.get("actions_v_w")
    if not table:
        raise ZenrlError("the guard needs the policy's action table (a match env's users or rich action set)")
    left, right = guard_turns(table)
    return {"radius_m": float(radius_m), "angle_deg": float(angle_deg), "turn_left": left, "turn_right": right}


def _guarded(module: torch.nn.Module, g: Mapping[str, Any], mixture: bool) -> torch.nn.Module:
    cls = _GuardedMixture if mixture else _Guarded
    return torch.jit.script(cls(module, g["radius_m"], g["angle_deg"], g["turn_left"], g["turn_right"]).eval())


def _guard_call(g: Mapping[str, Any]) -> str:
    return (f"; guarded: with obs['enemy_seen'] showing the other robot within {g['radius_m']} m and more than "
            f"{g['angle_deg']} degrees off the heading it returns {g['turn_left']} (turn left) or "
            f"{g['turn_right']} (turn right)")


def guard_exported(src: str | os.PathLike[str], out: str | os.PathLike[str], radius_m: float = GUARD_RADIUS_M,
                   angle_deg: float = GUARD_ANGLE_DEG) -> dict[str, Any]:
    """Write ``src`` (a ``zenrl export`` file: a program, load only one you trust) with the guard
    around it to ``out``; its ``zenrl.json`` gains ``guard``. Returns that description."""
    player = ExportedPlayer(src)  # refuses a damaged archive or a zenrl.json without env and inputs
    module, meta = player.module, player.meta
    g = _guard_meta(meta, radius_m, angle_deg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        guarded = _guarded(module, g, player.members > 1)
        meta = {**meta, "guard": g, "call": str(meta.get("call", "")) + _guard_call(g)}
        torch.jit.save(guarded, str(out), _extra_files={"zenrl.json": json.dumps(meta)})
    return {"out": str(out), **meta}


def _example_obs(space: gym.Space, seed: int = 0) -> Any:
    space.seed(seed)
    return space.sample()


def export(checkpoint: str, out: str | os.PathLike[str], env_id: str | None = None,
           env_kwargs: Mapping[str, Any] | None = None, members: Sequence[str] = (),
           guard: tuple[float, float] | None = None) -> dict[str, Any]:
    """Write the greedy policy of ``checkpoint`` as TorchScript (``torch.jit.trace``) to ``out``,
    with a ``zenrl.json`` extra file describing the inputs and the action set. Load it with
    ``torch.jit.load(out)`` (no zenrl needed). ``checkpoint``: a file, or a folder's newest.

    ``members``: more checkpoints of the same env: the file is then a mixed policy over
    ``checkpoint`` and them, one of which plays each match (``pick(i)`` seats member ``i``;
    zenrl draws one uniformly as each match begins; ``zenrl.json`` says ``"members": K``).

    ``guard``: ``(radius_m, angle_deg)``: the file plays with the guard (:class:`_Guarded`)
    around the policy; ``zenrl.json`` says ``"guard": {...}``."""
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
        # a Dict inside a Dict: its leaves keyed by path ("a/b"), as zenrl's fields name them
        leaves = flatten(space.spaces) if dict_obs else {"obs": space}
        keys = list(leaves)
        continuous = bool(getattr(nets[0], "continuous", False))
        bounds = (env.low, env.high) if continuous and isinstance(env, NormalisedActions) else None
        if continuous and bounds is None:
            raise ZenrlError(f"{checkpoint}: a continuous-action policy for an env whose actions are not normalised")
        start = env.start if isinstance(env, ShiftedActions) else 0
        ex = _example_obs(space)
        example = ({k: torch.as_tensor(np.asarray(v)) for k, v in flatten(ex).items()} if dict_obs
                   else torch.as_tensor(np.asarray(ex)))
        with torch.no_grad(), warnings.catch_warnings():
            # torch 2.13 deprecates TorchScript in favour of torch.export, but a TorchScript file
            # is what loads with a bare `torch.jit.load` (and from C++ libtorch) on a robot
            warnings.simplefilter("ignore", DeprecationWarning)
            traced = [torch.jit.trace(ExportedPolicy(net, keys, dict_obs, bounds, start).eval(), (example,), strict=False,
                                      check_trace=False) for net in nets]
            if len(traced) == 1:
                traced = traced[0]
            else:
                traced = torch.jit.script((_MixtureOfDicts if dict_obs else _MixtureOfTensors)(traced).eval())
        inputs = {}
        for k, sub in leaves.items():
            inputs[k] = {"shape": list(sub.shape), "dtype": str(sub.dtype)}
        made = env_config_for(cfg, env_id, env_kwargs)
        # the id as given ("mypkg.envs:MyEnv-v0" keeps the module that registers it), so that
        # `zenrl evaluate --exported` makes the env again
        meta = {"format": 1, "env": made.id, "env_kwargs": _jsonable(made.kwargs),
                "algo": cfg.algo, "inputs": inputs,
                "n_actions": int(env.action_space.shape[0]) if continuous else int(env.action_space.n),
                "call": ("policy({key: tensor}) " if dict_obs else "policy(tensor) ") +
                        ("-> float32[d] tensor, the action in the env's units within action_bounds (the Gaussian "
                         "policy's mean; one observation, no batch dim)" if continuous
                         else "-> int64 scalar tensor (one observation, no batch dim)"
                         + (f": the env's action, action_start {start} + the greedy index" if start else ""))}
        if start:
            meta["action_start"] = start
        if bounds is not None:
            meta["action_bounds"] = {"low": np.asarray(bounds[0]).tolist(), "high": np.asarray(bounds[1]).tolist()}
        if len(paths) > 1:
            meta["members"] = len(paths)
            meta["call"] += f"; a mixed policy of {len(paths)} members: policy.pick(i) seats member i as a match begins"
        if is_match_env(env):
            table = env.unwrapped.action_table
            meta["actions_v_w"] = np.asarray(table).tolist() if table is not None else None
        if guard is not None:
            g = _guard_meta(meta, *guard)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                traced = _guarded(traced, g, len(paths) > 1)
            meta["guard"] = g
            meta["call"] += _guard_call(g)
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

