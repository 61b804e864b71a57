"""A durable replay whose log disk fills up under it (a real 4 MiB tmpfs): ingest and sampling
go on from memory, the stats and ``zenrl status`` say the log is degraded; once space is freed
the log resumes, and a restarted replay restores every item the stopped one held. Real router,
replay, publishers and ``zenrl status`` are separate OS processes."""

import os
import re
import shutil
import signal
import subprocess
import sys

import pytest

from zenrl.common import protocol as P
from zenrl.common.replay_client import ZenohReplayClient
from zenrl.common.transport import Node
from tests.conftest import ROOT, replay_stats_reader, wait_until

pytestmark = pytest.mark.integration


def _replay_args(router, run_id, log_dir):
    return ["replay", "--router", router, "--run-id", run_id, "--log-level", "INFO",
            "--set", "replay.durable=true", "--set", f"replay.log_dir={log_dir}", "--set", "replay.min_size=1",
            "--set", "replay.stats_interval_s=0.2", "--set", "replay.capacity=100000",
            "--set", "replay.flush_interval_s=0.05", "--set", "replay.durable_retry_s=0.3",
            "--set", "replay.snapshot_interval_s=1", "--set", "replay.max_abs_reward=1e12"]


def _publish(procs, router, run_id, name, chunks, seed):
    p = procs.start(name, ["tests/integration/procs.py", "publish", "--router", router, "--run", run_id,
                           "--actor", name, "--chunks", str(chunks), "--chunk", "50", "--seed", str(seed)])
    assert p.wait(timeout=60) == 0, procs.log(name)[-2000:]


def test_a_full_disk_does_not_stop_ingest_and_the_log_resumes(router, run_id, procs, small_disk):
    keys = P.Keys(run_id)
    log_dir = small_disk / "log"
    replay = procs.zenrl("replay", _replay_args(router, run_id, log_dir))
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        stats = replay_stats_reader(node, keys)
        client = ZenohReplayClient(node, keys, "learner", timeout_s=5.0)
        _publish(procs, router, run_id, "a", 20, 1)
        wait_until(lambda: (v := stats()) and v["durable_through"] == 1000, 30, "1000 items logged")

        filler = small_disk / "filler"
        with open(filler, "wb") as f:  # every free byte of the disk
            f.write(b"\0" * shutil.disk_usage(small_disk).free)
        _publish(procs, router, run_id, "b", 60, 2)
        s = wait_until(lambda: (v := stats()) and v["inserted_total"] == 4000 and v, 30, "4000 inserted")
        assert s["durable_degraded"] == 1 and "No space left" in s["durable_error"], s
        assert s["durable_backlog_items"] > 0 and s["durable_through"] < 4000 and s["rejected_total"] == 0, s
        b = client.sample(256, 0.5)  # served from memory meanwhile
        assert b.keys.shape == (256,) and b.replay_size == 4000
        table = subprocess.run([sys.executable, "-m", "zenrl.cli", "status", "--router", router, "--run-id", run_id],
                               capture_output=True, text=True, timeout=60, cwd=ROOT, env={**os.environ, "COLUMNS": "300"})
        assert re.search(r"DURABLE LOG DEGRADED \((append|fsync|resume): No space left on device; [0-9,]+ items in memory only\)",
                         table.stdout), table.stdout + table.stderr

        filler.unlink()
        s = wait_until(lambda: (v := stats()) and v["durable_degraded"] == 0 and v["durable_through"] == 4000 and v, 30,
                       "the log to resume")
        assert s["durable_resumes"] == 1 and s["durable_lost_items"] == 0, s
        _publish(procs, router, run_id, "c", 10, 3)
        wait_until(lambda: (v := stats()) and v["durable_through"] == 4500, 30, "4500 items logged")
    replay.send_signal(signal.SIGTERM)
    assert replay.wait(timeout=20) == 0, procs.log("replay")[-3000:]

    procs.zenrl("replay2", _replay_args(router, run_id, log_dir))
    with Node(router, 10.0) as node:
        stats = replay_stats_reader(node, keys)
        s = wait_until(lambda: (v := stats()) and v, 60, "the restarted replay's stats")
    assert s["restored_items"] == 4500 and s["inserted_total"] == 4500, s
    assert s["log_corrupt_records"] == 0 and s["log_skipped_items"] == 0 and s["log_torn_records"] == 0, s
