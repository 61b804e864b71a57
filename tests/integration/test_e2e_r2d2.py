"""R2D2 end to end: `zenrl run --config configs/stateless_cartpole_r2d2.yaml` starts a router,
the replay, the R2D2 learner, an actor and the evaluator as OS processes. With a small update
budget (far from a solve): the replay stores the actor's sequences and rejects none, the learner
trains on them (every update accepted, its rescaled Q values rise from ~0 towards the discounted
returns of +1 a step), the actor acts with the learner's weights, the evaluator plays them, the
checkpoint holds finite recurrent parameters, and the run stops cleanly with nothing left."""

import json
import math
import uuid

import pytest
import torch

from tests.conftest import run_zenrl, zenrl_pids
from zenrl.common.checkpoints import R2D2TrainingState, read_checkpoint
from zenrl.common.metrics import read_metrics

pytestmark = pytest.mark.integration

UPDATES = 600


def test_zenrl_run_r2d2_trains_on_stateless_cartpole_and_stops_cleanly(tmp_path):
    run_id = f"e2e-r2d2-{uuid.uuid4().hex[:8]}"  # unique: another test session may run beside this one
    p, run_dir, logs = run_zenrl(tmp_path, "configs/stateless_cartpole_r2d2.yaml", run_id, f"max_updates={UPDATES}",
                                 "max_wall_s=400", "target_return=null", "evaluator.interval_s=3",
                                 "learner.checkpoint_interval_s=600", timeout_s=600)
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), (summary["stop_reason"], logs)
    learner, replay = summary["learner"], summary["replay"]
    assert learner["updates"] >= UPDATES and learner["version"] > 1, learner
    assert learner["sequences_consumed"] >= UPDATES * 32 and learner["skipped_updates"] == 0, learner
    assert replay["rejected_total"] == 0 and replay["size"] >= 200, replay
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    trained = [r for r in read_metrics(run_dir / "metrics.jsonl") if r["source"] == "learner" and "q_mean" in r]
    q = [r["q_mean"] for r in trained]
    assert q and all(math.isfinite(v) for v in q) and max(q) > 0.5, (q, logs.get("learner.log"))
    # the sampled sequences were acted with the learner's weights (an actor that never took them
    # stamps -1: the lag would exceed the version)
    assert trained[-1]["policy_lag"] < trained[-1]["version"], trained[-1]
    evals = summary["evals"]
    assert evals and max(e["version"] for e in evals) > 1, (evals, logs.get("evaluator.log"))
    ckpts = sorted((run_dir / "checkpoints").glob("ckpt-*.pt"))
    assert ckpts, "the learner saved no checkpoint"
    state = read_checkpoint(ckpts[-1])  # the final one, written on stop
    assert isinstance(state, R2D2TrainingState) and state.updates >= UPDATES
    assert any(k.startswith("lstm.") for k in state.policy_state())
    assert all(torch.isfinite(t).all() for t in state.policy_state().values())
    assert not zenrl_pids(run_id), zenrl_pids(run_id)
