"""The client actors and the learner use to talk to the replay service over Zenoh.

It has the verbs of the in-memory replay (``insert``, ``sample``, ``update_priorities``) so the
same contract tests run against both, plus :class:`SamplePrefetcher`, which keeps several sample
requests in flight from a background thread so that a training step never waits on the network
when data is available.
"""

from __future__ import annotations

import collections
import itertools
import logging
import queue
import threading
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.errors import NotReady, ProtocolError, RemoteTimeout
from zenrl.common.roles import Supervisor
from zenrl.common.transport import Node

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sampled:
    """A sampled batch. keys int64[B], probabilities float64[B], weights float32[B] (IS weights
    normalised by their max), data ``{name: array[B, ...]}``; ``replay_size`` at sampling time.
    ``prepared``: what :class:`SamplePrefetcher`'s ``prepare`` made of it (e.g. tensors), if any."""

    keys: np.ndarray
    probabilities: np.ndarray
    weights: np.ndarray
    data: dict[str, np.ndarray]
    replay_size: int
    prepared: Any = None


class ZenohReplayClient:
    """Networked replay: ``insert`` publishes a :class:`TransitionBatch` (BLOCK), ``sample``
    queries ``replay/sample``, ``update_priorities`` publishes a :class:`PriorityUpdate`."""

    def __init__(self, node: Node, keys: P.Keys, actor_id: str = "client", timeout_s: float = 5.0,
                 max_message_bytes: int = P.DEFAULT_MAX_MESSAGE_BYTES, backlog_chunks: int = 512,
                 codec: str | None = None) -> None:
        self.node = node
        #: "lz4": inserted chunks carry their uint8 arrays compressed (see docs/protocol.md)
        self.codec = codec
        self.keys = keys
        self.actor_id = P.check_name("actor_id", actor_id)
        self.timeout_s = timeout_s
        self.max_bytes = max_message_bytes
        self._tx = None
        self._prio = None
        self._seq = itertools.count()
        self._req = itertools.count(1)
        self.sent_chunks = 0
        self.failed_chunks = 0
        #: chunks held while no replay subscribes (replay or router restarting), resent later
        self._backlog: collections.deque[bytes] = collections.deque()
        self.backlog_limit = backlog_chunks
        #: chunks that could not be delivered: backlog overflow or a failed put
        self.undelivered_chunks = 0
        #: how long a new publisher waits for the replay's subscription to become visible
        self.match_wait_s = min(1.0, timeout_s)

    def insert(self, batch: Mapping[str, np.ndarray], priorities: np.ndarray | None = None,
               policy_version: int = -1, frames: Mapping[str, np.ndarray] | None = None,
               frame_base: int | None = None) -> None:
        """Publish one chunk (``frames``/``frame_base``: frame mode, see
        :class:`~zenrl.common.protocol.TransitionBatch`). Raises ProtocolError if it would
        exceed the size cap."""
        if self._tx is None:
            self._tx = self.node.publisher(self.keys.transitions(self.actor_id))
            # a new publisher learns of existing subscribers only after a round trip to the
            # router: wait for that (bounded) so the first chunks are not held back needlessly
            self._wait_matching(self.match_wait_s)
        msg = P.TransitionBatch(actor_id=self.actor_id, policy_version=int(policy_version), seq=next(self._seq),
                                data=dict(batch), priorities=None if priorities is None else np.asarray(priorities, np.float32),
                                frames=None if frames is None else dict(frames), frame_base=frame_base)
        payload = msg.encode(self.max_bytes, self.codec)
        if not self._tx.matching_status.matching:
            # nobody would receive it (replay down, or the router restarting): hold it
            self._backlog.append(payload)
            while len(self._backlog) > self.backlog_limit:
                self._backlog.popleft()
                self.undelivered_chunks += 1
            return
        while self._backlog:
            self._put(self._backlog.popleft())
        self._put(payload)

    def _put(self, payload: bytes) -> None:
        try:
            self._tx.put(payload)
            self.sent_chunks += 1
        except Exception as e:  # zenoh.ZError when the session is gone; counted, not silent
            self.failed_chunks += 1
            self.undelivered_chunks += 1
            log.warning("could not publish a chunk: %s", e)

    def _wait_matching(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not self._tx.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def flush_backlog(self, timeout_s: float = 2.0) -> int:
        """Send held chunks once a replay is reachable, waiting up to ``timeout_s`` for one
        (called before an actor stops); returns the chunks still held (then undelivered)."""
        if self._tx is not None and self._backlog and self._wait_matching(timeout_s):
            while self._backlog:
                self._put(self._backlog.popleft())
        return len(self._backlog)

    @property
    def backlog(self) -> int:
        return len(self._backlog)

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray, poisoned: np.ndarray | None = None) -> None:
        """Publish new priorities (keys int64[B], priorities float32[B]) and the keys of items
        found poisonous (int64[P] or None: the replay stops sampling them, see
        :class:`~zenrl.common.protocol.PriorityUpdate`) as one message: the one way priorities
        reach the replay (the learner calls it from its sender's thread, with the priorities of
        several batches merged)."""
        if self._prio is None:
            self._prio = self.node.publisher(self.keys.priorities)
        bad = np.zeros(0, np.int64) if poisoned is None else np.asarray(poisoned, np.int64)
        k, p = np.asarray(keys, np.int64), np.asarray(priorities, np.float32)
        for i in range(0, max(1, bad.shape[0]), P.MAX_SAMPLE_BATCH):  # the message's cap on poisoned keys
            part = bad[i:i + P.MAX_SAMPLE_BATCH]
            self._prio.put(P.PriorityUpdate(keys=k, priorities=p, poisoned=part if part.size else None).encode(self.max_bytes))
            k, p = k[:0], p[:0]

    def request_payload(self, batch_size: int, beta: float) -> bytes:
        return P.SampleRequest(request_id=next(self._req), batch_size=int(batch_size), beta=float(beta)).encode()

    def parse_reply(self, payload: bytes) -> Sampled:
        """Decode a sample reply; raise :class:`NotReady` for a not-ready answer."""
        rep = P.SampleReply.decode(payload, self.max_bytes)
        if rep.status != "ok":
            raise NotReady(rep.reason)
        return Sampled(rep.keys, rep.probabilities, rep.weights, rep.data, rep.replay_size)

    def sample(self, batch_size: int, beta: float) -> Sampled:
        """Blocking sample; raises :class:`NotReady` or :class:`RemoteTimeout`."""
        return self.parse_reply(self.node.query(self.keys.sample, self.request_payload(batch_size, beta), self.timeout_s))


