"""The game package boundary: a finished match reports its outcome in the last step's ``info``
(``outcome``, ``my_score``, ``enemy_score``), generic code (``EnvBatch``) reads it from there,
and no generic package imports ``zenrl.games``."""

import ast
import math
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT
from zenrl.actor.batch_env import EnvBatch
from zenrl.common.config import EnvConfig

#: world poses (x, y, yaw): red facing FriedShrimp_S, blue facing FriedShrimp_N, both in reading
#: range; "away" keeps a robot at its start, reading nothing
RED_READS, BLUE_READS = (0.0, -0.75, math.pi / 2), (0.0, 0.75, -math.pi / 2)
RED_AWAY, BLUE_AWAY = (0.0, -1.3, math.pi / 2), (0.0, 1.3, -math.pi / 2)
STOP = 2  # users' action (0, 0): the agent stays where it was put
#: short matches against an idle bot: called after 0.5 s when the scores differ, a draw at 1.5 s
MATCH = {"opponents": "idle", "side": "red", "lidar_noise": 0.0, "match_time": 0.5, "sudden_death_time": 1.0}


def _play(env, red, blue, side="red"):
    env.reset(seed=0, options={"side": side})
    env.set_poses(red, blue)
    infos, done = [], False
    while not done:
        _, _, term, trunc, info = env.step(STOP)
        infos.append(info)
        done = term or trunc
    return infos


@pytest.mark.parametrize("side,red,blue,want", [
    ("red", RED_READS, BLUE_AWAY, ("win", 1, 0)),
    ("blue", RED_READS, BLUE_AWAY, ("loss", 0, 1)),
    ("blue", RED_AWAY, BLUE_READS, ("win", 1, 0)),
    ("red", RED_AWAY, BLUE_AWAY, ("draw", 0, 0)),
])
def test_a_finished_match_puts_its_outcome_in_the_last_info(make_bw, side, red, blue, want):
    env = make_bw(**{**MATCH, "side": "random"})
    infos = _play(env, red, blue, side)
    last = infos[-1]
    assert last["war_state"]["state"] == "stop"
    assert (last["outcome"], last["my_score"], last["enemy_score"]) == want
    assert isinstance(last["my_score"], int) and isinstance(last["enemy_score"], int)
    # only the step that ends the match carries it
    assert len(infos) > 1 and not any("outcome" in i for i in infos[:-1])


def test_a_match_cut_off_by_max_steps_has_an_outcome(make_bw):
    env = make_bw(**MATCH, max_steps=3)
    infos = _play(env, RED_READS, BLUE_AWAY)
    assert len(infos) == 3 and infos[-1]["war_state"]["state"] == "running"
    assert (infos[-1]["outcome"], infos[-1]["my_score"], infos[-1]["enemy_score"]) == ("win", 1, 0)


def test_env_batch_reports_win_draw_loss_from_info():
    """Real Burger War envs stepped by the generic EnvBatch: env 0 wins, env 1 loses, env 2 draws."""
    envs = EnvBatch(EnvConfig(id="zenrl/BurgerWar-v0", kwargs=MATCH), 3, seed=0)
    try:
        envs.reset()
        for env, (red, blue) in zip(envs.envs, [(RED_READS, BLUE_AWAY), (RED_AWAY, BLUE_READS), (RED_AWAY, BLUE_AWAY)]):
            env.unwrapped.set_poses(red, blue)
        outcomes: dict[int, int | None] = {}
        for _ in range(100):
            res = envs.step(np.full(3, STOP))
            for i, out in zip(np.flatnonzero(res.terminated | res.truncated), res.ep_outcomes):
                outcomes.setdefault(int(i), out)
            if len(outcomes) == 3:
                break
        assert outcomes == {0: 1, 1: -1, 2: 0}
    finally:
        envs.close()


def test_env_batch_reports_no_outcome_for_an_env_without_one():
    envs = EnvBatch(EnvConfig(id="CartPole-v1"), 2, seed=0)
    try:
        envs.reset()
        outs: list = []
        for _ in range(500):
            outs += envs.step(np.zeros(2, np.int64)).ep_outcomes
            if outs:
                break
        assert outs and all(o is None for o in outs)
    finally:
        envs.close()


GENERIC = ("actor", "learner", "replay", "common")


def _game_imports(path, root=ROOT) -> list[str]:
    """``zenrl.games`` imports anywhere in a module (top level or inside functions), and
    ``importlib.import_module("zenrl.games...")`` calls."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] if node.level == 0 else []
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) in ("import_module", "__import__")
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            names = [node.args[0].value]
        found += [f"{path.relative_to(root)}:{node.lineno}: {n}" for n in names
                  if n.split(".")[:2] == ["zenrl", "games"] or n.split(".")[0] == "games"]
    return found


def test_generic_packages_do_not_import_the_games():
    files = [f for d in GENERIC for f in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 20
    bad = [hit for f in files for hit in _game_imports(f)]
    assert not bad, "generic code imports a game (read the match result from info instead):\n" + "\n".join(bad)


def test_the_boundary_scan_finds_an_import(tmp_path):
    # the scan above must be able to fail: each form it looks for is found
    src = tmp_path / "m.py"
    src.write_text("import zenrl.games.burgerwar\n"
                   "def f():\n    from zenrl.games.burgerwar.judge import match_outcome\n"
                   "    importlib.import_module('zenrl.games.burgerwar.env')\n"
                   "ENTRY = 'zenrl.games.burgerwar.env:BurgerWarEnv'\n")
    hits = [h.split(": ")[1] for h in _game_imports(src, tmp_path)]
    assert hits == ["zenrl.games.burgerwar", "zenrl.games.burgerwar.judge", "zenrl.games.burgerwar.env"]


def test_importing_generic_code_loads_no_game():
    """Registering the ids and making the env batch machinery importable loads no game module
    (gymnasium imports the game on the first ``make``)."""
    code = ("import sys, zenrl.common.envs, zenrl.common.env_factory, zenrl.actor.batch_env, zenrl.actor.evaluator\n"
            "import gymnasium\n"
            "assert gymnasium.spec('zenrl/BurgerWar-v0').entry_point == 'zenrl.games.burgerwar.env:BurgerWarEnv'\n"
            "print(sorted(m for m in sys.modules if m.startswith('zenrl.games')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
