"""The replay's journal (``replay.durable``): what survives a restart, and what happens when the
disk fails under it.

Every chunk the replay inserts is appended to an append-only log as the bytes it arrived as, with
the key of its first item (:class:`~zenrl.replay.durable.ReplayLog` holds the file format:
segments, records, fsync, pruning, priority snapshots). :class:`Journal` adds how the service uses
it: :meth:`Journal.restore` rebuilds the storage at start-up, :meth:`Journal.after_insert` and
:meth:`Journal.tick` keep the cadence (fsync every ``replay.flush_interval_s``, then drop the
segments the ring has overwritten; a priority snapshot every ``replay.snapshot_interval_s``),
:meth:`Journal.finish` writes the final snapshot and closes the log on stop. Callers hold the
replay's lock.

**Restore** inserts the longest suffix of the log whose keys run on without a gap, each record
with the keys it had (a record lost to corruption, or chunks never logged, leave a gap: the
records before the last gap are not restored, so no key moves and the live keys stay one range),
then applies the priority snapshot (keys overwritten since are ignored; an unreadable snapshot
is counted and the priorities logged at insert are kept).

**A failing disk** (any ``OSError`` on a write, fsync, rename: ``ENOSPC``, ``EDQUOT``, ``EIO``)
never stops ingest. The journal turns *degraded* (``durable_degraded`` in the stats): the open
segment is cut back to its last fsync, and the chunks appended since then and every chunk
inserted while degraded are kept in memory (the *backlog*, their wire bytes) instead; the replay
keeps inserting and serving samples. Every ``replay.durable_retry_s`` the journal writes the
backlog to a new segment, fsyncs it and writes a snapshot; once that succeeds the log is whole
again and appends resume (``durable_resumes``). The backlog drops chunks the ring has overwritten
(they are gone from memory too; no loss), and past ``replay.durable_backlog_bytes`` its oldest
chunks (``durable_lost_items``: a restart after the log resumes then restores from the oldest
chunk still backlogged on). What a restart restores is in docs/architecture.md (Durability).
"""

from __future__ import annotations

import collections
import logging
import os
import time
from pathlib import Path
from typing import Any

from zenrl.common import protocol as P
from zenrl.common.errors import ProtocolError
from zenrl.common.atomic_files import fsync_dir
from zenrl.replay.durable import RecordRef, ReplayLog

log = logging.getLogger(__name__)


def contiguous_suffix(refs: list[RecordRef]) -> int:
    """Index of the first record of the longest tail of ``refs`` whose keys run on without a gap
    or overlap (``first_key`` of each = ``first_key + n_items`` of the one before with items).
    Records of no items (a frame chunk whose transitions were all dropped: it still carries
    frames) hold no key and are not compared."""
    start, end = 0, None
    for i, r in enumerate(refs):
        if not r.n_items:
            continue
        if end is not None and r.first_key != end:
            start = i
        end = r.first_key + r.n_items
    return start