class SamplePrefetcher:
    """Keeps ``in_flight`` sample requests outstanding and queues ready batches.

    ``get(timeout)`` returns a :class:`Sampled` or ``None``; taking a batch issues the request
    that replaces it, from the consumer's thread (a Zenoh call: 50 us alone, ~0.2 ms in a busy
    learner, measured with py-spy), so no
    thread wakes per batch on the learner's side but Zenoh's own. A not-ready reply, a timeout
    or a bad reply re-issues that request after ``backoff_s`` from a helper thread that sleeps
    otherwise (the replay answers not-ready at once, so this never hangs). ``beta`` is read at
    request time from ``beta_fn()``.

    ``prepare(sampled)``, if given, runs when a reply arrives (off the consumer's thread) and its
    result is the batch's ``prepared`` field: the learner turns the arrays into tensors there, so
    a training step starts on a batch that is ready to use. A reply it raises on is counted in
    ``errors`` and dropped.

    ``batches_per_request`` = k > 1 asks for k * ``batch_size`` items per request and splits
    the reply into k batches of ``batch_size`` (rows dealt out by a random permutation, so each
    batch is an unbiased draw from the stratified sample); a replacement request goes out once
    per k batches taken, so the consumer pays the Zenoh call once per k training steps. The
    price: a batch's items were drawn up to k * ``in_flight`` batches before it is used, with
    the priorities of that time.

    The helper thread is a watched one (:meth:`~zenrl.common.roles.Supervisor.thread` of the
    ``sup`` given to :meth:`start`, the role's supervisor): an exception in one retry round is
    counted and logged there and the next round runs; if the thread dies the role fails
    (:class:`~zenrl.common.roles.RoleFailed`), and retries waiting with no round finished are
    reported as ``stalled``.
    """

    #: how long one round of the helper thread waits for a retry to be due (its idle heartbeat)
    IDLE_WAIT_S = 0.5

    def __init__(self, client: ZenohReplayClient, batch_size: int, beta_fn, in_flight: int = 4,
                 prepare: Callable[[Sampled], Any] | None = None, backoff_s: float = 0.05,
                 batches_per_request: int = 1, seed: int | None = None) -> None:
        if batches_per_request < 1 or batch_size * batches_per_request > P.MAX_SAMPLE_BATCH:
            raise ValueError(f"batches_per_request={batches_per_request} with batch_size={batch_size}: "
                             f"need >= 1 and at most {P.MAX_SAMPLE_BATCH} items per request")
        self.client = client
        self.prepare = prepare
        self.batch_size = batch_size
        self.beta_fn = beta_fn
        self.in_flight = in_flight
        self.backoff_s = backoff_s
        self.per_request = batches_per_request
        self._perm_rng = np.random.default_rng(seed)
        self._taken = 0  # batches taken since the last replacement request (consumer's thread only)
        # requests in flight + waiting for a retry + those whose batches are ready or partly taken
        # == in_flight at all times
        self._ready: queue.Queue[Sampled] = queue.Queue()
        self._retry = 0
        self._lock = threading.Lock()
        self._retry_due = threading.Event()
        self._stop = threading.Event()
        self._thread: Any = None
        self.not_ready = 0
        self.timeouts = 0
        self.errors = 0
        self.last_not_ready_reason = ""

    def start(self, sup: Supervisor | None = None) -> "SamplePrefetcher":
        """Start the helper thread under ``sup`` (a private supervisor if None) and issue the
        first ``in_flight`` requests."""
        sup = sup if sup is not None else Supervisor()
        self._thread = sup.thread("sample-retry", self._retry_round, self._stop, pending=lambda: self._retry)
        for _ in range(self.in_flight):
            self._issue()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._retry_due.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _issue(self) -> None:
        if self._stop.is_set():
            return
        try:
            self.client.node.query_async(self.client.keys.sample,
                                         self.client.request_payload(self.batch_size * self.per_request, self.beta_fn()),
                                         self.client.timeout_s, self._on_reply)
        except Exception as e:  # zenoh.ZError (session closing): counted, retried after the backoff
            self.errors += 1
            log.warning("could not send a sample request: %s", e)
            self._failed()

    def _failed(self) -> None:
        with self._lock:
            self._retry += 1
        self._retry_due.set()

    def _retry_round(self) -> None:
        """One round of the helper thread: once a retry is due, wait ``backoff_s`` and re-issue
        every request waiting for a retry."""
        if not self._retry_due.wait(self.IDLE_WAIT_S):
            return
        if self._stop.wait(self.backoff_s):
            return
        self._retry_due.clear()
        with self._lock:
            n, self._retry = self._retry, 0
        for _ in range(n):
            self._issue()

    def _on_reply(self, payload: bytes | None) -> None:
        # Runs on a Zenoh thread: never block here, never call into Zenoh.
        if payload is None:
            self.timeouts += 1
            self._failed()
            return
        try:
            s = self.client.parse_reply(payload)
        except NotReady as e:
            self.not_ready += 1
            self.last_not_ready_reason = str(e)
            self._failed()
            return
        except ProtocolError as e:
            self.errors += 1
            log.warning("bad sample reply: %s", e)
            self._failed()
            return
        try:
            parts = self._split(s)
            if self.prepare is not None:
                parts = [replace(part, prepared=self.prepare(part)) for part in parts]
        except Exception as e:  # a batch the learner cannot use: counted, the rest go on
            self.errors += 1
            log.warning("could not prepare a sampled batch: %s", e)
            self._failed()
            return
        for part in parts:
            self._ready.put_nowait(part)

    def _split(self, s: Sampled) -> list[Sampled]:
        k, b = self.per_request, self.batch_size
        if k == 1:
            return [s]
        if len(s.keys) != k * b:
            raise ProtocolError("keys", f"{len(s.keys)} items in a reply to a request for {k * b}", "shape")
        rows = self._perm_rng.permutation(k * b).reshape(k, b)
        return [Sampled(s.keys[r], s.probabilities[r], s.weights[r], {n: a[r] for n, a in s.data.items()}, s.replay_size)
                for r in rows]

    def get(self, timeout_s: float = 1.0) -> Sampled | None:
        """The next ready batch, or ``None`` after ``timeout_s``."""
        try:
            s = self._ready.get(timeout=timeout_s)
        except queue.Empty:
            return None
        self._taken += 1
        if self._taken == self.per_request:
            self._taken = 0
            self._issue()
        return s


__all__ = ["Sampled", "ZenohReplayClient", "SamplePrefetcher", "RemoteTimeout", "NotReady"]
