"""The replay's journal (``replay.durable``): what survives a restart.

Every chunk the replay inserts is appended to an append-only log as the bytes it arrived as, with
the key of its first item (:class:`~zenrl.replay.durable.ReplayLog` holds the file format:
segments, records, fsync, pruning, priority snapshots). :class:`Journal` adds how the service uses
it: :meth:`Journal.restore` rebuilds the storage at start-up (the same keys as before, then the
newest priority snapshot: keys overwritten since are ignored), :meth:`Journal.after_insert` keeps
the cadence (fsync every ``replay.flush_interval_s``, then drop the segments the ring has
overwritten; a priority snapshot every ``replay.snapshot_interval_s``), :meth:`Journal.finish`
writes the final snapshot and closes the log on stop. Callers hold the replay's lock.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from zenrl.common import protocol as P
from zenrl.common.errors import ProtocolError
from zenrl.replay.durable import ReplayLog

log = logging.getLogger(__name__)


class Journal(ReplayLog):
    """A :class:`ReplayLog` in ``directory`` plus the replay's restore and snapshot cadence."""

    def __init__(self, directory: str | Path, segment_items: int, flush_interval_s: float,
                 snapshot_interval_s: float) -> None:
        super().__init__(directory, segment_items, flush_interval_s)
        self.snapshot_interval_s = snapshot_interval_s
        self._last_snapshot = time.monotonic()

    def restore(self, ingest: Any, max_bytes: int) -> int:
        """Insert every record of the log through ``ingest.insert_logged`` (an
        :class:`~zenrl.replay.ingest.Ingest`, which allocates the storage from the first one),
        then apply the newest priority snapshot. Returns the items restored."""
        records = 0
        for rec in self.read():
            try:
                msg = P.TransitionBatch.decode(rec.payload, max_bytes)
            except ProtocolError as e:  # cannot happen for records we wrote; never fatal
                log.warning("skipping an undecodable log record: %s", e)
                continue
            records += ingest.insert_logged(msg, rec.payload, rec.first_key) is not None
        if ingest.store is None:
            return 0
        buf = ingest.store.buffer
        snap = self.load_priorities()
        if snap is not None:
            buf.update_priorities(*snap)
        log.info("replay restored %d items (keys up to %d) from %d log records", buf.size, buf.inserts_total - 1, records)
        return buf.size

    def after_insert(self, buffer: Any) -> None:
        """After chunks were appended: fsync when due (then prune what the ring overwrote) and
        snapshot the priorities when due."""
        if self.maybe_flush():
            self.prune(buffer.inserts_total - buffer.capacity)
        if time.monotonic() - self._last_snapshot >= self.snapshot_interval_s:
            self.snapshot(buffer)

    def snapshot(self, buffer: Any) -> None:
        """Flush, then write a priority snapshot of ``buffer`` (None: nothing stored yet)."""
        if buffer is None:
            return
        keys, prios = buffer.raw_priorities()
        self.flush()
        self.snapshot_priorities(keys, prios, buffer.inserts_total)
        self._last_snapshot = time.monotonic()

    def finish(self, buffer: Any) -> None:
        """On stop: the final snapshot, then close the log."""
        self.snapshot(buffer)
        self.close()

    def stats_values(self) -> dict[str, Any]:
        return {"log_bytes_written": self.bytes_written, "log_disk_bytes": self.disk_bytes(),
                "log_torn_records": self.torn_records, "durable_through": self.durable_through}
