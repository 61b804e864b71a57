"""A replay whose storage could not fit in memory once full (replay/store.py ``check_memory``):
with checks on (the item's size is the env's), the replay stops on it as on a configuration
error, before the slots are allocated; without them (the size came from a sender's chunk) that
chunk is rejected. In process; the memory limit is given or patched (the machine's is real in
tests/integration/test_first_contact.py)."""

import logging

import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.errors import ConfigError, MemoryTooSmall
from zenrl.replay import store
from zenrl.replay.service import ReplayService
from zenrl.replay.store import SLOT_OVERHEAD_BYTES, check_memory, memory_limit

B = 8
GIB = 1 << 30


def _payload(seq=0):
    rng = np.random.default_rng(seq)
    data = {"obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32), "action": rng.integers(0, 2, B),
            "reward": np.ones(B, np.float32), "next_obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32),
            "terminated": np.zeros(B, bool), "n": np.ones(B, np.uint8)}
    return P.TransitionBatch("a0", 0, seq, data).encode()


#: the bytes of one stored item of _payload: obs and next_obs 16 each, action 8, reward 4, terminated 1, n 1,
#: and the policy version the replay records with it (int64)
ITEM = 16 + 16 + 8 + 4 + 1 + 1 + 8


def test_the_limit_is_the_machines_memory_or_its_containers_below_it():
    limit = memory_limit()
    assert limit is not None  # Linux
    have, what = limit
    total = next(int(x.split()[1]) * 1024 for x in open("/proc/meminfo") if x.startswith("MemTotal:"))
    assert 0 < have <= total and (what == "the machine's memory") == (have == total)


