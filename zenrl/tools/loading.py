"""Shared by the tools: finding a checkpoint, loading its policy and env, optional imports,
machine-readable output."""

from __future__ import annotations

import ctypes
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import gymnasium as gym

from zenrl.common.config import EnvConfig, RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.errors import ZenrlError
from zenrl.common.networks import num_actions
from zenrl.common.checkpoints import list_checkpoints, read_checkpoint
from zenrl.common.policy_io import GreedyPolicy, build_network, checkpoint_config

log = logging.getLogger(__name__)

MATCH_OPPONENTS = ("cheese", "teriyaki", "clubhouse", "waypoint")


def need(module: str, what: str):
    """Import an optional dependency or fail with the install hint."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ZenrlError(f"{what} needs the '{module.split('.')[0]}' package: pip install 'zenrl[viz]' "
                         f"(or pip install {module.split('.')[0]})") from None


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------
def env_config_for(cfg: RunConfig, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None) -> EnvConfig:
    """The env a checkpoint was trained on, with ``env_id`` / ``env_kwargs`` overriding it
    (kwargs are merged key by key; a different id starts from the given kwargs only)."""
    if env_id is None or env_id == cfg.env.id:
        kw = dict(cfg.env.kwargs)
        kw.update(env_kwargs or {})
        return EnvConfig(id=cfg.env.id, kwargs=kw, max_episode_steps=cfg.env.max_episode_steps)
    return EnvConfig(id=env_id, kwargs=dict(env_kwargs or {}))


def is_match_env(env: gym.Env) -> bool:
    from zenrl.common.envs.burgerwar import BurgerWarEnv

    return isinstance(env.unwrapped, BurgerWarEnv)


def _match_kwargs(kwargs: Mapping[str, Any], opponents: Sequence[str]) -> dict[str, Any]:
    """Env kwargs for evaluating against scripted ``opponents`` (self-play's "policy" entry and
    callables are dropped: the opponent is chosen per episode)."""
    kw = {k: v for k, v in kwargs.items() if k not in ("opponent_policy",)}
    kw["opponents"] = list(opponents)
    return kw


def load_policy_env(checkpoint: str | os.PathLike[str], env_id: str | None = None,
                    env_kwargs: Mapping[str, Any] | None = None, render_mode: str | None = None,
                    opponents: Sequence[str] | None = None, sample: bool = False) -> tuple[GreedyPolicy, gym.Env, RunConfig]:
    """Checkpoint -> (greedy policy, a fresh env it plays in, the checkpoint's config).
    ``sample``: the policy draws from an actor-critic's action distribution instead."""
    state = read_checkpoint(checkpoint)
    cfg = checkpoint_config(state)
    ecfg = env_config_for(cfg, env_id, env_kwargs)
    if opponents is not None:
        ecfg = EnvConfig(id=ecfg.id, kwargs=_match_kwargs(ecfg.kwargs, opponents), max_episode_steps=ecfg.max_episode_steps)
    env = make_env(ecfg, render_mode=render_mode)
    net = build_network(state, env.observation_space, env.action_space)
    try:
        policy = GreedyPolicy(net, num_actions(env.action_space), name=Path(checkpoint).name, sample=sample)
    except ValueError as e:
        env.close()
        raise ZenrlError(f"{checkpoint}: {e}") from None
    return policy, env, cfg

def print_json_line(obj: Any, stream=None) -> None:
    """One compact JSON line (the last stdout line of the tools is machine-readable)."""
    (stream or sys.stdout).write(json.dumps(obj, default=float) + "\n")


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """A checkpoint file as given, or the newest ``ckpt-*.pt`` of a folder: a run folder
    (``runs/<id>``, whose ``checkpoints/`` is searched) or a checkpoints folder."""
    p = Path(path)
    if p.is_file():
        return p
    if not p.exists():
        raise ZenrlError(f"--checkpoint {str(p)!r} does not exist (give a ckpt-*.pt file, a run folder or its checkpoints folder)")
    folder = p / "checkpoints" if (p / "checkpoints").is_dir() else p
    found = list_checkpoints(folder)
    if not found:
        raise ZenrlError(f"--checkpoint {str(p)!r}: no ckpt-*.pt checkpoint in {str(folder)!r}")
    log.info("newest checkpoint of %s: %s", p, found[-1])
    return found[-1]


def quiet_native_imports() -> None:
    """Import pybullet with its ``pybullet build time: ...`` banner sent to stderr: the banner
    is printed by C code into stdout's C buffer, which would otherwise come out at exit, after the
    tools' JSON line that a script reads as the last line of stdout."""
    if "pybullet" in sys.modules:
        return
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        try:
            import pybullet  # noqa: F401
        except ImportError:
            return
        finally:
            ctypes.CDLL(None).fflush(None)
    finally:
        os.dup2(saved, 1)
        os.close(saved)
