"""Vectorized n-step transition builder for E envs stepped together (Ape-X actors).

For a start step ``j`` the emitted transition holds::

    obs      = s_j                       action = a_j
    reward   = sum_{k=0}^{m-1} gamma^k r_{j+k}      n = m  (m <= n_step)
    next_obs = s_{j+m}                   terminated = whether the episode terminated at j+m-1

``m = n_step`` in mid-episode; at an episode end every pending start is emitted with the
steps that remain (``m < n_step``). ``terminated`` stops bootstrapping
(``discount = gamma ** m * (1 - terminated)``); ``truncated`` bootstraps from ``next_obs``, which
is then the episode's final observation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Emitted:
    """Transitions emitted by one :meth:`NStepBuilder.add`. ``data`` fields have leading dim K;
    ``env`` int64[K] says which env each came from; ``q_sa`` float32[K] is Q(s_j, a_j) as
    computed when acting (for the initial priority); ``pending`` bool[K] marks transitions whose
    ``next_obs`` is the obs the actor will act on next (bootstrap from the next forward pass)."""

    data: dict[str, np.ndarray]
    env: np.ndarray
    q_sa: np.ndarray
    pending: np.ndarray

    def __len__(self) -> int:
        return int(self.env.shape[0])


class NStepBuilder:
    def __init__(self, num_envs: int, n_step: int, gamma: float) -> None:
        if n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {n_step}")
        self.E, self.n, self.gamma = num_envs, n_step, gamma
        self.count = np.zeros(num_envs, np.int64)
        self.t = 0
        self._obs: dict[str, np.ndarray] | None = None
        self._act = np.zeros((n_step, num_envs), np.int64)
        self._rew = np.zeros((n_step, num_envs), np.float64)
        self._q = np.zeros((n_step, num_envs), np.float32)
        self._disc = gamma ** np.arange(n_step, dtype=np.float64)

    def reset(self) -> None:
        self.count[:] = 0

    def add(self, obs: dict[str, np.ndarray], actions: np.ndarray, rewards: np.ndarray, q_sa: np.ndarray,
            next_obs: dict[str, np.ndarray], terminated: np.ndarray, truncated: np.ndarray) -> Emitted:
        """Record step t for every env. ``obs``: s_t (what was acted on); ``next_obs``: s_{t+1}
        (the final observation for envs whose episode ended). All arrays have leading dim E.
        Returns everything emitted, pending transitions first (see :meth:`add_split`)."""
        parts = [e for e in self.add_split(obs, actions, rewards, q_sa, next_obs, terminated, truncated) if e is not None]
        if not parts:
            return Emitted({}, np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, bool))
        if len(parts) == 1:
            return parts[0]
        data = {k: np.concatenate([p.data[k] for p in parts]) for k in parts[0].data}
        return Emitted(data, np.concatenate([p.env for p in parts]), np.concatenate([p.q_sa for p in parts]),
                       np.concatenate([p.pending for p in parts]))

    def add_split(self, obs: dict[str, np.ndarray], actions: np.ndarray, rewards: np.ndarray, q_sa: np.ndarray,
                  next_obs: dict[str, np.ndarray], terminated: np.ndarray,
                  truncated: np.ndarray) -> tuple[Emitted | None, Emitted | None]:
        """As :meth:`add`, but returns ``(pending, finished)`` separately (None where empty):
        ``pending`` are mid-episode n-step transitions (``next_obs`` is what the actor acts on
        next, so it bootstraps them from its next forward pass), ``finished`` those of episodes
        that ended at this step."""
        n, E = self.n, self.E
        if self._obs is None:
            self._obs = {k: np.zeros((n, E) + v.shape[1:], v.dtype) for k, v in obs.items()}
        pos = self.t % n
        for k, v in obs.items():
            self._obs[k][pos] = v
        self._act[pos] = actions
        self._rew[pos] = rewards
        self._q[pos] = q_sa
        self.count += 1
        done = terminated | truncated
        pending = finished = None

        full = np.flatnonzero((self.count == n) & ~done)
        if full.size:
            start = (self.t - n + 1) % n
            order = (start + np.arange(n)) % n
            R = self._disc @ self._rew[order][:, full]
            data = self._gather(start, full, next_obs, R, np.full(full.size, n, np.uint8), False, False)
            pending = Emitted(data, full, self._q[start, full], np.ones(full.size, bool))
            self.count[full] = n - 1

        ended = np.flatnonzero(done)
        if ended.size:
            # every pending start of every ended env, in one gather: env e with c starts emits
            # transitions with m = c, c-1, ..., 1 steps remaining
            counts = self.count[ended]
            envs = np.repeat(ended, counts)
            first = np.cumsum(counts) - counts
            m = (np.repeat(counts, counts) - (np.arange(envs.size) - np.repeat(first, counts))).astype(np.int64)
            start = (self.t - m + 1) % n
            k = np.arange(n)
            window = self._rew[(start[:, None] + k) % n, envs[:, None]]
            R = (window * np.where(k < m[:, None], self._disc, 0.0)).sum(axis=1)
            data = self._gather(start, envs, next_obs, R, m.astype(np.uint8), terminated[envs], truncated[envs])
            finished = Emitted(data, envs, self._q[start, envs], np.zeros(envs.size, bool))
            self.count[ended] = 0
        self.t += 1
        return pending, finished

    def _gather(self, start: int | np.ndarray, envs: np.ndarray, next_obs: dict[str, np.ndarray], R: np.ndarray,
                m: np.ndarray, terminated: bool | np.ndarray, truncated: bool | np.ndarray) -> dict[str, np.ndarray]:
        K = envs.size
        out: dict[str, np.ndarray] = {}
        for k, buf in self._obs.items():
            out[k] = buf[start, envs]
        out["action"] = self._act[start, envs]
        out["reward"] = R.astype(np.float32)
        for k, v in next_obs.items():
            out["next_" + k] = v[envs]
        out["terminated"] = np.zeros(K, bool) if terminated is False else np.asarray(terminated, bool)
        out["truncated"] = np.zeros(K, bool) if truncated is False else np.asarray(truncated, bool)
        out["n"] = m
        return out
