"""Acceptance runs, too long for every CI run (`pytest -m slow`): `zenrl run` with the shipped
CartPole configs must reach a greedy eval mean >= 475 over 10 episodes."""

import json
import uuid

import pytest

from tests.conftest import run_zenrl

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.mark.parametrize("config", ["configs/cartpole_apex.yaml", "configs/cartpole_a3c.yaml"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shipped_config_solves_cartpole(tmp_path, config, seed):
    run_id = f"solve-{seed}-{uuid.uuid4().hex[:8]}"
    p, run_dir, _ = run_zenrl(tmp_path, config, run_id, "target_return=475", "max_wall_s=900",
                              extra_args=("--seed", str(seed)), timeout_s=1200)
    assert p.returncode == 0, p.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["solved"], (summary["stop_reason"], [e["mean"] for e in summary["evals"]])
