"""A league agent's process resets itself where no launcher does (common/league_reset.py,
league.self_reset): the first generation heard is its own, a higher one stops it, it deletes the
old generation's files and exits with status 75; a process that was down meanwhile catches up
from its marker file."""

import threading

import pytest

from tests.conftest import ROOT
from zenrl.common import protocol as P
from zenrl import EXIT_CONFIG
from zenrl.common.config import load_config
from zenrl.common.league_reset import EXIT_GENERATION, GenerationReset, GenerationWatch, marker_path


class FakeNode:
    def __init__(self):
        self.subs = {}

    def subscribe(self, key, cb):
        self.subs[key] = cb


def say(node, generation, agent="exploiter", payload=None):
    key = P.Keys("lg").stats("league", "league")
    values = {f"generation/{agent}": generation, "players": 5}
    node.subs[key]("zenrl/lg/stats/league/league",
                   payload if payload is not None else P.Stats("league", "league", 1.0, values).encode())


def cfg_for(tmp_path, *sets):
    return load_config(None, ["league.enabled=true", "league.run_id=lg", "league.player=exploiter",
                              "league.agents={main: {role: main}, exploiter: {role: exploiter}}",
                              f"runs_dir={tmp_path}", *sets])


def test_a_new_generation_stops_the_process_and_deletes_the_old_files(tmp_path):
    cfg = cfg_for(tmp_path)
    node, stop = FakeNode(), threading.Event()
    w = GenerationWatch.for_config(cfg, node, "lg.exploiter", "learner", stop)
    ckpts = tmp_path / "lg.exploiter" / "checkpoints"
    ckpts.mkdir(parents=True)
    (ckpts / "ckpt-000000000100.pt").write_bytes(b"x")
    say(node, 2)                     # the first word: generation 2 is ours
    say(node, 2, agent="main")       # another agent's reset is not ours
    say(node, 1)                     # a stale message
    say(node, 3, payload=b"junk")
    assert not stop.is_set()
    w.finish([ckpts])                # no reset seen: nothing happens
    assert ckpts.is_dir() and marker_path(cfg, "lg.exploiter", "learner").read_text() == "2\n"
    say(node, 3)
    assert stop.is_set()
    with pytest.raises(GenerationReset, match=f"generation 3.*{EXIT_GENERATION}"):
        w.finish([ckpts])
    assert not ckpts.exists() and marker_path(cfg, "lg.exploiter", "learner").read_text() == "3\n"


def test_a_process_that_was_down_catches_up_from_its_marker(tmp_path):
    cfg = cfg_for(tmp_path)
    marker = marker_path(cfg, "lg.exploiter", "replay")
    marker.parent.mkdir(parents=True)
    marker.write_text("1\n")
    node, stop = FakeNode(), threading.Event()
    GenerationWatch.for_config(cfg, node, "lg.exploiter", "replay", stop)
    say(node, 2)  # the league moved on while this replay was down: its files are stale
    assert stop.is_set()


def test_an_actor_keeps_no_marker_and_only_agent_processes_watch(tmp_path):
    cfg = cfg_for(tmp_path)
    node, stop = FakeNode(), threading.Event()
    w = GenerationWatch.for_config(cfg, node, "lg.exploiter", "actor", stop, stateful=False)
    say(node, 4)
    say(node, 5)
    assert stop.is_set() and not list(tmp_path.rglob("league_generation.*"))
    with pytest.raises(GenerationReset):
        w.finish([])
    assert GenerationWatch.for_config(cfg_for(tmp_path, "league.self_reset=false"), FakeNode(), "x", "learner",
                                      threading.Event()) is None
    plain = load_config(None, [f"runs_dir={tmp_path}"])  # not a league agent's process
    assert GenerationWatch.for_config(plain, FakeNode(), "x", "learner", threading.Event()) is None


def test_agent_flag_gives_the_agents_config_or_a_one_line_error(tmp_path, capsys):
    from zenrl.cli import main
    from zenrl.common.errors import ConfigError
    from zenrl.launcher.league_run import agent_config

    cfg = load_config(ROOT / "configs/burgerwar_league_pfsp.yaml", [f"runs_dir={tmp_path}", "run_id=lg"])
    ex = agent_config(cfg, "exploiter")
    assert (ex.run_id, ex.league.run_id, ex.league.player, ex.league.self_reset) == ("lg.exploiter", "lg", "exploiter", True)
    assert ex.replay.capacity == 100000 and ex.actor.num_actors == 1 and not ex.evaluator.enabled
    with pytest.raises(ConfigError, match="not one of league.agents"):
        agent_config(cfg, "nobody")
    with pytest.raises(ConfigError, match="exploiter_init main needs zenrl run"):
        agent_config(cfg.model_copy(update={"league": cfg.league.model_copy(update={"exploiter_init": "main"})}),
                     "exploiter")
    assert main(["replay", "--agent", "main", "--run-id", "x"]) == EXIT_CONFIG  # CartPole: no league
    assert "league.enabled is false" in capsys.readouterr().err
