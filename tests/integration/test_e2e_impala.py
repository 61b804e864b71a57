"""IMPALA end to end: `zenrl run --config configs/cartpole_impala.yaml` starts a router, the IMPALA
learner, 2 actors and the evaluator as OS processes. While it runs, `zenrl status` lists every
role with the learner training; with an update budget, the greedy eval return must rise clearly
above a random policy's (~22 on CartPole-v1), the learner must have rejected nothing and trained
on T * B env steps per update, its checkpoint must hold finite params that `zenrl evaluate`
plays, and nothing may be left running. A second test: an actor publishing bad unrolls beside
the honest ones is rejected by reason and quarantined while the learner keeps training. Then
APPO on continuous actions (Pendulum-v1): the run, its checkpoint under `zenrl evaluate`, and
(slow) solving it."""

import json
import subprocess
import sys
import time
import uuid
import warnings

import numpy as np
import pytest
import torch

from tests.conftest import ROOT, free_port, wait_until, zenrl_pids
from zenrl.common import protocol as P
from zenrl.common.checkpoints import ImpalaTrainingState, read_checkpoint
from zenrl.common.networks import ActorCritic, BoxActions
from zenrl.common.specs import ArraySpec

pytestmark = pytest.mark.integration

RANDOM_CARTPOLE_RETURN = 22.0
CONFIG = "configs/cartpole_impala.yaml"


