"""Faults on the replay's disk: a bad record anywhere in a segment, a truncated priority
snapshot, a killed snapshot write, and a disk that fails (injected errors and a real full tmpfs).
None may stop start-up or ingest, and no restored item may change its key."""

import errno
import os
import shutil
import struct
import zlib

import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.replay import durable
from zenrl.replay.durable import HEADER, MAGIC_V1, ReplayLog, pack_header
from zenrl.replay.journal import contiguous_suffix
from zenrl.replay.service import ReplayService


def _payload(i, b=16, seed=0):
    rng = np.random.default_rng(seed + i)
    data = {"obs": rng.random((b, 4), dtype=np.float32) * 0.4, "action": rng.integers(0, 2, b),
            "reward": np.full(b, i, np.float32), "next_obs": rng.random((b, 4), dtype=np.float32) * 0.4,
            "terminated": np.zeros(b, bool), "n": np.full(b, 3, np.uint8)}
    return P.TransitionBatch("a0", i, i, data, rng.random(b).astype(np.float32) + 0.1).encode()


def _service(log_dir, **over):
    sets = [f"replay.{k}={v}" for k, v in {"durable": True, "capacity": 1000, "segment_items": 100,
                                             "log_dir": str(log_dir), **over}.items()]
    return ReplayService(load_config(None, sets, environ={}), node=None, run_id="r")


def _by_key(svc):
    """``{key: reward}`` of every stored item (a chunk's reward is its index: the brute-force
    reference of which chunk each key holds)."""
    b = svc.buffer
    keys = b._keys[b._keys >= 0]
    return dict(zip(keys.tolist(), b._data["reward"][keys % b.capacity].tolist()))


# -- the record reader against a brute-force reference ---------------------------------------------
def _write_log(tmp_path, sizes, first=0):
    """A log of records with payloads of ``sizes`` bytes, each of 3 items; returns (path, spans):
    the byte span of each record in the segment and its key."""
    log = ReplayLog(tmp_path, 10**6)
    spans, key = [], first
    for i, n in enumerate(sizes):
        payload = bytes((i * 7 + j) % 251 for j in range(n))
        start = log.bytes_written
        log.append(key, 3, payload)
        spans.append((start, log.bytes_written, key, payload))
        key += 3
    log.close()
    return log.segments()[0], spans


def _intact(spans, damaged):
    """Brute force: the records none of whose bytes is in ``damaged`` (a set of offsets)."""
    return [(k, p) for a, b, k, p in spans if not any(a <= d < b for d in damaged)]


def _read(tmp_path):
    log = ReplayLog(tmp_path, 10**6)
    return [(r.first_key, r.payload) for r in log.read()], log


def test_a_flipped_byte_anywhere_costs_only_its_record(tmp_path):
    seg, spans = _write_log(tmp_path, [5, 40, 1, 17, 33, 2])
    clean = seg.read_bytes()
    for off in range(len(clean)):
        bad = bytearray(clean)
        bad[off] ^= 0x5A
        seg.write_bytes(bytes(bad))
        got, log = _read(tmp_path)
        assert got == _intact(spans, {off}), off
        assert log.corrupt_records + log.torn_records == 1, off


def test_garbage_between_records_and_wrong_length_prefixes(tmp_path):
    seg, spans = _write_log(tmp_path, [20, 20, 20, 20])
    clean = seg.read_bytes()
    everything = _intact(spans, set())
    # garbage inserted between records 1 and 2 (nothing lost), magic lookalikes included
    cut = spans[2][0]
    seg.write_bytes(clean[:cut] + b"ZRL2" + b"\xff" * 30 + b"ZRL1" + bytes(24) + clean[cut:])
    got, log = _read(tmp_path)
    assert got == everything and log.corrupt_records == 1 and log.torn_records == 0
    # record 1's length prefix says more, then less, than its payload
    for delta in (+7, -7, 2**31):
        bad = bytearray(clean)
        a = spans[1][0]
        (length,) = struct.unpack_from("<I", bad, a + 16)
        struct.pack_into("<I", bad, a + 16, (length + delta) % 2**32)
        seg.write_bytes(bytes(bad))
        got, _ = _read(tmp_path)
        assert got == _intact(spans, {a + 16}), delta
    # a whole record overwritten with random bytes
    bad = bytearray(clean)
    a, b = spans[2][:2]
    bad[a:b] = np.random.default_rng(0).integers(0, 256, b - a, dtype=np.uint8).tobytes()
    seg.write_bytes(bytes(bad))
    assert _read(tmp_path)[0] == _intact(spans, {a})


