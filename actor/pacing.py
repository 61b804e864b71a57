"""Pacing an actor's batched steps to a cap on env steps per second (``actor.max_steps_per_s``),
so that on a small machine the learner keeps the CPU. Pure logic with an injectable clock."""

from __future__ import annotations

import time
from typing import Callable


class StepPacer:
    """``wait()`` before each batched step of ``envs`` env steps keeps the rate at or below
    ``max_steps_per_s``. A pacer that fell behind (slow steps) resumes from now instead of
    bursting to catch up. ``max_steps_per_s=None`` never waits."""

    def __init__(self, max_steps_per_s: float | None, envs: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = None if max_steps_per_s is None else envs / max_steps_per_s
        self._clock = clock
        self._next = clock()

    def delay(self) -> float:
        """Seconds to wait before the next batched step (0 when none); advances the schedule."""
        if self.period_s is None:
            return 0.0
        self._next += self.period_s
        d = self._next - self._clock()
        if d <= 0:
            self._next = self._clock()
            return 0.0
        return d
