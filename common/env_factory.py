"""Building environments from :class:`EnvConfig` (registers zenrl's own env ids first)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from zenrl.common.config import EnvConfig
from zenrl.common.errors import ConfigError
from zenrl.common.specs import box_wire_dtype


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
    except TypeError as e:
        if render_mode is not None and "render_mode" in str(e):
            raise ConfigError(f"env.id={cfg.id!r} takes no render_mode: it renders no {render_mode} frames") from None
        raise ConfigError(f"env.id={cfg.id!r} with env.kwargs={cfg.kwargs!r} cannot be made: {e}") from None
    except (gym.error.Error, ValueError) as e:
        raise ConfigError(f"env.id={cfg.id!r} with env.kwargs={cfg.kwargs!r} cannot be made: {e}") from None
    return normalised_actions(wire_observations(env))


def _wire_space(space: gym.Space) -> gym.Space:
    """The observation space as zenrl ships it (:func:`zenrl.common.specs.obs_fields`'s rule): a
    uint8 Box stays, any other Box becomes float32 (same bounds), a MultiBinary a float32 Box of
    0/1, a Discrete stays (its int64 index); a Dict of those, each converted; a Tuple a Dict of
    its members keyed ``"0"``, ``"1"``, ... (Blackjack's ``Tuple(Discrete(32), Discrete(11),
    Discrete(2))``: three one-hot encoded fields), and a 1-D MultiDiscrete a Dict of its
    Discretes, likewise. Other spaces are left to the spec's refusal."""
    if isinstance(space, gym.spaces.Dict):
        return gym.spaces.Dict({k: _wire_space(v) for k, v in space.spaces.items()})
    if isinstance(space, gym.spaces.Tuple):
        return gym.spaces.Dict({str(i): _wire_space(v) for i, v in enumerate(space.spaces)})
    if isinstance(space, gym.spaces.MultiDiscrete) and len(space.shape) == 1:
        return gym.spaces.Dict({str(i): gym.spaces.Discrete(int(n), start=int(s0))
                                for i, (n, s0) in enumerate(zip(space.nvec, space.start))})
    if isinstance(space, gym.spaces.MultiBinary):
        return gym.spaces.Box(0.0, 1.0, tuple(space.shape), np.float32)
    if isinstance(space, gym.spaces.Box) and space.dtype != box_wire_dtype(space.dtype):
        return gym.spaces.Box(np.asarray(space.low, np.float64).astype(np.float32),
                              np.asarray(space.high, np.float64).astype(np.float32), space.shape, np.float32)
    return space


def wire_observations(env: gym.Env) -> gym.Env:
    """An env whose observations are not all of the dtypes zenrl ships (an int or float64 Box, a
    MultiBinary) is wrapped in :class:`WireObservations`; the others (float32 and uint8 Boxes,
    Discrete, the match envs) are left as they are."""
    space = env.observation_space
    wire = _wire_space(space)
    return env if wire == space else WireObservations(env, wire)


class WireObservations(gym.ObservationWrapper):
    """Observations cast to the dtypes of ``wire`` (:func:`_wire_space`): what the actors send,
    the replay and learners check against the env's spec, and the networks read. Without it, an
    env with an int64 Box observation had every chunk refused by the replay (``obs_dtype``)."""

    def __init__(self, env: gym.Env, wire: gym.Space) -> None:
        super().__init__(env)
        self.observation_space = wire

    def observation(self, obs):
        return _cast(obs, self.env.observation_space, self.observation_space)


def _cast(obs, space: gym.Space, wire: gym.Space):
    """``obs`` of the env's ``space`` as an observation of ``wire`` (:func:`_wire_space` of it)."""
    if isinstance(space, gym.spaces.Dict):
        return {k: _cast(obs[k], space.spaces[k], sub) for k, sub in wire.spaces.items()}
    if isinstance(space, gym.spaces.Tuple):
        return {str(i): _cast(o, s, wire.spaces[str(i)]) for i, (o, s) in enumerate(zip(obs, space.spaces))}
    if isinstance(space, gym.spaces.MultiDiscrete) and isinstance(wire, gym.spaces.Dict):
        return {str(i): np.int64(v) for i, v in enumerate(np.asarray(obs))}
    if isinstance(wire, gym.spaces.Box):
        return np.asarray(obs, wire.dtype)
    return obs


def normalised_actions(env: gym.Env) -> gym.Env:
    """A 1-D ``Box`` action space with finite bounds becomes [-1, 1]^d (:class:`NormalisedActions`);
    a ``Discrete(n, start)`` with ``start != 0`` becomes ``Discrete(n)`` (:class:`ShiftedActions`).
    Other spaces, and Box spaces that cannot be rescaled (the algorithm refuses them by name), are
    left as they are."""
    space = env.action_space
    if isinstance(space, gym.spaces.Discrete):
        return ShiftedActions(env) if int(space.start) != 0 else env
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        return env
    if not (np.isfinite(space.low).all() and np.isfinite(space.high).all()) or not (space.high > space.low).all():
        return env
    return NormalisedActions(env)


class ShiftedActions(gym.ActionWrapper):
    """A ``Discrete(n, start)`` action space seen as ``Discrete(n)``: the networks, the replay's
    checks and the wire all use the index 0..n-1 (a Q-network's row, a softmax's entry), and the
    env gets ``start + index``. Without it an env with ``Discrete(3, start=-1)`` (left, none,
    right) was given 0..2: a shifted problem, or an env that checks its actions failing on 2."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        #: the env's first action: index i is the env's action ``start + i``
        self.start = int(env.action_space.start)
        self.action_space = gym.spaces.Discrete(int(env.action_space.n))

    def action(self, action: Any) -> np.int64:
        return np.int64(self.start + int(action))


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
        x = self.low + (a + 1.0) * 0.5 * (self.high - self.low)
        if np.dtype(self._dtype).kind in "iu":  # an integer Box: the nearest integer, not the one toward 0
            x = np.rint(x)
        return x.astype(self._dtype)
