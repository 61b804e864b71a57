"""The Burger War judge as pure logic."""

from zenrl.common.envs.bw_geometry import TARGET_NAMES
from zenrl.common.envs.bw_judge import BLUE, NEUTRAL, RED, Judge

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


def test_simultaneous_field_reads_cancel():
    j = Judge()
    assert j.read([IDX["Pudding_S"]], [IDX["Pudding_S"]]) == []
    assert j.owners[IDX["Pudding_S"]] == NEUTRAL


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


def test_match_ends_at_180_when_not_tied():
    j = Judge()
    j.read(blue_reads=[IDX["Omelette_S"]])
    j.set_time(179.9)
    assert j.state == "running" and j.winner is None
    j.set_time(180.0)
    assert j.state == "end" and j.winner == "b"
    assert j.war_state()["state"] == "end"


def test_sudden_death_ends_at_first_score_change():
    j = Judge()
    j.read([IDX["Tomato_N"]], [IDX["Tomato_S"]])
    j.set_time(180.0)
    assert j.state == "running" and j.sudden_death
    j.set_time(200.0)
    assert j.state == "running"
    j.read(blue_reads=[IDX["Tomato_N"]])  # blue retakes: 0 - 2
    assert j.state == "end" and j.winner == "b"


def test_draw_at_240():
    j = Judge()
    j.set_time(180.0)
    assert j.sudden_death and j.state == "running"
    j.set_time(239.9)
    assert j.state == "running"
    j.set_time(240.0)
    assert j.state == "end" and j.winner == "draw"


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
    from zenrl.common.envs.bw_judge import match_outcome

    assert match_outcome(_info("red", 3, 1, "r")) == ("win", 3, 1)
    assert match_outcome(_info("blue", 3, 1, "r")) == ("loss", 1, 3)
    # a higher score wins even if the match was cut off before the judge named a winner
    assert match_outcome(_info("blue", 0, 2)) == ("win", 2, 0)
    assert match_outcome(_info("red", 2, 2, "draw")) == ("draw", 2, 2)
    assert match_outcome(_info("red", 0, 0)) == ("draw", 0, 0)
    assert match_outcome({"TimeLimit.truncated": True}) is None
