"""What `zenrl run` derives for a league config (zenrl/launcher/league_run.py), and the rows of
`zenrl league status` (zenrl/launcher/league_status.py)."""

import numpy as np
import pytest

from tests.conftest import ROOT
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.errors import ConfigError
from zenrl.launcher.league_run import agent_configs, check_league
from zenrl.common.ratings import expected_score
from zenrl.launcher.league_status import ratings_of, rows_of


def test_each_agent_gets_its_own_run_id_folder_and_actors():
    cfg = load_config(ROOT / "configs/burgerwar_league_pfsp.yaml", ["runs_dir=/r"])
    agents = agent_configs(cfg, "lg1")
    assert set(agents) == {"main", "exploiter"}
    m, e = agents["main"], agents["exploiter"]
    assert (m.run_id, e.run_id) == ("lg1.main", "lg1.exploiter")
    assert m.runs_dir == e.runs_dir == "/r/lg1/agents"
    assert (m.league.run_id, m.league.player, e.league.player) == ("lg1", "main", "exploiter")
    assert (m.actor.num_actors, m.actor.envs_per_actor, e.actor.num_actors) == (2, 8, 1)
    assert m.evaluator.enabled and not e.evaluator.enabled
    assert e.replay.capacity == 100_000 and m.replay.capacity == 300_000  # the exploiter's override


def test_a_bad_agent_override_names_the_agent():
    cfg = load_config(None, ["league.enabled=true", "league.agents.main.role=main",
                             "league.agents.exploiter.role=exploiter",
                             "league.agents.exploiter.overrides={learner.lr: -1}"])
    with pytest.raises(ConfigError, match=r"league\.agents\.exploiter\.overrides: learner\.lr"):
        agent_configs(cfg, "lg1")
    with pytest.raises(ConfigError, match="longer than 64"):
        agent_configs(load_config(None, ["league.enabled=true"]), "x" * 60)


def test_check_league_needs_a_match_env_with_those_bots():
    # every algorithm's actors take league opponents; only Ape-X and R2D2 learners can start
    # from main's checkpoint
    with pytest.raises(ConfigError, match="league.exploiter_init: main .* algo impala"):
        check_league(load_config(None, ["league.enabled=true", "algo=impala", "league.exploiter_init=main"]))
    with pytest.raises(ConfigError, match="match env"):
        check_league(load_config(None, ["league.enabled=true", "algo=a3c"]))
    with pytest.raises(ConfigError, match="match env"):
        check_league(load_config(None, ["league.enabled=true"]))
    with pytest.raises(ConfigError, match="opponents.pool.main-best: a league player's name"):
        check_league(load_config(None, ["league.enabled=true", "env.id=zenrl/BurgerWar-v0",
                                        "opponents.pool.main-best.bot=cheese"]))
    with pytest.raises(ConfigError, match="opponents.pool.cheese: the name is taken"):
        check_league(load_config(None, ["league.enabled=true", "env.id=zenrl/BurgerWar-v0",
                                        "opponents.pool.cheese.bot=cheese"]))
    with pytest.raises(ConfigError, match="league.bots: 'robocop'"):
        check_league(load_config(None, ["league.enabled=true", "env.id=zenrl/BurgerWar-v0",
                                        "league.bots=[cheese, robocop]"]))


def test_status_rows():
    ids = {"cheese": 0, "main": 1, "main-s1": 2}
    counts = np.zeros((3, 3, 3), np.int64)
    counts[1, 0] = [5, 1, 2]
    counts[0, 1] = [2, 1, 5]
    counts[1, 1] = [3, 0, 0]  # self-play
    t = P.LeagueTable(ids=ids, kinds={"cheese": "bot", "main": "learner", "main-s1": "snapshot"},
                      roles={"cheese": "bot", "main": "main", "main-s1": "main"},
                      versions={"cheese": -1, "main": 40, "main-s1": 20}, generations={"cheese": 0, "main": 0, "main-s1": 0},
                      counts=counts, main_pfsp={"cheese": 0.4, "main": 0.35, "main-s1": 0.25}, values={})
    rows = {r["id"]: r for r in rows_of(P.LeagueTable.decode(t.encode()))}
    assert rows["cheese"]["vs_main"] == [5, 1, 2] and rows["cheese"]["games"] == 8
    assert rows["main"]["games"] == 11 and "vs_main" not in rows["main"]
    assert rows["main-s1"]["games"] == 0 and rows["main-s1"]["pfsp"] == pytest.approx(0.25)


