"""A durable replay under full ingest load stops on SIGTERM within 5 s, exit code 0, with its log
flushed and its final snapshot written: a restarted replay recovers every item the stopped one
had inserted. Real router, replay and publishers are separate OS processes."""

import json
import re
import signal
import subprocess
import time

import pytest

from zenrl.common import protocol as P
from zenrl.common.transport import Node
from tests.conftest import replay_stats_reader, wait_until

pytestmark = pytest.mark.integration


def _replay_args(router, run_id, log_dir):
    return ["replay", "--router", router, "--run-id", run_id, "--log-level", "INFO",
            "--set", "replay.durable=true", "--set", f"replay.log_dir={log_dir}",
            "--set", "replay.stats_interval_s=0.2", "--set", "replay.capacity=2000000",
            # a short queue is saturated quickly: the callback then waits drop_after_s per chunk
            "--set", "replay.queue_size=4", "--set", "replay.ingest_batch_chunks=1",
            "--set", "replay.drop_after_s=2.0", "--set", "replay.max_abs_reward=1e12", "--set", "replay.snapshot_interval_s=60"]


def test_sigterm_under_ingest_load_flushes_and_exits(router, run_id, procs, tmp_path):
    keys = P.Keys(run_id)
    log_dir = tmp_path / "replay-log"
    replay = procs.zenrl("replay", _replay_args(router, run_id, log_dir))
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        stats = replay_stats_reader(node, keys)
        for i in range(4):
            procs.start(f"pub{i}", ["tests/integration/procs.py", "publish", "--router", router, "--run", run_id,
                                    "--actor", f"p{i}", "--chunks", "1000000", "--chunk", "2000", "--seed", str(i + 1)])
        # all four publishing flat out (BLOCK: each waits for the replay's short queue)
        wait_until(lambda: (v := stats()) and v["inserted_total"] >= 100_000, 90, "100,000 inserted transitions")
        t0 = time.monotonic()
        replay.send_signal(signal.SIGTERM)
        try:
            rc = replay.wait(timeout=15)
        except subprocess.TimeoutExpired:
            pytest.fail(f"replay still running 15 s after SIGTERM under load\n{procs.log('replay')[-3000:]}")
        took = time.monotonic() - t0
    assert rc == 0, procs.log("replay")[-3000:]
    assert took < 5.0, f"replay took {took:.1f} s to stop under load\n{procs.log('replay')[-3000:]}"
    text = procs.log("replay")
    m = re.search(r"replay log flushed: (\d+) items inserted", text)
    assert m, text[-3000:]
    inserted = int(m.group(1))
    assert inserted > 0
    assert (log_dir / "priorities.npz").exists()
    for i in range(4):  # stop the publishers before the restart, so nothing new arrives
        p = procs.procs[1 + i][1]
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=20)

    # a restarted replay on the same log recovers exactly what the stopped one inserted
    procs.zenrl("replay2", _replay_args(router, run_id, log_dir))
    with Node(router, 10.0) as node:
        stats = replay_stats_reader(node, keys)
        s = wait_until(lambda: (v := stats()) and v, 60, "the restarted replay's stats")
    assert s["restored_items"] == inserted and s["inserted_total"] == inserted, json.dumps(s)
    assert s["log_torn_records"] == 0
