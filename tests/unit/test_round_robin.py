"""``zenrl evaluate --round-robin``: every pair of policies and bots plays N matches on fresh seeds,
half on each side; the table and the ratings follow from the matches."""

from __future__ import annotations

import json

import pytest

from tests.unit.test_tools import BW, SHORT_MATCH, make_checkpoint
from zenrl import tools
from zenrl.cli import main as cli_main
from zenrl.common.errors import ZenrlError
from zenrl.common.ratings import PairRecord, fit_ratings


@pytest.fixture(scope="module")
def players(tmp_path_factory):
    d = tmp_path_factory.mktemp("rr")
    a = make_checkpoint(d / "a", BW, SHORT_MATCH, seed=1)
    b = make_checkpoint(d / "b", BW, SHORT_MATCH, seed=2)
    exported = d / "b_exported.pt"
    tools.export(str(b), exported)
    return {"a": str(a), "b": str(b), "exported": str(exported)}


def test_round_robin_plays_every_pair_on_both_sides(players):
    a, b = players["a"], str(players["exported"])
    out = tools.round_robin([a, b, "cheese", "idle"], matches=4, seed=70, progress=False, allow_exported=True)
    names = out["players"]
    assert names == ["ckpt-000000000010.pt", "b_exported.pt", "cheese", "idle"]
    assert out["skipped"] == [["cheese", "idle"]]  # two bots do not meet
    res = out["results"]
    assert len(res) == 5 * 4 and sorted(r["seed"] for r in res) == list(range(70, 90))  # a fresh seed each
    for x, y in [(a, b), (a, "cheese"), (a, "idle"), (b, "cheese"), (b, "idle")]:
        rs = [r for r in res if {r["red"], r["blue"]} == {x, y}]
        assert len(rs) == 4 and sum(r["red"] == x for r in rs) == 2  # half on each side
    for r in res:
        if r["red_score"] != r["blue_score"]:  # a decided score decides the match (no sudden-death call here)
            assert r["winner"] == ("red" if r["red_score"] > r["blue_score"] else "blue")
    # the table is the matches' count, the ratings the fit of the table
    records = []
    for p in out["pairs"]:
        files = out["files"]
        rs = [r for r in res if {r["red"], r["blue"]} == {files[p["a"]], files[p["b"]]}]
        wins = sum(r["winner"] != "draw" and r[r["winner"]] == files[p["a"]] for r in rs)
        losses = sum(r["winner"] != "draw" and r[r["winner"]] == files[p["b"]] for r in rs)
        assert (p["a_wins"], p["b_wins"], p["draws"]) == (wins, losses, len(rs) - wins - losses)
        records.append(PairRecord(p["a"], p["b"], p["a_wins"], p["draws"], p["b_wins"]))
    want = fit_ratings(names, records)
    for r in out["ratings"]:
        assert r["elo"] == pytest.approx(want[r["player"]].elo) and r["matches"] == want[r["player"]].games
    assert sum(p["matches"] for p in out["pairs"]) == 20


def test_round_robin_cli_and_its_errors(players, tmp_path, capsys):
    js = tmp_path / "rr.json"
    rc = cli_main(["evaluate", "--checkpoint", players["a"], "--round-robin", f"{players['b']},cheese",
                   "--episodes", "2", "--workers", "2", "--no-progress", "--anchor", "cheese", "--json", str(js)])
    assert rc == 0
    out = capsys.readouterr().out
    last = json.loads(out.strip().splitlines()[-1])
    assert last["kind"] == "round_robin" and last["anchor"] == "cheese" and "results" not in last
    assert {r["player"]: r["elo"] for r in last["ratings"]}["cheese"] == 0
    assert "round robin" in out and "Elo" in out
    assert len(json.loads(js.read_text())["results"]) == 6
    assert cli_main(["evaluate", "--round-robin", f"{players['a']},cheese", "--policy", "sample"]) == 2
    assert "greedy policies only" in capsys.readouterr().err
    with pytest.raises(ZenrlError, match="at least one policy file"):
        tools.round_robin(["cheese", "waypoint"], matches=1, progress=False)
    with pytest.raises(ZenrlError, match="exported TorchScript policy.*--exported"):
        tools.round_robin([players["a"], players["exported"]], matches=1, progress=False)
    with pytest.raises(ZenrlError, match="--anchor 'nobody'"):
        tools.round_robin([players["a"], "cheese"], matches=1, progress=False, anchor="nobody")
    with pytest.raises(ZenrlError, match="'nobody'.*neither a bot"):
        tools.round_robin([players["a"], "nobody"], matches=1, progress=False)
