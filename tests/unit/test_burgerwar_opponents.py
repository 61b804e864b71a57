"""Scripted Burger War opponents."""

import numpy as np
import pytest

from zenrl.games.burgerwar import opponents as bo
from zenrl.games.burgerwar.env import BurgerWarEnv

STOP = 2  # the users' (0, 0) action


def _play_vs_idle(name, side, until_points, max_time=180.0):
    """Agent stands still; returns (opponent's score, field markers it took, time)."""
    env = BurgerWarEnv(opponents=name, side=side)
    try:
        env.reset(seed=0)
        opp = "b" if side == "red" else "r"
        taken = set()
        while True:
            _, _, term, _, info = env.step(STOP)
            ws = info["war_state"]
            taken |= {c["name"] for c in info["captures"] if c["player"] == opp
                      and not c["name"].startswith(("RE_", "BL_"))}
            if term or ws["scores"][opp] >= until_points or ws["time"] >= max_time:
                return ws["scores"][opp], taken, ws["time"]
    finally:
        env.close()


@pytest.mark.parametrize("name,side", [("cheese", "red"), ("teriyaki", "blue"),
                                       ("clubhouse", "red"), ("waypoint", "blue")])
def test_scripted_enemy_scores_against_idle(name, side):
    score, taken, t = _play_vs_idle(name, side, until_points=1)
    assert score >= 1 and t < 180.0


@pytest.mark.parametrize("name", ["teriyaki", "waypoint"])
def test_touring_enemies_visit_several_markers(name):
    _, taken, _ = _play_vs_idle(name, "red", until_points=99, max_time=60.0)
    assert len(taken) >= 3, taken


def test_teriyaki_grid_is_coarse_heading_table():
    g = bo.teriyaki_grid(8)
    assert g.shape == (8, 8) and np.all(np.abs(g) <= np.pi)
    # the start cell sends it towards the centre (+y in its own frame), give or take 45 deg
    t = bo.Teriyaki()
    assert abs(t._cell_heading(0.05, -1.3) - np.pi / 2) < np.pi / 4


def test_cheese_drives_back_and_forth():
    env = BurgerWarEnv(opponents="cheese", side="red", lidar_noise=0.0)
    try:
        env.reset(seed=0)
        ys = []
        for _ in range(250):
            env.step(STOP)
            ys.append(env.poses[1, 1])  # blue: its forward is -y in the world
        travelled = 1.3 - np.array(ys)
        assert travelled.max() == pytest.approx(0.92, abs=0.05)
        assert travelled[np.argmax(travelled):].min() == pytest.approx(0.17, abs=0.05)
    finally:
        env.close()


def test_clubhouse_detects_enemy_in_front():
    env = BurgerWarEnv(opponents="idle", lidar_noise=0.0)
    try:
        env.reset(seed=0)
        env.set_poses((0.0, -0.9, np.pi / 2), (0.0, -0.4, 0.0))
        lidar = env._scan(0)
        seen = bo.detect_enemy(bo.OpponentView(0.0, -0.9, np.pi / 2, 0.0, lidar), bo._bearings())
        assert seen is not None
        bearing, dist = seen
        assert abs(bearing) < 0.1 and 0.3 < dist < 0.6
        # nothing near: no detection
        env.set_poses((0.0, -0.9, np.pi / 2), (0.0, 1.3, 0.0))
        lidar = env._scan(0)
        assert bo.detect_enemy(bo.OpponentView(0.0, -0.9, np.pi / 2, 0.0, lidar), bo._bearings()) is None
    finally:
        env.close()


def test_opponent_mixture_sampled_per_episode():
    env = BurgerWarEnv(opponents={"idle": 1.0, "random": 1.0, "cheese": 2.0})
    try:
        names = set()
        env.reset(seed=0)
        for _ in range(12):
            _, info = env.reset()
            names.add(info["opponent"])
        assert names == {"idle", "random", "cheese"}
    finally:
        env.close()


def test_bad_opponent_options():
    with pytest.raises(ValueError):
        BurgerWarEnv(opponents="nope")
    with pytest.raises(ValueError):
        BurgerWarEnv(opponents="policy")  # needs opponent_policy


@pytest.mark.parametrize("side", ["red", "blue"])
def test_raider_reads_every_robot_marker_of_an_enemy_in_the_open(side):
    """The agent drives a little out of its corner and stops; the raider reads its L, R and B
    within 45 s (the last of them after about 21 s)."""
    env = BurgerWarEnv(opponents="raider", side=side)
    try:
        env.reset(seed=1)
        opp, prefix = ("b", "RE_") if side == "red" else ("r", "BL_")
        robot = set()
        for i in range(10 ** 4):
            _, _, term, _, info = env.step(0 if i < 12 else STOP)  # (0.2, 0): forward
            robot |= {c["name"] for c in info["captures"] if c["player"] == opp and c["name"].startswith(("RE_", "BL_"))}
            if term or len(robot) == 3 or info["war_state"]["time"] > 45.0:
                break
        assert robot == {prefix + m for m in ("L", "R", "B")}, robot
    finally:
        env.close()


def test_raider_view_has_the_enemy_pose_and_what_it_took():
    """The env gives a ``needs_enemy`` opponent the agent's true pose in the opponent's own
    frame and which of the agent's robot markers the opponent owns."""
    env = BurgerWarEnv(opponents="raider", side="red", lidar_noise=0.0)
    try:
        env.reset(seed=0)
        seen = []
        act = env.opponent.act
        env.opponent.act = lambda view: (seen.append(view), act(view))[1]
        env.set_poses((0.3, -0.5, 0.2), (0.0, 1.3, -np.pi / 2))
        names = list(bo.geo.TARGET_NAMES)
        env.judge.owners[names.index("RE_R")] = 2  # blue (the raider) holds the agent's right marker
        env.judge.owners[names.index("RE_B")] = 1  # not the raider's: red's own code
        env.step(STOP)
        v = seen[-1]
        # blue's own frame is the world turned 180 degrees
        assert v.enemy[0] == pytest.approx(-0.3, abs=0.02) and v.enemy[1] == pytest.approx(0.5, abs=0.02)
        assert np.cos(v.enemy[2] - (0.2 + np.pi)) == pytest.approx(1.0, abs=1e-3)
        assert v.taken == (False, True, False)
        assert bo.Waypoint().needs_enemy is False and v.obs is None
    finally:
        env.close()
