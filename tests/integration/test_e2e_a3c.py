"""A3C end to end: `zenrl run --config configs/cartpole_a3c.yaml` starts a router, the A3C
learner (parameter server), 2 workers and the evaluator as OS processes; with an update budget,
the greedy return (live evals, or the final checkpoint's) must rise clearly above a random
policy's (~22 on CartPole-v1), the learner must have rejected nothing, its checkpoint must hold
finite params, and nothing may be left running."""

import json
import uuid

import pytest
import torch

from tests.conftest import run_zenrl, zenrl_pids
from zenrl import tools
from zenrl.common.checkpoints import A3CTrainingState, read_checkpoint

pytestmark = pytest.mark.integration

RANDOM_CARTPOLE_RETURN = 22.0


def _leftovers(run_id: str) -> list[int]:
    return zenrl_pids(run_id)


def test_zenrl_run_a3c_learns_cartpole(tmp_path):
    run_id = f"e2e-a3c-{uuid.uuid4().hex[:8]}"  # unique: another test session may run beside this one
    p, run_dir, logs = run_zenrl(tmp_path, "configs/cartpole_a3c.yaml", run_id, "max_updates=2000", "max_wall_s=600",
                                 "target_return=null", "evaluator.interval_s=3")
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    evals = [e["mean"] for e in summary["evals"]]
    assert evals, logs.get("evaluator.log")
    learner = summary["learner"]
    assert learner["updates"] >= 2000 and learner["version"] > 1
    assert learner["rejected_total"] == 0 and learner["params_restored"] == 0, learner
    assert summary["env_steps"] > 0
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    ckpts = sorted((run_dir / "checkpoints").glob("ckpt-*.pt"))
    assert ckpts, "the learner saved no checkpoint"
    state = read_checkpoint(ckpts[-1])
    assert isinstance(state, A3CTrainingState) and state.updates >= 2000
    assert all(torch.isfinite(t).all() for t in state.policy_state().values())
    # learned: the live evals, or the final checkpoint's greedy return on fixed seeds (a loaded
    # machine runs the live evaluator only a few times before the update budget is spent)
    final = tools.evaluate(str(ckpts[-1]), episodes=10, seed=7_000_000, progress=False)["rows"][0]["return_mean"]
    assert max(*evals, final) >= 5 * RANDOM_CARTPOLE_RETURN, (evals, final, logs.get("learner.log"))
    assert (run_dir / "config.yaml").is_file() and (run_dir / "metrics.jsonl").is_file()
    assert list((run_dir / "tb").rglob("events.out.tfevents.*")), "no TensorBoard events"
    assert not _leftovers(run_id), _leftovers(run_id)


def test_zenrl_run_a3c_on_continuous_actions(tmp_path):
    """Pendulum-v1 (a Box action space) under configs/pendulum_a3c.yaml with an update budget:
    the workers' gradients (the Gaussian's log std among them) are applied and none is
    rejected, the evaluator's greedy (mean) returns are Pendulum returns, and the checkpoint
    plays under `zenrl evaluate`."""
    run_id = f"e2e-a3c-box-{uuid.uuid4().hex[:8]}"
    p, run_dir, logs = run_zenrl(tmp_path, "configs/pendulum_a3c.yaml", run_id, "max_updates=800", "max_wall_s=300",
                                 "target_return=null", "evaluator.interval_s=1")
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    learner = summary["learner"]
    assert learner["updates"] >= 800 and learner["rejected_total"] == 0 and learner["params_restored"] == 0, learner
    evals = [e["mean"] for e in summary["evals"]]
    assert evals and all(-16.3 * 200 <= m <= 0 for m in evals), (evals, logs.get("evaluator.log"))
    state = read_checkpoint(sorted((run_dir / "checkpoints").glob("ckpt-*.pt"))[-1])
    assert isinstance(state, A3CTrainingState) and state.policy_state()["log_std"].shape == (1,)
    res = tools.evaluate(str(run_dir), episodes=2, seed=7_000_000, progress=False)
    assert res["env"] == "Pendulum-v1" and -16.3 * 200 <= res["rows"][0]["return_mean"] <= 0
    assert not _leftovers(run_id), _leftovers(run_id)


@pytest.mark.slow
def test_zenrl_run_a3c_solves_pendulum(tmp_path):
    """The shipped A3C config solves Pendulum-v1 (greedy eval >= -200 over 10 episodes; a random
    policy gets about -1200) within its wall-clock budget."""
    run_id = f"e2e-a3c-solve-{uuid.uuid4().hex[:8]}"
    p, run_dir, logs = run_zenrl(tmp_path, "configs/pendulum_a3c.yaml", run_id, "max_wall_s=480")
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("solved"), (summary["stop_reason"], [e["mean"] for e in summary["evals"]])
    assert summary["learner"]["rejected_total"] == 0
