"""Durable replay: an append-only log of inserted chunks plus periodic priority snapshots, so the
replay's contents survive a SIGKILL losing at most the last ``flush_interval_s`` of inserts.

Layout of the log directory::

    seg-<first key, 16 digits>.log   records, in insert order
    priorities.npz                   keys int64[K], priorities float32[K], inserts_total (atomic)

A record is a 28-byte header ``<magic "ZRL1", first_key u64, n_items u32, length u32,
crc32 u32, reserved u32>`` followed by ``length`` bytes: the chunk exactly as it came over the
wire (a ``transitions`` message). Replaying a segment stops at the first record that is short
or fails its CRC (a torn tail from a crash) and truncates the file there. A segment is deleted
once the ring has overwritten every item in it, so disk use stays bounded by about
``capacity + segment_items`` items. Nothing here imports zenoh.
"""

from __future__ import annotations

import logging
import os
import struct
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

log = logging.getLogger(__name__)

MAGIC = b"ZRL1"
HEADER = struct.Struct("<4sQIIII")


@dataclass(frozen=True)
class Record:
    first_key: int
    n_items: int
    payload: bytes


def _segment_name(first_key: int) -> str:
    return f"seg-{first_key:016d}.log"


class ReplayLog:
    """Writer and reader of one replay's log directory.

    ``append`` is cheap (a buffered write); ``maybe_flush`` fsyncs at most every
    ``flush_interval_s``; ``prune`` deletes fully overwritten segments.
    """

    def __init__(self, directory: str | os.PathLike[str], segment_items: int, flush_interval_s: float = 1.0) -> None:
        if segment_items < 1:
            raise ValueError(f"segment_items must be >= 1, got {segment_items}")
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.segment_items = segment_items
        self.flush_interval_s = flush_interval_s
        self._f = None
        self._seg_items = 0
        self._last_flush = time.monotonic()
        self.bytes_written = 0
        self.torn_records = 0
        self._next_key = 0
        #: every item with a key below this is on disk (fsynced)
        self.durable_through = 0

    # -- reading ---------------------------------------------------------------------------
    def segments(self) -> list[Path]:
        return sorted(self.dir.glob("seg-*.log"))

    def read(self) -> Iterator[Record]:
        """Every intact record, oldest first; a torn tail is reported, truncated and skipped."""
        for seg in self.segments():
            with open(seg, "r+b") as f:
                good = 0
                while True:
                    head = f.read(HEADER.size)
                    if not head:
                        break
                    rec = None
                    if len(head) == HEADER.size:
                        magic, key, n, length, crc, _ = HEADER.unpack(head)
                        if magic == MAGIC:
                            payload = f.read(length)
                            if len(payload) == length and zlib.crc32(payload) == crc:
                                rec = Record(key, n, payload)
                    if rec is None:
                        self.torn_records += 1
                        log.warning("replay log %s: torn or corrupt record at byte %d; truncating there", seg.name, good)
                        f.truncate(good)
                        break
                    good = f.tell()
                    yield rec

    def load_priorities(self) -> tuple[np.ndarray, np.ndarray] | None:
        p = self.dir / "priorities.npz"
        if not p.exists():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                return z["keys"].astype(np.int64), z["priorities"].astype(np.float32)
        except (OSError, ValueError, KeyError) as e:
            log.warning("priority snapshot unreadable (%s); using the priorities logged at insert", e)
            return None

    # -- writing ---------------------------------------------------------------------------
    def append(self, first_key: int, n_items: int, payload: bytes) -> None:
        if self._f is None or self._seg_items >= self.segment_items:
            self._roll(first_key)
        self._f.write(HEADER.pack(MAGIC, first_key, n_items, len(payload), zlib.crc32(payload), 0))
        self._f.write(payload)
        self._seg_items += n_items
        self._next_key = first_key + n_items
        self.bytes_written += HEADER.size + len(payload)

    def _roll(self, first_key: int) -> None:
        if self._f is not None:
            self.flush()
            self._f.close()
        self._f = open(self.dir / _segment_name(first_key), "ab")
        self._seg_items = 0

    def flush(self) -> None:
        if self._f is not None:
            self._f.flush()
            os.fsync(self._f.fileno())
        self.durable_through = self._next_key
        self._last_flush = time.monotonic()

    def maybe_flush(self) -> bool:
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()
            return True
        return False

    def snapshot_priorities(self, keys: np.ndarray, priorities: np.ndarray, inserts_total: int) -> None:
        tmp = self.dir / f".priorities.tmp-{os.getpid()}.npz"
        with open(tmp, "wb") as f:
            np.savez(f, keys=np.asarray(keys, np.int64), priorities=np.asarray(priorities, np.float32),
                     inserts_total=np.array(inserts_total, np.int64))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.dir / "priorities.npz")

    def prune(self, oldest_live_key: int) -> int:
        """Delete segments whose every item has a key below ``oldest_live_key``."""
        segs = self.segments()
        removed = 0
        for seg, nxt in zip(segs, segs[1:]):  # never the newest (it is being written)
            if int(nxt.name[4:20]) <= oldest_live_key:
                seg.unlink(missing_ok=True)
                removed += 1
        return removed

    def disk_bytes(self) -> int:
        return sum(p.stat().st_size for p in self.dir.iterdir() if p.is_file())

    def close(self) -> None:
        if self._f is not None:
            self.flush()
            self._f.close()
            self._f = None