def test_a_cut_at_every_offset_keeps_the_whole_records_and_truncates(tmp_path):
    seg, spans = _write_log(tmp_path, [9, 30, 1, 12])
    clean = seg.read_bytes()
    for cut in range(len(clean) + 1):
        seg.write_bytes(clean[:cut])
        got, log = _read(tmp_path)
        assert got == [(k, p) for a, b, k, p in spans if b <= cut], cut
        whole = max([b for a, b, _, _ in spans if b <= cut], default=0)
        assert seg.stat().st_size == whole and log.torn_records == (cut != whole), cut


def test_old_format_records_are_still_read(tmp_path):
    recs = [(0, 16, _payload(0)), (16, 16, _payload(1))]
    with open(tmp_path / "seg-0000000000000000.log", "wb") as f:
        for key, n, p in recs:
            f.write(HEADER.pack(MAGIC_V1, key, n, len(p), zlib.crc32(p), 0) + p)
    svc = _service(tmp_path)
    assert svc.buffer.size == 32 and _by_key(svc) == {k: float(k // 16) for k in range(32)}
    svc.ingest(_payload(2))  # appended in the new format after the old records
    svc.close()
    assert _by_key(_service(tmp_path)) == {k: float(k // 16) for k in range(48)}


def test_contiguous_suffix():
    R = durable.RecordRef
    refs = [R(None, 0, k, n, 0) for k, n in [(0, 3), (3, 3), (9, 3), (12, 1), (13, 2)]]
    assert contiguous_suffix(refs) == 2
    assert contiguous_suffix(refs[:2]) == 0 and contiguous_suffix([]) == 0
    assert contiguous_suffix(refs[:2] + [R(None, 0, 1, 5, 0)]) == 2  # keys going back: a break too
    # a record of no items (frames only) holds no key, whatever its header says
    assert contiguous_suffix(refs[:2] + [R(None, 0, 99, 0, 0), R(None, 0, 6, 2, 0)]) == 0


def test_a_bad_record_in_the_middle_neither_stops_start_up_nor_moves_keys(tmp_path):
    a = _service(tmp_path, segment_items=1000)
    for i in range(12):
        a.ingest(_payload(i))
    a.close()
    seg = a.journal.segments()[0]
    rec = HEADER.size + len(_payload(0))
    blob = bytearray(seg.read_bytes())
    blob[5 * rec + 40] ^= 1  # inside chunk 5 (keys 80..95)
    seg.write_bytes(bytes(blob))
    b = _service(tmp_path, segment_items=1000)
    # the chunks after the bad one, with their own keys (reward i = chunk i = keys 16i..16i+15)
    assert _by_key(b) == {k: float(k // 16) for k in range(96, 192)}
    assert b.journal.corrupt_records == 1 and b.journal.skipped_items == 5 * 16
    assert b.stats_values()["log_corrupt_records"] == 1
    assert b.ingest(_payload(12)) == 16 and b.buffer.inserts_total == 208  # keys go on
    b.close()
    assert set(_by_key(_service(tmp_path, segment_items=1000))) == set(range(96, 208))


# -- the priority snapshot -----------------------------------------------------------------------
def test_a_truncated_priority_snapshot_at_every_offset(tmp_path):
    a = _service(tmp_path / "log")
    for i in range(6):
        a.ingest(_payload(i))
    keys = np.arange(0, 96, 5)
    a.buffer.update_priorities(keys, np.full(keys.size, 77.0, np.float32))
    a.close()
    snap = tmp_path / "log" / "priorities.npz"
    full = snap.read_bytes()
    want_logged = _service(tmp_path / "ref")  # the same chunks, no snapshot: priorities logged at insert
    for i in range(6):
        want_logged.ingest(_payload(i))
    all_keys = np.arange(96)
    logged = want_logged.buffer.priorities_of(all_keys)
    log = ReplayLog(tmp_path / "log", 100)
    for cut in range(len(full)):
        snap.write_bytes(full[:cut])
        assert log.load_priorities() is None, cut
    assert log.snapshot_unreadable == len(full)
    for cut in list(range(0, len(full), 97)) + [len(full) - 1]:  # through the whole restore
        snap.write_bytes(full[:cut])
        b = _service(tmp_path / "log")
        assert _by_key(b) == {k: float(k // 16) for k in range(96)}, cut
        np.testing.assert_allclose(b.buffer.priorities_of(all_keys), logged)
        assert b.stats_values()["log_snapshot_unreadable"] == 1
    snap.write_bytes(full)
    np.testing.assert_allclose(_service(tmp_path / "log").buffer.priorities_of(all_keys),
                               a.buffer.priorities_of(all_keys))


def test_a_snapshot_of_wrong_shapes_or_values_is_refused(tmp_path):
    log = ReplayLog(tmp_path, 10)
    for keys, prios in [(np.arange(3), np.ones(2)), (np.arange(2), np.array([1.0, np.nan])),
                        (np.arange(2), np.array([1.0, -1.0])), (np.ones((2, 2)), np.ones((2, 2)))]:
        np.savez(tmp_path / "priorities.npz", keys=keys, priorities=prios, inserts_total=np.array(3))
        assert log.load_priorities() is None
    assert log.snapshot_unreadable == 4


def test_killed_snapshot_write_leaves_nothing_and_the_rename_is_made_durable(tmp_path, monkeypatch):
    (tmp_path / ".priorities.tmp-4242.npz").write_bytes(b"half a snapshot")
    synced = []
    monkeypatch.setattr(durable, "fsync_dir", lambda d: synced.append(d))
    log = ReplayLog(tmp_path, 10)
    assert not list(tmp_path.glob(".priorities.tmp-*"))
    log.snapshot_priorities(np.arange(3), np.ones(3), 3)
    assert synced == [tmp_path] and (tmp_path / "priorities.npz").exists()
    monkeypatch.setattr(durable.np, "savez", lambda *a, **k: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
    with pytest.raises(OSError):
        log.snapshot_priorities(np.arange(3), np.ones(3), 3)
    assert not list(tmp_path.glob(".priorities.tmp-*"))  # a failed write removes its temp file


# -- a failing disk ------------------------------------------------------------------------------
class _Disk:
    """os.fsync failing with ``err`` while ``full`` (the write of a full disk surfaces at fsync)."""

    def __init__(self, monkeypatch, err):
        self.full, self.err, real = False, err, os.fsync

        def fsync(fd):
            if self.full:
                raise OSError(self.err, os.strerror(self.err))
            real(fd)
        monkeypatch.setattr(durable.os, "fsync", fsync)


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EDQUOT, errno.EIO])
def test_injected_disk_error_degrades_then_resumes_and_a_restart_restores_memory(tmp_path, monkeypatch, err):
    disk = _Disk(monkeypatch, err)
    a = _service(tmp_path, flush_interval_s=0.000001, durable_retry_s=0.000001, segment_items=48, min_size=1)
    for i in range(5):
        a.ingest(_payload(i))
    disk.full = True
    for i in range(5, 20):
        assert a.ingest(_payload(i)) == 16  # ingest goes on
    s = a.stats_values()
    assert s["durable_degraded"] == 1 and s["durable_disk_errors"] >= 2 and os.strerror(err) in s["durable_error"]
    assert s["durable_backlog_items"] >= 15 * 16 and s["inserted_total"] == 320
    reply = a.sample_reply(P.SampleRequest(1, 32, 0.4))
    assert reply.status == "ok" and reply.keys.size == 32  # samples answered from memory
    disk.full = False
    a.ingest(_payload(20))  # the next insert retries the log, which resumes
    s = a.stats_values()
    assert s["durable_degraded"] == 0 and s["durable_resumes"] == 1 and s["durable_backlog_items"] == 0
    assert s["durable_through"] == 336 and s["durable_lost_items"] == 0
    for i in range(21, 25):
        a.ingest(_payload(i))
    a.close()
    b = _service(tmp_path, segment_items=48)
    assert _by_key(b) == _by_key(a) == {k: float(k // 16) for k in range(400)}
    assert b.journal.corrupt_records == 0 and b.journal.skipped_items == 0


def test_a_crash_while_degraded_restores_what_was_logged_before(tmp_path, monkeypatch):
    disk = _Disk(monkeypatch, errno.ENOSPC)
    a = _service(tmp_path, flush_interval_s=0.000001, durable_retry_s=1000, segment_items=1000)
    for i in range(5):
        a.ingest(_payload(i))
    disk.full = True
    for i in range(5, 9):
        a.ingest(_payload(i))
    # SIGKILL now: what the disk got is what the last fsync covered
    b = _service(tmp_path, segment_items=1000)
    assert set(_by_key(b)) == set(range(a.journal.durable_through)) and a.journal.durable_through >= 64


def test_a_backlog_past_its_cap_drops_its_oldest_and_a_restart_keeps_keys(tmp_path, monkeypatch):
    disk = _Disk(monkeypatch, errno.ENOSPC)
    cap = 3 * len(_payload(0))
    a = _service(tmp_path, flush_interval_s=0.000001, durable_retry_s=1000, durable_backlog_bytes=cap,
                 segment_items=1000)
    for i in range(4):
        a.ingest(_payload(i))
    disk.full = True
    for i in range(4, 12):
        a.ingest(_payload(i))
    s = a.stats_values()
    assert s["durable_backlog_items"] == 3 * 16 and s["durable_lost_items"] == 5 * 16
    disk.full = False
    a.journal.resume(a.buffer)
    a.close()
    b = _service(tmp_path, segment_items=1000)
    # the log: chunks 0-3, a gap (4-8 lost), 9-11 from the backlog: the suffix after the gap
    assert _by_key(b) == {k: float(k // 16) for k in range(9 * 16, 12 * 16)}
    assert b.journal.skipped_items == 4 * 16


def test_overwritten_chunks_leave_the_backlog_without_loss(tmp_path, monkeypatch):
    disk = _Disk(monkeypatch, errno.ENOSPC)
    a = _service(tmp_path, capacity=64, flush_interval_s=0.000001, durable_retry_s=1000, segment_items=32)
    a.ingest(_payload(0))
    disk.full = True
    for i in range(1, 30):
        a.ingest(_payload(i))
    assert a.stats_values()["durable_backlog_items"] <= 64 + 16 and a.journal.lost_items == 0
    disk.full = False
    a.journal.resume(a.buffer)
    a.close()
    assert _by_key(_service(tmp_path, capacity=64, segment_items=32)) == _by_key(a)


@pytest.fixture
def small_disk(tmpfs):
    return tmpfs("1m")


def test_a_real_full_disk(small_disk):
    log_dir = small_disk / "log"
    a = _service(log_dir, flush_interval_s=0.000001, durable_retry_s=0.000001, segment_items=64, capacity=4000)
    filler = small_disk / "filler"
    with open(filler, "wb") as f:  # leave about 20 records of room
        f.write(b"\0" * (shutil.disk_usage(small_disk).free - 20 * (HEADER.size + len(_payload(0)))))
    n = 0
    while not a.journal.degraded:
        assert a.ingest(_payload(n)) == 16
        n += 1
        assert n < 200, "the disk never filled"
    for i in range(n, n + 40):  # well past the full disk
        assert a.ingest(_payload(i)) == 16
    s = a.stats_values()
    assert s["durable_degraded"] == 1 and "No space left" in s["durable_error"] and s["inserted_total"] == (n + 40) * 16
    filler.unlink()
    a.ingest(_payload(n + 40))
    assert a.stats_values()["durable_degraded"] == 0
    a.close()
    b = _service(log_dir, segment_items=64, capacity=4000)
    assert _by_key(b) == {k: float(k // 16) for k in range((n + 41) * 16)}
    assert b.journal.corrupt_records == 0


def test_pack_header_covers_every_header_byte():
    h = pack_header(5, 3, b"abc")
    for i in range(24):
        bad = bytearray(h)
        bad[i] ^= 0x10
        assert zlib.crc32(bytes(bad[:24])) != struct.unpack("<I", h[24:])[0]


def test_an_unreadable_segment_costs_only_its_records(tmp_path):
    a = _service(tmp_path, segment_items=32)
    for i in range(6):
        a.ingest(_payload(i))
    a.close()
    segs = a.journal.segments()
    assert len(segs) == 3
    segs[0].unlink()
    segs[0].mkdir()  # open() of it raises an OSError, as a segment on a failing sector would
    b = _service(tmp_path, segment_items=32)
    assert _by_key(b) == {k: float(k // 16) for k in range(32, 96)} and b.journal.corrupt_records == 1
