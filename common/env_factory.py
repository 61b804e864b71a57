"""Building environments from :class:`EnvConfig` (registers zenrl's own env ids first)."""

from __future__ import annotations

import gymnasium as gym

from zenrl.common.config import EnvConfig
from zenrl.common.errors import ConfigError


def make_env(cfg: EnvConfig, render_mode: str | None = None) -> gym.Env:
    """``gymnasium.make(cfg.id, **cfg.kwargs)``; a bad id or option is a :class:`ConfigError`."""
    import zenrl.common.envs  # noqa: F401  (registers zenrl/BurgerWar-v0 and friends)

    kw = dict(cfg.kwargs)
    if cfg.max_episode_steps is not None:
        kw["max_episode_steps"] = cfg.max_episode_steps
    if render_mode is not None:
        kw["render_mode"] = render_mode
    try:
        return gym.make(cfg.id, **kw)
    except (gym.error.Error, TypeError, ValueError) as e:
        raise ConfigError(f"env.id={cfg.id!r} with env.kwargs={cfg.kwargs!r} cannot be made: {e}") from None
