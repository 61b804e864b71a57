"""The Burger War judge as pure logic.

Each rule's source: the contest kit's judge server (``judge/judgeServer.py``: ``WarState``,
``Referee.judgeTargetId``, ``isOverMatchTime``, ``isCalledGame``) and the "Judge" section of
``shared/notes/burger-war.md``.
"""

import pytest

from zenrl.games.burgerwar.geometry import TARGET_NAMES
from zenrl.games.burgerwar.judge import BLUE, NEUTRAL, RED, Judge

IDX = {n: i for i, n in enumerate(TARGET_NAMES)}
FIELD = [n for n in TARGET_NAMES if not n.startswith(("RE_", "BL_"))]


def test_war_state_shape():
    j = Judge(players=("agent", "cheese"))
    ws = j.war_state()
    assert set(ws) == {"players", "ready", "scores", "state", "targets", "time"}
    assert ws["players"] == {"r": "agent", "b": "cheese"}
    assert ws["ready"] == {"r": True, "b": True}
    assert ws["scores"] == {"r": 0, "b": 0}
    assert ws["state"] == "running"
    assert len(ws["targets"]) == 18
    assert all(set(t) == {"name", "player", "point"} and t["player"] == "n" for t in ws["targets"])
    points = {t["name"]: t["point"] for t in ws["targets"]}
    assert points["RE_B"] == 5 and points["BL_L"] == 3 and points["FriedShrimp_N"] == 1
    assert isinstance(ws["time"], float)


def test_field_marker_retake_and_recount():
    j = Judge()
    ev = j.read(red_reads=[IDX["Tomato_N"]])
    assert ev[0]["name"] == "Tomato_N" and ev[0]["player"] == "r" and ev[0]["previous"] == "n"
    assert j.scores == (1, 0)
    assert j.read(red_reads=[IDX["Tomato_N"]]) == []  # already mine
    ev = j.read(blue_reads=[IDX["Tomato_N"]])
    assert ev[0]["previous"] == "r"
    assert j.scores == (0, 1)
    j.read(red_reads=[IDX["Tomato_N"]])
    assert j.scores == (1, 0) and j.owners[IDX["Tomato_N"]] == RED


def test_two_reads_of_one_marker_in_a_tick_the_later_request_wins():
    """Source: the contest kit's judge server (judge/judgeServer.py) serves one request at a
    time and sets the target's owner to the requester; notes "Judge": a field marker belongs
    to whoever read it last."""
    for order, later in (("rb", BLUE), ("br", RED)):
        j = Judge()
        ev = j.read([IDX["Pudding_S"]], [IDX["Pudding_S"]], order=order)
        assert j.owners[IDX["Pudding_S"]] == later
        assert j.scores == ((1, 0) if later == RED else (0, 1))
        # both requests are served: the earlier capture, then the later retake
        assert [(e["player"], e["previous"]) for e in ev] == (
            [("r", "n"), ("b", "r")] if order == "rb" else [("b", "n"), ("r", "b")])
    # a marker the later reader already owns: the earlier request takes it, the later retakes it
    j = Judge()
    j.read(red_reads=[IDX["Tomato_S"]])
    ev = j.read([IDX["Tomato_S"]], [IDX["Tomato_S"]], order="br")
    assert j.owners[IDX["Tomato_S"]] == RED and [e["player"] for e in ev] == ["b", "r"]
    ev = j.read([IDX["Tomato_S"]], [IDX["Tomato_S"]], order="rb")
    assert j.owners[IDX["Tomato_S"]] == BLUE and [e["player"] for e in ev] == ["b"]


def test_read_order_is_validated():
    with pytest.raises(ValueError, match="order must be one of"):
        Judge().read([0], [1], order="red")


def test_robot_markers_stay_taken_and_own_markers_unreadable():
    j = Judge()
    assert j.read(red_reads=[IDX["RE_B"]]) == []  # own marker
    assert j.read(blue_reads=[IDX["BL_L"]]) == []
    j.read(red_reads=[IDX["BL_B"]])
    assert j.scores == (5, 0)
    assert j.read(blue_reads=[IDX["BL_B"]]) == []  # cannot take back
    assert j.owners[IDX["BL_B"]] == RED
    j.read(blue_reads=[IDX["RE_L"], IDX["RE_R"]])
    assert j.scores == (5, 6)
    assert j.read(red_reads=[IDX["RE_L"]]) == []
    assert j.scores == (5, 6)


def test_called_game_at_diff_10():
    j = Judge()
    j.read(red_reads=[IDX["BL_B"], IDX["BL_L"]])  # 8
    assert j.state == "running"
    j.read(red_reads=[IDX["FriedShrimp_N"]])
    assert j.state == "running" and j.scores == (9, 0)
    j.read(red_reads=[IDX["FriedShrimp_S"]])
    assert j.state == "stop" and j.winner == "r"
    assert j.read(blue_reads=[IDX["FriedShrimp_S"]]) == []  # nothing after the call
    j.set_time(100.0)
    assert j.state == "stop"


