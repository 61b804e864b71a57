"""Numbers go here (logging is for events): rates, rejection counters, and a run's metrics
writer (TensorBoard through tensorboardX, plus a JSONL file any script can read)."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any, Mapping

log = logging.getLogger(__name__)


class RateMeter:
    """Events per second over the interval since the last :meth:`rate` call."""

    def __init__(self) -> None:
        self.total = 0
        self._last_total = 0
        self._last_t = time.monotonic()
        self._lock = threading.Lock()

    def add(self, n: int = 1) -> None:
        with self._lock:
            self.total += n

    def rate(self) -> float:
        with self._lock:
            now = time.monotonic()
            dt = max(now - self._last_t, 1e-9)
            r = (self.total - self._last_total) / dt
            self._last_total, self._last_t = self.total, now
            return r


class RejectCounter:
    """Counts rejected inputs by reason and logs them without flooding: the first rejection of
    each reason is logged at once, later ones at most once per ``log_every_s`` with a count."""

    def __init__(self, logger: logging.Logger, what: str, log_every_s: float = 10.0, verb: str = "rejected") -> None:
        self.counts: Counter[str] = Counter()
        self._log = logger
        self._what = what
        self._verb = verb  # the log line's first word (an actor's env checks fix what they count)
        self._every = log_every_s
        self._last: dict[str, float] = {}
        self._unlogged: Counter[str] = Counter()
        self._lock = threading.Lock()

    def reject(self, reason: str, detail: str, source: str = "") -> None:
        with self._lock:
            self.counts[reason] += 1
            now = time.monotonic()
            if now - self._last.get(reason, -1e18) >= self._every:
                extra = f" (+{self._unlogged[reason]} more since last report)" if self._unlogged[reason] else ""
                self._log.warning("%s %s%s [%s]: %s%s", self._verb, self._what, f" from {source}" if source else "", reason,
                                  detail, extra)
                self._last[reason] = now
                self._unlogged[reason] = 0
            else:
                self._unlogged[reason] += 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_values(self, prefix: str = "rejected_") -> dict[str, int]:
        with self._lock:
            out = {f"{prefix}{k}": v for k, v in self.counts.items()}
        out[f"{prefix}total"] = sum(v for k, v in out.items())
        return out


class MetricsWriter:
    """Writes scalars to ``<run_dir>/metrics.jsonl`` (one JSON object per line:
    ``{"time", "source", "step", <name>: value, ...}``) and to TensorBoard event files in
    ``<run_dir>/tb/``. Thread-safe."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._f = open(self.run_dir / "metrics.jsonl", "a", buffering=1)
        self._lock = threading.Lock()
        self._tb = None
        if tensorboard:
            try:
                from tensorboardX import SummaryWriter

                self._tb = SummaryWriter(str(self.run_dir / "tb"))
            except ImportError:  # optional at run time; the JSONL file is always written
                log.warning("tensorboardX is not installed; writing metrics.jsonl only")

    def write(self, source: str, step: int, values: Mapping[str, Any]) -> None:
        nums = {k: v for k, v in values.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        with self._lock:
            self._f.write(json.dumps({"time": time.time(), "source": source, "step": int(step), **nums}) + "\n")
            if self._tb is not None:
                for k, v in nums.items():
                    self._tb.add_scalar(f"{source}/{k}", v, int(step))

    def close(self) -> None:
        with self._lock:
            self._f.close()
            if self._tb is not None:
                self._tb.close()


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """All records of a run's ``metrics.jsonl`` (``path``: the run folder or the file itself; a
    torn last line, from a run still writing, is skipped)."""
    out: list[dict[str, Any]] = []
    p = Path(path)
    if p.is_dir():
        p = p / "metrics.jsonl"
    if not p.exists():
        return out
    for line in p.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out