class Journal(ReplayLog):
    """A :class:`ReplayLog` in ``directory`` plus the replay's restore, snapshot cadence and
    degraded mode (see the module docstring)."""

    def __init__(self, directory: str | Path, segment_items: int, flush_interval_s: float,
                 snapshot_interval_s: float, retry_s: float = 5.0, backlog_bytes: int = 256 << 20) -> None:
        super().__init__(directory, segment_items, flush_interval_s)
        self.snapshot_interval_s = snapshot_interval_s
        self.retry_s = retry_s
        self.backlog_bytes = backlog_bytes
        self._last_snapshot = time.monotonic()
        #: records appended since the last fsync: (first_key, n_items, payload)
        self._pending: collections.deque[tuple[int, int, bytes]] = collections.deque()
        #: records not on disk while degraded, oldest first
        self._backlog: collections.deque[tuple[int, int, bytes]] = collections.deque()
        self._backlog_size = self._backlog_items = 0
        self.degraded = False
        self.degraded_error = ""
        self.disk_errors = 0
        self.resumes = 0
        self.lost_items = 0
        self.skipped_items = 0
        self._next_retry = 0.0

    # -- restore ---------------------------------------------------------------------------
    def restore(self, ingest: Any, max_bytes: int) -> int:
        """Insert the records of the log's contiguous suffix through ``ingest.insert_logged`` (an
        :class:`~zenrl.replay.ingest.Ingest`, which allocates the storage from the first one with
        that record's first key), then apply the newest priority snapshot. Returns the items
        restored; ``skipped_items`` counts the valid items before the last gap (not restored)."""
        refs = self.index()
        start = contiguous_suffix(refs)
        if start:
            self.skipped_items = sum(r.n_items for r in refs[:start])
            log.warning("replay log: keys jump from %d to %d (records lost or never logged); restoring from key %d on, "
                        "%d older logged items not restored", refs[start - 1].first_key + refs[start - 1].n_items,
                        refs[start].first_key, refs[start].first_key, self.skipped_items)
        suffix = refs[start:]
        # a record of no items holds no key (its header's is arbitrary): it goes at the key of the
        # next record that has items, so that the storage, allocated from the first record, starts
        # at the right key
        at, keys = None, []
        for ref in reversed(suffix):
            if ref.n_items or at is None:
                at = ref.first_key
            keys.append(at)
        keys.reverse()
        records = 0
        for ref, key in zip(suffix, keys):
            try:
                rec = self.read_ref(ref)
            except OSError as e:  # a sector gone bad since the index was read
                log.warning("replay log %s: record at byte %d unreadable (%s); skipped", ref.path.name, ref.offset, e)
                self.corrupt_records += 1
                continue
            try:
                msg = P.TransitionBatch.decode(rec.payload, max_bytes)
            except ProtocolError as e:  # a record we wrote under another config; never fatal
                log.warning("skipping an undecodable log record: %s", e)
                continue
            records += ingest.insert_logged(msg, rec.payload, key) is not None
        if ingest.store is None:
            return 0
        buf = ingest.store.buffer
        self._next_key = self.durable_through = buf.inserts_total
        snap = self.load_priorities()
        if snap is not None:
            try:
                buf.update_priorities(*snap)
            except ValueError as e:
                self.snapshot_unreadable += 1
                log.warning("priority snapshot not applied (%s); using the priorities logged at insert", e)
        log.info("replay restored %d items (keys up to %d) from %d log records", buf.size, buf.inserts_total - 1, records)
        return buf.size

    # -- appending, with the disk allowed to fail -------------------------------------------------
    def append(self, first_key: int, n_items: int, payload: bytes) -> None:
        """Log one inserted chunk; never raises on a disk error (the chunk is backlogged)."""
        rec = (first_key, n_items, payload)
        if self.degraded:
            self._keep(rec)
            return
        try:
            super().append(first_key, n_items, payload)
        except OSError as e:
            self._fail(e, "append")
            self._keep(rec)
            return
        self._pending.append(rec)

    def flush(self) -> None:
        super().flush()
        self._pending.clear()

    def _guarded(self, what: str, fn: Any, *args: Any) -> bool:
        """``fn(*args)``; an OSError turns the journal degraded. Returns whether it succeeded."""
        if self.degraded:
            return False
        try:
            fn(*args)
            return True
        except OSError as e:
            self._fail(e, what)
            return False

    def _fail(self, e: OSError, what: str) -> None:
        """Turn degraded after a disk error: cut the open segment back to its last fsync and
        keep what was appended since then in the backlog."""
        self.disk_errors += 1
        self.degraded_error = f"{what}: {os.strerror(e.errno) if e.errno else e}"
        if not self.degraded:
            log.error("replay log: %s failed (%s); going on in memory (durable_degraded), retrying every %g s",
                      what, e, self.retry_s)
        self.degraded = True
        self._next_retry = time.monotonic() + self.retry_s
        if self._f is not None:
            try:
                self._f.close()  # its buffered bytes may not be written: the segment is cut below
            except OSError:
                pass
            self._f = None
            if self._seg_path is not None:
                try:
                    os.truncate(self._seg_path, self._flushed_size)
                except OSError as te:  # the reader skips what is left there
                    log.warning("replay log: could not cut %s back to %d bytes: %s", self._seg_path.name,
                                self._flushed_size, te)
        pending, self._pending = self._pending, collections.deque()
        for rec in reversed(pending):
            self._backlog.appendleft(rec)
            self._backlog_size += len(rec[2])
            self._backlog_items += rec[1]

    def _keep(self, rec: tuple[int, int, bytes]) -> None:
        self._backlog.append(rec)
        self._backlog_size += len(rec[2])
        self._backlog_items += rec[1]
        while self._backlog_size > self.backlog_bytes and len(self._backlog) > 1:
            self.lost_items += self._drop_oldest()

    def _drop_oldest(self) -> int:
        _, n, payload = self._backlog.popleft()
        self._backlog_size -= len(payload)
        self._backlog_items -= n
        return n

    def _trim(self, oldest_live_key: int) -> None:
        """Drop backlogged chunks the ring has overwritten entirely (no loss: gone from memory)."""
        while self._backlog and self._backlog[0][0] + self._backlog[0][1] <= oldest_live_key:
            self._drop_oldest()

    def resume(self, buffer: Any) -> bool:
        """Write the backlog to a new segment, fsync it and the directory, write a snapshot of
        ``buffer``; on success the journal is no longer degraded. On a disk error the new bytes
        are removed again and the journal stays degraded. Returns whether it resumed."""
        self._next_retry = time.monotonic() + self.retry_s
        first = self._backlog[0][0] if self._backlog else self._next_key
        path = self.dir / f"seg-{first:016d}.log"
        existed = path.exists()
        try:
            size0 = path.stat().st_size if existed else 0
            self._seg_path, self._f = path, open(path, "ab")
            self._flushed_size, self._seg_items = size0, 0
            for rec in self._backlog:
                self._write(*rec)
            self._f.flush()
            os.fsync(self._f.fileno())
            fsync_dir(self.dir)
            if buffer is not None:
                self.snapshot_priorities(*buffer.raw_priorities(), buffer.inserts_total)
        except OSError as e:
            self.disk_errors += 1
            self.degraded_error = f"resume: {os.strerror(e.errno) if e.errno else e}"
            if self._f is not None:
                try:
                    self._f.close()
                except OSError:
                    pass
                self._f = None
            try:
                if existed:
                    os.truncate(path, size0)
                else:
                    path.unlink(missing_ok=True)
            except OSError:
                pass
            log.debug("replay log still failing (%s); retrying in %g s", e, self.retry_s)
            return False
        n = self._backlog_items
        self._flushed_size = self._f.tell()
        self.durable_through = self._next_key
        self._backlog.clear()
        self._backlog_size = self._backlog_items = 0
        self.degraded, self.degraded_error = False, ""
        self.resumes += 1
        now = time.monotonic()
        self._last_flush = self._last_snapshot = now
        log.warning("replay log resumed: %d items written from memory", n)
        return True

    # -- cadence -----------------------------------------------------------------------------
    def after_insert(self, buffer: Any) -> None:
        """After chunks were appended, and periodically (:meth:`tick`): fsync when due (then
        prune the segments the ring overwrote) and snapshot the priorities when due; while
        degraded, retry the log when due."""
        if self.degraded:
            if buffer is not None:
                self._trim(buffer.inserts_total - buffer.capacity)
            if time.monotonic() >= self._next_retry:
                self.resume(buffer)
            return
        oldest = 0 if buffer is None else buffer.inserts_total - buffer.capacity
        if self._guarded("fsync", self._flush_and_prune, oldest) and \
                time.monotonic() - self._last_snapshot >= self.snapshot_interval_s:
            self.snapshot(buffer)

    tick = after_insert

    def _flush_and_prune(self, oldest_live_key: int) -> None:
        if self.maybe_flush():
            self.prune(oldest_live_key)

    def snapshot(self, buffer: Any) -> None:
        """Flush, then write a priority snapshot of ``buffer`` (None: nothing stored yet)."""
        if buffer is None or self.degraded:
            return
        keys, prios = buffer.raw_priorities()
        if self._guarded("fsync", self.flush) and self._guarded("snapshot", self.snapshot_priorities, keys, prios,
                                                                buffer.inserts_total):
            self._last_snapshot = time.monotonic()

    def finish(self, buffer: Any) -> None:
        """On stop: the final snapshot, then close the log (a degraded journal tries to resume
        once first; what it cannot write is lost, and said so)."""
        if self.degraded:
            self.resume(buffer)
        if self.degraded:
            log.error("replay log: the disk still fails (%s); %d items inserted since are not logged",
                      self.degraded_error, self._backlog_items)
            return
        self.snapshot(buffer)
        self._guarded("close", self.close)

    def stats_values(self) -> dict[str, Any]:
        return {"log_bytes_written": self.bytes_written, "log_disk_bytes": self.disk_bytes(),
                "log_torn_records": self.torn_records, "log_corrupt_records": self.corrupt_records,
                "log_skipped_items": self.skipped_items, "log_snapshot_unreadable": self.snapshot_unreadable,
                "durable_through": self.durable_through, "durable_degraded": int(self.degraded),
                "durable_error": self.degraded_error, "durable_disk_errors": self.disk_errors,
                "durable_backlog_items": self._backlog_items, "durable_backlog_bytes": self._backlog_size,
                "durable_lost_items": self.lost_items, "durable_resumes": self.resumes}