def _zenrl(*args, timeout_s=120):
    return subprocess.run([sys.executable, "-m", "zenrl.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout_s)


def _launch(tmp_path, run_id, *sets, config=CONFIG):
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", config, "--run-id", run_id, "--no-progress",
           "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]"]
    for s in sets:
        cmd += ["--set", s]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _finish(launcher, timeout_s=600):
    try:
        out, _ = launcher.communicate(timeout=timeout_s)
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
    return out


def _status_rows(run_dir):
    p = _zenrl("status", str(run_dir), "--json", "--wait", "3", timeout_s=60)
    if p.returncode not in (0, 1) or not p.stdout.strip():
        return {}
    return {r["role"]: r for r in json.loads(p.stdout.strip().splitlines()[-1])["processes"]}


def test_zenrl_run_impala_learns_cartpole(tmp_path):
    run_id = f"e2e-impala-{uuid.uuid4().hex[:8]}"  # unique: another test session may run beside this one
    run_dir = tmp_path / run_id
    # 1,500 updates: ~10 s of training, so that a `zenrl status` (an interpreter's start and a 3 s
    # wait) on a loaded machine sees the run while it trains; with 500 the run once ended first
    launcher = _launch(tmp_path, run_id, "max_updates=1500", "max_wall_s=600", "target_return=null",
                       "evaluator.interval_s=1")
    try:
        wait_until(lambda: (run_dir / "launcher.json").is_file() or launcher.poll() is not None, 60, "launcher.json")

        def training():
            rows = _status_rows(run_dir)
            ok = {"learner", "actor", "evaluator"} <= set(rows) and rows["learner"].get("updates", 0) > 0
            if ok:
                return rows
            return {"ended": True} if launcher.poll() is not None else None  # fails below, saying so

        rows = wait_until(training, 180, "every role in zenrl status, the learner training")
        assert "ended" not in rows, "the run ended before zenrl status saw it train"
    finally:
        out = _finish(launcher)
    assert launcher.returncode == 0, out[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    logs = {f.name: f.read_text()[-3000:] for f in (run_dir / "logs").glob("*.log")}
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    evals = [e["mean"] for e in summary["evals"]]
    assert evals, logs.get("evaluator.log")
    assert max(evals) >= 5 * RANDOM_CARTPOLE_RETURN, (evals, logs.get("learner.log"))
    learner = summary["learner"]
    assert learner["updates"] >= 500 and learner["version"] > 500
    assert learner["rejected_total"] == 0 and learner["skipped_updates"] == 0, learner
    assert learner["env_steps_trained"] == learner["updates"] * 32 * 8  # T * B of the config
    assert summary["env_steps"] >= learner["env_steps_trained"]
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    ckpts = sorted((run_dir / "checkpoints").glob("ckpt-*.pt"))
    assert ckpts, "the learner saved no checkpoint"
    state = read_checkpoint(ckpts[-1])
    assert isinstance(state, ImpalaTrainingState) and state.updates >= 500
    assert all(torch.isfinite(t).all() for t in state.policy_state().values())
    assert list((run_dir / "tb").rglob("events.out.tfevents.*")), "no TensorBoard events"
    assert not zenrl_pids(run_id), zenrl_pids(run_id)
    # the checkpoint plays under `zenrl evaluate` (the greedy policy of the actor-critic)
    ev = _zenrl("evaluate", "--checkpoint", str(run_dir), "--episodes", "3", "--workers", "1", "--no-progress",
                "--json", str(tmp_path / "eval.json"), timeout_s=300)
    assert ev.returncode == 0, ev.stderr[-3000:]
    res = json.loads((tmp_path / "eval.json").read_text())
    assert res["env"] == "CartPole-v1" and len(res["results"]) == 3
    assert all(np.isfinite(r["ret"]) and r["ret"] >= 1 for r in res["results"])


PENDULUM = "configs/pendulum_appo.yaml"
#: Pendulum-v1's return per 200-step episode lies in [-16.27 * 200, 0]
PENDULUM_WORST = -16.3 * 200


def _pendulum_run(tmp_path, run_id, *sets, timeout_s=600):
    launcher = _launch(tmp_path, run_id, *sets, config=PENDULUM)
    out = _finish(launcher, timeout_s)
    assert launcher.returncode == 0, out[-3000:]
    run_dir = tmp_path / run_id
    return run_dir, json.loads((run_dir / "summary.json").read_text())


def test_zenrl_run_appo_takes_continuous_actions(tmp_path):
    """Pendulum-v1 (a Box action space) under the shipped APPO config, with an update budget: the
    actors' float actions and log-densities reach the learner and none is rejected, every update
    trains on T * B env steps, the evaluator's greedy (mean) returns are Pendulum returns; the
    checkpoint plays under `zenrl evaluate` with either policy, and `zenrl export` writes a
    program that returns the mean action in the env's units and plays as the checkpoint does."""
    run_id = f"e2e-appo-box-{uuid.uuid4().hex[:8]}"
    run_dir, summary = _pendulum_run(tmp_path, run_id, "max_updates=600", "target_return=null", "evaluator.interval_s=1")
    logs = {f.name: f.read_text()[-3000:] for f in (run_dir / "logs").glob("*.log")}
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    learner = summary["learner"]
    assert learner["updates"] >= 600 and learner["rejected_total"] == 0 and learner["skipped_updates"] == 0, learner
    assert learner["env_steps_trained"] == learner["updates"] * 32 * 8
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    evals = [e["mean"] for e in summary["evals"]]
    assert evals and all(PENDULUM_WORST <= m <= 0 for m in evals), (evals, logs.get("evaluator.log"))
    state = read_checkpoint(sorted((run_dir / "checkpoints").glob("ckpt-*.pt"))[-1])
    assert state.policy_state()["log_std"].shape == (1,)
    assert all(torch.isfinite(t).all() for t in state.policy_state().values())
    assert not zenrl_pids(run_id), zenrl_pids(run_id)
    for policy in ("greedy", "sample"):
        ev = _zenrl("evaluate", "--checkpoint", str(run_dir), "--episodes", "2", "--workers", "1", "--no-progress",
                    "--policy", policy, "--json", str(tmp_path / f"{policy}.json"), timeout_s=300)
        assert ev.returncode == 0, ev.stderr[-3000:]
        res = json.loads((tmp_path / f"{policy}.json").read_text())
        assert res["env"] == "Pendulum-v1" and len(res["results"]) == 2
        assert all(PENDULUM_WORST <= r["ret"] <= 0 and r["length"] == 200 for r in res["results"]), res["results"]
    # exported: a program that returns the mean torque in the env's units, [-2, 2] for Pendulum
    ex = _zenrl("export", "--checkpoint", str(run_dir), "--out", str(tmp_path / "p.pt"), timeout_s=120)
    assert ex.returncode == 0, ex.stderr[-3000:]
    extra = {"zenrl.json": ""}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch 2.13 deprecates TorchScript
        program = torch.jit.load(str(tmp_path / "p.pt"), _extra_files=extra)
    meta = json.loads(extra["zenrl.json"])
    assert meta["action_bounds"] == {"low": [-2.0], "high": [2.0]} and meta["n_actions"] == 1
    net = ActorCritic({"obs": ArraySpec((3,), "float32")}, BoxActions(1), state.run_config().network)
    net.load_state_dict(state.policy_state())
    obs = np.random.default_rng(0).uniform([-1, -1, -8], [1, 1, 8]).astype(np.float32)
    with torch.no_grad():
        want = 2.0 * net({"obs": torch.from_numpy(obs[None])})[0][0]
        got = program(torch.from_numpy(obs))
    assert got.dtype == torch.float32 and got.shape == (1,) and float(got.abs().max()) <= 2.0
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    # and plays as the checkpoint does: the same greedy returns on the same seeds
    ev = _zenrl("evaluate", "--checkpoint", str(tmp_path / "p.pt"), "--exported", "--episodes", "2", "--workers", "1",
                "--no-progress", "--json", str(tmp_path / "exported.json"), timeout_s=300)
    assert ev.returncode == 0, ev.stderr[-3000:]
    greedy = json.loads((tmp_path / "greedy.json").read_text())["results"]
    exported = json.loads((tmp_path / "exported.json").read_text())["results"]
    assert [r["ret"] for r in exported] == pytest.approx([r["ret"] for r in greedy], rel=1e-4)


@pytest.mark.slow
def test_zenrl_run_appo_solves_pendulum(tmp_path):
    """The shipped APPO config solves Pendulum-v1 (greedy eval >= -200 over 10 episodes; a random
    policy gets about -1200) well within its wall-clock budget."""
    run_id = f"e2e-appo-solve-{uuid.uuid4().hex[:8]}"
    run_dir, summary = _pendulum_run(tmp_path, run_id, "max_wall_s=480", timeout_s=600)
    assert summary["stop_reason"].startswith("solved"), (summary["stop_reason"], [e["mean"] for e in summary["evals"]])
    assert summary["learner"]["rejected_total"] == 0


def _bad_unroll(actor, seq, T, version):
    """An unroll whose actions the env does not have (reason action_range)."""
    rng = np.random.default_rng(seq)
    return P.Unroll(actor_id=actor, policy_version=version, seq=seq,
                    obs={"obs": rng.uniform(-0.1, 0.1, (T + 1, 4)).astype(np.float32)},
                    action=np.full(T, 7, np.int64), behaviour_logp=np.full(T, -0.7, np.float32),
                    reward=np.ones(T, np.float32), terminated=np.zeros(T, bool), truncated=np.zeros(T, bool))


def test_hostile_actor_is_quarantined_while_the_honest_ones_train(tmp_path):
    from zenrl.common.transport import Node

    run_id = f"e2e-impala-h-{uuid.uuid4().hex[:8]}"
    run_dir = tmp_path / run_id
    launcher = _launch(tmp_path, run_id, "max_wall_s=300", "target_return=null", "evaluator.enabled=false",
                       "impala.quarantine_rejections=5", "impala.quarantine_s=120")
    keys = P.Keys(run_id)
    try:
        wait_until(lambda: (run_dir / "launcher.json").is_file() or launcher.poll() is not None, 60, "launcher.json")
        node = Node(json.loads((run_dir / "launcher.json").read_text())["router"], 30.0)
        try:
            stats = node.subscribe_latest(keys.stats("learner", "learner"))

            def learner_stats():
                payload = stats.take()
                return P.Stats.decode(payload).values if payload is not None else None

            first = wait_until(lambda: (lambda v: v if v and v.get("updates", 0) > 0 else None)(learner_stats()),
                               180, "the learner training")
            pub = node.publisher(keys.unrolls("evil"))
            for seq in range(40):
                pub.put(_bad_unroll("evil", seq, 32, int(first["version"])).encode())
                pub.put(b"\x93garbage")
                time.sleep(0.01)  # paced: the router is shared with the run's own traffic

            def quarantined():
                v = learner_stats()
                ok = v and v.get("quarantined", 0) >= 1 and v.get("dropped_quarantined", 0) > 0 \
                    and v.get("updates", 0) > first["updates"] + 20
                return v if ok else None

            v = wait_until(quarantined, 120, "the hostile actor quarantined while the learner trains on")
        finally:
            node.close()
    finally:
        launcher.terminate()
        out = _finish(launcher, 120)
    assert launcher.returncode == 0, out[-3000:]
    assert v["rejected_action_range"] >= 1 and v["rejected_malformed"] >= 1, v
    assert v["rejected_from/evil"] == v["rejected_total"] >= 5, v  # nothing of the honest actors' rejected
    assert "evil" in v["quarantined_sources"] and v["skipped_updates"] == 0, v
    assert not zenrl_pids(run_id), zenrl_pids(run_id)
