"""The league service's handling of messages (league/service.py) with an in-memory node: what
it answers, what it counts and rejects, what survives a restart (league/store.py)."""

import json

import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.transport import LatestValue
from zenrl.league.service import LeagueService
from zenrl.league.store import STATE_FILE


class FakeNode:
    def __init__(self):
        self.subs, self.queryables, self.latest = {}, {}, {}

    def subscribe(self, key, cb):
        self.subs[key] = cb

    def subscribe_latest(self, key):
        lv = self.latest[key] = LatestValue()
        return lv

    def queryable(self, key, handler):
        self.queryables[key] = handler


class Clock:
    def __init__(self, t=1000.0):
        self.t = t

    def __call__(self):
        return self.t


def make(tmp_path, clock, *sets):
    cfg = load_config(None, ["league.enabled=true", "league.bots=[cheese, teriyaki]", "league.decay=1.0",
                             "league.live_refresh_s=0.001", "league.min_games=2", "league.snapshot_interval_s=100",
                             "league.exploiter_reset_s=500", *sets])
    node = FakeNode()
    svc = LeagueService(cfg, node, "lg", directory=tmp_path / "league", clock=clock)
    svc.start(node, None)
    node.svc = svc
    return svc, node


def broadcast(node, agent, version, updates=None):
    params = {"w": np.arange(4, dtype=np.float32) + version}
    payload = P.Weights(version=version, learner_id="learner", arch="mlp", updates=version * 10 if updates is None else updates,
                        params=params).encode()
    node.latest[P.Keys(f"lg.{agent}").weights].set("k", payload)


def result(node, actor="a0", **kw):
    """Publish a result of ``actor``; unless ``ticket`` is given, with a ticket the league issued
    for that very pairing (as if the league had assigned it)."""
    m = dict(actor_id=actor, player="main", generation=0, player_version=1, opponent="cheese",
             opponent_version=-1, outcome=1, my_score=7, enemy_score=2)
    m.update(kw)
    if "ticket" not in kw:
        m["ticket"] = node.svc.tickets.issue(actor, m["player"], m["opponent"], m["opponent_version"])
    node.subs[P.LeagueKeys("lg").results_all](f"zenrl/lg/league/results/{actor}", P.MatchResult(**m).encode())


def ask(node, player="main", actor="a0"):
    rep = node.queryables[P.LeagueKeys("lg").opponent](P.OpponentRequest(player, actor).encode())
    return P.OpponentReply.decode(rep)


def test_results_are_counted_and_hostile_ones_rejected(tmp_path):
    clock = Clock()
    svc, node = make(tmp_path, clock)
    result(node)
    result(node, outcome=-1, opponent="teriyaki")
    assert svc.league.payoff.wdl("main", "cheese") == (1, 0, 0)
    assert svc.league.payoff.wdl("teriyaki", "main") == (1, 0, 0)
    key = "zenrl/lg/league/results/a0"
    on = node.subs[P.LeagueKeys("lg").results_all]
    on(key, b"\x93garbage")
    on(key, P.MatchResult("a0", "main", 0, 1, "cheese", -1, 1).encode()[:-3])
    result(node, player="cheese")              # a bot does not learn
    result(node, opponent="nobody")            # not a player
    result(node, opponent="cheese", opponent_version=5)  # bots have no version
    result(node, generation=3)                 # ahead of the league
    result(node, actor="a1", opponent="cheese")
    on("zenrl/lg/league/results/a9", P.MatchResult("a0", "main", 0, 1, "cheese", -1, 1).encode())  # spoofed id
    bad = P.MatchResult("a0", "main", 0, 1, "cheese", -1, 1).encode().replace(b"\xa7outcome\x01", b"\xa7outcome\x07")
    on(key, bad)
    real = svc.league.record
    svc.league.record = lambda *a: 1 / 0  # a bug in the handling code: that message alone is lost, counted
    result(node)
    svc.league.record = real
    vals, _ = svc.report(1.0)
    assert vals["rejected_internal/ZeroDivisionError"] == 1
    assert vals["rejected_malformed"] == 2
    assert vals["rejected_unknown_player"] == 1 and vals["rejected_unknown_opponent"] == 1
    assert vals["rejected_opponent_version"] == 1 and vals["rejected_generation"] == 1
    assert vals["rejected_actor_id"] == 1 and vals["rejected_field"] == 1
    assert vals["results_total"] == 3  # the two good ones and a1's
    assert svc.league.payoff.wdl("main", "cheese") == (2, 0, 0)


