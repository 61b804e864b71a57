"""The learner's guard against batches and gradients it must not trust (no I/O).

A non-finite loss or gradient norm skips the update (the optimizer never steps on it); skipped
updates are counted and logged at most once per interval; after ``max_bad`` skipped in a row the
caller rolls back (to its last good checkpoint). Parameters are checked finite before they are
published or checkpointed.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Callable, Iterable

import torch

log = logging.getLogger(__name__)


def params_finite(params: Iterable[torch.Tensor]) -> bool:
    """Whether every floating-point tensor in ``params`` is finite (one reduction each)."""
    return all(bool(torch.isfinite(p).all()) for p in params if p.is_floating_point())


class UpdateGuard:
    """Counts skipped updates; ``rollback_due`` after ``max_bad`` in a row."""

    def __init__(self, max_bad: int, log_interval_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if max_bad < 1:
            raise ValueError(f"max_bad must be >= 1, got {max_bad}")
        self.max_bad = max_bad
        self.log_interval_s = log_interval_s
        self.clock = clock
        self.skipped = 0  #: updates skipped so far
        self.in_a_row = 0  #: skipped since the last good update
        self.rollbacks = 0
        self.unpublishable = 0  #: times parameters were found non-finite before a publish or save
        self._last_log = -math.inf
        self._unlogged = 0

    def accept(self, loss: float, grad_norm: float) -> bool:
        """Whether an update with this loss and (pre-clip) gradient norm may step."""
        if math.isfinite(loss) and math.isfinite(grad_norm):
            self.in_a_row = 0
            return True
        self.skipped += 1
        self.in_a_row += 1
        self._unlogged += 1
        now = self.clock()
        if now - self._last_log >= self.log_interval_s:
            log.warning("skipped %d update(s) with a non-finite loss or gradient (loss %s, gradient norm %s); "
                        "%d in a row, %d in all", self._unlogged, loss, grad_norm, self.in_a_row, self.skipped)
            self._last_log = now
            self._unlogged = 0
        return False

    @property
    def rollback_due(self) -> bool:
        return self.in_a_row >= self.max_bad

    def rolled_back(self) -> None:
        self.rollbacks += 1
        self.in_a_row = 0

    def values(self) -> dict[str, int]:
        return {"skipped_updates": self.skipped, "rollbacks": self.rollbacks, "params_unpublishable": self.unpublishable}