def test_check_memory_refuses_above_the_limit_and_warns_above_80_percent(caplog):
    limit = (10 * GIB, "the machine's memory")
    per = 1000 - SLOT_OVERHEAD_BYTES  # a slot costs 1000 bytes in all
    with pytest.raises(MemoryTooSmall) as e:
        check_memory(11 * GIB // 1000, per, limit)
    assert str(e.value) == ("replay.capacity = 11,811,160 items of 975 bytes need 11.0 GiB once full, and the "
                            "machine's memory is 10.0 GiB: lower replay.capacity, or set replay.max_bytes to the "
                            "memory the replay may take")
    assert isinstance(e.value, ConfigError)
    with caplog.at_level(logging.WARNING, logger="zenrl.replay.store"):
        check_memory(9 * GIB // 1000, per, limit)  # 90%
        assert len(caplog.records) == 1 and "would take 90% of it once full" in caplog.records[0].getMessage()
        check_memory(7 * GIB // 1000, per, limit)  # 70%: nothing said
        assert len(caplog.records) == 1


def _service(checks: bool, capacity: int):
    sets = [f"replay.capacity={capacity}", "replay.min_size=1", f"replay.check_semantics={str(checks).lower()}"]
    return ReplayService(load_config(None, sets, environ={}), node=None, run_id="r")


def test_a_checked_replay_too_large_for_its_memory_stops_before_allocating(monkeypatch):
    # 1,000 slots of ITEM + overhead bytes against a limit one byte short of them
    monkeypatch.setattr(store, "machine_memory", lambda: (1000 * (ITEM + SLOT_OVERHEAD_BYTES) - 1, "the limit"))
    allocated = []
    real = store.PlainStore.allocate
    monkeypatch.setattr(store.PlainStore, "allocate", classmethod(lambda cls, *a: allocated.append(1) or real(*a)))
    svc = _service(True, 1000)
    assert svc.ingest_many([(_payload(1), "zenrl/r/transitions/a0"), (_payload(2), "zenrl/r/transitions/a0")]) == 0
    assert svc.buffer is None and not allocated  # refused before the slots were allocated
    assert "replay.capacity = 1,000 items of 54 bytes need" in str(svc.ingestor.fatal)
    with pytest.raises(MemoryTooSmall):
        svc.step(0.0)  # the role loop ends the role on it (exit code 2)
    assert svc.ingest_many([(_payload(3), "zenrl/r/transitions/a0")]) == 0  # nothing stored meanwhile
    svc.close()


def test_a_replay_that_fits_is_allocated(monkeypatch):
    monkeypatch.setattr(store, "machine_memory", lambda: (1000 * (ITEM + SLOT_OVERHEAD_BYTES), "the limit"))
    svc = _service(True, 1000)
    assert svc.ingest_many([(_payload(1), "zenrl/r/transitions/a0")]) == B
    assert svc.buffer.capacity == 1000 and svc.buffer.bytes_per_item == ITEM and svc.ingestor.fatal is None
    svc.step(0.0)
    svc.close()


def test_max_bytes_sizes_the_ring_within_the_limit(monkeypatch):
    monkeypatch.setattr(store, "machine_memory", lambda: (1000 * (ITEM + SLOT_OVERHEAD_BYTES), "the limit"))
    svc = ReplayService(load_config(None, ["replay.capacity=1000000", "replay.min_size=1", f"replay.max_bytes={500 * ITEM}"],
                                    environ={}), node=None, run_id="r")
    assert svc.ingest_many([(_payload(1), "zenrl/r/transitions/a0")]) == B
    assert svc.buffer.capacity == 500
    svc.close()


def test_an_unchecked_replay_rejects_the_chunk_that_sized_it(monkeypatch):
    """Without the checks the item's size is the sender's: a chunk must not stop the replay."""
    monkeypatch.setattr(store, "machine_memory", lambda: (100 * (ITEM + SLOT_OVERHEAD_BYTES), "the limit"))
    svc = _service(False, 1000)
    assert svc.ingest_many([(_payload(1), "zenrl/r/transitions/a0")]) == 0
    assert svc.ingestor.fatal is None and svc.stats_values()["rejected_memory"] == 1
    svc.step(0.0)
    svc.close()


def test_a_replay_near_its_limit_is_warned_about_once(monkeypatch, caplog):
    monkeypatch.setattr(store, "machine_memory", lambda: (int(1000 * (ITEM + SLOT_OVERHEAD_BYTES) / 0.9), "the limit"))
    with caplog.at_level(logging.WARNING, logger="zenrl.replay.store"):
        svc = _service(True, 1000)
        assert svc.ingest_many([(_payload(1), "zenrl/r/transitions/a0")]) == B
    said = [r.getMessage() for r in caplog.records if "once full" in r.getMessage()]
    assert len(said) == 1 and "would take 90% of it" in said[0], said
    svc.close()


def test_replays_sharing_a_machine_each_get_their_share(monkeypatch):
    """replay.replays_per_machine = N (`zenrl run` sets it to the replays it starts): a ring that
    fits the machine alone is refused when it does not fit 1/N of it."""
    monkeypatch.setattr(store, "machine_memory", lambda: (10 * GIB, "the machine's memory"))
    assert memory_limit(4) == (10 * GIB // 4, "1/4 of the machine's memory (replay.replays_per_machine = 4)")
    assert memory_limit(1) == memory_limit() == (10 * GIB, "the machine's memory")
    monkeypatch.setattr(store, "machine_memory", lambda: (1500 * (ITEM + SLOT_OVERHEAD_BYTES), "the machine's memory"))
    for share, fits in ((1, True), (2, False)):
        svc = ReplayService(load_config(None, ["replay.capacity=1000", "replay.min_size=1",
                                               f"replay.replays_per_machine={share}"], environ={}), node=None, run_id="r")
        assert svc.ingest_many([(_payload(1), "zenrl/r/transitions/a0")]) == (B if fits else 0)
        if not fits:
            assert "and 1/2 of the machine's memory (replay.replays_per_machine = 2) is" in str(svc.ingestor.fatal)
        svc.close()


def test_zenrl_run_tells_each_replay_how_many_share_the_machine(tmp_path, monkeypatch):
    from pathlib import Path

    from zenrl.launcher import supervisor
    from zenrl.launcher.supervisor import Launcher

    started = []

    class Started:
        pid = 1

        def __init__(self, cmd, **_kw):
            started.append(cmd)

    monkeypatch.setattr(supervisor.subprocess, "Popen", Started)
    root = Path(__file__).resolve().parents[2]
    for cfg, sets, want in ((None, ["replay.shards=3"], 3), (None, [], 1),
                            (root / "configs/burgerwar_league_pfsp.yaml", ["run_id=lg1"], None)):
        la = Launcher(load_config(cfg, [f"runs_dir={tmp_path}", *sets], environ={}))
        (la.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        replays = [c for c in la._plan() if c.role == "replay"]
        want = len(replays) if want is None else want
        assert len(replays) == want and (cfg is None or want > 1)
        started.clear()
        for c in replays:
            la._spawn(c)
        told = [cmd[cmd.index("--set") + 1] if "--set" in cmd else None for cmd in started]
        assert told == ([f"replay.replays_per_machine={want}"] * want if want > 1 else [None]), told
