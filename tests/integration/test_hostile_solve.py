"""CartPole still solves with one hostile actor sending a tenth of the replay's traffic as
poison (out-of-range actions, huge rewards, out-of-bounds observations, wrong n, absurd
priorities): `zenrl run` with the shipped Ape-X config, the hostile actor a separate process on
the same router."""

import json
import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT, free_port

pytestmark = pytest.mark.integration  # ~25 s on 2 cores (the run solves in ~7 s from its first step)


def test_cartpole_solves_with_a_hostile_actor(tmp_path, run_id):
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    run = subprocess.Popen([sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml",
                            "--run-id", run_id, "--no-progress", "--set", f"runs_dir={tmp_path}",
                            "--set", f"transport.listen=[{ep}]", "--set", "max_wall_s=300"],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    hostile = subprocess.Popen([sys.executable, "tests/integration/procs.py", "poison", "--router", ep, "--run", run_id,
                                "--fraction", "0.1"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = run.communicate(timeout=420)
    finally:
        if run.poll() is None:
            run.kill()
        hostile.terminate()
        h_out, _ = hostile.communicate(timeout=30)
    assert run.returncode == 0, out[-3000:]
    summary = json.loads((tmp_path / run_id / "summary.json").read_text())
    assert summary["solved"], (summary["stop_reason"], [e["mean"] for e in summary["evals"]])
    m = re.search(r"POISON (\d+)", h_out)
    assert m and int(m.group(1)) >= 6, h_out[-2000:]  # every kind of poison was sent at least once
    poison = int(m.group(1)) * 256
    honest = summary["replay"]["inserted_total"]
    assert poison >= 0.08 * (poison + honest), (poison, honest)  # about a tenth of the traffic
    # refused, not stored (the summary holds the replay's last stats, up to 2 s old: a lower bound)
    assert summary["replay"]["rejected_total"] >= 6
    assert summary["restarts"]["learner"] == 0 and summary["restarts"]["replay"] == 0  # no crash, no crash loop
    replay_log = (tmp_path / run_id / "logs" / "replay.log").read_text()
    for reason in ("action_range", "reward_bound", "obs_bounds", "n_range", "priority_bound"):
        assert f"[{reason}]" in replay_log, reason
