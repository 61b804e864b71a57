"""Acceptance runs, too long for every CI run (`pytest -m slow`): `zenrl run` with the shipped
CartPole configs must reach a greedy eval mean >= 475 over 10 episodes."""

import json
import subprocess
import sys

import pytest

from tests.conftest import ROOT, free_port

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.mark.parametrize("config", ["configs/cartpole_apex.yaml", "configs/cartpole_a3c.yaml"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shipped_config_solves_cartpole(tmp_path, config, seed):
    run_id = f"solve-{seed}"
    port = free_port()
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", config, "--run-id", run_id, "--seed", str(seed),
           "--no-progress", "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[tcp/127.0.0.1:{port}]",
           "--set", "target_return=475", "--set", "max_wall_s=900"]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1200)
    assert p.returncode == 0, p.stderr[-3000:]
    summary = json.loads((tmp_path / run_id / "summary.json").read_text())
    assert summary["solved"], (summary["stop_reason"], [e["mean"] for e in summary["evals"]])
