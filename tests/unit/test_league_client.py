"""The actor's league chooser (common/league_client.py) against the league service's handlers,
in process: prefetched assignments, weights fetched once per version and checked, the fallback
while the league is away, every finished match reported."""

import numpy as np
import pytest
import torch

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.league_client import LeagueChooser, parse_pool_name, pool_name
from zenrl.common.networks import QNetwork, params_to_arrays
from zenrl.common.opponents import MatchResult, OpponentPool
from zenrl.common.transport import LatestValue
from zenrl.league.service import LeagueService



def net():
    from zenrl.common.config import NetworkConfig
    from zenrl.common.specs import ArraySpec

    return QNetwork({"obs": ArraySpec((6,), "float32")}, 3, NetworkConfig(hidden=[8]))


class Wire:
    """A node that routes the client's queries and puts to the service's handlers; replies are
    held until :meth:`deliver` (as Zenoh's thread would deliver them later)."""

    def __init__(self):
        self.subs, self.queryables, self.latest = {}, {}, {}
        self.pending = []
        self.up = True
        self.queries = 0

    def subscribe(self, key, cb):
        self.subs[key] = cb

    def subscribe_latest(self, key):
        lv = self.latest[key] = LatestValue()
        return lv

    def queryable(self, key, handler):
        self.queryables[key] = handler

    def query_async(self, key, payload, timeout_s, cb):
        self.queries += 1
        self.pending.append((key, payload, cb))

    def deliver(self):
        pending, self.pending = self.pending, []
        for key, payload, cb in pending:
            cb(self.queryables[key](payload) if self.up else None)

    def put(self, key, payload):
        for pattern, cb in self.subs.items():
            if pattern.endswith("/*") and key.startswith(pattern[:-1]):
                cb(key, payload)


class Clock:
    t = 0.0

    def __call__(self):
        return self.t


def setup(tmp_path, player="main", **sets):
    over = ["league.enabled=true", "league.bots=[cheese]", "league.live_refresh_s=0.001", "league.prefetch=3",
            "league.run_id=lg", f"league.player={player}", "league.selfplay_share=0.5", "league.first_wait_s=0"]
    cfg = load_config(None, over + [f"league.{k}={v}" for k, v in sets.items()])
    wire = Wire()
    ticks = iter(range(1000, 10**6))
    svc = LeagueService(cfg, wire, "lg", directory=tmp_path, clock=lambda: float(next(ticks)))
    svc.start(wire, None)
    clock = Clock()
    ch = LeagueChooser(cfg, wire, "a0", net, version_fn=lambda: 7, clock=clock)
    return svc, wire, ch, clock


def broadcast(wire, svc, agent, version, params):
    wire.latest[P.Keys(f"lg.{agent}").weights].set(
        "k", P.Weights(version=version, learner_id="l", arch=_arch(), updates=version, params=params).encode())
    svc.step(0.0)


def _arch():
    from zenrl.common.networks import arch_fingerprint

    return arch_fingerprint(net())


def test_prefetched_assignments_and_weights_fetched_once(tmp_path):
    svc, wire, ch, clock = setup(tmp_path)
    pool = OpponentPool(3)
    rng = np.random.default_rng(0)
    assert ch(pool, rng) is None  # nothing answered yet: the env's own draw
    assert wire.queries == 3
    torch.manual_seed(1)
    src = net()
    broadcast(wire, svc, "main", 4, params_to_arrays(src))
    wire.deliver()
    names = [ch(pool, rng) for _ in range(40)]
    for _ in range(20):
        wire.deliver()
        names.append(ch(pool, rng))
    got = {parse_pool_name(n)[0] for n in names if n is not None}
    assert got == {"cheese", "main"}
    # the weights of main@4 were fetched once, and are the learner's
    entry = pool.get(pool_name("main", 4))
    assert ch.counts["weights_loaded"] == 1
    x = torch.randn(5, 6)
    assert torch.equal(entry.net({"obs": x}), src({"obs": x}))
    assert entry.epsilon == pytest.approx(0.05)
    # a newer served version replaces the older one in the pool
    broadcast(wire, svc, "main", 9, params_to_arrays(net()))
    for _ in range(20):
        wire.deliver()
        ch(pool, rng)
    assert pool_name("main", 9) in pool and pool_name("main", 4) not in pool


def test_fallback_while_the_league_is_away_then_back(tmp_path):
    svc, wire, ch, clock = setup(tmp_path)
    pool = OpponentPool(3)
    rng = np.random.default_rng(0)
    ch(pool, rng)
    wire.deliver()
    first = ch(pool, rng)
    assert parse_pool_name(first) == ("cheese", -1)
    wire.up = False
    for _ in range(10):
        wire.deliver()
        assert ch(pool, rng) == first  # the last opponent again
    assert ch.counts["timeouts"] >= 1
    asked = wire.queries
    ch(pool, rng)
    assert wire.queries == asked  # backs off for a second
    clock.t += 2.0
    wire.up = True
    ch(pool, rng)
    assert wire.queries > asked
    wire.deliver()
    assert ch(pool, rng) is not None and ch.counts["fallback"] >= 10


