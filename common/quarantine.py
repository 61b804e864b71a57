"""Quarantine of a source that keeps sending what a checker rejects: its traffic is dropped
unread for a while. The replay (Ape-X transition chunks) and the IMPALA learner (unrolls) use
it; pure (no zenoh), unit-tested with an injected clock."""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable


@dataclass
class QuarantineEntry:
    until: float
    reason: str
    count: int = 0


class Quarantine:
    """A source with ``rejections`` rejected chunks within ``window_s`` seconds has its traffic
    dropped for ``duration_s`` seconds. ``clock`` is injectable for tests. Not thread-safe:
    the replay calls it under its own lock (``is_quarantined`` reads a dict, safe without it)."""

    def __init__(self, rejections: int, window_s: float, duration_s: float,
                 clock: Callable[[], float] = time.monotonic, max_sources: int = 10_000) -> None:
        self.rejections = rejections
        self.window_s = window_s
        self.duration_s = duration_s
        self.clock = clock
        self.max_sources = max_sources
        self._recent: dict[str, collections.deque[float]] = {}
        self.active: dict[str, QuarantineEntry] = {}
        self.total = 0  #: quarantines imposed so far

    def record(self, source: str, reason: str) -> bool:
        """Count one rejection of ``source``; returns True if this put it in quarantine."""
        now = self.clock()
        if self.rejections <= 0 or self.is_quarantined(source, now):
            return False
        q = self._recent.get(source)
        if q is None:
            if len(self._recent) >= self.max_sources:  # bounded memory whatever ids are invented
                self._recent.pop(next(iter(self._recent)))
            q = self._recent[source] = collections.deque()
        q.append(now)
        while q and q[0] < now - self.window_s:
            q.popleft()
        if len(q) < self.rejections:
            return False
        del self._recent[source]
        self.active[source] = QuarantineEntry(now + self.duration_s, reason)
        self.total += 1
        return True

    def is_quarantined(self, source: str, now: float | None = None) -> bool:
        e = self.active.get(source)
        if e is None:
            return False
        return (self.clock() if now is None else now) < e.until

    def drop(self, source: str) -> bool:
        """Count and say whether a message from ``source`` is to be dropped now."""
        e = self.active.get(source)
        if e is None or self.clock() >= e.until:
            return False
        e.count += 1
        return True

    def expire(self) -> list[str]:
        """Forget quarantines that are over; returns the sources released."""
        now = self.clock()
        done = [s for s, e in self.active.items() if now >= e.until]
        for s in done:
            del self.active[s]
        return done

    def describe(self) -> str:
        """One line for status displays: ``source (reason, N dropped, Ts left); ...``."""
        now = self.clock()
        return "; ".join(f"{s} ({e.reason}, {e.count} dropped, {max(0.0, e.until - now):.0f} s left)"
                         for s, e in sorted(self.active.items()) if now < e.until)


class SourceLedger:
    """Who sent what was rejected, for a service that takes messages from many senders (the
    replay's chunks, the IMPALA learner's unrolls): rejections per source name (at most
    ``max_sources`` names kept, the most rejected published; the totals by reason are the
    caller's :class:`~zenrl.common.metrics.RejectCounter`), exceptions other than the protocol's
    own by type (``rejected_internal/<Type>``), and the :class:`Quarantine` they feed. Thread-safe
    (``lock`` guards all of it, the quarantine included)."""

    def __init__(self, quarantine: Quarantine, max_sources: int = 10_000) -> None:
        self.quarantine = quarantine
        self.max_sources = max_sources
        self.by_source: collections.Counter[str] = collections.Counter()
        self.internal: collections.Counter[str] = collections.Counter()
        self.lock = threading.Lock()

    def rejected(self, source: str, reason: str) -> bool:
        """Count one rejection of ``source``; True when it has just been quarantined. The
        quarantine sees every rejection, also of sources past ``max_sources``."""
        with self.lock:
            if source in self.by_source or len(self.by_source) < self.max_sources:
                self.by_source[source] += 1
            return self.quarantine.record(source, reason)

    def internal_error(self, e: BaseException) -> bool:
        """Count an exception by type; True for the first of its type (worth a traceback)."""
        t = type(e).__name__
        with self.lock:
            self.internal[t] += 1
            return self.internal[t] == 1

    def values(self, top: int, expire: bool = False) -> dict[str, Any]:
        """``rejected_internal/<Type>``, the ``top`` most rejected ``rejected_from/<source>`` and
        the quarantine (``quarantined``, ``quarantined_sources``, ``quarantines_total``);
        ``expire``: forget the quarantines that are over first (a caller that acts on releases,
        like the replay's tokens, calls ``quarantine.expire()`` itself under ``lock``)."""
        with self.lock:
            if expire:
                self.quarantine.expire()
            v: dict[str, Any] = {f"rejected_internal/{t}": n for t, n in self.internal.items()}
            v.update({f"rejected_from/{s}": n for s, n in self.by_source.most_common(top)})
            v["quarantined"] = len(self.quarantine.active)
            v["quarantined_sources"] = self.quarantine.describe()
            v["quarantines_total"] = self.quarantine.total
        return v
