"""R2D2 frame mode end to end: `zenrl run` with `algo: r2d2` on Burger War's camera
(`zenrl/BurgerWarImage-v0`, a uint8 image) starts a router, the replay, the learner and an actor
as OS processes. The actor sends its sequences as frame ids with each frame once (lz4), the
replay stores them in frame mode and rejects none, the learner trains on the rebuilt image
sequences (every update accepted), and the run stops cleanly."""

import json
import uuid

import pytest

from tests.conftest import run_zenrl

pytestmark = pytest.mark.integration

UPDATES = 20
M = 8


def test_zenrl_run_r2d2_on_camera_frames_trains_and_stores_each_frame_once(tmp_path):
    run_id = f"e2e-r2d2-frames-{uuid.uuid4().hex[:8]}"
    p, run_dir, logs = run_zenrl(
        tmp_path, "configs/burgerwar_r2d2.yaml", run_id, f"max_updates={UPDATES}", "max_wall_s=500",
        "env.id=zenrl/BurgerWarImage-v0", "env.kwargs.image_size=36", "env.kwargs.match_time=20",
        "network.conv=true", "network.hidden=[16]", "actor.num_actors=1", "actor.envs_per_actor=2",
        f"actor.chunk_size={2 * M}", "actor.compress=lz4", f"r2d2.sequence_length={M}", "r2d2.burn_in=4",
        "r2d2.n_step=2", "r2d2.lstm_size=16", "r2d2.block_steps=4", "replay.capacity=2000", "replay.min_size=16",
        f"replay.frames_per_item={M // 2 + 1}", "learner.batch_size=8", "learner.publish_every_updates=5",
        "evaluator.enabled=false", "learner.checkpoint_interval_s=600", timeout_s=600)
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), (summary["stop_reason"], logs)
    learner, replay = summary["learner"], summary["replay"]
    assert learner["updates"] >= UPDATES and learner["skipped_updates"] == 0, learner
    assert replay["rejected_total"] == 0 and replay["size"] >= 16, replay
    # frame mode: each frame stored once, about m/2 new frames per sequence (not m+1)
    assert 0 < replay["frames_stored"] <= replay["inserted_total"] * (M // 2 + 2), replay
    assert replay["frames_unresolved_items"] == 0, replay
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
