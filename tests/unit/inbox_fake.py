"""An in-memory stand-in for :class:`zenrl.common.transport.Inbox` (unit tests only): a bounded
FIFO that the test fills as Zenoh's receive thread would (:meth:`FakeInbox.put` waits while it is
full), and that the replay's ingest thread pulls from."""

from __future__ import annotations

import queue
import threading


class FakeReceived:
    """:class:`zenrl.common.transport.Received` of a payload already in memory; counts copies."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key = key
        self._payload = payload
        self.copied = 0

    @property
    def nbytes(self) -> int:
        return len(self._payload)

    def data(self) -> bytes:
        self.copied += 1
        return self._payload


class FakeInbox:
    def __init__(self, key: str, capacity: int) -> None:
        self.subscription = key
        self.capacity = capacity
        self._q: queue.Queue[FakeReceived] = queue.Queue(maxsize=capacity)
        self._closed = threading.Event()
        self.received: list[FakeReceived] = []

    def put(self, key: str, payload: bytes, timeout: float | None = 10.0) -> FakeReceived:
        """What Zenoh's receive thread does with a sample: wait for room (``queue.Full`` after
        ``timeout``), then queue it."""
        r = FakeReceived(key, payload)
        self._q.put(r, timeout=timeout)
        self.received.append(r)
        return r

    def close(self) -> None:
        self._closed.set()

    def get(self) -> FakeReceived | None:
        while True:
            try:
                return self._q.get(timeout=0.01)
            except queue.Empty:
                if self._closed.is_set():
                    return None

    def get_nowait(self) -> FakeReceived | None:
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None

    def qsize(self) -> int:
        return self._q.qsize()
