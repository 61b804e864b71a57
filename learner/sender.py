"""The learner's outgoing traffic off the training thread: priorities merged per wake-up and
weights broadcasts, put from a thread of its own that the role's supervisor watches."""

from __future__ import annotations

import collections
import logging
import threading
from typing import Any, Callable

import numpy as np

from zenrl.common.roles import Supervisor

log = logging.getLogger(__name__)

#: how long a learner's close waits for its helper threads in all: the launcher kills a process
#: 5 s after SIGTERM, and the save before the close and the session's close need their share
CLOSE_BUDGET_S = 3.0


class BackgroundSender:
    """Puts payloads from a thread of its own so the training step never waits on the network.

    ``send`` queues bytes for a publisher; ``send_priorities`` queues one batch's new priorities
    for ``update(keys, priorities)`` (the replay client's
    :meth:`~zenrl.common.replay_client.ZenohReplayClient.update_priorities`, the one way
    priorities are sent), and the priorities queued since the last wake-up go out in one call
    (concatenated in order, so for a key sampled twice the later value wins, as the replay
    applies them). With
    ``linger_s`` > 0 the thread waits that long after the first item before it sends, so it
    wakes once per few training steps instead of once per step (each wake-up of another thread
    costs the training thread a GIL hand-off). Over ``max_items`` queued, items are dropped and
    counted in ``dropped``; a failed put or encoding is counted in ``failed``, the other items of
    that wake-up are still sent.

    The thread is a watched one (:meth:`~zenrl.common.roles.Supervisor.thread` of ``sup``, the
    role's supervisor; a private one if None): a wake-up with a failed put raises its first
    error after sending the rest, so the supervisor counts it by type (``errors/<Type>``), logs
    it rate-limited and runs the next wake-up; a sender whose every wake-up fails for the
    supervisor's ``give_up_s``, or whose thread dies, fails the role
    (:class:`~zenrl.common.roles.RoleFailed` from ``sup.check()``).
    """

    #: how long one unit of the thread waits for the first item (its heartbeat when idle)
    IDLE_WAIT_S = 0.5

    def __init__(self, max_items: int = 256, linger_s: float = 0.0, sup: Supervisor | None = None) -> None:
        self.max_items = max_items
        self.linger_s = linger_s
        self._items: collections.deque[tuple[Any, Any]] = collections.deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.dropped = 0
        self.failed = 0
        self.sent = 0
        self.sup = sup if sup is not None else Supervisor()
        self._t = self.sup.thread("sender", self._unit, self._stop, pending=lambda: len(self._items), drain=self._drain)

    def _queue(self, publisher: Any, item: Any) -> None:
        if len(self._items) >= self.max_items:
            self.dropped += 1
            return
        self._items.append((publisher, item))
        if not self._wake.is_set():
            self._wake.set()

    def send(self, publisher: Any, payload: bytes) -> None:
        self._queue(publisher, payload)

    def send_priorities(self, update: Callable[..., Any], keys: np.ndarray, priorities: np.ndarray,
                        poisoned: np.ndarray | None = None) -> None:
        """keys int64[B], priorities float32[B] (held by reference: do not modify them), for
        ``update(keys, priorities)`` on the sender's thread; ``poisoned`` int64[P]: keys the
        learner found poisonous, then sent as ``update(keys, priorities, poisoned)``."""
        self._queue(update, (keys, priorities, poisoned))

    def _unit(self) -> None:
        """One wake-up: wait for the first item, linger, send everything queued."""
        if not self._wake.wait(self.IDLE_WAIT_S):
            return
        if self.linger_s > 0:
            self._stop.wait(self.linger_s)  # cut short by close(): the drain sends the rest
        self._wake.clear()
        self._drain()

    def _drain(self) -> None:
        items = []
        while self._items:
            items.append(self._items.popleft())
        self._flush(items)

    def _flush(self, items: list[tuple[Any, Any]]) -> None:
        # priorities for one target become one call, made where their first part was queued
        # (bound methods of one object compare equal: the dict merges them)
        merged: dict[Any, tuple[list, list]] = {}
        out: list[tuple[Any, Any]] = []
        for target, item in items:
            if isinstance(item, bytes):
                out.append((target, item))
                continue
            parts = merged.get(target)
            if parts is None:
                parts = merged[target] = ([], [], [])
                out.append((target, parts))
            parts[0].append(item[0])
            parts[1].append(item[1])
            if item[2] is not None and len(item[2]):
                parts[2].append(item[2])
        first_error: Exception | None = None
        for target, item in out:
            try:
                if isinstance(item, bytes):
                    target.put(item)
                elif item[2]:
                    target(np.concatenate(item[0]), np.concatenate(item[1]), np.concatenate(item[2]))
                else:
                    target(np.concatenate(item[0]), np.concatenate(item[1]))
                self.sent += 1
            except Exception as e:  # zenoh.ZError if the session closed, an encoding error: send the rest
                self.failed += 1
                first_error = first_error or e
        if first_error is not None:
            raise first_error  # counted and logged by the supervisor; the next wake-up runs

    def close(self, timeout: float = CLOSE_BUDGET_S) -> bool:
        """Send what is queued, then stop the thread; wait at most ``timeout`` s for it. False
        if it is still sending then (a daemon thread: it does not hold the process's exit)."""
        self._stop.set()
        self._wake.set()
        self._t.join(timeout=max(0.0, timeout))
        if self._t.is_alive():
            log.warning("the learner's sender was still sending after %.1f s; leaving it", timeout)
            return False
        return True
