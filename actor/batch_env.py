"""A batch of environments stepped together in one process (same-step auto-reset)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import gymnasium as gym
import numpy as np

from zenrl.common.config import EnvConfig
from zenrl.common.env_factory import make_env
from zenrl.common.networks import flat_obs

#: ``info["outcome"]`` of an episode's last step (a match env's result from the agent's side, e.g.
#: ``zenrl.games.burgerwar``) -> the sign reported in :attr:`StepResult.ep_outcomes`
_OUTCOME_SIGN = {"win": 1, "draw": 0, "loss": -1}


def stack_flat(obs_list: list) -> dict[str, np.ndarray]:
    """List of E single observations -> flat named arrays with leading dim E (a Dict inside a
    Dict gives ``obs/<key>/<key>``, as :func:`~zenrl.common.specs.obs_fields` names it)."""
    return flat_obs(_stacked(obs_list))


def _stacked(items: list) -> Any:
    if isinstance(items[0], Mapping):
        return {k: _stacked([o[k] for o in items]) for k in items[0]}
    return np.stack(items)


@dataclass
class StepResult:
    """One batched step. ``obs``: the observation to act on next (reset obs for envs that just
    ended); ``next_obs``: the observation that followed the action (the *final* one for envs that
    ended). rewards float32[E], terminated/truncated bool[E]; finished episodes' returns and
    lengths, and their outcomes: +1 win, 0 draw, -1 loss from the last step's ``info["outcome"]``
    ("win" | "draw" | "loss", what a match env reports), None when the info has no outcome (any
    other env)."""

    obs: dict[str, np.ndarray]
    next_obs: dict[str, np.ndarray]
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    ep_returns: list[float]
    ep_lengths: list[int]
    ep_outcomes: list[int | None]


class EnvBatch:
    """E independent envs; :meth:`step` auto-resets finished ones in the same call."""

    def __init__(self, cfg: EnvConfig, num_envs: int, seed: int) -> None:
        self.envs = [make_env(cfg) for _ in range(num_envs)]
        self.num_envs = num_envs
        self.seed = seed
        self.single_observation_space: gym.Space = self.envs[0].observation_space
        self.single_action_space: gym.Space = self.envs[0].action_space
        self._ret = np.zeros(num_envs, np.float64)
        self._len = np.zeros(num_envs, np.int64)
        self._obs: list = []

    def reset(self) -> dict[str, np.ndarray]:
        self._obs = [env.reset(seed=self.seed + i)[0] for i, env in enumerate(self.envs)]
        self._ret[:] = 0
        self._len[:] = 0
        return stack_flat(self._obs)

    def step(self, actions: np.ndarray) -> StepResult:
        E = self.num_envs
        rew = np.zeros(E, np.float32)
        term = np.zeros(E, bool)
        trunc = np.zeros(E, bool)
        nxt = list(self._obs)
        rets, lens, outs = [], [], []
        for i, env in enumerate(self.envs):
            o, r, te, tr, info = env.step(actions[i])
            rew[i], term[i], trunc[i] = r, te, tr
            nxt[i] = o
            self._ret[i] += r
            self._len[i] += 1
            if te or tr:
                rets.append(float(self._ret[i]))
                lens.append(int(self._len[i]))
                m = info.get("outcome")
                outs.append(None if m is None else _OUTCOME_SIGN[m])
                self._ret[i] = 0
                self._len[i] = 0
                o, _ = env.reset()
            self._obs[i] = o
        obs = stack_flat(self._obs)
        return StepResult(obs, stack_flat(nxt) if rets else obs, rew, term, trunc, rets, lens, outs)

    def close(self) -> None:
        for env in self.envs:
            env.close()
