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