def test_results_reach_the_table(tmp_path):
    svc, wire, ch, clock = setup(tmp_path, player="exploiter")
    pool = OpponentPool(3)
    rng = np.random.default_rng(0)
    broadcast(wire, svc, "main", 3, params_to_arrays(net()))
    ch(pool, rng)
    wire.deliver()
    ch(pool, rng)
    wire.deliver()
    name = ch(pool, rng)
    assert parse_pool_name(name) == ("main", 3)
    ch.report(MatchResult(name, "red", "win", 9, 1))
    ch.report(MatchResult(name, "red", "win", 9, 1))           # one assignment, one result
    ch.report(MatchResult("cheese", "blue", "loss", 0, 10))    # the env's own draw: the league assigned none
    ch.report(MatchResult("None", "blue", "loss", 0, 10))      # an episode no one chose: not reported
    assert svc.league.payoff.wdl("exploiter", "main") == (1, 0, 0)
    assert svc.league.payoff.wdl("exploiter", "cheese") == (0, 0, 0)
    assert ch.counts["reported"] == 1 and ch.counts["unticketed"] == 2 and ch.counts["unreported"] == 1
    assert svc.rejects.total == 0
    assert svc.league.since_rate("exploiter", ["main"]) == (1.0, 1)


def test_weights_of_another_architecture_are_refused(tmp_path):
    svc, wire, ch, clock = setup(tmp_path, player="exploiter")
    pool = OpponentPool(3)
    rng = np.random.default_rng(0)
    other = {"w": np.zeros(3, np.float32)}
    wire.latest[P.Keys("lg.main").weights].set(
        "k", P.Weights(version=2, learner_id="l", arch="other", updates=2, params=other).encode())
    svc.step(0.0)
    for _ in range(4):
        ch(pool, rng)
        wire.deliver()
    assert ch.counts["weights_rejected"] >= 1 and len(pool) == 0
    assert ch(pool, rng) is None


def test_only_the_first_reset_waits_for_the_league(tmp_path):
    svc, wire, ch, clock = setup(tmp_path)
    ch.first_wait_s = 5.0
    pool = OpponentPool(3)
    rng = np.random.default_rng(0)
    real = ch.pump

    def pump(pool):  # the league answers while the first reset waits
        wire.deliver()
        real(pool)
        clock.t += 0.1

    ch.pump = pump
    first = ch(pool, rng)
    assert parse_pool_name(first) == ("cheese", -1) and ch.counts["fallback"] == 0
    ch.pump = real
    wire.up = False
    t0 = clock.t
    while ch.ready:
        ch(pool, rng)
    assert ch(pool, rng) is not None and clock.t == t0  # later resets fall back at once
    assert ch.counts["fallback"] == 1


def test_a_frozen_file_of_the_pool_is_a_league_player(tmp_path):
    from zenrl.common.opponents import Opponent

    svc, wire, ch, clock = setup(tmp_path, **{"selfplay_share": 0.0})
    assert "champ" not in svc.league.players  # no opponents.pool in this config
    over = ["league.enabled=true", "league.bots=[cheese]", "league.run_id=lg", "league.player=main",
            "league.first_wait_s=0", "league.selfplay_share=0", "opponents.pool.champ.path=/models/champ.pt"]
    cfg = load_config(None, over)
    wire = Wire()
    svc = LeagueService(cfg, wire, "lg", directory=tmp_path / "f", clock=lambda: 1000.0)
    svc.start(wire, None)
    assert svc.league.players["champ"].kind == "frozen"
    assert svc.league.distribution("main") == pytest.approx({"cheese": 0.5, "champ": 0.5})
    ch = LeagueChooser(cfg, wire, "a0", net, clock=Clock())
    pool = OpponentPool(3)
    pool.add(Opponent("champ", "exported", 1.0, player=lambda obs: 0))  # what build_pool loaded
    rng = np.random.default_rng(0)
    got = set()
    for _ in range(30):
        ch(pool, rng)
        wire.deliver()
        got.add(ch(pool, rng))
    assert "champ" in got
    ch.report(MatchResult("champ", "red", "draw", 3, 3))
    assert svc.league.payoff.wdl("main", "champ") == (0, 1, 0)
    # a result claiming a version for a frozen file is refused
    bad = P.MatchResult("a0", "main", 0, 1, "champ", 4, 1).encode()
    wire.subs[P.LeagueKeys("lg").results_all]("zenrl/lg/league/results/a0", bad)
    assert svc.rejects.counts["opponent_version"] == 1


def test_a_live_opponent_served_newer_than_assigned_still_counts(tmp_path):
    """The league assigns main@3; before the actor fetches its weights the learner broadcasts
    version 5, which the league serves. The match is played against main@5, reported as such,
    and counted (ticket for 3, served 5); a result citing a version never served is not."""
    svc, wire, ch, clock = setup(tmp_path, player="exploiter")
    pool = OpponentPool(3)
    rng = np.random.default_rng(0)
    broadcast(wire, svc, "main", 3, params_to_arrays(net()))
    ch(pool, rng)
    wire.deliver()              # assignments for main@3
    assert ch(pool, rng) is None  # its weights are asked for
    broadcast(wire, svc, "main", 5, params_to_arrays(net()))
    wire.deliver()              # the weights reply: version 5
    name = ch(pool, rng)
    assert parse_pool_name(name) == ("main", 5)
    ch.report(MatchResult(name, "red", "win", 9, 1))
    assert svc.rejects.total == 0 and svc.league.payoff.wdl("exploiter", "main") == (1, 0, 0)
    # an older version than the ticket's, or another opponent, is still refused
    t = svc.tickets.issue("a0", "exploiter", "main", 5)
    assert svc.tickets.redeem("a0", t, "exploiter", "main", 4, newer_ok=True)[0] == "ticket_mismatch"
    t = svc.tickets.issue("a0", "exploiter", "main", 5)
    assert svc.tickets.redeem("a0", t, "exploiter", "cheese", 6, newer_ok=True)[0] == "ticket_mismatch"
    t = svc.tickets.issue("a0", "exploiter", "main", 5)
    assert svc.tickets.redeem("a0", t, "exploiter", "main", 6)[0] == "ticket_mismatch"  # exact unless newer_ok
