"""Actors and the replay survive a router restart: Zenoh clients reconnect by themselves, the
actor holds (or counts) what could not be delivered, and data flows again afterwards. Also
`zenrl status` lists the live processes with their stats."""

import json
import subprocess
import sys
import time

import pytest

from zenrl.common import protocol as P
from zenrl.common.transport import Node, open_router
from tests.conftest import ROOT, free_port, wait_until

pytestmark = pytest.mark.integration


def _replay_inserted(ep, keys):
    with Node(ep, 10.0) as node:
        latest = node.subscribe_latest(keys.stats("replay", "replay"))
        raw = latest.wait(5.0)
        return 0 if raw is None else P.Stats.decode(raw).values["inserted_total"]


def test_router_restart_and_status(run_id, procs):
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    keys = P.Keys(run_id)
    router = open_router([ep])
    try:
        common = ["--router", ep, "--run-id", run_id, "--set", "replay.stats_interval_s=0.5", "--set", "replay.min_size=10",
                  "--set", "actor.envs_per_actor=4", "--set", "actor.episode_report_s=0.5", "--set", "network.hidden=[32]"]
        procs.zenrl("replay", ["replay", *common])
        actor = procs.zenrl("actor", ["actor", "--id", "a0", "--slot", "0", *common])
        wait_until(lambda: _replay_inserted(ep, keys) > 500, 120, "transitions reaching the replay")

        # zenrl status sees both processes and their stats
        out = subprocess.run([sys.executable, "-m", "zenrl.cli", "status", "--run-id", run_id, "--router", ep, "--json",
                              "--wait", "1.5"], cwd=ROOT, capture_output=True, text=True, timeout=60)
        status = json.loads(out.stdout.strip().splitlines()[-1])
        roles = {r["role"]: r for r in status["processes"]}
        assert set(roles) >= {"replay", "actor"}, status
        assert roles["replay"]["size"] > 0 and roles["actor"]["env_steps"] > 0

        # the replay's count before the outage: anything beyond it was delivered after the restart
        before = _replay_inserted(ep, keys)
        assert before > 500, before
        router.close()
        time.sleep(3.0)  # the outage itself (its length, not a wait for a condition)
        assert actor.poll() is None, "the actor died with the router"
        router = open_router([ep])
        wait_until(lambda: _replay_inserted(ep, keys) > before + 500, 120, "data flowing again after the restart")
        assert actor.poll() is None
    finally:
        router.close()
