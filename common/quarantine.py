"""Quarantine of a source that keeps sending what a checker rejects: its traffic is dropped
unread for a while. The replay (Ape-X transition chunks) and the IMPALA learner (unrolls) use
it; pure (no zenoh), unit-tested with an injected clock."""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Callable


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