def test_called_game_refuses_the_later_request_of_the_same_tick():
    """Source: judgeServer.py judgeTargetId stops the match right after the request that makes
    |diff| >= 10 (isCalledGame) and refuses requests once the state is not "running"."""
    j = Judge()
    j.read(red_reads=[IDX["BL_B"], IDX["BL_L"], IDX["Tomato_N"]])  # 9 - 0
    ev = j.read([IDX["Tomato_S"]], [IDX["Tomato_S"], IDX["RE_B"]], order="rb")
    assert j.state == "stop" and j.scores == (10, 0) and [e["player"] for e in ev] == ["r"]
    # served the other way round, blue's requests come first and the match goes on
    j = Judge()
    j.read(red_reads=[IDX["BL_B"], IDX["BL_L"], IDX["Tomato_N"]])
    j.read([IDX["Tomato_S"]], [IDX["Tomato_S"], IDX["RE_B"]], order="br")
    assert j.state == "running" and j.scores == (10, 5)


def test_match_ends_at_180_when_not_tied():
    j = Judge()
    j.read(blue_reads=[IDX["Omelette_S"]])
    j.set_time(179.9)
    assert j.state == "running" and j.winner is None
    j.set_time(180.0)
    assert j.state == "stop" and j.winner == "b"
    assert j.war_state()["state"] == "stop"


def test_sudden_death_ends_when_the_scores_differ():
    """Source: judgeServer.py isOverMatchTime: past match_time the match stops only when the
    scores differ; notes "Judge": sudden death up to 60 s more."""
    j = Judge()
    j.read([IDX["Tomato_N"]], [IDX["Tomato_S"]])
    j.set_time(180.0)
    assert j.state == "running" and j.sudden_death
    j.set_time(200.0)
    assert j.state == "running"
    j.read(blue_reads=[IDX["Tomato_N"]])  # blue retakes: 0 - 2
    assert j.state == "stop" and j.winner == "b" and j.time == 200.0
    assert j.war_state()["state"] == "stop"


def test_simultaneous_score_in_sudden_death_is_not_a_draw():
    """Source: judgeServer.py serves requests one at a time and stops (isOverMatchTime) before
    the next one as soon as the scores differ: the first request served wins; the match never
    ends tied before 240 s."""
    for order, winner in (("rb", "r"), ("br", "b")):
        j = Judge()
        j.set_time(181.0)
        ev = j.read([IDX["Omelette_N"]], [IDX["Pudding_S"]], order=order)
        assert j.state == "stop" and j.winner == winner and len(ev) == 1
        assert j.owners[IDX["Omelette_N" if winner == "r" else "Pudding_S"]] != NEUTRAL


def test_sudden_death_goes_on_while_tied():
    """Source: judgeServer.py isOverMatchTime compares the two scores: requests that change
    nothing (markers the reader already owns) leave them tied and the match goes on."""
    j = Judge()
    j.read([IDX["Tomato_N"]], [IDX["Tomato_S"]])  # 1 - 1
    j.set_time(185.0)
    assert j.read([IDX["Tomato_N"]], [IDX["Tomato_S"]], order="br") == []
    assert j.scores == (1, 1) and j.state == "running"
    j.set_time(239.9)
    assert j.state == "running" and j.sudden_death


def test_draw_at_240():
    """Source: judgeServer.py isOverMatchTime: past match_time + extend_time (60 s) the match
    stops whatever the scores."""
    j = Judge()
    j.set_time(180.0)
    assert j.sudden_death and j.state == "running"
    j.set_time(239.9)
    assert j.state == "running"
    j.set_time(240.0)
    assert j.state == "stop" and j.winner == "draw"


def test_finished_match_reports_stop_never_end():
    """Source: judgeServer.py: WarState starts in "end" (before the match), setStateStop sets
    "stop" for every finish (time, called game); the contest's clients wait for "stop"."""
    from zenrl.games.burgerwar.judge import PRE_MATCH, STOP

    assert (PRE_MATCH, STOP) == ("end", "stop")
    seen = set()
    for setup in ("called", "time", "sudden_death", "draw"):
        j = Judge()
        seen.add(j.state)
        if setup == "called":
            j.read(red_reads=[IDX["BL_B"], IDX["BL_L"], IDX["BL_R"]])
        elif setup == "time":
            j.read(red_reads=[IDX["Tomato_N"]])
            j.set_time(180.0)
        elif setup == "sudden_death":
            j.set_time(200.0)
            j.read(blue_reads=[IDX["Tomato_N"]])
        else:
            j.set_time(240.0)
        assert j.done and j.war_state()["state"] == "stop", setup
    assert seen == {"running"}


