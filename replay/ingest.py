"""The replay's ingest: from a ``transitions/<actor>`` message to items in the store.

Chunks wait in Zenoh's own bounded FIFO (:meth:`zenrl.common.transport.Node.inbox`), which
Zenoh's receive thread fills without the GIL; no Python thread stands between it and the ingest
thread. The ingest thread runs :meth:`Ingest.unit` over and over: wait for a chunk, take it and
whatever else is queued (up to ``replay.ingest_batch_chunks`` chunks and ``replay.queue_max_bytes``
bytes; a quarantined source's chunk is dropped unread, an oversized one refused unread) and
:meth:`Ingest.ingest_many` them:

1. decode each message (:class:`~zenrl.common.protocol.TransitionBatch`: form, sizes, finiteness);
2. the first chunk that passes the checks allocates the storage (:func:`zenrl.replay.store.allocate`);
3. each chunk must fit the storage's layout (``spec``), then mean what the env allows
   (:mod:`zenrl.replay.checks`, with ``replay.check_semantics``);
4. the good ones are inserted together and each is appended to the journal.

The FIFO holds ``min(replay.queue_size, max(1, replay.queue_max_bytes // chunk cap))`` chunks
(so what waits there stays within ``queue_max_bytes``); when it is full, Zenoh's receive thread
waits, and with it the senders (BLOCK). That wait must stay below Zenoh's 5 s fuse
(the sending side closes a link stalled that long): :meth:`Ingest.relieve`, run every
``drop_after_s / 4`` by a thread of its own, drops and counts (``dropped_queue_full``) what waits
in the FIFO while the ingest thread has been busy with one batch for ``replay.drop_after_s``.

A bad chunk is rejected alone and counted by reason (``rejected_<reason>``) and by source; a
source that keeps sending bad chunks is quarantined. Any other exception while one chunk is
handled is caught and counted as ``rejected_internal`` and ``rejected_internal/<Type>``, and the
next chunk is handled: no message can end the ingest thread.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Iterable, Iterator

from zenrl.common import protocol as P
from zenrl.common.errors import MemoryTooSmall, ProtocolError, SpecMismatch
from zenrl.common.metrics import RateMeter, RejectCounter
from zenrl.common.quarantine import Quarantine, SourceLedger
from zenrl.replay.checks import Checker
from zenrl.replay.store import Chunk, Store, allocate, check_one

log = logging.getLogger(__name__)

#: Sources listed by name in the stats' per-source rejection counts (the most rejected first).
TOP_SOURCES = 20
#: Sources whose rejections are counted by name, the heaviest kept (the totals count them all;
#: the quarantine tracks as many on its own).
MAX_SOURCES = 1024


def source_of(key: str) -> str:
    """The sender a ``transitions/<actor>`` key names (its last segment)."""
    return key.rsplit("/", 1)[-1]


class Ingest:
    """Intake, checks and insert of transitions chunks. ``lock`` guards the store (shared with
    sampling and the journal); ``journal`` (or None) gets each inserted chunk. The chunks come from
    ``inbox`` (set by the service: a :class:`~zenrl.common.transport.Inbox` of ``inbox_capacity``
    chunks), or are handed to :meth:`ingest_many` directly (in-process use, the journal's replay)."""

    def __init__(self, rcfg: Any, seed: int, max_bytes: int, checker: Checker | None, lock: threading.Lock,
                 journal: Any | None = None) -> None:
        self.rcfg, self.seed, self.max_bytes = rcfg, seed, max_bytes
        self.checker = checker
        self.lock = lock
        self.journal = journal
        self.store: Store | None = None
        #: where chunks wait (``get()``, ``get_nowait()`` of :class:`~zenrl.common.transport.Received`)
        self.inbox: Any | None = None
        #: chunks the inbox holds: as many of the largest admitted chunk as ``queue_max_bytes`` takes
        #: (at least one, at most ``queue_size``), so that what waits there stays within it
        self.inbox_capacity = min(rcfg.queue_size, max(1, rcfg.queue_max_bytes // max_bytes))
        #: chunks the ingest thread has taken from the inbox and not finished
        self.in_hand = 0
        #: monotonic time the ingest thread started on its current batch; None between batches
        self._busy_since: float | None = None
        self.limits = P.DecodeLimits(rcfg.max_decoded_bytes, None if checker is None else checker.packed_shapes())
        #: set first on shutdown (ends the relief thread's wait)
        self.closing = threading.Event()
        self.rejects = RejectCounter(log, "message")
        self.quarantine = Quarantine(rcfg.quarantine_rejections, rcfg.quarantine_window_s, rcfg.quarantine_s)
        #: rejections by source, internal errors by type, the quarantine they feed; its lock guards
        #: them (rejections come from the ingest thread, stats and expiry from the role loop) and
        #: is never held while taking ``lock``
        self.ledger = SourceLedger(self.quarantine, MAX_SOURCES)
        self.inserted = RateMeter()
        #: set by the service: records each stored chunk's sender (``Origins.record``), so that
        #: items the learner reports poisonous are charged to it
        self.origins: Any | None = None
        self.dropped_queue_full = 0
        self.dropped_quarantined = 0
        #: the storage the first chunk asked for cannot fit in memory (MemoryTooSmall): the role
        #: loop raises it (exit 2) and nothing is stored meanwhile
        self.fatal: MemoryTooSmall | None = None

    # -- the intake -----------------------------------------------------------------------------
    def unit(self) -> int:
        """The ingest thread's unit of work: wait for a chunk (the GIL released), then ingest it
        together with what else waits (one insert and tree update for many chunks). Returns items
        inserted; 0 when the inbox is closed (the service is stopping)."""
        first = None if self.inbox is None else self.inbox.get()
        if first is None:  # closed (or not attached): stopping; wait, never spin
            if self.closing.is_set():
                time.sleep(0.01)
            else:
                self.closing.wait(0.2)
            return 0
        return self._ingest_from(first)

    def _ingest_from(self, first: Any) -> int:
        """Ingest ``first`` and what waits behind it as one batch (:meth:`_pull`)."""
        self._busy_since = time.monotonic()
        try:
            return self.ingest_many(self._pull(first))
        finally:
            self.in_hand = 0
            self._busy_since = None

    def _pull(self, first: Any) -> Iterator[tuple[bytes, str]]:
        """``first`` and the chunks that wait behind it, up to ``replay.ingest_batch_chunks``
        chunks and ``replay.queue_max_bytes`` bytes (the first always); if that is less than a
        batch, once more after ``replay.ingest_linger_s``. What waits in the inbox
        is taken at once (leaving it empty: Zenoh's receive thread, if it waited on a full
        inbox, is woken once and refills it while the batch is ingested, not once per chunk).
        An inbox of one chunk is also taken from as the batch is decoded, so that what the
        receive thread puts in meanwhile joins the batch."""
        taken, held = 0, 0
        limit_n, limit_b = self.rcfg.ingest_batch_chunks, self.rcfg.queue_max_bytes
        cap = min(limit_n, self.inbox_capacity + 1)
        waiting = [first]
        size = self._take_waiting(waiting, first.nbytes, cap, limit_b)
        linger = self.rcfg.ingest_linger_s
        # a short batch waits once for more (the stop's event ends the wait)
        if linger > 0 and len(waiting) < cap and size < limit_b and not self.closing.wait(linger):
            size = self._take_waiting(waiting, size, cap, limit_b)
        for i, r in enumerate(waiting):
            item = self._take(r)
            waiting[i] = None  # a dropped chunk's buffer goes now
            if item is not None:
                taken += 1
                held += len(item[0])
                self.in_hand = taken
                yield item
        while self.inbox_capacity == 1 and taken < limit_n and held < limit_b:
            r = self.inbox.get_nowait()
            if r is None:
                return
            item = self._take(r)
            if item is not None:
                taken += 1
                held += len(item[0])
                self.in_hand = taken
                yield item

    def _take_waiting(self, waiting: list[Any], size: int, cap: int, limit_b: int) -> int:
        """Append what waits in the inbox to ``waiting`` (holding ``size`` bytes) while it has
        fewer than ``cap`` chunks and ``limit_b`` bytes; returns the bytes it then holds."""
        while len(waiting) < cap and size < limit_b:
            r = self.inbox.get_nowait()
            if r is None:
                break
            waiting.append(r)
            size += r.nbytes
        return size

    def _take(self, r: Any) -> tuple[bytes, str] | None:
        """A received chunk's ``(payload, key)``, or None when it is dropped unread: its source is
        quarantined (a dict lookup), or it exceeds the chunk cap (refused before it is copied)."""
        if self.quarantine.active and self.quarantine.drop(source_of(r.key)):
            self.dropped_quarantined += 1
            return None
        n = r.nbytes
        if n > self.max_bytes:
            self.reject("size", f"{n} bytes exceeds the cap of {self.max_bytes} bytes", r.key)
            return None
        return r.data(), r.key

    def pending(self) -> int:
        """Chunks the ingest thread has taken and not finished (a thread stuck on the chunks it
        holds has input waiting: the supervisor reports it stalled)."""
        return self.in_hand

    def drain(self) -> None:
        """On stop (the inbox closed): insert (and log) what waits in it, not lose it."""
        while self.inbox is not None:
            r = self.inbox.get_nowait()
            if r is None:
                return
            self._ingest_from(r)

    def relieve(self) -> int:
        """If the ingest thread has been busy with one batch for ``replay.drop_after_s``, drop
        (and count) the chunks waiting in the inbox, so that Zenoh's receive thread, waiting on a
        full inbox, never waits into the 5 s fuse that closes the link. Returns chunks dropped."""
        since = self._busy_since
        if self.inbox is None or since is None:
            return 0
        busy = time.monotonic() - since
        if busy < self.rcfg.drop_after_s:
            return 0
        n = 0
        while (r := self.inbox.get_nowait()) is not None:
            n += 1
            self.dropped_queue_full += 1
            self.rejects.reject("queue_full", f"the ingest thread has been busy with one batch for {busy:.1f} s "
                                f"(inbox of {self.inbox_capacity} full); chunk dropped", r.key)
        return n

    def relief_unit(self) -> None:
        """The relief thread's unit: :meth:`relieve` every ``replay.drop_after_s / 4``."""
        if self.closing.is_set():  # stopping: wait for the thread's stop, never spin
            time.sleep(0.05)
        elif not self.closing.wait(self.rcfg.drop_after_s / 4):
            self.relieve()

    # -- decode, check, insert -------------------------------------------------------------------
    def ingest_many(self, items: Iterable[tuple[bytes, str]]) -> int:
        """Decode, check and insert each ``(payload, source)`` (``items`` is consumed as the chunks
        are decoded); the good ones as one batch (a new batch each time the decoded chunks reach
        ``replay.max_decoded_bytes``, so that the decoded data held at once stays bounded). A bad
        chunk is rejected and counted alone. Returns the items inserted."""
        chunks: list[Chunk] = []
        held, n = 0, 0
        for payload, source in items:
            c = self._guard(source, self._decode, payload, source)
            if c is None:
                continue
            chunks.append(c)
            held += c.nbytes
            if held >= self.rcfg.max_decoded_bytes:
                n += self._store_batch(chunks)
                chunks, held = [], 0
        return n + self._store_batch(chunks)

    def _store_batch(self, chunks: list[Chunk]) -> int:
        """Check and insert decoded chunks as one batch; returns the items inserted."""
        if not chunks:
            return 0
        with self.lock:
            if self.fatal is not None:
                return 0
            if self.store is None:
                chunks = self._allocate(chunks)
            chunks = [c for c in chunks if self._guard(c.source, self._fits, c)]
            if self.checker is not None and chunks:
                chunks = self._checked(chunks)
            n = self._insert(chunks) if chunks else 0
        self.inserted.add(n)
        return n

    def _decode(self, payload: bytes, source: str) -> Chunk | None:
        try:
            msg = P.TransitionBatch.decode(payload, self.max_bytes, self.limits)
        except ProtocolError as e:
            self.reject(e.reason, str(e), source)
            return None
        if msg.frames is not None and source and source_of(source) != msg.actor_id:
            self.reject("source", f"a frame-mode chunk names actor {msg.actor_id!r} but arrived on {source}", source)
            return None
        return Chunk.of(payload, msg, source)

    def _allocate(self, chunks: list[Chunk]) -> list[Chunk]:
        """Allocate the storage from the first chunk that passes the checks (caller holds the
        lock). Returns the chunks left to insert, that one first."""
        for i, c in enumerate(chunks):
            if self.checker is not None and not self._guard(c.source, self._passes, c):
                continue
            try:
                self.store = allocate(c, self.rcfg, self.seed, self.checker is not None)
            except MemoryTooSmall as e:
                if self.checker is None:  # unchecked: the chunk's own fields sized it, not the env's
                    self.reject("memory", str(e), c.sender)
                    continue
                log.error("%s", e)
                self.fatal = e
                return []
            except (ValueError, SpecMismatch) as e:
                self.reject("spec", str(e), c.sender)
                continue
            except Exception as e:  # noqa: BLE001 - e.g. a shape too large to allocate: this chunk only
                self._internal(e, c.source)
                continue
            return chunks[i:]
        return []

    def _fits(self, c: Chunk) -> bool:
        why = self.store.fits(c)
        if why:
            self.reject("spec", why, c.sender)
        return not why

    def _passes(self, c: Chunk) -> bool:
        why = check_one(self.checker, c)
        if why is not None:
            self.reject(why.reason, why.detail, c.sender)
        return why is None

    def _checked(self, chunks: list[Chunk]) -> list[Chunk]:
        """The chunks that pass the semantic checks (caller holds the lock)."""
        try:
            verdicts = self.store.check(self.checker, chunks)
        except Exception:  # noqa: BLE001 - find the chunk that raises: each is checked alone
            return [c for c in chunks if self._guard(c.source, self._passes, c)]
        ok = []
        for c, why in zip(chunks, verdicts):
            if why is None:
                ok.append(c)
            else:
                self.reject(why.reason, why.detail, c.sender)
        return ok

    def _insert(self, chunks: list[Chunk]) -> int:
        """Insert the chunks in order and journal each (caller holds the lock). An unexpected
        exception from a multi-chunk insert that stored nothing is retried chunk by chunk, so
        that it costs only the chunk that raises it."""
        before = self.store.buffer.inserts_total
        try:
            results: list[Any] = self.store.insert(chunks)
        except Exception as e:  # noqa: BLE001 - one chunk's failure must not end the ingest thread
            if len(chunks) > 1 and self.store.buffer.inserts_total == before:
                return sum(self._insert([c]) for c in chunks)
            for c in chunks:
                self._internal(e, c.source)
            return 0
        n = 0
        for c, res in zip(chunks, results):
            if isinstance(res, (SpecMismatch, ValueError)):
                self.reject("spec", str(res), c.sender)
                continue
            if res.dropped:
                self.rejects.reject("unresolved_frames", f"{res.dropped} transitions name frames this replay does "
                                    "not hold (a lost chunk, or evicted); dropped", c.msg.actor_id)
            if self.journal is not None:  # a failing disk is no chunk's fault: the supervisor counts it
                first = int(res.keys[0]) if res.keys.size else self.store.buffer.inserts_total
                self.journal.append(first, int(res.keys.size), c.payload)
            n += int(res.keys.size)
            if self.origins is not None:
                self.origins.record(res.keys, c.sender, self.store.buffer.capacity)
        if self.journal is not None:
            self.journal.after_insert(self.store.buffer)
        return n

    def insert_logged(self, msg: P.TransitionBatch, payload: bytes, first_key: int) -> int | None:
        """Insert one record of the journal at start-up, with the keys it had (no checks: we
        wrote it). Returns the items inserted, None when the record does not fit (skipped)."""
        c = Chunk.of(payload, msg)
        try:
            if self.store is None:
                # a log written without the checks (or for another env) may hold other fields
                vetted = self.checker is not None and msg.frames is None and self.checker.check_fields(msg.data) is None
                self.store = allocate(c, self.rcfg, self.seed, vetted, first_key)  # MemoryTooSmall ends the role
            elif first_key != self.store.buffer.inserts_total:
                log.warning("replay log gap: expected key %d, record starts at %d", self.store.buffer.inserts_total, first_key)
            why = self.store.fits(c)
            res = self.store.insert([c])[0] if not why else SpecMismatch(why)
        except MemoryTooSmall:
            raise  # a ValueError too, but not a record to skip: the role ends on it
        except (ValueError, SpecMismatch) as e:
            res = e
        if isinstance(res, Exception):
            log.warning("skipping a log record that does not fit the replay: %s", res)
            return None
        return int(res.keys.size)

    # -- rejections -------------------------------------------------------------------------------
    def _guard(self, source: str, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``; an exception other than the expected rejections is counted as
        ``internal`` against ``source`` and None returned."""
        try:
            return fn(*args)
        except Exception as e:  # noqa: BLE001 - one message's failure costs that message only
            self._internal(e, source)
            return None

    def _internal(self, e: BaseException, source: str) -> None:
        t = type(e).__name__
        first = self.ledger.internal_error(e)
        self.reject("internal", f"{t}: {e}", source)
        if first:  # the first of each type with its traceback, the rest counted
            log.error("ingest of a chunk from %s raised %s; counted as rejected_internal, going on", source, t, exc_info=e)

    def reject(self, reason: str, detail: str, source: str) -> None:
        """Count a rejected chunk by reason and by source (the actor id in its key); a source
        that keeps sending bad chunks is quarantined. Callers may hold the lock or not."""
        self.rejects.reject(reason, detail, source)
        src = source_of(source)
        if self.ledger.rejected(src, reason):
            log.warning("source %s quarantined for %.0f s: %d rejected chunks within %.0f s (last: %s)", src,
                        self.rcfg.quarantine_s, self.rcfg.quarantine_rejections, self.rcfg.quarantine_window_s, reason)

    def stats_values(self) -> dict[str, Any]:
        """``inserts_per_s``, the drop counters, ``ingest_queue`` (chunks the ingest thread holds),
        ``rejected_<reason>`` (with ``rejected_internal/<Type>``), the top
        ``rejected_from/<source>`` and the quarantine."""
        v: dict[str, Any] = {
            "inserts_per_s": self.inserted.rate(),
            "dropped_queue_full": self.dropped_queue_full,
            "ingest_queue": self.in_hand,
        }
        v.update(self.rejects.as_values())
        v.update(self.ledger.values(TOP_SOURCES))
        v["dropped_quarantined"] = self.dropped_quarantined
        return v