def test_status_ratings_count_each_match_once():
    ids = {"cheese": 0, "main": 1, "waypoint": 2, "main-s1": 3}
    counts = np.zeros((4, 4, 3), np.int64)
    for a, b, rec in ((1, 0, [30, 0, 10]), (1, 2, [20, 0, 20]), (1, 1, [9, 0, 0])):
        counts[a, b] = rec
        counts[b, a] = rec[::-1]
    t = P.LeagueTable(ids=ids, kinds=dict.fromkeys(ids, "bot"), roles=dict.fromkeys(ids, "bot"),
                      versions=dict.fromkeys(ids, -1), generations=dict.fromkeys(ids, 0), counts=counts,
                      main_pfsp={}, values={})
    r, why = ratings_of(t)
    assert why is None
    assert r["main"].games == 80 and r["cheese"].games == 40  # not doubled, self-play left out
    assert np.isnan(r["main-s1"].elo)
    # main beats cheese 3:1 and waypoint 1:1 (one virtual draw each): expected scores follow
    assert expected_score(r["main"].elo, r["cheese"].elo) == pytest.approx(30.5 / 41, abs=1e-6)
    assert expected_score(r["main"].elo, r["waypoint"].elo) == pytest.approx(0.5, abs=1e-6)


def test_status_of_a_stopped_run_reads_the_saved_league(tmp_path):
    import yaml

    from zenrl.league.core import League
    from zenrl.league.store import LeagueStore
    from zenrl.launcher.league_status import saved_table

    cfg = load_config(None, ["league.enabled=true", "league.bots=[cheese]", "opponents.pool.champ.path=x.pt"])
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    assert saved_table(tmp_path) is None
    lg = League(cfg.league, 0.0, frozen=["champ"])
    lg.record("main", "cheese", 1)
    lg.record("main", "champ", 0)
    lg.record("exploiter", "main", -1)
    LeagueStore(tmp_path / "league", 1 << 20).save(lg)
    t = saved_table(tmp_path)
    assert t.values["saved"] and t.values["results_total"] == 3
    rows = {r["id"]: r for r in rows_of(t)}
    assert rows["cheese"]["vs_main"] == [1, 0, 0] and rows["exploiter"]["vs_main"] == [1, 0, 0]
    assert rows["champ"]["kind"] == "frozen" and rows["champ"]["vs_main"] == [0, 1, 0]


def test_a_reset_exploiter_starts_from_a_copy_of_mains_newest_checkpoint(tmp_path):
    from zenrl.launcher.league_run import exploiter_init

    cfg = load_config(ROOT / "configs/burgerwar_league_pfsp.yaml", [f"runs_dir={tmp_path}", "league.exploiter_init=main"])
    agents = agent_configs(cfg, "lg1")
    run_dir = tmp_path / "lg1"
    assert exploiter_init(agents, "exploiter", run_dir) is None  # main has no checkpoint yet: fresh
    ck = tmp_path / "lg1" / "agents" / "lg1.main" / "checkpoints"
    ck.mkdir(parents=True)
    (ck / "ckpt-000000000100.pt").write_bytes(b"old")
    (ck / "ckpt-000000000200.pt").write_bytes(b"new")
    out = exploiter_init(agents, "exploiter", run_dir)
    assert out == run_dir / "agents" / "exploiter.init.pt" and out.read_bytes() == b"new"
    (ck / "ckpt-000000000200.pt").unlink()  # main may prune it: the exploiter's copy stays
    assert out.read_bytes() == b"new"
    assert exploiter_init(agents, "main", run_dir) is None  # only an exploiter
    fresh = agent_configs(load_config(ROOT / "configs/burgerwar_league_pfsp.yaml",
                                      [f"runs_dir={tmp_path}", "league.exploiter_init=fresh"]), "lg1")
    assert exploiter_init(fresh, "exploiter", run_dir) is None


def test_a_resumed_runs_exploiter_past_its_first_generation_gets_mains_checkpoint(tmp_path):
    from zenrl.launcher.supervisor import Launcher

    def learner_args(resume, applied):
        cfg = load_config(ROOT / "configs/burgerwar_league_pfsp.yaml",
                          [f"runs_dir={tmp_path}", "run_id=lg1", "league.exploiter_init=main"])
        la = Launcher(cfg, resume=resume)
        la.applied = applied
        kids = {c.name: c for c in la._plan()}
        assert "main-replay" in kids and "exploiter-replay" in kids
        return kids["exploiter-learner"].args, kids["main-learner"].args

    ck = tmp_path / "lg1" / "agents" / "lg1.main" / "checkpoints"
    ck.mkdir(parents=True)
    (ck / "ckpt-000000000100.pt").write_bytes(b"main's")
    init = f"learner.init_from={tmp_path / 'lg1' / 'agents' / 'exploiter.init.pt'}"
    ex, main = learner_args(True, {"exploiter": 2, "main": 0})
    assert ex == ["--auto-resume", "--set", init] and main == ["--auto-resume"]
    assert learner_args(True, {"exploiter": 0})[0] == ["--auto-resume"]  # the first generation: fresh
    assert learner_args(False, {"exploiter": 2})[0] == []                # a new run
