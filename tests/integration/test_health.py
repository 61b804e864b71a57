"""`python -m zenrl.health` (the container probes): healthy only while the named process holds
its liveliness token at the router and publishes its stats; a router that cannot be reached
fails readiness and passes liveness (--unreachable-ok)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.conftest import ROOT, free_port, wait_until

pytestmark = pytest.mark.integration


def _health(ep: str, run_id: str, *args: str) -> tuple[int, dict]:
    env = dict(os.environ, ZENRL_ROUTER=ep, ZENRL__RUN_ID=run_id)
    p = subprocess.run([sys.executable, "-m", "zenrl.health", *args], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=60)
    return p.returncode, json.loads(p.stdout.strip().splitlines()[-1])


def test_health_follows_the_process(router, run_id, procs):
    common = ["--router", router, "--run-id", run_id, "--set", "replay.stats_interval_s=0.5"]
    rc, out = _health(router, run_id, "--role", "replay", "--id", "replay")
    assert rc == 1 and "no liveliness token" in out["reason"], out
    replay = procs.zenrl("replay", ["replay", *common])
    wait_until(lambda: _health(router, run_id, "--role", "replay", "--id", "replay", "--stats-within-s", "5")[0] == 0,
               60, "the replay healthy")
    # another role, another id, or another run: not this process
    assert _health(router, run_id, "--role", "learner")[0] == 1
    assert _health(router, run_id, "--role", "replay", "--id", "replay-2")[0] == 1
    assert _health(router, run_id, "--role", "replay", "--id-prefix", "{hostname}-")[0] == 1
    assert _health(router, run_id + "x", "--role", "replay")[0] == 1
    replay.terminate()
    replay.wait(30)
    wait_until(lambda: _health(router, run_id, "--role", "replay", "--id", "replay")[0] == 1, 30,
               "the replay unhealthy once it stopped")


def test_health_agent_looks_under_the_agents_run_id(router, run_id, procs, tmp_path):
    """A league agent's replay (--agent exploiter) is healthy to the probe with the same
    --agent, and invisible to one without it or with the other agent's."""
    config = str(ROOT / "configs/cluster_league.yaml")
    procs.zenrl("replay", ["replay", "--config", config, "--agent", "exploiter", "--router", router, "--run-id", run_id,
                           "--set", f"runs_dir={tmp_path}", "--set", "replay.stats_interval_s=0.5"])
    probe = ["--role", "replay", "--id", "replay", "--config", config]
    wait_until(lambda: _health(router, run_id, *probe, "--agent", "exploiter", "--stats-within-s", "5")[0] == 0, 60,
               "the exploiter's replay healthy")
    rc, out = _health(router, run_id, *probe, "--agent", "exploiter")
    assert rc == 0 and out["run_id"] == f"{run_id}.exploiter", out
    assert _health(router, run_id, *probe)[0] == 1
    assert _health(router, run_id, *probe, "--agent", "main")[0] == 1


def test_health_router_unreachable(run_id):
    ep = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    rc, out = _health(ep, run_id, "--role", "learner", "--connect-timeout-s", "0.5")
    assert rc == 1 and "router unreachable" in out["reason"], out
    rc, out = _health(ep, run_id, "--role", "learner", "--connect-timeout-s", "0.5", "--unreachable-ok")
    assert rc == 0 and out["ok"], out
