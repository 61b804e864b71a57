"""The replay's answers to learners: sample replies and priority updates.

* ``replay/sample`` (:class:`~zenrl.common.protocol.SampleRequest` ->
  :class:`~zenrl.common.protocol.SampleReply`): a batch is sampled in proportion to priority when
  the replay is ready for it (:meth:`Sampler.readiness`: at least ``replay.min_size`` items, and
  ``replay.samples_per_insert`` not exceeded); otherwise "not ready" is answered at once with the
  reason, never by waiting.
* ``replay/priorities`` (:class:`~zenrl.common.protocol.PriorityUpdate`): new priorities for
  sampled keys; keys overwritten since are ignored by the storage. Its ``poisoned`` keys (items
  that made the learner's loss or gradient non-finite) are removed from sampling for good
  (:meth:`~zenrl.replay.buffer.InMemoryReplay.remove`) and each is charged to the source that
  sent it (:class:`Origins`) as a ``poison`` rejection, which feeds the quarantine.

Both run on Zenoh's callback threads and take the replay's lock around the storage.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.errors import ProtocolError
from zenrl.common.metrics import RateMeter, RejectCounter

log = logging.getLogger(__name__)


#: the name charged for a poisoned item whose sender is not known (restored from the log, or
#: past the name cap); not a valid actor id, so never an actor's quarantine
UNKNOWN_SOURCE = "(unknown)"


class Origins:
    """Who sent each stored item: per slot (``key % capacity``) the key recorded and an index into
    the sender names (at most ``max_names`` kept; later ones are :data:`UNKNOWN_SOURCE`). The
    ingest records every stored chunk (:meth:`record`, one fancy assignment per chunk); sampling
    looks the senders of poisoned keys up. Callers hold the replay's lock."""

    def __init__(self, max_names: int = 10_000) -> None:
        self.max_names = max_names
        self._key: np.ndarray | None = None
        self._src: np.ndarray | None = None
        self._names: list[str] = []
        self._ids: dict[str, int] = {}

    def record(self, keys: np.ndarray, source: str, capacity: int) -> None:
        """Items ``keys`` int64[K] (stored in a buffer of ``capacity`` slots) came from ``source``."""
        if self._key is None or self._key.shape[0] != capacity:
            self._key = np.full(capacity, -1, np.int64)
            self._src = np.full(capacity, -1, np.int32)
        sid = self._ids.get(source)
        if sid is None:
            sid = -1
            if len(self._names) < self.max_names:
                sid = self._ids[source] = len(self._names)
                self._names.append(source)
        n = keys.shape[0]
        if n == 0:
            return
        s0 = int(keys[0]) % capacity
        if n <= capacity and int(keys[-1]) - int(keys[0]) == n - 1:  # a chunk's keys are consecutive
            n1 = min(n, capacity - s0)
            self._key[s0:s0 + n1], self._src[s0:s0 + n1] = keys[:n1], sid
            if n1 < n:
                self._key[:n - n1], self._src[:n - n1] = keys[n1:], sid
            return
        slots = keys % capacity
        self._key[slots] = keys
        self._src[slots] = sid

    def sources_of(self, keys: np.ndarray) -> list[str]:
        """The sender of each of ``keys`` int64[K] (:data:`UNKNOWN_SOURCE` where not recorded)."""
        if self._key is None:
            return [UNKNOWN_SOURCE] * len(keys)
        slots = keys % self._key.shape[0]
        sid = np.where(self._key[slots] == keys, self._src[slots], -1)
        return [self._names[i] if i >= 0 else UNKNOWN_SOURCE for i in sid.tolist()]


