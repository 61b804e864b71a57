"""`zenrl run` of the league config end to end (slow): the league service and both agents'
replay, learner and actors run as real processes; main agent snapshots join the league, the
exploiter plays the main agent and is reset (its processes restarted afresh, its snapshot
joining), and nothing is left running afterwards."""

import json

import pytest

from tests.conftest import run_zenrl, zenrl_pids

pytestmark = [pytest.mark.integration, pytest.mark.slow]

MATCH = {"opponents": {"cheese": 1}, "side": "random", "reward": "zero_sum", "control_hz": 5, "action_set": "rich",
         "match_time": 10.0, "sudden_death_time": 2.0}
SETS = ("max_wall_s=150", f"env.kwargs={json.dumps(MATCH)}", "evaluator.enabled=false", "replay.min_size=300",
        "replay.samples_per_insert=null", "learner.batch_size=32", "learner.checkpoint_interval_s=20",
        "league.agents.main.num_actors=1", "league.agents.main.envs_per_actor=4",
        "league.agents.exploiter.envs_per_actor=4", "league.snapshot_interval_s=30", "league.min_snapshot_interval_s=20",
        "league.exploiter_reset_s=60", "league.exploiter_init=main", "league.live_refresh_s=5", "league.save_interval_s=2")


def test_league_run_snapshots_and_resets(tmp_path, run_id):
    p, run_dir, logs = run_zenrl(tmp_path, "configs/burgerwar_league_pfsp.yaml", run_id, *SETS, timeout_s=600)
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_wall_s"), summary["stop_reason"]
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    state = json.loads((run_dir / "league" / "state.json").read_text())
    players = {d["id"]: d for d in state["players"]}
    assert any(d["kind"] == "snapshot" and d["parent"] == "main" for d in players.values()), players
    gen = players["exploiter"]["generation"]
    assert gen >= 1, players["exploiter"]
    assert any(d["kind"] == "snapshot" and d["parent"] == "exploiter" for d in players.values()), players
    applied = json.loads((run_dir / "league_applied.json").read_text())
    assert applied["exploiter"] == gen  # zenrl run restarted the exploiter for its last generation
    assert "reset to generation 1" in p.stderr
    # the reset exploiter started from main's newest checkpoint (league.exploiter_init: main)
    assert "exploiter starts from main's ckpt-" in p.stderr, p.stderr[-3000:]
    assert "initial weights from" in (run_dir / "logs" / "exploiter-learner.log").read_text()
    # zenrl run restarts a reset agent itself: its children never stop on their own (league.self_reset)
    assert not [f.name for f in (run_dir / "logs").glob("*.log") if "to be started afresh" in f.read_text()]
    counts = {(a, b): (w, d, l_) for a, b, w, d, l_ in state["payoff"]["counts"]}
    assert sum(counts.get(("exploiter", "main"), (0, 0, 0))) >= 1, counts
    assert sum(sum(v) for (a, _), v in counts.items() if a == "main") >= 4, counts
    for rid in (run_id, f"{run_id}.main", f"{run_id}.exploiter"):
        assert not zenrl_pids(rid), zenrl_pids(rid)


@pytest.mark.parametrize("algo", ["r2d2", "impala", "a3c"])
def test_a_league_of_any_algorithm(tmp_path, run_id, algo):
    """The same league with R2D2, IMPALA or A3C agents: every agent's actors take their
    opponents from the league and report their matches (main against the bots and itself, the
    exploiter against main); IMPALA and A3C agents run without a replay."""
    sets = [s for s in SETS if not s.startswith(("max_wall_s", "league.exploiter_reset_s"))]
    if algo == "r2d2":  # its capacity counts sequences of 80 steps (~127 KB each here), not transitions
        sets += ["replay.capacity=4000", 'league.agents.exploiter.overrides={"replay.capacity": 2000}']
    p, run_dir, logs = run_zenrl(tmp_path, "configs/burgerwar_league_pfsp.yaml", run_id, *sets, f"algo={algo}",
                                 "max_wall_s=110", "league.exploiter_init=fresh", timeout_s=600)
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_wall_s"), summary["stop_reason"]
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    has_replay = algo == "r2d2"
    assert any(n.startswith("main-replay") for n in logs) == has_replay, sorted(logs)
    state = json.loads((run_dir / "league" / "state.json").read_text())
    counts = {(a, b): (w, d, l_) for a, b, w, d, l_ in state["payoff"]["counts"]}
    assert sum(counts.get(("exploiter", "main"), (0, 0, 0))) >= 1, counts
    assert sum(sum(v) for (a, _), v in counts.items() if a == "main") >= 4, counts
    for name in ("main-actor-0", "exploiter-actor-0"):
        assert "Traceback" not in logs[f"{name}.log"], logs[f"{name}.log"]
    for rid in (run_id, f"{run_id}.main", f"{run_id}.exploiter"):
        assert not zenrl_pids(rid), zenrl_pids(rid)
