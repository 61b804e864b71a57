"""A sharded replay end to end: `zenrl run` CartPole Ape-X with replay.shards=2 starts a router,
two replay services (replay-0, replay-1, each with its own durable log), the learner, 2 actors
and the evaluator as OS processes. Actor slot i writes to shard i % 2, so each shard takes one
actor's chunks; the learner samples both by their priority mass and sends each item's new
priority back to its own shard. While it runs `zenrl status` lists both shards and the learner's
draws from each; with the update budget of the unsharded e2e test the greedy eval return must
rise as high, and everything must stop cleanly. A second test kills one shard's process under a
learner's client and starts it again."""

import json
import subprocess
import sys
import uuid

import pytest

from tests.conftest import ROOT, free_port, wait_until, zenrl_pids

pytestmark = pytest.mark.integration

RANDOM_CARTPOLE_RETURN = 22.0


def _zenrl(*args, timeout_s=120):
    return subprocess.run([sys.executable, "-m", "zenrl.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout_s)


def _status_rows(run_dir):
    p = _zenrl("status", str(run_dir), "--json", "--wait", "3", timeout_s=60)
    if p.returncode not in (0, 1) or not p.stdout.strip():
        return {}
    return {f"{r['role']}/{r['id']}": r for r in json.loads(p.stdout.strip().splitlines()[-1])["processes"]}


def test_zenrl_run_apex_on_two_replay_shards(tmp_path):
    run_id = f"shards-{uuid.uuid4().hex[:8]}"
    run_dir = tmp_path / run_id
    # two shards of half the single replay's capacity and min_size: one replay's worth in all
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml", "--run-id", run_id,
           "--no-progress", "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]"]
    for s in ("replay.shards=2", "replay.capacity=7500", "replay.min_size=1000", "replay.durable=true",
              "max_updates=5000", "max_wall_s=600", "target_return=null", "evaluator.interval_s=3"):
        cmd += ["--set", s]
    launcher = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_until(lambda: (run_dir / "launcher.json").is_file() or launcher.poll() is not None, 60, "launcher.json")

        def both_shards_serving():
            rows = _status_rows(run_dir)
            learner = rows.get("learner/learner", {})
            ok = (all(rows.get(f"replay/replay-{k}", {}).get("inserted_total", 0) > 0 for k in (0, 1))
                  and all(learner.get(f"replay{k}_items", 0) > 0 for k in (0, 1)))
            return rows if ok or launcher.poll() is not None else None

        rows = wait_until(both_shards_serving, 300, "both shards in zenrl status, the learner drawing from both")
    finally:
        try:
            out, _ = launcher.communicate(timeout=600)
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.wait()
    logs = {f.name: f.read_text()[-3000:] for f in (run_dir / "logs").glob("*.log")}
    assert launcher.returncode == 0, (out[-3000:], logs)
    assert "replay/replay-0" in rows and "replay/replay-1" in rows, rows.keys()
    assert "replay" not in {r.split("/")[1] for r in rows}  # no unsharded replay beside them
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    shards = summary["replays"]
    assert set(shards) == {"replay-0", "replay-1"}
    for sid, v in shards.items():
        # each shard took one actor's chunks, served samples, and had priorities sent back to it
        assert v["inserted_total"] > 1000 and v["sample_batches_total"] > 0, (sid, v)
        assert v["priority_updates_total"] > 0 and v["priority_keys_total"] > 1000, (sid, v)
        assert v["rejected_total"] == 0, (sid, v)
    learner = summary["learner"]
    assert learner["replay_shards_up"] == 2 and learner["updates"] >= 5000
    items = [learner[f"replay{k}_items"] for k in (0, 1)]
    assert min(items) > 0.1 * sum(items), items  # both shards feed the learner, roughly by mass
    assert all(learner[f"replay{k}_priority_keys"] > 1000 for k in (0, 1))  # sent back to each shard
    evals = [e["mean"] for e in summary["evals"]]
    assert evals and max(evals) >= 4 * RANDOM_CARTPOLE_RETURN, (evals, logs.get("learner.log"))
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    for k in (0, 1):  # each shard its own durable log, flushed on the way out
        assert list((run_dir / "replay" / f"shard-{k}").iterdir()), f"shard {k} wrote no durable log"
        log = (run_dir / "logs" / f"replay-{k}.log").read_text()
        assert "replay log flushed" in log and "Traceback" not in log, log[-3000:]
    assert not zenrl_pids(run_id), zenrl_pids(run_id)


def test_a_killed_shard_is_left_out_and_rejoins_when_it_is_back(router, run_id, procs):
    """Two `zenrl replay --shard k` processes, a publisher each, the learner's sharded client in
    this process: SIGKILL shard 1 and sampling goes on from shard 0 alone (the failure counted,
    nothing raised but the one batch's error); start it again, refill it, and it is drawn from
    again."""
    from zenrl.common import protocol as P
    from zenrl.common.errors import NotReady, RemoteTimeout
    from zenrl.common.replay_client import ShardedReplayClient
    from zenrl.common.transport import Node

    def replay(k):
        return procs.zenrl(f"replay{k}", ["replay", "--router", router, "--run-id", run_id, "--shard", str(k),
                                          "--set", "replay.shards=2", "--set", "replay.min_size=200"])

    def publish(k, seed):
        return procs.start(f"pub{k}-{seed}", ["tests/integration/procs.py", "publish", "--router", router, "--run", run_id,
                                              "--actor", f"a{k}", "--shard", str(k), "--chunks", "20", "--chunk", "50",
                                              "--seed", str(seed), "--plain"])

    replays = [replay(0), replay(1)]
    pubs = [publish(0, 1), publish(1, 2)]
    with Node(router, 10.0) as node:
        client = ShardedReplayClient(node, run_id, 2, "learner", timeout_s=2.0, seed=0)

        def draw():
            try:
                return client.sample(64, 0.5)
            except (NotReady, RemoteTimeout):
                return None

        def batch_from(shards):
            s = draw()
            return s if s is not None and set(client.shard_of(s.keys)[0].tolist()) == shards else None

        assert all(p.wait(timeout=60) == 0 for p in pubs)
        wait_until(lambda: batch_from({0, 1}), 60, "a batch drawn from both shards")
        replays[1].kill()
        replays[1].wait(timeout=10)
        # the shard's failure costs batches (counted), never an exception other than the batch's own
        wait_until(lambda: batch_from({0}), 30, "batches from shard 0 alone")
        for _ in range(10):
            s = client.sample(64, 0.5)
            assert set(client.shard_of(s.keys)[0].tolist()) == {0}
        v = client.values()
        assert v["replay_shards_up"] == 1 and v["replay1_up"] == 0
        assert client.state[1].reason.startswith("RemoteTimeout"), client.state[1].reason  # why it is out
        replays[1] = replay(1)
        assert publish(1, 3).wait(timeout=60) == 0
        wait_until(lambda: batch_from({0, 1}), 60, "shard 1 drawn from again")
        assert client.values()["replay_shards_up"] == 2
        assert all(p.poll() is None for p in (replays[0], replays[1]))
