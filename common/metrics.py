"""Numbers go here (logging is for events): rates, rejection counters, and a run's metrics
writer (TensorBoard through tensorboardX, plus a JSONL file any script can read)."""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import socket
import struct
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


#: seconds before a TensorBoard events file that failed to be written is opened anew
TB_RETRY_S = 30.0
#: a failing metrics write is logged at most this often
WRITE_ERROR_EVERY_S = 60.0


def tf_record(data: bytes) -> bytes:
    """``data`` framed as one TFRecord (what TensorBoard's event files hold): length, its masked
    CRC-32C, the data, its masked CRC-32C; little-endian."""
    from tensorboardX.record_writer import masked_crc32c

    head = struct.pack("<Q", len(data))
    return head + struct.pack("<I", masked_crc32c(head)) + data + struct.pack("<I", masked_crc32c(data))


class MetricsWriter:
    """Writes scalars to ``<run_dir>/metrics.jsonl`` (one JSON object per line:
    ``{"time", "source", "step", <name>: value, ...}``) and to a TensorBoard event file in
    ``<run_dir>/tb/`` (tensorboardX's protos). Thread-safe.

    A write that fails (a full disk) is counted (:attr:`failed_writes`) and logged at most once a
    minute, and the caller goes on: metrics are not worth stopping a run for; the events go to a
    new file after :data:`TB_RETRY_S` (the old one may end in a torn record). The events are
    written in the caller's thread, flushed without fsync: tensorboardX's ``SummaryWriter``
    writes from a thread of its own, which died on the first failed write, after which every
    write waited forever on its full queue, and the process at its exit."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._f = open(self.run_dir / "metrics.jsonl", "a", buffering=1)
        self._lock = threading.Lock()
        self.failed_writes = 0
        self._said_at: float | None = None
        self._tb: Any = None
        self._tb_on = False
        self._tb_retry_at = 0.0
        self._tb_files = 0
        if tensorboard:
            if importlib.util.find_spec("tensorboardX") is None:  # optional at run time; the JSONL file is always written
                log.warning("tensorboardX is not installed; writing metrics.jsonl only")
            else:
                self._tb_on = True
                self._open_tb()

    def _failed(self, what: str, e: OSError) -> None:
        self.failed_writes += 1
        now = time.monotonic()
        if self._said_at is None or now - self._said_at >= WRITE_ERROR_EVERY_S:
            self._said_at = now
            log.warning("cannot write %s in %s: %s; going on without it (%d metrics writes failed so far)", what,
                        self.run_dir, e, self.failed_writes)

    def _open_tb(self) -> None:
        from tensorboardX.proto.event_pb2 import Event

        # a new name for every file this process opens: a reopened one must not append to a torn record
        self._tb_files += 1
        path = (self.run_dir / "tb" /
                f"events.out.tfevents.{int(time.time())}.{socket.gethostname()}.{os.getpid()}.{self._tb_files}")
        try:
            path.parent.mkdir(exist_ok=True)
            self._tb = open(path, "ab")
            self._tb.write(tf_record(Event(wall_time=time.time(), file_version="brain.Event:2").SerializeToString()))
            self._tb.flush()
        except OSError as e:
            self._close_tb()
            self._failed("TensorBoard events", e)

    def _close_tb(self) -> None:
        if self._tb is not None:
            try:
                self._tb.close()
            except OSError:
                pass  # the file stays readable up to its torn record
        self._tb, self._tb_retry_at = None, time.monotonic() + TB_RETRY_S

    def _write_tb(self, step: int, tags: Mapping[str, float]) -> None:
        from tensorboardX.proto.event_pb2 import Event
        from tensorboardX.proto.summary_pb2 import Summary

        if self._tb is None:
            if time.monotonic() < self._tb_retry_at:
                return
            self._open_tb()
            if self._tb is None:
                return
        ev = Event(wall_time=time.time(), step=step,
                   summary=Summary(value=[Summary.Value(tag=k, simple_value=float(v)) for k, v in tags.items()]))
        try:
            self._tb.write(tf_record(ev.SerializeToString()))
            self._tb.flush()
        except OSError as e:
            self._close_tb()
            self._failed("TensorBoard events", e)

    def write(self, source: str, step: int, values: Mapping[str, Any]) -> None:
        nums = {k: v for k, v in values.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        line = json.dumps({"time": time.time(), "source": source, "step": int(step), **nums}) + "\n"
        with self._lock:
            try:
                self._f.write(line)
            except OSError as e:
                self._failed("metrics.jsonl", e)
            if self._tb_on:
                self._write_tb(int(step), {f"{source}/{k}": v for k, v in nums.items()})

    def close(self) -> None:
        with self._lock:
            try:
                self._f.close()
            except OSError as e:  # its last line could not be flushed
                self._failed("metrics.jsonl", e)
            self._tb_on = False
            self._close_tb()


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
