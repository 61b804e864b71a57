"""Building environments from :class:`EnvConfig` (registers zenrl's own env ids first)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

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
        env = gym.make(cfg.id, **kw)
    except (gym.error.Error, TypeError, ValueError) as e:
        raise ConfigError(f"env.id={cfg.id!r} with env.kwargs={cfg.kwargs!r} cannot be made: {e}") from None
    return normalised_actions(env)


def normalised_actions(env: gym.Env) -> gym.Env:
    """A 1-D ``Box`` action space with finite bounds becomes [-1, 1]^d (:class:`NormalisedActions`).
    Other spaces, and Box spaces that cannot be rescaled (the algorithm refuses them by name), are
    left as they are."""
    space = env.action_space
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        return env
    if not (np.isfinite(space.low).all() and np.isfinite(space.high).all()) or not (space.high > space.low).all():
        return env
    return NormalisedActions(env)


class NormalisedActions(gym.ActionWrapper):
    """Actions in [-1, 1]^d, clipped to it (a Gaussian policy's samples fall outside now and
    then), then mapped linearly onto the env's bounds ``[low, high]``: the policy sees one scale
    for every env. (Gymnasium's ``ClipAction`` advertises an unbounded space, so this does both.)"""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        inner = env.action_space
        #: float64[d]: the env's own bounds, which [-1, 1] maps onto
        self.low, self.high = inner.low.astype(np.float64), inner.high.astype(np.float64)
        self._dtype = inner.dtype
        self.action_space = gym.spaces.Box(-1.0, 1.0, inner.shape, np.float32)

    def action(self, action: np.ndarray) -> np.ndarray:
        a = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        return (self.low + (a + 1.0) * 0.5 * (self.high - self.low)).astype(self._dtype)
