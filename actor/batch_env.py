"""A batch of environments stepped together in one process (same-step auto-reset)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import gymnasium as gym
import numpy as np

from zenrl.actor.env_guard import RESET_RETRIES, EnvGuard, EnvLimits, reward_number
from zenrl.common.config import EnvConfig
from zenrl.common.errors import EnvOutputError
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
    """E independent envs; :meth:`step` auto-resets finished ones in the same call. What the envs
    give is checked by an :class:`~zenrl.actor.env_guard.EnvGuard` with the run's ``limits``
    (NaN or Inf always; reward bound and observation bounds where the run checks them)."""

    def __init__(self, cfg: EnvConfig, num_envs: int, seed: int, limits: EnvLimits | None = None) -> None:
        self.envs = [make_env(cfg) for _ in range(num_envs)]
        self.num_envs = num_envs
        self.seed = seed
        self.single_observation_space: gym.Space = self.envs[0].observation_space
        self.single_action_space: gym.Space = self.envs[0].action_space
        self.guard = EnvGuard(cfg.id, self.single_observation_space, limits)
        self._ret = np.zeros(num_envs, np.float64)
        self._len = np.zeros(num_envs, np.int64)
        self._obs: list = []

    def reset(self) -> dict[str, np.ndarray]:
        self._obs = [env.reset(seed=self.seed + i)[0] for i, env in enumerate(self.envs)]
        self._ret[:] = 0
        self._len[:] = 0
        return self._screen_resets(self._stacked(self._obs), range(self.num_envs))

    def step(self, actions: np.ndarray) -> StepResult:
        E = self.num_envs
        guard = self.guard
        rew = np.zeros(E, np.float32)
        term = np.zeros(E, bool)
        trunc = np.zeros(E, bool)
        raw = [0.0] * E
        nxt = list(self._obs)
        infos = []
        lo, hi = guard.reward_range
        plain = True  # every reward finite and within the run's bound (NaN fails both comparisons)
        for i, env in enumerate(self.envs):
            o, r, te, tr, info = env.step(actions[i])
            if type(r) is not float:
                r = reward_number(r, guard.env_id)
            if not lo <= r <= hi:
                plain = False
            raw[i] = r
            rew[i], term[i], trunc[i] = r, te, tr
            nxt[i] = o
            infos.append(info)
        if not plain:
            for r in raw:
                guard.reward(r)  # one beyond the run's bound stops the actor; NaN and Inf are cut below
        after = self._stacked(nxt)
        if not (plain and guard.clean(after)):
            bad = guard.bad_rows(after, rew)
            if bad is not None:
                after = self._screen_steps(bad, nxt, rew, raw, term, trunc)
        rets, lens, outs = [], [], []
        ended = []
        for i, env in enumerate(self.envs):
            self._ret[i] += raw[i]
            self._len[i] += 1
            o = nxt[i]
            if term[i] or trunc[i]:
                rets.append(float(self._ret[i]))
                lens.append(int(self._len[i]))
                m = infos[i].get("outcome")
                outs.append(None if m is None else _OUTCOME_SIGN[m])
                self._ret[i] = 0
                self._len[i] = 0
                o, _ = env.reset()
                ended.append(i)
            self._obs[i] = o
        if not ended:
            return StepResult(after, after, rew, term, trunc, rets, lens, outs)
        obs = self._screen_resets(self._stacked(self._obs), ended)
        return StepResult(obs, after, rew, term, trunc, rets, lens, outs)

    def _stacked(self, obs_list: list) -> dict[str, np.ndarray]:
        """:func:`stack_flat` of the envs' observations, in the dtypes their space names
        (:meth:`~zenrl.actor.env_guard.EnvGuard.conform`); observations of different shapes are an
        :class:`~zenrl.common.errors.EnvOutputError`."""
        try:
            flat = stack_flat(obs_list)
        except ValueError as e:  # np.stack of arrays of different shapes
            raise EnvOutputError(f"env {self.guard.env_id} gave observations of different shapes ({e})") from None
        return self.guard.conform(flat)

    def values(self) -> dict[str, int]:
        """The envs' problems the guard met: ``env_steps_cut``, ``env_obs_clipped``,
        ``env_resets_retried``."""
        return self.guard.values()

    def _screen_steps(self, rows: np.ndarray, nxt: list, rew: np.ndarray, raw: list, term: np.ndarray,
                      trunc: np.ndarray) -> dict[str, np.ndarray]:
        """Fix the steps of ``rows`` in place: clip an observation outside the bounds; cut a step
        with NaN or Inf (truncated, reward 0, the observation before it as its last). Returns the
        batch of observations after the step, stacked again."""
        g = self.guard
        for i in rows:
            i = int(i)
            fixed, notes, broken = g.fix(nxt[i])
            if broken or not math.isfinite(raw[i]):
                what = notes[0] if broken else f"reward {raw[i]}"
                g.note("steps_cut", f"{what} (env {i} of the batch); the episode is cut there: truncated, that step "
                              "dropped (counted as env_steps_cut)")
                nxt[i] = self._obs[i]
                rew[i], raw[i] = 0.0, 0.0
                term[i], trunc[i] = False, True
            elif notes:
                g.note("obs_clipped", f"{notes[0]} (env {i} of the batch); clipped to the bounds (counted as env_obs_clipped; "
                               f"fix the env's observation_space, or set {g.limits.bounds_setting or 'the bound checks'}=false)")
                nxt[i] = fixed
        return self._stacked(nxt)

    def _screen_resets(self, obs: dict[str, np.ndarray], rows: Any) -> dict[str, np.ndarray]:
        """The batch ``obs`` of which ``rows`` are fresh resets: a reset with NaN or Inf is retried
        (:data:`~zenrl.actor.env_guard.RESET_RETRIES` times, then
        :class:`~zenrl.common.errors.EnvOutputError`), one outside the bounds clipped."""
        g = self.guard
        bad = None if g.clean(obs) else g.bad_rows(obs)
        if bad is None:
            return obs
        rows = set(int(i) for i in rows)
        for i in (int(i) for i in bad if int(i) in rows):
            for attempt in range(RESET_RETRIES + 1):
                fixed, notes, broken = g.fix(self._obs[i])
                if not broken:
                    break
                if attempt == RESET_RETRIES:
                    raise EnvOutputError(f"env {g.env_id}'s reset gave an observation with NaN or Inf "
                                         f"{RESET_RETRIES + 1} times in a row ({notes[0]})")
                g.note("resets_retried", f"{notes[0]} after a reset (env {i} of the batch); reset again (counted as env_resets_retried)")
                self._obs[i], _ = self.envs[i].reset()
            if notes:
                g.note("obs_clipped", f"{notes[0]} after a reset (env {i} of the batch); clipped to the bounds (counted as "
                               "env_obs_clipped)")
                self._obs[i] = fixed
        return self._stacked(self._obs)

    def close(self) -> None:
        for env in self.envs:
            env.close()
