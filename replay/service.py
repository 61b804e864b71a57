"""The replay service (``zenrl replay``): a prioritized replay behind Zenoh.

Keys (see :class:`zenrl.common.protocol.Keys`):

* subscribes ``transitions/*`` (:class:`TransitionBatch`): the Zenoh callback only enqueues the
  raw bytes into a bounded queue (never stalling the sender past Zenoh's 5 s BLOCK fuse: a chunk
  that cannot be queued within ``replay.drop_after_s`` is dropped and counted); one ingest
  thread decodes, validates and inserts;
* answers ``replay/sample`` (:class:`SampleRequest` -> :class:`SampleReply`); "not ready" (too
  few items, or the samples-per-insert limit) is answered at once, never by waiting;
* subscribes ``replay/priorities`` (:class:`PriorityUpdate`); updates for overwritten keys are
  ignored by the buffer;
* publishes :class:`Stats` on ``stats/replay/<id>`` every ``replay.stats_interval_s``;
* declares the liveliness token ``alive/replay/<id>``.

The storage is allocated from the spec of the first valid batch (or restored from disk); every
later batch must match it. Bad input on any key is rejected, counted by reason and logged
without flooding; the service keeps serving everyone else. With ``replay.check_semantics``
(default) chunks are also checked against the run's env spec (:mod:`zenrl.replay.checks`:
actions, ``n``, observation dtypes and bounds, reward and priority bounds) and rejections are
counted by source too; a source that keeps failing is quarantined (its chunks dropped unread in
the callback, a ``quarantine/<actor>`` liveliness token held, both refreshed with the stats).

On stop: the transitions subscriber is undeclared and the callback returns at once, the ingest
thread inserts what was queued, then the durable log is flushed and the final snapshot written;
the caller closes the session.
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.errors import ProtocolError, SpecMismatch
from zenrl.common.metrics import RateMeter, RejectCounter
from zenrl.common.specs import spec_of_batch
from zenrl.common.transport import Node
from zenrl.replay.buffer import InMemoryReplay
from zenrl.replay.checks import ChunkChecker, Quarantine
from zenrl.replay.durable import ReplayLog
from zenrl.replay.frames import FrameChunk, FrameReplay

log = logging.getLogger(__name__)

#: Sources listed by name in the stats' per-source rejection counts (the most rejected first).
TOP_SOURCES = 20

#: Column the service adds to every item: the weight version the actor acted with (policy lag).
POLICY_VERSION_FIELD = "meta/policy_version"


class ReplayService:
    """Owns an :class:`InMemoryReplay` and serves it over Zenoh. Thread-safe: the buffer is
    guarded by one lock shared by the ingest thread and the Zenoh callbacks."""

    def __init__(self, cfg: RunConfig, node: Node, run_id: str, service_id: str = "replay") -> None:
        self.cfg = cfg
        self.rcfg = cfg.replay
        self.node = node
        self.keys = P.Keys(run_id)
        self.id = service_id
        self.max_bytes = cfg.transport.max_message_bytes
        self.buffer: InMemoryReplay | None = None
        self._lock = threading.Lock()
        self._queue: queue.Queue[tuple[str, bytes]] = queue.Queue(maxsize=self.rcfg.queue_size)
        self._rng = np.random.default_rng(cfg.seed + 17)
        self.rejects = RejectCounter(log, "message")
        self.inserted = RateMeter()
        self.sampled = RateMeter()
        self.dropped_queue_full = 0
        self.not_ready_replies = 0
        self.sampled_items = 0
        self._stop = threading.Event()
        #: set first on shutdown: the transitions callback then returns at once (never waits on
        #: a queue that is about to stop being drained)
        self._closing = threading.Event()
        self.dropped_stopping = 0
        self._tx_sub = None
        self._threads: list[threading.Thread] = []
        self._stats_pub = None
        self._spec_sig: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
        self.checker = make_checker(cfg) if self.rcfg.check_semantics else None
        self.quarantine = Quarantine(self.rcfg.quarantine_rejections, self.rcfg.quarantine_window_s, self.rcfg.quarantine_s)
        self._quarantine_tokens: dict[str, Any] = {}
        #: the storage's fields are known to be the env's (set when allocated from a checked chunk)
        self._spec_vetted = False
        self.rejected_by_source: collections.Counter[str] = collections.Counter()
        self.dropped_quarantined = 0
        self.journal: ReplayLog | None = None
        self.restored_items = 0
        self._last_snapshot = time.monotonic()
        if self.rcfg.durable:
            log_dir = self.rcfg.log_dir or str(Path(cfg.runs_dir) / run_id / "replay")
            self.journal = ReplayLog(log_dir, self.rcfg.segment_items or max(1, self.rcfg.capacity // 8), self.rcfg.flush_interval_s)
            self.restore()

    # -- wiring -----------------------------------------------------------------------------
    def start(self) -> None:
        self._stats_pub = self.node.publisher(self.keys.stats("replay", self.id))
        t = threading.Thread(target=self._ingest_loop, name="replay-ingest", daemon=True)
        t.start()
        self._threads.append(t)
        self._tx_sub = self.node.subscribe(self.keys.transitions_all, self._on_transitions)
        self.node.subscribe(self.keys.priorities, self._on_priorities)
        self.node.queryable(self.keys.sample, self._on_sample)
        self.node.token(self.keys.alive("replay", self.id))
        log.info("replay service %s up on %s", self.id, self.keys.prefix)

    def run(self, stop: threading.Event) -> None:
        """Serve until ``stop`` is set, publishing stats periodically."""
        self.start()
        try:
            while not stop.wait(self.rcfg.stats_interval_s):
                self.publish_stats()
        finally:
            self.shutdown()

    def shutdown(self) -> None:
        """Stop in an order that cannot stall under ingest load: refuse new chunks (the
        callback returns at once) and undeclare the transitions subscriber, let the ingest
        thread insert what is already queued, then flush the log and write the final snapshot.
        The session is closed by the caller after this returns."""
        self._closing.set()
        if self._tx_sub is not None:
            try:
                self._tx_sub.undeclare()
            except zenoh.ZError as e:  # the session may be gone (router down): go on stopping
                log.debug("undeclaring the transitions subscriber failed: %s", e)
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        if self.journal is not None:
            with self._lock:
                self.snapshot()
                self.journal.close()
            log.info("replay log flushed: %d items inserted, %d stored",
                     0 if self.buffer is None else self.buffer.inserts_total,
                     0 if self.buffer is None else self.buffer.size)

    # -- durability ---------------------------------------------------------------------------
    def restore(self) -> None:
        """Rebuild the buffer from the log (same keys as before), then apply the newest
        priority snapshot (keys overwritten since are ignored)."""
        records = 0
        for rec in self.journal.read():
            try:
                msg = P.TransitionBatch.decode(rec.payload, self.max_bytes)
            except ProtocolError as e:  # cannot happen for records we wrote; never fatal
                log.warning("skipping an undecodable log record: %s", e)
                continue
            if msg.frames is not None:
                if self.buffer is not None and rec.first_key != self.buffer.inserts_total:
                    log.warning("replay log gap: expected key %d, record starts at %d", self.buffer.inserts_total, rec.first_key)
                try:
                    records += self._insert_frames(msg, rec.first_key) is not None
                except (ValueError, SpecMismatch) as e:
                    log.warning("skipping a log record that does not fit the replay: %s", e)
                continue
            data = self._with_meta(msg)
            if self.buffer is None:
                self.buffer = self._make_buffer(data)
                self.buffer.start_at(rec.first_key)
                # a log written without the checks (or for another env) may hold other fields
                self._spec_vetted = self.checker is not None and self.checker.check_fields(msg.data) is None
                self._spec_sig = {k: (v.shape, np.dtype(v.dtype)) for k, v in self.buffer.spec.items()}
            elif rec.first_key != self.buffer.inserts_total:
                log.warning("replay log gap: expected key %d, record starts at %d", self.buffer.inserts_total, rec.first_key)
            self.buffer.insert(data, msg.priorities)
            records += 1
        if self.buffer is None:
            return
        snap = self.journal.load_priorities()
        if snap is not None:
            self.buffer.update_priorities(*snap)
        self.restored_items = self.buffer.size
        log.info("replay restored %d items (keys up to %d) from %d log records", self.buffer.size,
                 self.buffer.inserts_total - 1, records)

    def snapshot(self) -> None:
        """Priority snapshot + flush (caller holds the lock)."""
        if self.journal is None or self.buffer is None:
            return
        keys, prios = self.buffer.raw_priorities()
        self.journal.flush()
        self.journal.snapshot_priorities(keys, prios, self.buffer.inserts_total)
        self._last_snapshot = time.monotonic()

    # -- ingest -----------------------------------------------------------------------------
    def _on_transitions(self, key: str, payload: bytes) -> None:
        if self.quarantine.active and self.quarantine.drop(source_of(key)):
            self.dropped_quarantined += 1  # unread: a quarantined source costs a dict lookup
            return
        # wait for queue space in short slices so that a shutdown is noticed at once, not after
        # drop_after_s per chunk (a full queue's consumer may be the one stopping)
        deadline = time.monotonic() + self.rcfg.drop_after_s
        while not self._closing.is_set():
            try:
                self._queue.put((key, payload), timeout=min(0.05, max(0.0, deadline - time.monotonic())))
                return
            except queue.Full:
                if time.monotonic() >= deadline:
                    self.dropped_queue_full += 1
                    self.rejects.reject("queue_full", f"ingest queue full for {self.rcfg.drop_after_s} s; chunk dropped", key)
                    return
        self.dropped_stopping += 1  # arrived while stopping: never inserted, so never acknowledged as such

    def _ingest_loop(self) -> None:
        while not self._stop.is_set():
            try:
                first = self._queue.get(timeout=0.2)
            except queue.Empty:
                if self.journal is not None:
                    with self._lock:
                        self.journal.maybe_flush()
                continue
            self._ingest_queued(first)
        # stopping: what was queued before the subscriber went is inserted (and logged), not lost
        while True:
            try:
                first = self._queue.get_nowait()
            except queue.Empty:
                return
            self._ingest_queued(first)

    def _ingest_queued(self, first: tuple[str, bytes]) -> None:
        batch = [first]  # drain what is queued: one insert (and tree update) for many chunks
        while len(batch) < self.rcfg.ingest_batch_chunks:
            try:
                batch.append(self._queue.get_nowait())
            except queue.Empty:
                break
        self.ingest_many([(payload, key) for key, payload in batch])

    def ingest(self, payload: bytes, source: str = "") -> int:
        """Decode, validate and insert one :class:`TransitionBatch`; returns items inserted
        (0 if rejected)."""
        return self.ingest_many([(payload, source)])

    def ingest_many(self, items: list[tuple[bytes, str]]) -> int:
        """Decode and validate each ``(payload, source)`` (form, then meaning); insert the valid
        ones as one batch. A bad chunk is rejected and counted alone, by reason and by source.
        Returns the items inserted.

        The semantic checks run once on the combined batch (the insert needs it anyway), so their
        per-call cost is paid once per batch, not per chunk; only when the batch fails are its
        chunks checked one by one to find and reject the bad ones."""
        good: list[tuple[bytes, P.TransitionBatch, dict[str, np.ndarray], str]] = []
        framed_msgs: list[tuple[bytes, P.TransitionBatch, str]] = []
        for payload, source in items:
            try:
                msg = P.TransitionBatch.decode(payload, self.max_bytes)
            except ProtocolError as e:
                self._reject(e.reason, str(e), source)
                continue
            if msg.frames is not None:  # frame mode
                framed_msgs.append((payload, msg, source))
                continue
            good.append((payload, msg, self._with_meta(msg), source))
        framed = self._ingest_frames(framed_msgs) if framed_msgs else 0
        if not good:
            return framed
        with self._lock:
            if self.buffer is None:
                if self.checker is not None:  # the first chunk defines the storage: check it alone
                    good = [g for g in good if self._passes(g)]
                    if not good:
                        return framed
                try:
                    self.buffer = self._make_buffer(good[0][2])
                except (ValueError, SpecMismatch) as e:
                    self._reject("spec", str(e), good[0][3], locked=True)
                    return framed
                self._spec_sig = {k: (v.shape, np.dtype(v.dtype)) for k, v in self.buffer.spec.items()}
                self._spec_vetted = self.checker is not None
            ok = []
            for g in good:
                why = self._spec_mismatch(g[2])
                if why:
                    self._reject("spec", why, g[3], locked=True)
                else:
                    ok.append(g)
            if not ok:
                return framed
            data, prios = self._combine(ok)
            # every chunk here matches the storage's fields; once those are known to be the env's
            # (_spec_vetted), only the values need checking
            if self.checker is not None and self.checker.check(
                    data if self._spec_vetted else {k: v for k, v in data.items() if k != POLICY_VERSION_FIELD},
                    prios, fields_checked=self._spec_vetted) is not None:
                ok = [g for g in ok if self._passes(g)]
                if not ok:
                    return framed
                data, prios = self._combine(ok)
            try:
                keys = self.buffer.insert(data, prios)
            except (SpecMismatch, ValueError) as e:  # validated above; kept as a last guard
                self.rejects.reject("invalid", str(e), ok[0][3])
                return framed
            if self.journal is not None:
                off = 0
                for payload, msg, _, _ in ok:
                    self.journal.append(int(keys[off]), msg.batch_size, payload)
                    off += msg.batch_size
                if self.journal.maybe_flush():
                    self.journal.prune(self.buffer.inserts_total - self.buffer.capacity)
                if time.monotonic() - self._last_snapshot >= self.rcfg.snapshot_interval_s:
                    self.snapshot()
        n = int(keys.shape[0])
        self.inserted.add(n)
        return n + framed

    def _ingest_frames(self, chunks: list[tuple[bytes, P.TransitionBatch, str]]) -> int:
        """Check and insert frame-mode chunks, in arrival order, as one ``insert_many`` (and log
        each: later chunks may name its frames). A bad chunk is rejected alone. Returns the items
        inserted."""
        inserted = 0
        with self._lock:
            todo: list[tuple[bytes, P.TransitionBatch, str, FrameChunk]] = []
            for payload, msg, source in chunks:
                if self.checker is not None:
                    why = self.checker.check_scalars(msg.data, msg.priorities) or self.checker.check_frames(msg.frames)
                    if why is not None:
                        self._reject(why.reason, why.detail, source, locked=True)
                        continue
                fc = self._frame_chunk(msg, source)
                if fc is not None:
                    todo.append((payload, msg, source, fc))
            if not todo:
                return 0
            results = self.buffer.insert_many([t[3] for t in todo])
            for (payload, msg, source, _), res in zip(todo, results):
                if isinstance(res, (ValueError, SpecMismatch)):
                    self._reject("spec", str(res), source, locked=True)
                    continue
                if res.dropped:
                    self.rejects.reject("unresolved_frames", f"{res.dropped} transitions name frames this replay does "
                                        "not hold (a lost chunk, or evicted); dropped", msg.actor_id)
                if self.journal is not None:
                    first = int(res.keys[0]) if res.keys.size else self.buffer.inserts_total
                    self.journal.append(first, int(res.keys.size), payload)
                inserted += int(res.keys.size)
            if self.journal is not None:
                if self.journal.maybe_flush():
                    self.journal.prune(self.buffer.inserts_total - self.buffer.capacity)
                if time.monotonic() - self._last_snapshot >= self.rcfg.snapshot_interval_s:
                    self.snapshot()
        self.inserted.add(inserted)
        return inserted

    def _frame_chunk(self, msg: P.TransitionBatch, source: str = "", first_key: int | None = None) -> FrameChunk | None:
        """One frame-mode chunk as the store takes it (caller holds the lock); allocates a
        FrameReplay on the first chunk. None when rejected (the rejection is counted)."""
        refs = msg.frame_refs()
        data = self._with_meta(msg)
        batch = {k: v for k, v in data.items() if k not in refs}
        if self.buffer is None:
            ref_stack = {k: (0 if v.ndim == 1 else int(v.shape[1])) for k, v in refs.items()}
            try:
                self.buffer = FrameReplay(spec_of_batch(batch), spec_of_batch(msg.frames), ref_stack, self.rcfg.capacity,
                                          frames_per_item=self.rcfg.frames_per_item, max_bytes=self.rcfg.max_bytes,
                                          alpha=self.rcfg.alpha, uniform=self.rcfg.uniform, seed=self.cfg.seed)
            except (ValueError, SpecMismatch) as e:
                self._reject("spec", str(e), source or msg.actor_id, locked=True)
                return None
            if first_key is not None:
                self.buffer.start_at(first_key)
            log.info("replay storage allocated (frame mode): %d items, %d frames, %d bytes per item",
                     self.buffer.capacity, self.buffer.frame_capacity, self.buffer.bytes_per_item)
        elif not isinstance(self.buffer, FrameReplay):
            self._reject("spec", "a frame-mode chunk, but this replay stores full observations", source or msg.actor_id,
                         locked=True)
            return None
        return FrameChunk(msg.actor_id, msg.frame_base, msg.frames, batch, refs, msg.priorities)

    def _insert_frames(self, msg: P.TransitionBatch, first_key: int | None = None):
        """One frame-mode chunk from the log (caller holds the lock, or is restoring). Returns
        the InsertResult, or None when rejected."""
        fc = self._frame_chunk(msg, first_key=first_key)
        if fc is None:
            return None
        return self.buffer.insert(fc.stream, fc.frame_base, fc.frames, fc.batch, fc.refs, fc.priorities)

    def _combine(self, ok: list[tuple[bytes, P.TransitionBatch, dict[str, np.ndarray], str]]
                 ) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """One batch from several chunks (caller holds the lock)."""
        if len(ok) == 1:
            return ok[0][2], ok[0][1].priorities
        data = {k: np.concatenate([g[2][k] for g in ok]) for k in ok[0][2]}
        if all(g[1].priorities is not None for g in ok):
            return data, np.concatenate([g[1].priorities for g in ok])
        # chunks without priorities take the running max, as on their own
        mp = np.float32(self.buffer.max_priority)
        return data, np.concatenate([g[1].priorities if g[1].priorities is not None
                                     else np.full(g[1].batch_size, mp, np.float32) for g in ok])

    def _passes(self, g: tuple[bytes, P.TransitionBatch, dict[str, np.ndarray], str]) -> bool:
        """Semantic check of one chunk; a failure is rejected and counted (caller holds the lock)."""
        why = self.checker.check(g[1].data, g[1].priorities)
        if why is None:
            return True
        self._reject(why.reason, why.detail, g[3], locked=True)
        return False

    def _reject(self, reason: str, detail: str, source: str, locked: bool = False) -> None:
        """Count a rejected chunk by reason and by source (the actor id in its key); a source
        that keeps sending bad chunks is quarantined."""
        src = source_of(source)
        self.rejects.reject(reason, detail, source)
        if locked:
            self._count_source(src, reason)
        else:
            with self._lock:
                self._count_source(src, reason)

    def _count_source(self, src: str, reason: str) -> None:
        if src not in self.rejected_by_source and len(self.rejected_by_source) >= 10_000:
            return  # bounded memory however many ids a sender invents (the totals still count)
        self.rejected_by_source[src] += 1
        if self.quarantine.record(src, reason):
            log.warning("source %s quarantined for %.0f s: %d rejected chunks within %.0f s (last: %s)", src,
                        self.rcfg.quarantine_s, self.rcfg.quarantine_rejections, self.rcfg.quarantine_window_s, reason)

    def _spec_mismatch(self, data: dict[str, np.ndarray]) -> str:
        if isinstance(self.buffer, FrameReplay):
            return "a chunk of full observations, but this replay stores frames (frame mode)"
        sig = self._spec_sig
        if data.keys() != sig.keys():
            return f"fields {sorted(data)} differ from the replay's {sorted(sig)}"
        for k, a in data.items():
            shape, dt = sig[k]
            if a.shape[1:] != shape or a.dtype != dt:
                return f"field {k}: {a.dtype.name}{list(a.shape[1:])} differs from the replay's {dt.name}{list(shape)}"
        return ""

    @staticmethod
    def _with_meta(msg: P.TransitionBatch) -> dict[str, np.ndarray]:
        data = dict(msg.data)
        data[POLICY_VERSION_FIELD] = np.full(msg.batch_size, msg.policy_version, np.int64)
        return data

    def _make_buffer(self, data: dict[str, np.ndarray]) -> InMemoryReplay:
        spec = spec_of_batch(data)
        buf = InMemoryReplay(spec, capacity=self.rcfg.capacity, max_bytes=self.rcfg.max_bytes,
                             alpha=self.rcfg.alpha, uniform=self.rcfg.uniform, seed=self.cfg.seed)
        log.info("replay storage allocated: %d items x %d bytes, fields %s", buf.capacity,
                 buf.bytes_per_item, {k: (v.shape, v.dtype) for k, v in spec.items()})
        return buf

    # -- priorities -------------------------------------------------------------------------
    def _on_priorities(self, key: str, payload: bytes) -> None:
        try:
            msg = P.PriorityUpdate.decode(payload, self.max_bytes)
        except ProtocolError as e:
            self.rejects.reject(e.reason, str(e), key)
            return
        if self.checker is not None and msg.priorities.size and float(msg.priorities.max()) > self.rcfg.max_priority:
            self.rejects.reject("priority_bound", f"priority update {float(msg.priorities.max()):.3g} exceeds "
                                f"replay.max_priority {self.rcfg.max_priority:.3g}", key)
            return
        with self._lock:
            if self.buffer is not None:
                self.buffer.update_priorities(msg.keys.astype(np.int64), msg.priorities.astype(np.float64))

    # -- sampling ---------------------------------------------------------------------------
    def readiness(self, batch_size: int) -> str:
        """``""`` if a batch of ``batch_size`` may be sampled now, else the reason why not."""
        size = 0 if self.buffer is None else self.buffer.size
        if size < max(self.rcfg.min_size, 1):
            return f"min_size {self.rcfg.min_size} > size {size}"
        spi = self.rcfg.samples_per_insert
        if spi is not None:
            allowed = spi * self.buffer.inserts_total + self.rcfg.spi_tolerance
            if self.sampled_items + batch_size > allowed:
                return f"samples_per_insert {spi} reached ({self.sampled_items} sampled, {self.buffer.inserts_total} inserted)"
        return ""

    def _on_sample(self, payload: bytes) -> bytes:
        try:
            req = P.SampleRequest.decode(payload, self.max_bytes)
        except ProtocolError as e:
            self.rejects.reject(e.reason, str(e), self.keys.sample)
            return P.SampleReply(request_id=0, status="not_ready", reason=f"bad request: {e}").encode()
        return self.sample_reply(req).encode(self.max_bytes)

    def sample_reply(self, req: P.SampleRequest) -> P.SampleReply:
        with self._lock:
            why = self.readiness(req.batch_size)
            size = 0 if self.buffer is None else self.buffer.size
            if why:
                self.not_ready_replies += 1
                return P.SampleReply(request_id=req.request_id, status="not_ready", reason=why, replay_size=size)
            s = self.buffer.sample(req.batch_size, req.beta, self._rng)
            self.sampled_items += req.batch_size
        self.sampled.add(1)
        return P.SampleReply(request_id=req.request_id, status="ok", replay_size=size,
                             keys=s.keys, probabilities=s.probabilities, weights=s.weights, data=s.data)

    # -- stats ------------------------------------------------------------------------------
    def stats_values(self) -> dict[str, Any]:
        with self._lock:
            b = self.buffer
            v: dict[str, Any] = {
                "size": 0 if b is None else b.size,
                "capacity": self.rcfg.capacity if b is None else b.capacity,
                "bytes": 0 if b is None else b.nbytes,
                "inserted_total": 0 if b is None else b.inserts_total,
                "stale_priority_updates": 0 if b is None else b.stale_updates,
            }
            if isinstance(b, FrameReplay):
                v.update({"frames_stored": b.frames_stored, "frames_unresolved_items": b.unresolved,
                          "evicted_by_frames": b.evicted_by_frames})
        v.update({
            "inserts_per_s": self.inserted.rate(),
            "sample_batches_per_s": self.sampled.rate(),
            "sample_batches_total": self.sampled.total,
            "not_ready_replies": self.not_ready_replies,
            "dropped_queue_full": self.dropped_queue_full,
            "dropped_stopping": self.dropped_stopping,
            "ingest_queue": self._queue.qsize(),
            "restored_items": self.restored_items,
        })
        if self.journal is not None:
            v.update({"log_bytes_written": self.journal.bytes_written, "log_disk_bytes": self.journal.disk_bytes(),
                      "log_torn_records": self.journal.torn_records,
                      "durable_through": self.journal.durable_through})
        v.update(self.rejects.as_values())
        with self._lock:
            for src, n in self.rejected_by_source.most_common(TOP_SOURCES):
                v[f"rejected_from/{src}"] = n
            v["quarantined"] = len(self.quarantine.active)
            v["quarantined_sources"] = self.quarantine.describe()
            v["quarantines_total"] = self.quarantine.total
        v["dropped_quarantined"] = self.dropped_quarantined
        return v

    def update_quarantine(self) -> None:
        """Hold a liveliness token ``quarantine/<source>`` while a source is quarantined, so
        that slot claims (see zenrl.actor.slots) treat its exploration slot as free."""
        with self._lock:
            released = self.quarantine.expire()
            active = list(self.quarantine.active)
        for src in released:
            tok = self._quarantine_tokens.pop(src, None)
            log.info("source %s released from quarantine", src)
            if tok is not None:
                try:
                    tok.undeclare()
                except zenoh.ZError as e:
                    log.debug("undeclaring the quarantine token of %s failed: %s", src, e)
        for src in active:
            if src not in self._quarantine_tokens:
                try:
                    self._quarantine_tokens[src] = self.node.session.liveliness().declare_token(self.keys.quarantined(src))
                except (zenoh.ZError, P.ProtocolError) as e:
                    log.warning("could not declare the quarantine token of %s: %s", src, e)

    def publish_stats(self) -> None:
        self.update_quarantine()
        vals = self.stats_values()
        if self._stats_pub is not None:
            self._stats_pub.put(P.Stats(role="replay", id=self.id, time=time.time(), values=vals).encode())
        log.debug("replay stats %s", vals)


def source_of(key: str) -> str:
    """The sender a ``transitions/<actor>`` key names (its last segment)."""
    return key.rsplit("/", 1)[-1]


def make_checker(cfg: RunConfig) -> ChunkChecker:
    """The semantic checks for this run's env, built from the config as the learner builds its
    network (an env is made once to read its spaces, then closed)."""
    env = make_env(cfg.env)
    try:
        return ChunkChecker.from_spaces(env.observation_space, env.action_space, cfg.actor.n_step,
                                        cfg.replay.max_abs_reward, cfg.replay.max_priority, cfg.replay.check_obs_bounds)
    finally:
        env.close()


def main(cfg: RunConfig, run_id: str, stop: threading.Event, service_id: str = "replay") -> None:
    """Entry point of ``zenrl replay``: build, run until ``stop``, close the session."""
    with Node.from_config(cfg.transport) as node:
        ReplayService(cfg, node, run_id, service_id).run(stop)
