"""Exploration schedules shared by actors, the launcher and the slot service."""

from __future__ import annotations

import numpy as np


def apex_epsilon(slot: int, num_slots: int, base: float = 0.4, alpha: float = 7.0) -> float:
    """Ape-X ladder: slot ``i`` of ``N`` acts with ``base ** (1 + alpha * i / (N - 1))``;
    ``N = 1`` gets ``base``. A slot beyond ``N - 1`` wraps around."""
    if num_slots < 1:
        raise ValueError(f"num_slots must be >= 1, got {num_slots}")
    if slot < 0:
        raise ValueError(f"slot must be >= 0, got {slot}")
    if num_slots == 1:
        return float(base)
    i = slot % num_slots
    return float(base ** (1.0 + alpha * i / (num_slots - 1)))


def env_epsilons(slot: int, num_slots: int, envs_per_actor: int, base: float = 0.4, alpha: float = 7.0) -> np.ndarray:
    """float64[E]: the ladder spread over every env of every actor. Env ``k`` of actor slot
    ``i`` takes rung ``i * E + k`` of a ladder of ``N * E`` rungs, so a few actors with many
    envs each still cover the whole ladder (with E = 1 this is exactly :func:`apex_epsilon`)."""
    n = num_slots * envs_per_actor
    return np.array([apex_epsilon(slot * envs_per_actor + k, n, base, alpha) for k in range(envs_per_actor)])


def van_der_corput(k: int) -> float:
    """k-th point of the base-2 van der Corput sequence: 0, 1/2, 1/4, 3/4, 1/8, ... Any prefix
    of it is spread evenly over [0, 1)."""
    x, denom = 0.0, 1.0
    while k:
        denom *= 2.0
        k, bit = divmod(k, 2)
        x += bit / denom
    return x


def elastic_env_epsilons(slot: int, envs_per_actor: int, base: float = 0.4, alpha: float = 7.0) -> np.ndarray:
    """float64[E] for actors whose slots come from the running system (any number may join or
    leave): rung ``r = slot * E + k`` takes ``base ** (1 + alpha * vdc(r))`` so that the slots
    0..N-1 in use always cover the Ape-X ladder evenly, whatever N is."""
    if slot < 0:
        raise ValueError(f"slot must be >= 0, got {slot}")
    return np.array([base ** (1.0 + alpha * van_der_corput(slot * envs_per_actor + k)) for k in range(envs_per_actor)])


class EpsilonGreedy:
    """Per-env epsilon-greedy actions: env i acts at random with probability ``eps[i]``, else
    greedily. Uniforms and random actions are drawn ``draw_steps`` steps at a time (one rng call
    per 64 steps instead of three per step)."""

    def __init__(self, eps: np.ndarray, num_actions: int, rng: np.random.Generator, draw_steps: int = 64) -> None:
        self.eps = np.asarray(eps, np.float64)
        self.num_actions = num_actions
        self.rng = rng
        self.draw_steps = draw_steps
        self._u = np.zeros((0, self.eps.size))
        self._ra = np.zeros((0, self.eps.size), np.int64)
        self._i = 0

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """q: float[E, A] -> int64[E] actions."""
        if self._i >= self._u.shape[0]:
            self._u = self.rng.random((self.draw_steps, self.eps.size))
            self._ra = self.rng.integers(0, self.num_actions, (self.draw_steps, self.eps.size))
            self._i = 0
        i = self._i
        self._i += 1
        return np.where(self._u[i] < self.eps, self._ra[i], q.argmax(1))
