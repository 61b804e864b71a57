"""The real thing end to end: `zenrl run` starts a router, the replay, the learner, 2 actors and
the evaluator as OS processes; with an update budget, the greedy eval return must rise clearly
above a random policy's (~22 on CartPole-v1), and nothing may be left running."""

import json

import pytest

from tests.conftest import run_zenrl, zenrl_pids
from zenrl.placement import plan, usable_cpus

pytestmark = pytest.mark.integration

RANDOM_CARTPOLE_RETURN = 22.0


def _leftovers(run_id: str) -> list[int]:
    return zenrl_pids(run_id)


def test_zenrl_run_learns_cartpole(tmp_path, run_id):
    p, run_dir, logs = run_zenrl(tmp_path, "configs/cartpole_apex.yaml", run_id, "max_updates=5000", "max_wall_s=600",
                                 "target_return=null", "evaluator.interval_s=3")
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    evals = [e["mean"] for e in summary["evals"]]
    assert evals, logs.get("evaluator.log")
    assert max(evals) >= 4 * RANDOM_CARTPOLE_RETURN, (evals, logs.get("learner.log"))
    assert summary["learner"]["updates"] >= 5000
    assert summary["replay"]["rejected_total"] == 0
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    assert list((run_dir / "checkpoints").glob("ckpt-*.pt")), "the learner saved no checkpoint"
    assert (run_dir / "config.yaml").is_file() and (run_dir / "metrics.jsonl").is_file()
    assert list((run_dir / "tb").rglob("events.out.tfevents.*")), "no TensorBoard events"
    assert not _leftovers(run_id), _leftovers(run_id)
    placed = plan("auto", True, 1, usable_cpus())
    if placed is not None:  # a 2-4 CPU machine (CI): the learner ran alone on its CPU
        learner_log = (run_dir / "logs" / "learner.log").read_text()
        assert f"cpu placement: CPUs {placed['learner'].cpus}, nice +0" in learner_log, learner_log[:2000]
        assert f"cpu placement: CPUs {placed['actor'].cpus}, nice +5" in (run_dir / "logs" / "actor-0.log").read_text()
