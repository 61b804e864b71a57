"""A bounded queue of raw messages that is fair per source, for a learner's Zenoh callback (the
A3C parameter server's gradients). Pure (no Zenoh), thread-safe, unit-tested.

* **Bounded**: at most ``max_items`` messages. A put into a full queue never blocks the callback:
  it evicts the oldest message of the source holding the most (the putter itself when it is
  among them), so a source that floods only ever pushes out its own messages.
* **Fair**: one FIFO per source; :meth:`FairQueue.get` serves the sources round-robin (oldest
  first within each), so a source that floods gets one turn in N like every other, and a quiet
  source's message waits behind at most one message of each other source.

The source is the sender's name in the key (``gradients/<worker>``); a sender that rotates names
still cannot grow the queue past ``max_items``. Counters (``counters``): ``queued``, ``taken``,
``evicted``; :meth:`FairQueue.evicted_values` names the :data:`TOP_EVICTED` sources evicted most.

**Turns waited** (:meth:`FairQueue.wait_values`): for each message taken, the messages of other
sources taken while it waited, divided by the messages of its own source it queued behind plus
one (itself). Served round-robin, that is at most the number of other sources that had messages
waiting; the queue keeps each source's largest. Unlike a source's share of all the turns, which
grows with the turns a slow source leaves unused, it does not depend on how fast anyone sends.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Generic, TypeVar

T = TypeVar("T")

#: sources whose evictions are counted by name (the totals count them all)
TOP_EVICTED = 20
#: sources tracked by name for eviction counts at most (a sender rotating names cannot grow them)
MAX_TRACKED = 10_000


class FairQueue(Generic[T]):
    """See the module docstring. ``max_items`` >= 1."""

    def __init__(self, max_items: int) -> None:
        if max_items < 1:
            raise ValueError(f"max_items must be >= 1, got {max_items}")
        self.max_items = max_items
        #: per source: its messages (item, messages taken at put, its own taken at put, own ahead at put)
        self._fifos: dict[str, collections.deque[tuple[T, int, int, int]]] = {}
        self._own_taken: dict[str, int] = {}  # per source in _fifos: its messages taken so far
        self._turn: collections.deque[str] = collections.deque()  # round-robin order of the sources in _fifos
        self._count = 0
        self._cv = threading.Condition()
        self.counters: collections.Counter[str] = collections.Counter()
        self._evicted_by: collections.Counter[str] = collections.Counter()
        self._wait_max: dict[str, float] = {}

    def __len__(self) -> int:
        return self._count

    def put(self, source: str, item: T) -> bool:
        """Queue ``item`` from ``source``; never blocks. Returns whether another message (of the
        source holding the most) was evicted to make room."""
        with self._cv:
            evicted = self._count >= self.max_items
            if evicted:
                victim = self._biggest(source)
                self._pop(victim)
                self.counters["evicted"] += 1
                if victim in self._evicted_by or len(self._evicted_by) < MAX_TRACKED:
                    self._evicted_by[victim] += 1
            fifo = self._fifos.get(source)
            if fifo is None:
                fifo = self._fifos[source] = collections.deque()
                self._own_taken[source] = 0
                self._turn.append(source)
            fifo.append((item, self.counters["taken"], self._own_taken[source], len(fifo)))
            self._count += 1
            self.counters["queued"] += 1
            self._cv.notify()
            return evicted

    def get(self, timeout: float) -> tuple[str, T] | None:
        """The next ``(source, item)``, sources served round-robin; waits up to ``timeout``
        seconds for one, else None."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while not self._count:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cv.wait(left)
            source = self._turn[0]
            self._turn.rotate(-1)
            _, taken_at_put, own_at_put, ahead = self._fifos[source][0]
            others = (self.counters["taken"] - taken_at_put) - (self._own_taken[source] - own_at_put)
            turns = others / (ahead + 1)
            if source in self._wait_max or len(self._wait_max) < MAX_TRACKED:
                self._wait_max[source] = max(self._wait_max.get(source, 0.0), turns)
            self.counters["taken"] += 1
            self._own_taken[source] += 1
            return source, self._pop(source)

    def sizes(self) -> dict[str, int]:
        """Messages held per source."""
        with self._cv:
            return {s: len(f) for s, f in self._fifos.items()}

    def evicted_values(self, prefix: str = "queue_dropped_from") -> dict[str, int]:
        """``{prefix + "/<source>": n}``: messages evicted, for the :data:`TOP_EVICTED` sources
        evicted most (the total is ``counters["evicted"]``)."""
        with self._cv:
            return {f"{prefix}/{s}": n for s, n in self._evicted_by.most_common(TOP_EVICTED)}

    def wait_values(self, prefix: str = "queue_wait_turns_max_from") -> dict[str, float]:
        """``{prefix + "/<source>": turns}``: the largest turns waited (module docstring) of a
        message of that source, for the :data:`TOP_EVICTED` sources with the largest."""
        with self._cv:
            top = sorted(self._wait_max.items(), key=lambda kv: -kv[1])[:TOP_EVICTED]
            return {f"{prefix}/{s}": round(v, 3) for s, v in top}

    # -- under the lock --------------------------------------------------------------------
    def _biggest(self, putter: str) -> str:
        """The source holding the most messages; the putter wins ties (it evicts its own)."""
        mine = len(self._fifos.get(putter, ()))
        best = max(self._fifos, key=lambda s: len(self._fifos[s]))
        return putter if mine and mine >= len(self._fifos[best]) else best

    def _pop(self, source: str) -> T:
        fifo = self._fifos[source]
        item = fifo.popleft()[0]
        self._count -= 1
        if not fifo:
            del self._fifos[source]
            del self._own_taken[source]
            self._turn.remove(source)
        return item
