"""Durable replay log: restore after a crash, torn tail skipped, bounded disk use."""

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.replay.durable import HEADER, ReplayLog
from zenrl.replay.service import ReplayService


def _payload(i, b=16, seed=0):
    rng = np.random.default_rng(seed + i)
    data = {"obs": rng.random((b, 4), dtype=np.float32) * 0.4, "action": rng.integers(0, 2, b),
            "reward": np.full(b, i, np.float32), "next_obs": rng.random((b, 4), dtype=np.float32) * 0.4,
            "terminated": np.zeros(b, bool), "n": np.full(b, 3, np.uint8)}
    return P.TransitionBatch("a0", i, i, data, rng.random(b).astype(np.float32) + 0.1).encode()


def _service(tmp_path, **over):
    sets = [f"replay.{k}={v}" for k, v in {"durable": True, "capacity": 1000, "segment_items": 100,
                                             "log_dir": str(tmp_path / "log"), **over}.items()]
    return ReplayService(load_config(None, sets, environ={}), node=None, run_id="r")


def test_restore_gives_back_items_keys_and_priorities(tmp_path):
    a = _service(tmp_path)
    for i in range(20):
        assert a.ingest(_payload(i)) == 16
    keys = np.arange(0, 320, 7, dtype=np.int64)
    a.buffer.update_priorities(keys, np.full(keys.size, 50.0))
    a.close()  # SIGTERM path: flush + snapshot

    b = _service(tmp_path)
    assert b.buffer.size == 320 and b.buffer.inserts_total == 320
    np.testing.assert_allclose(b.buffer.priorities_of(keys), a.buffer.priorities_of(keys))
    for f in a.buffer.spec:
        np.testing.assert_array_equal(b.buffer._data[f], a.buffer._data[f])
    # new inserts continue the key sequence
    assert b.ingest(_payload(99)) == 16 and b.buffer.inserts_total == 336


def test_crash_keeps_everything_up_to_the_last_flush_and_skips_a_torn_tail(tmp_path):
    a = _service(tmp_path, flush_interval_s=1000)  # no periodic flush: we flush by hand
    for i in range(10):
        a.ingest(_payload(i))
    a.journal.flush()
    flushed = a.journal.durable_through
    for i in range(10, 13):
        a.ingest(_payload(i))
    a.journal._f.flush()  # what reached the OS before a SIGKILL ...
    seg = a.journal.segments()[-1]
    size = seg.stat().st_size
    with open(seg, "r+b") as f:  # ... with the last record torn mid-write
        f.truncate(size - 100)
    b = _service(tmp_path)
    assert b.buffer.size >= flushed == 160
    assert b.buffer.size == 12 * 16  # 12 intact records, the torn 13th skipped
    assert b.journal.torn_records == 1
    assert seg.stat().st_size < size - 100  # the torn bytes were cut off
    # the torn bytes were cut off, so appending after restore yields a clean log
    b.ingest(_payload(50))
    b.close()
    c = _service(tmp_path)
    assert c.buffer.size == 13 * 16 and c.journal.torn_records == 0


def test_disk_use_is_bounded_over_many_ring_wraps(tmp_path):
    a = _service(tmp_path, capacity=200, segment_items=48, flush_interval_s=0.000001)
    record = HEADER.size + len(_payload(0))
    peak = 0
    for i in range(200):  # 3200 items = 16 wraps of the ring
        a.ingest(_payload(i))
        peak = max(peak, a.journal.disk_bytes())
    bound = ((200 + 2 * 48) // 16 + 2) * record + 64_000  # ring + two segments + the snapshot
    assert peak <= bound, (peak, bound)
    assert len(a.journal.segments()) <= 200 // 48 + 3
    a.close()
    b = _service(tmp_path, capacity=200, segment_items=48)
    assert b.buffer.size == 200 and b.buffer.inserts_total == 3200


def test_log_reader_on_garbage(tmp_path):
    log = ReplayLog(tmp_path, 10)
    (tmp_path / "seg-0000000000000000.log").write_bytes(b"not a log at all" * 10)
    assert list(log.read()) == [] and log.torn_records == 1