def test_a_result_counts_only_against_an_open_ticket_of_its_actor_once(tmp_path):
    clock = Clock()
    svc, node = make(tmp_path, clock, "league.ticket_rate_per_s=2", "league.ticket_burst=8",
                     "league.prefetch=4", "league.open_tickets_per_actor=3")
    rep = ask(node)  # a bot, a frozen file or main itself: whatever PFSP drew
    assert rep.status == "ok" and rep.ticket > 0
    good = dict(player="main", opponent=rep.opponent, opponent_version=rep.version, ticket=rep.ticket)
    result(node, **good)
    assert svc.league.results_total == 1
    result(node, **good)                                    # the same result again: the ticket is spent
    result(node, **{**good, "ticket": rep.ticket ^ 1})      # a ticket never issued
    rep2 = ask(node)
    result(node, actor="a1", **{**good, "ticket": rep2.ticket})  # a0's ticket, reported by a1
    other = "teriyaki" if rep2.opponent != "teriyaki" else "cheese"
    result(node, **{**good, "opponent": other, "opponent_version": -1, "ticket": rep2.ticket})  # another pairing
    result(node, **{**good, "opponent": rep2.opponent, "opponent_version": rep2.version, "ticket": rep2.ticket})
    vals, _ = svc.report(1.0)
    assert vals["rejected_ticket_unknown"] == 4 and vals["rejected_ticket_mismatch"] == 1
    assert svc.league.results_total == 1  # a misused ticket is spent too
    # the rate: 8 at once (2 spent above), then 2 a second
    got = [ask(node).status for _ in range(8)]
    assert got == ["ok"] * 6 + ["busy"] * 2
    assert svc.report(1.0)[0]["rejected_request_rate"] == 2
    assert ask(node, actor="a2").status == "ok"  # another actor has its own bucket
    clock.t += 1.0
    assert [ask(node).status for _ in range(3)] == ["ok", "ok", "busy"]
    # at most 3 open per actor: the oldest of a0's went, the newest still count
    assert svc.tickets.open_count("a0") == 3 and svc.tickets.dropped_tickets > 0
    assert svc.report(1.0)[0]["tickets_open"] == 4


def test_opponents_follow_pfsp_and_weights_are_served(tmp_path):
    clock = Clock()
    svc, node = make(tmp_path, clock)
    rep = ask(node, "exploiter")
    assert rep.status == "none"  # main not heard yet
    assert ask(node, "nobody").status == "unknown"
    broadcast(node, "main", 3)
    assert svc.step(0.0)
    rep = ask(node, "exploiter")
    assert (rep.status, rep.opponent, rep.kind, rep.version) == ("ok", "main", "learner", 3)
    wq = node.queryables[P.LeagueKeys("lg").weights]
    w = P.PlayerWeights.decode(wq(P.PlayerWeightsRequest("main", 3).encode()))
    assert w.status == "ok" and w.version == 3 and np.array_equal(w.params["w"], np.arange(4) + 3)
    assert P.PlayerWeights.decode(wq(P.PlayerWeightsRequest("cheese", -1).encode())).status == "missing"
    assert wq(b"junk") is None
    for _ in range(3):
        result(node, outcome=1)  # main beats cheese: x = 3.5 / 4
    dist = svc.league.distribution("main")
    f = np.array([(1 - 3.5 / 4) ** 2, 0.25])
    assert dist["cheese"] == pytest.approx(0.65 * f[0] / f.sum())
    n = 4000
    got = []
    for i in range(n):
        clock.t += 1.0  # one assignment a second: within the ticket rate
        got.append(ask(node).opponent)
    for k, p in dist.items():
        assert got.count(k) / n == pytest.approx(p, abs=0.03)


def test_snapshot_and_reset_and_restart(tmp_path):
    clock = Clock()
    svc, node = make(tmp_path, clock)
    broadcast(node, "main", 5)
    broadcast(node, "exploiter", 9, updates=900)
    svc.step(0.0)
    clock.t += 100
    assert svc.step(0.0)  # main's timer
    assert ("snapshot", "main", "main-s1", "timer") in svc.events
    for _ in range(2):
        result(node, player="exploiter", opponent="main", opponent_version=5)
    svc.step(0.0)
    assert ("reset", "exploiter", "exploiter-g0-s1", "win_rate") in svc.events
    vals, _ = svc.report(1.0)
    assert vals["generation/exploiter"] == 1 and vals["snapshots"] == 2
    result(node, opponent="main-s1", opponent_version=5, outcome=-1)
    result(node, opponent="main-s1", opponent_version=4)  # not the version it was served at
    svc.save()
    state = json.loads((tmp_path / "league" / STATE_FILE).read_text())
    assert {p["id"] for p in state["players"]} >= {"main-s1", "exploiter-g0-s1"}
    # restart: same players, table, generation; snapshot weights from their files
    svc2, node2 = make(tmp_path, clock)
    assert svc2.restored and list(svc2.league.players) == list(svc.league.players)
    assert svc2.league.payoff.counts == svc.league.payoff.counts
    assert svc2.league.players["exploiter"].generation == 1
    wq = node2.queryables[P.LeagueKeys("lg").weights]
    w = P.PlayerWeights.decode(wq(P.PlayerWeightsRequest("main-s1", 5).encode()))
    assert w.version == 5 and np.array_equal(w.params["w"], np.arange(4) + 5)
    # the old exploiter learner's broadcasts stay ignored after the restart
    broadcast(node2, "exploiter", 10, updates=950)
    svc2.step(0.0)
    assert not svc2.league.available("exploiter")
    table = P.LeagueTable.decode(node2.queryables[P.LeagueKeys("lg").table](b""))
    i, j = table.ids["main"], table.ids["main-s1"]
    assert table.counts[i, j].tolist() == [0, 0, 1] and table.counts[j, i].tolist() == [1, 0, 0]
    assert sum(table.main_pfsp.values()) == pytest.approx(1.0)


def test_unreadable_state_is_an_error_not_a_fresh_league(tmp_path):
    (tmp_path / "league").mkdir()
    (tmp_path / "league" / STATE_FILE).write_text("{torn")
    with pytest.raises(ValueError, match="unreadable"):
        make(tmp_path, Clock())
