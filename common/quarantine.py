"""Quarantine of a source that keeps sending what a checker rejects: its traffic is dropped
unread for a while. The replay (Ape-X transition chunks) and the IMPALA learner (unrolls) use
it; pure (no zenoh), unit-tested with an injected clock."""

from __future__ import annotations

import collections
import heapq
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable


#: Longest status line (a stats string; the protocol admits 4096 characters).
MAX_LINE = 4000


@dataclass
class QuarantineEntry:
    until: float
    reason: str
    count: int = 0


class Quarantine:
    """A source with ``rejections`` rejected chunks within ``window_s`` seconds has its traffic
    dropped for ``duration_s`` seconds. ``clock`` is injectable for tests. Not thread-safe:
    the replay calls it under its own lock (``is_quarantined`` reads a dict, safe without it).

    Memory is bounded whatever names senders invent, and quarantine is never switched off: the
    recent rejections of at most ``max_sources`` sources are kept, least recently rejected
    forgotten first (so a source that keeps failing stays tracked however many one-off names
    pass by); at most ``max_sources`` quarantines are held, and a new one displaces the one that
    ends soonest. Names are only a sender's claim: one that invents a new name for every few
    chunks is never quarantined, only counted (the router's access control binds names to
    credentials; see docs/architecture.md)."""

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
        q = self._recent.pop(source, None)  # re-inserted last: the dict's order is least recent first
        if q is None:
            if len(self._recent) >= self.max_sources:  # bounded memory whatever ids are invented
                self._recent.pop(next(iter(self._recent)))
            q = collections.deque()
        self._recent[source] = q
        q.append(now)
        while q and q[0] < now - self.window_s:
            q.popleft()
        if len(q) < self.rejections:
            return False
        del self._recent[source]
        if source not in self.active and len(self.active) >= self.max_sources:
            self.expire()
            if len(self.active) >= self.max_sources:  # displace the quarantine that ends soonest
                del self.active[min(self.active, key=lambda s: self.active[s].until)]
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

    def describe(self, top: int = 10) -> str:
        """One line for status displays, the ``top`` sources that dropped most first: ``source
        (reason, N dropped, Ts left); ...`` and ``... and K more`` (a bounded line, a stats
        string, whatever the number of quarantined names)."""
        now = self.clock()
        live = [(s, e) for s, e in self.active.items() if now < e.until]
        shown = sorted(live, key=lambda x: (-x[1].count, x[0]))[:top]
        line = "; ".join(f"{s} ({e.reason}, {e.count} dropped, {max(0.0, e.until - now):.0f} s left)" for s, e in shown)
        more = f"; ... and {len(live) - len(shown)} more" if len(live) > len(shown) else ""
        return line[:MAX_LINE - len(more)] + more


class TopCounter:
    """Counts per key in bounded memory, keeping the heaviest (the Space-Saving algorithm of
    Metwally et al.): at most ``capacity`` keys; a new key past that replaces the least counted
    one and inherits its count plus one. So any key counted more than ``total / capacity`` times
    is always held, and a held key's count exceeds its true count by at most the count it
    inherited (:meth:`error`). Mapping-like reads (``c[key]``, ``in``, ``len``). Not thread-safe."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.counts: dict[str, int] = {}
        self._err: dict[str, int] = {}
        self.total = 0
        #: (count, key) entries, some stale (a key counted since): the least counted key is found
        #: in O(log n) amortized, not by a scan per new key (which a stream of invented names
        #: would turn into a cost per message)
        self._heap: list[tuple[int, str]] = []

    def add(self, key: str, n: int = 1) -> None:
        self.total += n
        if key in self.counts:
            self.counts[key] += n
        elif len(self.counts) < self.capacity:
            self.counts[key] = n
            self._err[key] = 0
        else:
            low = self._pop_least()
            base = self.counts.pop(low)
            del self._err[low]
            self.counts[key] = base + n
            self._err[key] = base
        heapq.heappush(self._heap, (self.counts[key], key))
        if len(self._heap) > 4 * self.capacity:  # drop the stale entries
            self._heap = [(c, k) for k, c in self.counts.items()]
            heapq.heapify(self._heap)

    def _pop_least(self) -> str:
        while True:
            c, k = heapq.heappop(self._heap)
            if self.counts.get(k) == c:
                return k

    def error(self, key: str) -> int:
        """How much ``key``'s count may exceed its true count."""
        return self._err.get(key, 0)

    def most_common(self, n: int) -> list[tuple[str, int]]:
        return sorted(self.counts.items(), key=lambda kv: (-kv[1], kv[0]))[:n]

    def __getitem__(self, key: str) -> int:
        return self.counts.get(key, 0)

    def __contains__(self, key: object) -> bool:
        return key in self.counts

    def __len__(self) -> int:
        return len(self.counts)


class SourceLedger:
    """Who sent what was rejected, for a service that takes messages from many senders (the
    replay's chunks, the IMPALA learner's unrolls): rejections per source name (a
    :class:`TopCounter` of ``max_sources`` names, the heaviest kept, the ``top`` most rejected
    published; the totals by reason are the caller's :class:`~zenrl.common.metrics.RejectCounter`),
    exceptions other than the protocol's own by type (``rejected_internal/<Type>``), and the
    :class:`Quarantine` they feed. Thread-safe (``lock`` guards all of it, the quarantine
    included)."""

    def __init__(self, quarantine: Quarantine, max_sources: int = 1024) -> None:
        self.quarantine = quarantine
        self.max_sources = max_sources
        self.by_source = TopCounter(max_sources)
        self.internal: collections.Counter[str] = collections.Counter()
        self.lock = threading.Lock()

    def rejected(self, source: str, reason: str) -> bool:
        """Count one rejection of ``source``; True when it has just been quarantined. The
        quarantine sees every rejection, whatever the number of names."""
        with self.lock:
            self.by_source.add(source)
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
            v["quarantined_sources"] = self.quarantine.describe(top)
            v["quarantines_total"] = self.quarantine.total
        return v
