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
import math
import queue
import threading
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping, Union

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
    ``prepared``: what :class:`SamplePrefetcher`'s ``prepare`` made of it (e.g. tensors), if any.
    ``mass``: the replay's priority mass its reply reported (None if it did not)."""

    keys: np.ndarray
    probabilities: np.ndarray
    weights: np.ndarray
    data: dict[str, np.ndarray]
    replay_size: int
    prepared: Any = None
    mass: float | None = None


#: what a sample request ends in: a batch, or why there is none
SampleResult = Union[Sampled, NotReady, RemoteTimeout, ProtocolError]


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
        #: chunks that could not be delivered: backlog overflow, a failed put, or too large
        self.undelivered_chunks = 0
        #: chunks over the size cap sent as two halves (each counted again if split further)
        self.split_chunks = 0
        #: chunks over the size cap that could not be split (frame mode, one item): not sent
        self.oversized_chunks = 0
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
        try:
            payload = msg.encode(self.max_bytes, self.codec)
        except ProtocolError as e:
            if e.reason != "size":
                raise
            self._too_large(batch, priorities, policy_version, frames, e)
            return
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

    def _too_large(self, batch: Mapping[str, np.ndarray], priorities: np.ndarray | None, policy_version: int,
                   frames: Mapping[str, np.ndarray] | None, err: ProtocolError) -> None:
        """A chunk over the cap (the replay's ``replay.max_chunk_bytes``, which it would drop):
        sent as two halves, recursively; a frame-mode chunk (whose items refer to its frames) or a
        single item that is still too large is not sent, counted in ``oversized_chunks`` and
        logged."""
        n = len(next(iter(batch.values())))
        if frames is None and n > 1:
            self.split_chunks += 1
            h = n // 2
            for sl in (slice(0, h), slice(h, n)):
                self.insert({k: v[sl] for k, v in batch.items()}, None if priorities is None else np.asarray(priorities)[sl],
                            policy_version)
            return
        self.oversized_chunks += 1
        self.undelivered_chunks += 1
        if self.oversized_chunks == 1 or self.oversized_chunks % 1000 == 0:
            log.error("actor %s: %d chunk(s) of %d items not sent, too large for the replay (%s); lower actor.chunk_size "
                      "or raise replay.max_chunk_bytes", self.actor_id, self.oversized_chunks, n, err)

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
            raise NotReady(rep.reason, mass=rep.mass, size=rep.replay_size)
        return Sampled(rep.keys, rep.probabilities, rep.weights, rep.data, rep.replay_size, mass=rep.mass)

    def sample(self, batch_size: int, beta: float) -> Sampled:
        """Blocking sample; raises :class:`NotReady` or :class:`RemoteTimeout`."""
        return self.parse_reply(self.node.query(self.keys.sample, self.request_payload(batch_size, beta), self.timeout_s))

    def sample_async(self, batch_size: int, beta: float, on_done: Callable[[SampleResult], None]) -> None:
        """Send a sample request without waiting; ``on_done`` is called once, on a Zenoh thread,
        with the :class:`Sampled` batch or the error (:class:`NotReady`, :class:`RemoteTimeout`,
        :class:`ProtocolError`). Raises only if the request cannot be sent (session closing)."""
        def reply(payload: bytes | None) -> None:
            if payload is None:
                on_done(RemoteTimeout(f"no sample reply on {self.keys.sample} within {self.timeout_s} s"))
                return
            try:
                result: SampleResult = self.parse_reply(payload)
            except (NotReady, ProtocolError) as e:
                result = e
            on_done(result)

        self.node.query_async(self.keys.sample, self.request_payload(batch_size, beta), self.timeout_s, reply)


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

    def __init__(self, client: "ZenohReplayClient | ShardedReplayClient", batch_size: int, beta_fn, in_flight: int = 4,
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

    def stop(self, timeout: float = 5.0) -> None:
        """Stop issuing requests; wait at most ``timeout`` s for the retry thread."""
        self._stop.set()
        self._retry_due.set()
        if self._thread is not None:
            self._thread.join(timeout=max(0.0, timeout))

    def _issue(self) -> None:
        if self._stop.is_set():
            return
        try:
            self.client.sample_async(self.batch_size * self.per_request, self.beta_fn(), self._on_result)
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

    def _on_result(self, s: SampleResult) -> None:
        # Runs on a Zenoh thread (or the issuing one): never block here, never call into Zenoh.
        if isinstance(s, RemoteTimeout):
            self.timeouts += 1
            self._failed()
            return
        if isinstance(s, NotReady):
            self.not_ready += 1
            self.last_not_ready_reason = str(s)
            self._failed()
            return
        if isinstance(s, Exception):
            self.errors += 1
            log.warning("bad sample reply: %s", s)
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
        self.last_not_ready_reason = ""  # served again: a reason from before would mislead
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


@dataclass
class ShardState:
    """What the learner knows of one replay shard: its priority ``mass`` and ``size`` from its
    latest reply (either kind), whether it is ``up`` (its latest reply was ok), when it was last
    heard from and when it is probed next; and counters."""

    mass: float = 0.0
    size: int = 0
    up: bool = False
    heard_at: float = -math.inf
    probe_at: float = 0.0
    probing: bool = False
    reason: str = "not heard from yet"
    items: int = 0  #: items of this shard in batches handed out
    failed: int = 0  #: parts answered not ready, timed out or malformed (each drops its batch)
    probes: int = 0
    priority_keys: int = 0  #: keys whose priorities were sent back to it


class ShardedReplayClient:
    """The learner's client of a sharded replay (``replay.shards`` = N > 1): samples across the
    shards so that a batch is distributed as one replay holding every shard's items would draw it.

    Per batch of B: the per-shard counts are drawn ``c ~ Multinomial(B, q)``, with ``q_k = S_k /
    sum_j S_j`` over the shards that are up (``S_k``: shard k's priority mass from its latest
    reply, :attr:`~zenrl.common.protocol.SampleReply.mass`), and shard k is asked for ``c_k`` items,
    all concurrently. An item's probability is then rescaled to the global one, ``P(i) =
    P_k(i) * q_k``, i.e. ``(p_i + eps)^alpha / sum_j S_j`` (its expected count is ``B * q_k *
    P_k(i)``, as in one replay), and the IS weights are ``(N P(i))^-beta`` normalised by their max
    over the whole batch (``N`` = the shards' total size; it cancels in the normalisation), as
    :meth:`~zenrl.replay.buffer.InMemoryReplay.sample` does within one replay.

    Keys: shard k's key ``x`` is handed out as ``x * N + k``, so a batch's keys stay distinct
    and :meth:`update_priorities` sends each priority (and poisoned key) back to the shard its
    item came from, as that shard's key.

    A shard that answers not ready (empty, below ``replay.min_size``, rate limited), times out
    or answers garbage is marked down and counted (:class:`ShardState`); the batch it was part of
    is dropped (``on_done`` gets the error, the prefetcher retries after its backoff) and later
    batches are drawn from the other shards alone. A shard not up is probed every
    ``probe_s`` (a 1-item request), and one up but not heard from for ``refresh_s`` too (its
    mass would go stale while it draws no items): a probe's reply brings it back. With no
    shard up, a request fails at once with :class:`NotReady` naming each shard's reason.
    Probes are sent from the requesting thread (never from a Zenoh callback)."""

    def __init__(self, node: Node, run_id: str, shards: int, client_id: str = "client", timeout_s: float = 5.0,
                 max_message_bytes: int = P.DEFAULT_MAX_MESSAGE_BYTES, seed: int | None = None,
                 probe_s: float = 0.25, refresh_s: float = 1.0) -> None:
        if not 2 <= shards <= P.MAX_REPLAY_SHARDS:
            raise ValueError(f"shards={shards}: a sharded replay has 2..{P.MAX_REPLAY_SHARDS} shards")
        self.node = node
        self.n = shards
        self.timeout_s = timeout_s
        self.clients = [ZenohReplayClient(node, P.Keys(run_id, k), client_id, timeout_s, max_message_bytes)
                        for k in range(shards)]
        self.state = [ShardState() for _ in range(shards)]
        self.probe_s, self.refresh_s = probe_s, refresh_s
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._heard = threading.Condition(self._lock)
        #: batches dropped because one of their parts failed, and the items they held
        self.dropped_batches = 0
        self.dropped_items = 0

    # -- sampling ----------------------------------------------------------------------------
    def draw(self, batch_size: int) -> tuple[list[int], np.ndarray, np.ndarray] | str:
        """The shards up, their share ``q`` (float64[U]) and item counts (int64[U], summing to
        ``batch_size``) for one batch; or why no shard can serve."""
        with self._lock:
            up = [k for k, st in enumerate(self.state) if st.up and st.mass > 0.0]
            if not up:
                return "no replay shard ready: " + "; ".join(f"shard {k}: {st.reason}" for k, st in enumerate(self.state))
            mass = np.array([self.state[k].mass for k in up], np.float64)
            q = mass / mass.sum()
            counts = self._rng.multinomial(batch_size, q)
        return up, q, counts

    def sample_async(self, batch_size: int, beta: float, on_done: Callable[[SampleResult], None]) -> None:
        """As :meth:`ZenohReplayClient.sample_async`, across the shards (see the class)."""
        self._probe_due()
        d = self.draw(batch_size)
        if isinstance(d, str):
            on_done(NotReady(d))
            return
        up, q, counts = d
        parts = [(k, float(qk), int(c)) for k, qk, c in zip(up, q, counts) if c]
        g = _Gather(self, parts, beta, on_done)
        for k, _, c in parts:
            try:
                self.clients[k].sample_async(c, beta, lambda r, k=k: g.part(k, r))
            except Exception as e:  # zenoh.ZError (session closing): this part fails, the batch with it
                g.part(k, RemoteTimeout(f"could not ask replay shard {k}: {e}"))

    def sample(self, batch_size: int, beta: float) -> Sampled:
        """Blocking sample (probes every shard first if none is known to be up); raises
        :class:`NotReady`, :class:`RemoteTimeout` or :class:`ProtocolError`."""
        if not any(st.up for st in self.state):
            self.refresh()
        done = threading.Event()
        out: list[SampleResult] = []
        self.sample_async(batch_size, beta, lambda r: (out.append(r), done.set()))
        if not done.wait(self.timeout_s + 1.0):
            raise RemoteTimeout(f"no sample from the replay shards within {self.timeout_s} s")
        if isinstance(out[0], Exception):
            raise out[0]
        return out[0]

    def refresh(self, timeout_s: float | None = None) -> None:
        """Probe now every shard that is down or not heard from for ``refresh_s``, and wait (up
        to ``timeout_s``, default the query timeout) for their answers."""
        with self._lock:
            for st in self.state:
                st.probe_at = 0.0
        self._probe_due(force=True)
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        with self._heard:
            while any(st.probing for st in self.state):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._heard.wait(left)

    def _probe_due(self, force: bool = False) -> None:
        now = time.monotonic()
        due = []
        with self._lock:
            for k, st in enumerate(self.state):
                stale = not st.up or now - st.heard_at >= self.refresh_s
                if not st.probing and stale and (force or now >= st.probe_at):
                    st.probing, st.probe_at = True, now + self.probe_s
                    st.probes += 1
                    due.append(k)
        for k in due:
            try:
                self.clients[k].sample_async(1, 0.0, lambda r, k=k: self._probed(k, r))
            except Exception as e:  # session closing: counted as the probe's failure
                self._probed(k, RemoteTimeout(f"could not probe replay shard {k}: {e}"))

    def _probed(self, k: int, r: SampleResult) -> None:
        self.heard(k, r)
        with self._heard:
            self.state[k].probing = False
            self._heard.notify_all()

    def heard(self, k: int, r: SampleResult) -> None:
        """Record shard ``k``'s answer: up with the mass and size an ok reply reported, or down
        with the reason (an error; a not-ready reply's mass and size are kept)."""
        with self._lock:
            st = self.state[k]
            if isinstance(r, Sampled) and r.mass is None:
                st.up, st.reason = False, "its replies carry no priority mass (a replay older than sharding)"
            elif isinstance(r, Sampled):
                st.up, st.reason, st.heard_at = True, "ok", time.monotonic()
                st.mass, st.size = float(r.mass), int(r.replay_size)
            else:
                st.up, st.reason = False, f"{type(r).__name__}: {r}"
                if isinstance(r, NotReady):
                    st.heard_at = time.monotonic()
                    if r.mass is not None:
                        st.mass, st.size = r.mass, r.size

    def combine(self, parts: list[tuple[int, float, Sampled]], beta: float) -> Sampled:
        """One batch of the shards' ``parts`` ``(shard, q_k, its sample)``: keys as ``key * N +
        shard``, probabilities global (``P_k(i) * q_k``), IS weights over the whole batch."""
        n = self.n
        fields = parts[0][2].data.keys()
        for k, _, s in parts:
            if s.data.keys() != fields:
                raise ProtocolError("data", f"replay shard {k} sent fields {sorted(s.data)}, another "
                                    f"{sorted(fields)}: the shards disagree on the item spec", "field")
            if s.keys.size and (int(s.keys.min()) < 0 or int(s.keys.max()) > (P.INT64_MAX - k) // n):
                raise ProtocolError("keys", f"replay shard {k} sent keys outside 0..{P.INT64_MAX // n}", "field")
        keys = np.concatenate([s.keys.astype(np.int64) * n + k for k, _, s in parts])
        probs = np.concatenate([s.probabilities.astype(np.float64) * qk for _, qk, s in parts])
        if beta == 0.0 or not probs.size:
            weights = np.ones(probs.shape[0], np.float32)
        else:
            # (N P_i)^-beta / max_j (N P_j)^-beta = (min_j P_j / P_i)^beta, as within one replay
            with np.errstate(divide="ignore", invalid="ignore"):
                weights = np.power(probs.min() / probs, beta)
            if not np.isfinite(weights).all():
                raise ProtocolError("probabilities", "a replay shard sent a probability of 0 or a non-finite one",
                                    "nonfinite")
            weights = weights.astype(np.float32)
        try:
            data = {f: np.concatenate([s.data[f] for _, _, s in parts]) for f in fields}
        except ValueError as e:  # shapes or dtypes that do not stack
            raise ProtocolError("data", f"the replay shards' items do not stack: {e}", "shape") from None
        with self._lock:
            size = sum(st.size for st in self.state if st.up)
            for k, _, s in parts:
                self.state[k].items += len(s.keys)
        return Sampled(keys, probs, weights, data, size)

    # -- priorities --------------------------------------------------------------------------
    def shard_of(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global keys int64[K] -> (shard int64[K], the shard's key int64[K])."""
        k = np.asarray(keys, np.int64)
        return k % self.n, k // self.n

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray, poisoned: np.ndarray | None = None) -> None:
        """Send each priority (keys int64[B] as handed out, priorities float32[B]) and poisoned
        key (int64[P] or None) back to the shard its item came from, one message per shard
        concerned."""
        shard, local = self.shard_of(keys)
        prio = np.asarray(priorities, np.float32)
        bad_shard, bad_local = (self.shard_of(poisoned) if poisoned is not None
                                else (np.zeros(0, np.int64), np.zeros(0, np.int64)))
        for k in np.union1d(np.unique(shard), np.unique(bad_shard)).tolist():
            sel, bsel = shard == k, bad_shard == k
            self.clients[k].update_priorities(local[sel], prio[sel], bad_local[bsel] if bsel.any() else None)
            with self._lock:
                self.state[k].priority_keys += int(sel.sum())

    # -- stats -------------------------------------------------------------------------------
    def values(self) -> dict[str, Any]:
        """The learner's stats of the shards: ``replay_shards_up``, dropped batches, and per
        shard k ``replay<k>_mass``, ``_size``, ``_up``, ``_items``, ``_failed``, ``_priority_keys``."""
        with self._lock:
            v: dict[str, Any] = {"replay_shards_up": sum(st.up for st in self.state),
                                 "replay_dropped_batches": self.dropped_batches,
                                 "replay_dropped_items": self.dropped_items}
            for k, st in enumerate(self.state):
                v.update({f"replay{k}_mass": st.mass, f"replay{k}_size": st.size, f"replay{k}_up": int(st.up),
                          f"replay{k}_items": st.items, f"replay{k}_failed": st.failed,
                          f"replay{k}_priority_keys": st.priority_keys})
        return v


class _Gather:
    """One sharded batch being assembled: the parts' answers arrive on Zenoh threads; the last
    one combines them and calls ``on_done`` (once)."""

    def __init__(self, client: ShardedReplayClient, parts: list[tuple[int, float, int]], beta: float,
                 on_done: Callable[[SampleResult], None]) -> None:
        self.client, self.beta, self.on_done = client, beta, on_done
        self.want = {k: (qk, c) for k, qk, c in parts}
        self.got: dict[int, SampleResult] = {}
        self.lock = threading.Lock()

    def part(self, k: int, r: SampleResult) -> None:
        c = self.client
        if isinstance(r, Sampled) and len(r.keys) != self.want[k][1]:
            r = ProtocolError("keys", f"replay shard {k} sent {len(r.keys)} items, {self.want[k][1]} asked", "batch")
        c.heard(k, r)
        with self.lock:
            self.got[k] = r
            if len(self.got) < len(self.want):
                return
        failed = [(k, r) for k, r in sorted(self.got.items()) if not isinstance(r, Sampled)]
        if failed:
            with c._lock:
                for k, _ in failed:
                    c.state[k].failed += 1
                c.dropped_batches += 1
                c.dropped_items += sum(len(r.keys) for r in self.got.values() if isinstance(r, Sampled))
            k, err = failed[0]
            # the prefetcher counts a timeout, a not-ready or a bad reply, and retries the batch
            # (drawn from the shards still up)
            out: SampleResult = (NotReady(f"replay shard {k}: {err}") if isinstance(err, NotReady)
                                 else RemoteTimeout(f"replay shard {k}: {err}") if isinstance(err, RemoteTimeout)
                                 else err)
            self.on_done(out)
            return
        try:
            out = c.combine([(k, self.want[k][0], self.got[k]) for k in sorted(self.got)], self.beta)  # type: ignore[misc]
        except ProtocolError as e:
            with c._lock:
                c.dropped_batches += 1
            out = e
        self.on_done(out)


def replay_client_for(node: Node, run_id: str, shards: int, client_id: str, timeout_s: float,
                      max_message_bytes: int, seed: int | None = None) -> "ZenohReplayClient | ShardedReplayClient":
    """The learner's replay client: one replay (``shards`` = 1, the unsharded keys) or several."""
    if shards == 1:
        return ZenohReplayClient(node, P.Keys(run_id), client_id, timeout_s, max_message_bytes)
    return ShardedReplayClient(node, run_id, shards, client_id, timeout_s, max_message_bytes, seed)


__all__ = ["Sampled", "ZenohReplayClient", "ShardedReplayClient", "SamplePrefetcher", "RemoteTimeout", "NotReady",
           "replay_client_for"]
