"""Durable replay: an append-only log of inserted chunks plus periodic priority snapshots, so the
replay's contents survive a SIGKILL losing at most the last ``flush_interval_s`` of inserts.

Layout of the log directory::

    seg-<first key, 16 digits>.log   records, in insert order
    priorities.npz                   keys int64[K], priorities float32[K], inserts_total (atomic)

A record is a 28-byte header ``<magic "ZRL2", first_key u64, n_items u32, length u32,
payload crc32 u32, header crc32 u32>`` followed by ``length`` bytes: the chunk exactly as it came
over the wire (a ``transitions`` message). The header CRC covers the 24 bytes before it (the
payload CRC included), so a flipped bit anywhere in a record, its key and length too, fails it.
Records of the previous format (magic ``"ZRL1"``, the last header field 0 and no header CRC:
only the payload is checked) are still read.

Reading (:meth:`ReplayLog.index`) never stops at a bad record: a record that is short, has a
bad magic, length or CRC is skipped by resynchronizing on the next offset where a whole record
checks (magic, header CRC, payload CRC), and counted (``corrupt_records``); the valid records
after it are kept with the keys their headers carry. Bad bytes with no valid record after them
(a torn tail from a crash) are cut off the file (``torn_records``), so appending after a restore
gives a clean log. A segment is deleted once the ring has overwritten every item in it, so disk
use stays bounded by about ``capacity + segment_items`` items. Nothing here imports zenoh.
"""

from __future__ import annotations

import logging
import mmap
import os
import struct
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from zenrl.common.atomic_files import fsync_dir

log = logging.getLogger(__name__)

MAGIC = b"ZRL2"
#: the previous format: no header CRC (its last header field is 0)
MAGIC_V1 = b"ZRL1"
HEADER = struct.Struct("<4sQIIII")
_HEAD_CRC = struct.Struct("<4sQIII")  # the part of the header its CRC covers
#: a priority snapshot being written (a write killed midway leaves one; removed at start)
SNAPSHOT_TMP = ".priorities.tmp-"


def pack_header(first_key: int, n_items: int, payload: bytes) -> bytes:
    """The 28-byte header of a record of ``payload`` (current format)."""
    head = _HEAD_CRC.pack(MAGIC, first_key, n_items, len(payload), zlib.crc32(payload))
    return head + struct.pack("<I", zlib.crc32(head))


@dataclass(frozen=True)
class Record:
    first_key: int
    n_items: int
    payload: bytes


@dataclass(frozen=True)
class RecordRef:
    """Where a valid record lies: ``path`` and the byte ``offset`` of its payload."""
    path: Path
    offset: int
    first_key: int
    n_items: int
    length: int


def _segment_name(first_key: int) -> str:
    return f"seg-{first_key:016d}.log"


def _record_at(buf: "mmap.mmap", pos: int) -> tuple[int, int, int] | None:
    """``(first_key, n_items, length)`` of the valid record at ``pos`` of ``buf``, else None."""
    if len(buf) - pos < HEADER.size:
        return None
    magic, key, n, length, crc, hcrc = HEADER.unpack_from(buf, pos)
    if magic == MAGIC:
        if zlib.crc32(buf[pos:pos + _HEAD_CRC.size]) != hcrc:
            return None
    elif magic != MAGIC_V1 or hcrc != 0:
        return None
    start = pos + HEADER.size
    if not 0 < length <= len(buf) - start or zlib.crc32(buf[start:start + length]) != crc:
        return None
    return key, n, length


def _next_record(buf: "mmap.mmap", pos: int) -> int:
    """The first offset after ``pos`` where a valid record starts; -1 if none."""
    while True:
        cands = [i for i in (buf.find(MAGIC, pos + 1), buf.find(MAGIC_V1, pos + 1)) if i >= 0]
        if not cands:
            return -1
        pos = min(cands)
        if _record_at(buf, pos) is not None:
            return pos


