"""`zenrl run` with a frozen checkpoint as the only match opponent (opponents.pool): a short
Ape-X run on real processes reaches its update budget with the actors' matches played against
that checkpoint; a pool entry that names a missing file stops `zenrl run` before it starts
anything, with one error line naming the entry."""

import json
import re

import pytest

from tests.conftest import run_zenrl, zenrl_pids
from tests.unit.test_tools import make_checkpoint

pytestmark = pytest.mark.integration

# short matches (12 s + 4 s sudden death at 5 decisions/s: at most 80 steps) of the burgerwar_apex
# env, so that the actors finish several against the frozen policy within the update budget
MATCH = {"opponents": {"cheese": 1}, "side": "random", "reward": "zero_sum", "control_hz": 5, "action_set": "rich",
         "start_noise": 0.05, "match_time": 12.0, "sudden_death_time": 4.0}
SETS = ("max_updates=300", "max_wall_s=400", "replay.min_size=500", "actor.num_actors=1", "actor.envs_per_actor=4",
        "learner.batch_size=32", "learner.checkpoint_interval_s=30", "evaluator.enabled=false",
        f"env.kwargs={json.dumps(MATCH)}")


def test_zenrl_run_trains_against_a_frozen_checkpoint(tmp_path, run_id):
    frozen = make_checkpoint(tmp_path / "frozen", "zenrl/BurgerWar-v0", MATCH, seed=1)
    p, run_dir, logs = run_zenrl(tmp_path, "configs/burgerwar_apex.yaml", run_id, *SETS,
                                 f"opponents.pool.frozen.path={frozen}", "actor.episode_report_s=1")
    assert p.returncode == 0, (p.stderr[-3000:], logs)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("max_updates"), summary["stop_reason"]
    assert all(v == 0 for v in summary["restarts"].values()), summary["restarts"]
    actor_log = (run_dir / "logs" / "actor-0.log").read_text()
    assert re.search(r"opponent frozen: checkpoint .*ckpt-000000000010\.pt", actor_log), actor_log[-3000:]
    # every match the actor finished was against the frozen policy (cheese, env.kwargs' bot, none)
    tallies = re.findall(r"matches by opponent \(W/D/L\): (.*)", actor_log)
    assert tallies and re.fullmatch(r"frozen \d+/\d+/\d+", tallies[-1]), tallies
    assert not zenrl_pids(run_id), zenrl_pids(run_id)


def test_zenrl_run_refuses_a_missing_opponent_file_at_start(tmp_path, run_id):
    p, run_dir, _ = run_zenrl(tmp_path, "configs/burgerwar_apex.yaml", run_id, *SETS,
                              f"opponents.pool.gone.path={tmp_path / 'nope.pt'}", timeout_s=120)
    assert p.returncode == 2, p.stderr[-3000:]
    assert re.search(r"opponents\.pool\.gone: '.*nope\.pt' does not exist", p.stderr), p.stderr[-3000:]
    assert not run_dir.exists()  # refused before anything was created or started