class Sampler:
    """Sampling and priority updates over the storage ``buffer()`` returns (None before the
    first chunk). ``rejects`` counts bad requests with the replay's other rejections;
    ``check_priorities``: refuse priority updates above ``replay.max_priority``. ``origins``:
    who sent each stored item (the ingest records them); ``charge(reason, detail, source)``
    counts a poisoned item against its source (the ingest's ``reject``: by reason, by source,
    quarantine); without them poisoned items are still removed, and counted here only."""

    def __init__(self, rcfg: Any, seed: int, max_bytes: int, lock: threading.Lock, buffer: Callable[[], Any],
                 rejects: RejectCounter, sample_key: str, check_priorities: bool, origins: Origins | None = None,
                 charge: Callable[[str, str, str], None] | None = None) -> None:
        self.rcfg, self.max_bytes, self.lock = rcfg, max_bytes, lock
        self.buffer = buffer
        self.rejects = rejects
        self.sample_key = sample_key
        self.check_priorities = check_priorities
        self.rng = np.random.default_rng(seed + 17)
        self.sampled = RateMeter()
        self.sampled_items = 0
        self.not_ready_replies = 0
        self.origins = origins
        self.charge = charge
        self.poison_removed = 0  #: poisoned items removed from sampling
        self.poison_stale = 0  #: poisoned keys no longer stored (evicted, or removed already)
        self.priority_updates = 0  #: priority update messages taken (decoded and within bounds)
        self.priority_keys = 0  #: keys those updates named

    def readiness(self, batch_size: int) -> str:
        """``""`` if a batch of ``batch_size`` may be sampled now, else the reason why not
        (caller holds the lock)."""
        b = self.buffer()
        size = 0 if b is None else b.size
        if size < max(self.rcfg.min_size, 1):
            return f"min_size {self.rcfg.min_size} > size {size}"
        spi = self.rcfg.samples_per_insert
        if spi is not None:
            allowed = spi * b.inserts_total + self.rcfg.spi_tolerance
            if self.sampled_items + batch_size > allowed:
                return f"samples_per_insert {spi} reached ({self.sampled_items} sampled, {b.inserts_total} inserted)"
        return ""

    def on_sample(self, payload: bytes) -> bytes | bytearray:
        """The queryable's handler: a request's bytes -> the reply's bytes."""
        try:
            req = P.SampleRequest.decode(payload, self.max_bytes)
        except ProtocolError as e:
            self.rejects.reject(e.reason, str(e), self.sample_key)
            return P.SampleReply(request_id=0, status="not_ready", reason=f"bad request: {e}").encode()
        payload = None
        with self.lock:
            rep = self._reply(req, rows=True)
            if rep.data is not None and any(type(v) is P.Rows for v in rep.data.values()):
                # rows of the storage (P.Rows): gathered into the payload while the lock still
                # keeps the ingest from overwriting them
                payload = rep.encode(self.max_bytes)
        if payload is None:  # arrays of its own: encoded without holding up the ingest
            payload = rep.encode(self.max_bytes)
        if rep.status == "ok":
            self.sampled.add(1)
        return payload

    def reply(self, req: P.SampleRequest) -> P.SampleReply:
        """The reply to ``req``, its arrays gathered."""
        with self.lock:
            rep = self._reply(req, rows=False)
        if rep.status == "ok":
            self.sampled.add(1)
        return rep

    def _reply(self, req: P.SampleRequest, rows: bool) -> P.SampleReply:
        """(caller holds the lock) ``rows``: large fields as P.Rows of the storage, to be encoded
        before the lock is let go."""
        why = self.readiness(req.batch_size)
        b = self.buffer()
        size = 0 if b is None else b.size
        # the mass the probabilities are fractions of, in both replies: a learner sampling
        # across shards weighs this shard by it (common/replay_client.py)
        mass = 0.0 if b is None else b.priority_mass
        if why:
            self.not_ready_replies += 1
            return P.SampleReply(request_id=req.request_id, status="not_ready", reason=why, replay_size=size,
                                 mass=mass)
        s = b.sample(req.batch_size, req.beta, self.rng, rows=rows)
        self.sampled_items += req.batch_size
        return P.SampleReply(request_id=req.request_id, status="ok", replay_size=size,
                             keys=s.keys, probabilities=s.probabilities, weights=s.weights, data=s.data, mass=mass)

    def on_priorities(self, key: str, payload: bytes) -> None:
        """The subscriber of ``replay/priorities``."""
        try:
            msg = P.PriorityUpdate.decode(payload, self.max_bytes)
        except ProtocolError as e:
            self.rejects.reject(e.reason, str(e), key)
            return
        if self.check_priorities and msg.priorities.size and float(msg.priorities.max()) > self.rcfg.max_priority:
            self.rejects.reject("priority_bound", f"priority update {float(msg.priorities.max()):.3g} exceeds "
                                f"replay.max_priority {self.rcfg.max_priority:.3g}", key)
            return
        bad = msg.poisoned
        sources: list[str] = []
        with self.lock:
            b = self.buffer()
            if b is not None:
                if bad is not None and bad.size:  # first: a removed item takes no priority after
                    hit = b.remove(bad.astype(np.int64))
                    bad = bad[hit]
                    self.poison_removed += bad.shape[0]
                    self.poison_stale += hit.shape[0] - bad.shape[0]
                    sources = (self.origins.sources_of(bad.astype(np.int64)) if self.origins is not None
                               else [UNKNOWN_SOURCE] * bad.shape[0])
                if msg.keys.size:
                    b.update_priorities(msg.keys.astype(np.int64), msg.priorities.astype(np.float64))
            self.priority_updates += 1
            self.priority_keys += int(msg.keys.size)
        for k, src in zip(bad.tolist() if sources else [], sources):
            detail = f"item {k} made the learner's loss or gradient non-finite; removed from sampling"
            if self.charge is not None:
                self.charge("poison", detail, src)
            else:
                self.rejects.reject("poison", detail, src)

    def stats_values(self) -> dict[str, Any]:
        # read without the lock (its caller may hold it): one float, at worst a moment old
        b = self.buffer()
        mass = 0.0 if b is None else b.priority_mass
        return {"priority_mass": mass, "sample_batches_per_s": self.sampled.rate(), "sample_batches_total": self.sampled.total,
                "not_ready_replies": self.not_ready_replies, "poison_removed": self.poison_removed,
                "poison_stale": self.poison_stale, "priority_updates_total": self.priority_updates,
                "priority_keys_total": self.priority_keys}