def test_reset_clears_everything():
    j = Judge()
    j.read([IDX["BL_B"]])
    j.set_time(200)
    j.reset()
    assert j.scores == (0, 0) and j.state == "running" and not j.sudden_death
    assert (j.owners == NEUTRAL).all() and j.time == 0.0
    assert BLUE == 2


def _info(side, r, b, winner=None):
    return {"side": side, "war_state": {"scores": {"r": r, "b": b}}, "winner": winner}


def test_match_outcome_counts_like_the_contest():
    from zenrl.games.burgerwar.judge import match_outcome

    assert match_outcome(_info("red", 3, 1, "r")) == ("win", 3, 1)
    assert match_outcome(_info("blue", 3, 1, "r")) == ("loss", 1, 3)
    # a higher score wins even if the match was cut off before the judge named a winner
    assert match_outcome(_info("blue", 0, 2)) == ("win", 2, 0)
    assert match_outcome(_info("red", 2, 2, "draw")) == ("draw", 2, 2)
    assert match_outcome(_info("red", 0, 0)) == ("draw", 0, 0)
    assert match_outcome({"TimeLimit.truncated": True}) is None


def test_env_sudden_death_ends_with_stop_when_the_agent_scores():
    """The real env: tied at match_time -> sudden death (game[1] = 1) goes on; the agent's read
    makes the scores differ -> terminated, state "stop", with sudden-death time left."""
    import math

    from zenrl.games.burgerwar.env import BurgerWarEnv

    env = BurgerWarEnv(opponents="idle", lidar_noise=0.0, match_time=0.5, sudden_death_time=5.0)
    try:
        env.reset(seed=0)
        for _ in range(10):
            obs, _, term, _, info = env.step(2)
            assert not term and info["war_state"]["state"] == "running"
        assert obs["game"][1] == 1.0  # sudden death, tied 0 - 0
        env.set_poses((0.0, -0.75, math.pi / 2), (0.0, 1.3, -math.pi / 2))  # facing FriedShrimp_S
        _, _, term, _, info = env.step(2)
        assert term and info["war_state"]["state"] == "stop" and info["winner"] == "r"
        assert info["war_state"]["time"] < 5.5
    finally:
        env.close()


def test_robot_marker_points_split_each_score_by_where_it_came_from():
    """Field markers held count for the score, not for the robot-marker points; a robot marker
    counts its points (3, 3, 5) for whoever read it, from each side's point of view."""
    from zenrl.games.burgerwar.judge import robot_marker_points

    j = Judge()
    j.read(red_reads=[IDX["BL_B"], IDX[FIELD[0]]])  # red: the enemy's back (5) and a field marker
    j.read(blue_reads=[IDX["RE_L"], IDX[FIELD[1]], IDX[FIELD[2]]])  # blue: red's left (3), two field
    ws = j.war_state()
    assert ws["scores"] == {"r": 6, "b": 5}
    assert robot_marker_points({"side": "red", "war_state": ws}) == (5, 3)
    assert robot_marker_points({"side": "blue", "war_state": ws}) == (3, 5)
    assert robot_marker_points({"side": "red", "war_state": Judge().war_state()}) == (0, 0)
    assert robot_marker_points({"TimeLimit.truncated": True}) is None


def test_env_reports_robot_marker_points_at_the_end_of_a_match():
    """The real env's last step carries each side's robot-marker points, from the agent's side:
    a raider reads the markers of an agent that stands in the open."""
    from zenrl.games.burgerwar.env import BurgerWarEnv

    env = BurgerWarEnv(opponents="raider", side="blue", match_time=30.0, sudden_death_time=0.0)
    try:
        env.reset(seed=1)
        term = trunc = False
        i = 0
        while not (term or trunc):
            _, _, term, trunc, info = env.step(0 if i < 12 else 2)
            i += 1
            assert ("my_robot_points" in info) == (term or trunc)
        targets = info["war_state"]["targets"]
        taken = sum(t["point"] for t in targets if t["name"].startswith("BL_") and t["player"] == "r")
        read = sum(t["point"] for t in targets if t["name"].startswith("RE_") and t["player"] == "b")
        assert taken >= 6  # at least L and R in 30 s
        assert (info["my_robot_points"], info["enemy_robot_points"]) == (read, taken)
        field = {"r": 0, "b": 0}
        for t in targets:
            if not t["name"].startswith(("RE_", "BL_")) and t["player"] != "n":
                field[t["player"]] += t["point"]
        # the rest of each score is the field markers it holds
        assert info["my_score"] - info["my_robot_points"] == field["b"]
        assert info["enemy_score"] - info["enemy_robot_points"] == field["r"]
    finally:
        env.close()
