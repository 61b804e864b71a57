"""Shared by the tools: finding a checkpoint, loading its policy and env, optional imports,
machine-readable output."""

from __future__ import annotations

import ctypes
import logging
import os
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import gymnasium as gym

from zenrl import strict_json
from zenrl.common.config import EnvConfig, RunConfig, config_from_dict
from zenrl.common.env_factory import make_env
from zenrl.common.errors import ZenrlError
from zenrl.common.networks import action_size
from zenrl.common.checkpoints import list_checkpoints, read_checkpoint
from zenrl.common.policy_io import ExportedPlayer, GreedyPolicy, build_network, is_exported, load_policy  # noqa: F401  (re-exported)

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
    from zenrl.games.burgerwar.env import BurgerWarEnv

    return isinstance(env.unwrapped, BurgerWarEnv)


def _match_kwargs(kwargs: Mapping[str, Any], opponents: Sequence[str]) -> dict[str, Any]:
    """Env kwargs for evaluating against scripted ``opponents`` (self-play's "policy" entry and
    callables are dropped: the opponent is chosen per episode)."""
    kw = {k: v for k, v in kwargs.items() if k not in ("opponent_policy",)}
    kw["opponents"] = list(opponents)
    return kw


def exported_config(meta: Mapping[str, Any]) -> RunConfig:
    """A run config holding what an exported file says of its training: algo and env."""
    return config_from_dict({"algo": meta.get("algo", "apex"),
                             "env": {"id": meta["env"], "kwargs": dict(meta.get("env_kwargs") or {})}})


def refuse_unasked_export(path: str | os.PathLike[str], allow_exported: bool) -> bool:
    """True if ``path`` is a ``zenrl export`` file the caller may load. An exported file is a
    TorchScript program: loading it runs the code inside it, so it is loaded only when the user
    asked for exported policies explicitly (``allow_exported``, the tools' ``--exported``);
    otherwise it is a :class:`ZenrlError`. Checkpoints never need it: they are read with
    ``torch.load(..., weights_only=True)``, which runs no code."""
    if not is_exported(path):
        return False
    if not allow_exported:
        raise ZenrlError(f"{str(path)!r} is an exported TorchScript policy, and loading one runs the code inside it: "
                         "pass --exported to load exported files you trust")
    return True


def load_player(path: str | os.PathLike[str], observation_space: gym.Space, action_space: gym.Space,
                allow_exported: bool = False):
    """A checkpoint or (with ``allow_exported``) an exported file -> ``player(obs) -> int``
    (greedy) for an env with these single spaces; a mismatch is a :class:`ZenrlError` naming it.
    An opponent's action is an index of the match's action set: a continuous set is refused."""
    if not isinstance(action_space, gym.spaces.Discrete):
        raise ZenrlError(f"{path}: a policy plays the other robot through a discrete action set; this env's is "
                         f"{action_space} (scripted bots play against any set)")
    if refuse_unasked_export(path, allow_exported):
        player = ExportedPlayer(path)
        player.check_spaces(observation_space, action_space)
        return player
    try:
        return load_policy(path, observation_space, action_space)
    except ZenrlError as e:
        raise ZenrlError(f"{path}: {e}") from None


def load_policy_env(checkpoint: str | os.PathLike[str], env_id: str | None = None,
                    env_kwargs: Mapping[str, Any] | None = None, render_mode: str | None = None,
                    opponents: Sequence[str] | None = None, sample: bool = False,
                    allow_exported: bool = False) -> tuple[Any, gym.Env, RunConfig]:
    """Checkpoint or exported file -> (greedy policy, a fresh env it plays in, the config it was
    trained with: the whole config for a checkpoint, algo and env for an exported file).
    ``sample``: the policy draws from an actor-critic's action distribution instead (checkpoints only).
    ``allow_exported``: the user asked for exported files (see :func:`refuse_unasked_export`)."""
    exported = ExportedPlayer(checkpoint) if refuse_unasked_export(checkpoint, allow_exported) else None
    if exported is not None:
        if sample:
            raise ZenrlError(f"{checkpoint}: an exported policy is greedy only; --policy sample needs a checkpoint")
        cfg = exported_config(exported.meta)
    else:
        state = read_checkpoint(checkpoint)
        cfg = state.run_config()
    ecfg = env_config_for(cfg, env_id, env_kwargs)
    if opponents is not None:
        ecfg = EnvConfig(id=ecfg.id, kwargs=_match_kwargs(ecfg.kwargs, opponents), max_episode_steps=ecfg.max_episode_steps)
    env = make_env(ecfg, render_mode=render_mode)
    if exported is not None:
        try:
            exported.check_spaces(env.observation_space, env.action_space)
        except ZenrlError:
            env.close()
            raise
        return exported, env, cfg
    try:
        net = build_network(state, env.observation_space, env.action_space)
        policy = GreedyPolicy(net, action_size(env.action_space, state.algo), name=Path(checkpoint).name, sample=sample)
    except (ValueError, ZenrlError) as e:
        env.close()
        raise ZenrlError(f"{checkpoint}: {e}") from None
    return policy, env, cfg

def print_json_line(obj: Any, stream=None) -> None:
    """One compact JSON line (the last stdout line of the tools is machine-readable; no NaN)."""
    (stream or sys.stdout).write(strict_json.dumps(obj, default=float) + "\n")


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
