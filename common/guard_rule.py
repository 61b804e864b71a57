"""The match env's guard rule on detector readings, batched (numpy, no I/O).

The rule (docs/burgerwar.md, "The guard"): the other robot seen nearer than ``radius`` and more
than the guard's angle off the heading -> the fastest turn on the spot towards it. The match env
acts on it (``actor.guard_share``) and pays on it (``face_penalty``); the Ape-X learner teaches it
to the network (``learner.guard_imitation``). One definition here, so the three agree; the
TorchScript export keeps its own copy (it cannot call Python).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GuardRule:
    """``radius`` m; ``cos_angle`` the cosine of the angle off the heading beyond which the rule
    fires; ``left`` / ``right`` the action indices of the fastest turns on the spot."""

    radius: float
    cos_angle: float
    left: int
    right: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0.0 and -1.0 <= self.cos_angle <= 1.0):
            raise ValueError(f"guard rule needs radius > 0 and cos_angle in [-1, 1], got {self.radius!r}, {self.cos_angle!r}")

    def off_facing(self, seen: np.ndarray) -> np.ndarray:
        """bool[N]: whether each reading of ``seen`` (float[N, 3]: seen flag, x forward, y left,
        in m) puts the other robot nearer than ``radius`` and more than the angle off the heading.
        Non-finite readings never fire."""
        s = np.asarray(seen, np.float64).reshape(-1, 3)
        x, y = s[:, 1], s[:, 2]
        r = np.hypot(x, y)
        with np.errstate(invalid="ignore"):
            return (s[:, 0] > 0.5) & (r > 0.0) & (r < self.radius) & (x < r * self.cos_angle)

    def actions(self, seen: np.ndarray) -> np.ndarray:
        """int64[N]: the guard's action on each reading of ``seen`` (float[N, 3]), -1 where the
        rule does not fire."""
        s = np.asarray(seen, np.float64).reshape(-1, 3)
        turn = np.where(s[:, 2] > 0.0, self.left, self.right)
        return np.where(self.off_facing(s), turn, -1).astype(np.int64)