class ReplayLog:
    """Writer and reader of one replay's log directory.

    ``append`` is cheap (a buffered write); ``maybe_flush`` fsyncs at most every
    ``flush_interval_s``; ``prune`` deletes fully overwritten segments. Opening a directory
    removes the temporary file of a snapshot write that was killed midway.
    """

    def __init__(self, directory: str | os.PathLike[str], segment_items: int, flush_interval_s: float = 1.0) -> None:
        if segment_items < 1:
            raise ValueError(f"segment_items must be >= 1, got {segment_items}")
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.segment_items = segment_items
        self.flush_interval_s = flush_interval_s
        self._f = None
        self._seg_path: Path | None = None
        self._seg_items = 0
        #: size of the open segment at its last fsync (a failed write is cut back to it)
        self._flushed_size = 0
        self._last_flush = time.monotonic()
        self.bytes_written = 0
        self.torn_records = 0
        self.corrupt_records = 0
        self.corrupt_bytes = 0
        self.snapshot_unreadable = 0
        self._next_key = 0
        #: every item with a key below this is on disk (fsynced)
        self.durable_through = 0
        for tmp in self.dir.glob(SNAPSHOT_TMP + "*"):
            log.info("removing %s, left by a snapshot write that was killed", tmp.name)
            try:
                tmp.unlink(missing_ok=True)
            except OSError as e:
                log.warning("could not remove %s: %s", tmp.name, e)

    # -- reading ---------------------------------------------------------------------------
    def segments(self) -> list[Path]:
        return sorted(self.dir.glob("seg-*.log"))

    def index(self) -> list[RecordRef]:
        """Every valid record, oldest first, without reading payloads into memory. Bad bytes are
        skipped up to the next valid record (``corrupt_records``, ``corrupt_bytes``); bad bytes
        at the end of a segment (a torn tail) are cut off the file (``torn_records``)."""
        refs: list[RecordRef] = []
        for seg in self.segments():
            try:
                refs.extend(self._index_segment(seg))
            except OSError as e:  # an unreadable segment (EIO, not a file) costs its records only
                self.corrupt_records += 1
                log.warning("replay log %s unreadable (%s); its records are skipped", seg.name, e)
        return refs

    def _index_segment(self, seg: Path) -> list[RecordRef]:
        refs: list[RecordRef] = []
        cut = None
        with open(seg, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size == 0:
                return refs
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
                pos = 0
                while pos < size:
                    rec = _record_at(buf, pos)
                    if rec is None:
                        nxt = _next_record(buf, pos)
                        if nxt < 0:
                            cut = pos
                            break
                        self.corrupt_records += 1
                        self.corrupt_bytes += nxt - pos
                        log.warning("replay log %s: %d bad bytes at byte %d skipped; the records after them "
                                    "are kept", seg.name, nxt - pos, pos)
                        pos = nxt
                        continue
                    key, n, length = rec
                    refs.append(RecordRef(seg, pos + HEADER.size, key, n, length))
                    pos += HEADER.size + length
        if cut is not None:
            self.torn_records += 1
            log.warning("replay log %s: torn or corrupt record at byte %d with no valid record after it; "
                        "truncating there", seg.name, cut)
            try:
                os.truncate(seg, cut)
            except OSError as e:  # then the reader skips those bytes again next time
                log.warning("replay log %s: could not truncate (%s)", seg.name, e)
        return refs

    def read_ref(self, ref: RecordRef) -> Record:
        """The record ``ref`` points at (as found by :meth:`index`)."""
        with open(ref.path, "rb") as f:
            f.seek(ref.offset)
            return Record(ref.first_key, ref.n_items, f.read(ref.length))

    def read(self) -> Iterator[Record]:
        """Every valid record, oldest first (see :meth:`index`)."""
        for ref in self.index():
            yield self.read_ref(ref)

    def load_priorities(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(keys int64[K], priorities float32[K])`` of the snapshot, or None when there is none
        or it is unreadable (truncated, not an npz, fields missing or of the wrong shape,
        non-finite or negative priorities): counted in ``snapshot_unreadable``, never raised."""
        p = self.dir / "priorities.npz"
        if not p.exists():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                keys, prios = z["keys"], z["priorities"]
            if keys.ndim != 1 or prios.shape != keys.shape or keys.dtype.kind not in "iu" or prios.dtype.kind != "f":
                raise ValueError(f"keys {keys.dtype}{list(keys.shape)} and priorities {prios.dtype}{list(prios.shape)} "
                                 "are not two 1-D arrays of equal length")
            if not (np.isfinite(prios).all() and (prios >= 0).all()):
                raise ValueError("priorities not all finite and >= 0")
            return keys.astype(np.int64), prios.astype(np.float32)
        except Exception as e:  # noqa: BLE001 - zipfile, zlib, EOF, format errors: none may stop start-up
            self.snapshot_unreadable += 1
            log.warning("priority snapshot %s unreadable (%s: %s); using the priorities logged at insert",
                        p.name, type(e).__name__, e)
            return None

    # -- writing ---------------------------------------------------------------------------
    def append(self, first_key: int, n_items: int, payload: bytes) -> None:
        if self._f is None or self._seg_items >= self.segment_items:
            self._roll(first_key)
        self._write(first_key, n_items, payload)

    def _write(self, first_key: int, n_items: int, payload: bytes) -> None:
        self._f.write(pack_header(first_key, n_items, payload))
        self._f.write(payload)
        self._seg_items += n_items
        self._next_key = first_key + n_items
        self.bytes_written += HEADER.size + len(payload)

    def _roll(self, first_key: int) -> None:
        if self._f is not None:
            self.flush()
            self._f.close()
            self._f = None
        self._seg_path = self.dir / _segment_name(first_key)
        self._f = open(self._seg_path, "ab")
        self._flushed_size = self._f.tell()
        self._seg_items = 0

    def flush(self) -> None:
        if self._f is not None:
            self._f.flush()
            os.fsync(self._f.fileno())
            self._flushed_size = self._f.tell()
        self.durable_through = self._next_key
        self._last_flush = time.monotonic()

    def maybe_flush(self) -> bool:
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()
            return True
        return False

    def snapshot_priorities(self, keys: np.ndarray, priorities: np.ndarray, inserts_total: int) -> None:
        """Write the snapshot atomically: a temporary file, fsynced, renamed over the old one,
        then the directory fsynced (the rename itself durable). A failed write removes its
        temporary file and raises."""
        tmp = self.dir / f"{SNAPSHOT_TMP}{os.getpid()}.npz"
        try:
            with open(tmp, "wb") as f:
                np.savez(f, keys=np.asarray(keys, np.int64), priorities=np.asarray(priorities, np.float32),
                         inserts_total=np.array(inserts_total, np.int64))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.dir / "priorities.npz")
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        fsync_dir(self.dir)

    def prune(self, oldest_live_key: int) -> int:
        """Delete segments whose every item has a key below ``oldest_live_key``."""
        segs = self.segments()
        removed = 0
        for seg, nxt in zip(segs, segs[1:]):  # never the newest (it is being written)
            if int(nxt.name[4:20]) <= oldest_live_key:
                try:
                    seg.unlink(missing_ok=True)
                except OSError as e:  # not worth degrading the log for: it is retried at the next prune
                    log.warning("replay log: could not delete %s: %s", seg.name, e)
                    continue
                removed += 1
        return removed

    def disk_bytes(self) -> int:
        total = 0
        for p in self.dir.iterdir():
            try:
                total += p.stat().st_size if p.is_file() else 0
            except OSError:  # removed meanwhile
                pass
        return total

    def close(self) -> None:
        if self._f is not None:
            self.flush()
            self._f.close()
            self._f = None
