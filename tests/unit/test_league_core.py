"""The league's pure logic (league/core.py): payoff with counts, PFSP against probabilities
computed by hand, the roles' mixes, snapshot and reset rules, persistence."""

import json

import numpy as np
import pytest

from zenrl.common.config import LeagueConfig, load_config
from zenrl.league.core import BOT, LEARNER, SNAPSHOT, League, LearnerWeights, Payoff, pfsp_weights


def cfg(**kw) -> LeagueConfig:
    base = {"bots": ["cheese", "teriyaki"], "decay": 1.0, "prior_win_rate": 0.5, "prior_games": 1.0,
            "pfsp_p": 2.0, "selfplay_share": 0.35}
    base.update(kw)
    return LeagueConfig(**base)


def weights(version: int, updates: int | None = None) -> LearnerWeights:
    return LearnerWeights(version, version * 10 if updates is None else updates, "arch",
                          {"w": np.full(3, float(version), np.float32)})


def test_payoff_folds_both_sides_and_counts_draws():
    p = Payoff()
    p.record("main", "cheese", 1)
    p.record("main", "cheese", 0)
    p.record("cheese", "main", 1)
    assert p.wdl("main", "cheese") == (1, 1, 1)
    assert p.wdl("cheese", "main") == (1, 1, 1)
    p.record("main", "main", 1)  # self-play: once
    assert p.wdl("main", "main") == (1, 0, 0) and p.games("main", "main") == 1
    # (1 + 0.5 + 0.5 * 1) / (3 + 1)
    assert p.win_rate("main", "cheese") == pytest.approx(0.5)
    p.record("main", "cheese", 1)
    assert p.win_rate("main", "cheese", 0.5, 1.0) == pytest.approx((2 + 0.5 + 0.5) / 5)
    assert p.win_rate("main", "nobody", 0.3, 2.0) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="outcome"):
        p.record("main", "cheese", 2)


def test_decayed_counts_weigh_old_matches_down():
    p = Payoff(decay=0.5)
    p.record("a", "b", 1)   # w = 1
    p.record("a", "b", -1)  # w = 0.5, l = 1
    p.record("a", "b", -1)  # w = 0.25, l = 1.5
    assert p.decayed[("a", "b")] == pytest.approx([0.25, 0.0, 1.5])
    assert p.wdl("a", "b") == (1, 0, 2)
    # prior 0.5 worth 1 match
    assert p.win_rate("a", "b") == pytest.approx((0.25 + 0.5) / (1.75 + 1))
    assert p.win_rate("a", "b", decayed=False) == pytest.approx((1 + 0.5) / 4)


def test_pfsp_weights_by_hand():
    x = [0.7, 0.5, 0.2]
    hard = np.array([0.3 ** 2, 0.5 ** 2, 0.8 ** 2])
    assert pfsp_weights(x, "hard", 2.0) == pytest.approx(hard / hard.sum())
    var = np.array([0.21, 0.25, 0.16])
    assert pfsp_weights(x, "var") == pytest.approx(var / var.sum())
    assert pfsp_weights([1.0, 1.0], "hard") == pytest.approx([0.5, 0.5])  # all zero: uniform
    assert pfsp_weights([0.9, 0.4], "hard", 1.0) == pytest.approx([0.1 / 0.7, 0.6 / 0.7])
    with pytest.raises(ValueError):
        pfsp_weights([0.5], "linear")


def test_main_mix_pfsp_over_frozen_plus_selfplay():
    lg = League(cfg(), now=0.0)
    # nothing heard from main's learner: bots only, no self-play
    assert lg.distribution("main") == pytest.approx({"cheese": 0.5, "teriyaki": 0.5})
    for o in (1, 1, 1, -1):
        lg.record("main", "cheese", o)
    # x(cheese) = (3 + 0.5) / 5 = 0.7, x(teriyaki) = 0.5 (prior)
    d = lg.distribution("main")
    assert d == pytest.approx({"cheese": 0.09 / 0.34, "teriyaki": 0.25 / 0.34})
    lg.hear_weights("main", weights(5), now=1.0)
    d = lg.distribution("main")
    assert d == pytest.approx({"cheese": 0.65 * 0.09 / 0.34, "teriyaki": 0.65 * 0.25 / 0.34, "main": 0.35})
    assert sum(d.values()) == pytest.approx(1.0)
    # a snapshot joins the PFSP pool with the prior
    sid = lg.add_snapshot("main", now=2.0)
    d = lg.distribution("main")
    f = np.array([0.09, 0.25, 0.25])
    assert d[sid] == pytest.approx(0.65 * 0.25 / f.sum())
    assert d["main"] == pytest.approx(0.35)


def test_bot_share_keeps_beaten_bots_in_the_mix():
    lg = League(cfg(bot_share=0.2), now=0.0)
    lg.hear_weights("main", weights(5), now=1.0)
    for o in (1, 1, 1, -1):
        lg.record("main", "cheese", o)
    sid = lg.add_snapshot("main", now=2.0)
    # x: cheese 0.7, teriyaki 0.5, the snapshot 0.5 -> hard weights 0.09, 0.25, 0.25 over all
    # frozen players; 0.09, 0.25 over the bots alone
    every = np.array([0.09, 0.25, 0.25]) / 0.59
    bots = np.array([0.09, 0.25]) / 0.34
    d = lg.distribution("main")
    assert d["cheese"] == pytest.approx(0.45 * every[0] + 0.2 * bots[0])
    assert d["teriyaki"] == pytest.approx(0.45 * every[1] + 0.2 * bots[1])
    assert d[sid] == pytest.approx(0.45 * every[2])
    assert d["main"] == pytest.approx(0.35)
    assert sum(d.values()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="bot_share"):
        cfg(bot_share=0.7)  # 0.35 + 0.7 > 1


def test_exploiter_share_gives_main_matches_against_the_live_exploiters():
    agents = {"main": {"role": "main"}, "ex1": {"role": "exploiter"}, "ex2": {"role": "exploiter"}}
    lg = League(cfg(bot_share=0.2, exploiter_share=0.3, agents=agents), now=0.0)
    lg.hear_weights("main", weights(5), now=1.0)
    for o in (1, 1, 1, -1):
        lg.record("main", "cheese", o)
    # no exploiter heard yet: its share goes to the PFSP over the frozen players (x: cheese 0.7,
    # teriyaki 0.5 -> hard weights 0.09, 0.25), as without the option
    pf = np.array([0.09, 0.25]) / 0.34
    d = lg.distribution("main")
    assert set(d) == {"cheese", "teriyaki", "main"}
    assert d["cheese"] == pytest.approx(0.45 * pf[0] + 0.2 * pf[0])
    assert d["main"] == pytest.approx(0.35)
    # one exploiter heard: all 0.3 to it, the PFSP rest shrinks to 1 - 0.35 - 0.2 - 0.3
    lg.hear_weights("ex1", weights(2), now=2.0)
    d = lg.distribution("main")
    assert d["ex1"] == pytest.approx(0.3)
    assert d["cheese"] == pytest.approx(0.15 * pf[0] + 0.2 * pf[0])
    assert d["teriyaki"] == pytest.approx(0.15 * pf[1] + 0.2 * pf[1])
    assert sum(d.values()) == pytest.approx(1.0)
    # two: split evenly, whatever main's results against them
    lg.hear_weights("ex2", weights(3), now=2.0)
    for _ in range(5):
        lg.record("main", "ex1", 1)
    d = lg.distribution("main")
    assert d["ex1"] == pytest.approx(0.15) and d["ex2"] == pytest.approx(0.15)
    assert sum(d.values()) == pytest.approx(1.0)
    # an exploiter still plays only main
    assert lg.distribution("ex1") == {"main": 1.0}
    # nothing frozen available (no bots): self-play and the exploiters in proportion
    lg2 = League(cfg(bots=[], exploiter_share=0.3, agents=agents), now=0.0)
    lg2.hear_weights("main", weights(1), now=0.0)
    lg2.hear_weights("ex1", weights(1), now=0.0)
    assert lg2.distribution("main") == pytest.approx({"main": 0.35 / 0.65, "ex1": 0.3 / 0.65})
    with pytest.raises(ValueError, match="exploiter_share"):
        cfg(bot_share=0.4, exploiter_share=0.3)  # 0.35 + 0.4 + 0.3 > 1


def test_a_reset_exploiters_versions_never_repeat_an_earlier_generations():
    """Actors cache a live player's weights by (id, version): a fresh learner counts its
    versions from the start again, so the league serves them above the old generation's."""
    lg = League(cfg(exploiter_share=0.2), now=0.0)
    lg.hear_weights("main", weights(1), now=0.0)
    lg.hear_weights("exploiter", weights(7, updates=700), now=0.0)
    assert lg.weights_of("exploiter").version == 7
    lg.reset("exploiter", now=1.0, reason="timer")
    assert lg.hear_weights("exploiter", weights(7, updates=20), now=2.0)  # the new learner's version 7
    w = lg.weights_of("exploiter")
    assert w.version == 7 + 8 and w.updates == 20
    assert lg.players["exploiter"].version == 15
    # kept across a restart of the league, and a second reset counts on from there
    back = League.from_state(lg.cfg, json.loads(json.dumps(lg.to_state())), dict(lg.weights), now=3.0)
    back.hear_weights("exploiter", weights(9, updates=40), now=3.0)
    assert back.weights_of("exploiter").version == 9 + 8
    back.reset("exploiter", now=4.0, reason="timer")
    back.hear_weights("exploiter", weights(1, updates=0), now=5.0)
    assert back.weights_of("exploiter").version == 1 + 18
    # main, never reset, keeps its learner's own versions
    assert back.hear_weights("main", weights(3), now=5.0) and back.live["main"].version == 3


def test_exploiter_plays_only_the_current_main():
    lg = League(cfg(), now=0.0)
    assert lg.distribution("exploiter") == {}
    lg.hear_weights("main", weights(1), now=0.0)
    assert lg.distribution("exploiter") == {"main": 1.0}
    rng = np.random.default_rng(0)
    assert {lg.choose("exploiter", rng) for _ in range(20)} == {"main"}
    with pytest.raises(KeyError):
        lg.distribution("cheese")


def test_choose_follows_the_distribution():
    lg = League(cfg(), now=0.0)
    lg.hear_weights("main", weights(1), now=0.0)
    for o in (1, 1, 1, 1, 1, 1, 1, -1):
        lg.record("main", "cheese", o)
    dist = lg.distribution("main")
    rng = np.random.default_rng(1)
    n = 20000
    draws = [lg.choose("main", rng) for _ in range(n)]
    for k, p in dist.items():
        assert draws.count(k) / n == pytest.approx(p, abs=0.015)


def test_record_rejects_unknown_players():
    lg = League(cfg(), now=0.0)
    with pytest.raises(ValueError, match="learning agent"):
        lg.record("cheese", "main", 1)
    with pytest.raises(ValueError, match="not a player"):
        lg.record("main", "nobody", 1)
    with pytest.raises(ValueError, match="outcome"):
        lg.record("main", "cheese", 3)
    assert lg.results_total == 0


def test_main_snapshot_by_timer_and_by_win_rate():
    c = cfg(snapshot_interval_s=100, min_snapshot_interval_s=10, snapshot_win_rate=0.75, min_games=4)
    lg = League(c, now=0.0)
    assert lg.snapshot_due("main", 500.0) is None  # no weights heard: nothing to freeze
    lg.hear_weights("main", weights(3), now=1.0)
    assert lg.snapshot_due("main", 99.0) is None
    assert lg.snapshot_due("main", 100.0) == "timer"
    for o in (1, 1, 1):
        lg.record("main", "cheese", o)
    assert lg.snapshot_due("main", 20.0) is None  # 3 < min_games
    lg.record("main", "teriyaki", 0)  # 3.5 / 4 = 0.875
    assert lg.snapshot_due("main", 5.0) is None  # too soon
    assert lg.snapshot_due("main", 20.0) == "win_rate"
    events = lg.tick(20.0)
    assert events == [("snapshot", "main", "main-s1", "win_rate")]
    s = lg.players["main-s1"]
    assert (s.kind, s.parent, s.version, s.updates) == (SNAPSHOT, "main", 3, 30)
    assert lg.since_rate("main") == (0.0, 0)  # counting starts again
    assert lg.snapshot_due("main", 50.0) is None
    assert lg.weights_of("main-s1").version == 3


def test_exploiter_reset_by_win_rate_leaves_a_snapshot_and_ignores_the_old_learner():
    c = cfg(exploiter_reset_s=1000, exploiter_win_rate=0.6, min_games=3, exploiter_snapshot_on_timeout=False)
    lg = League(c, now=0.0)
    lg.hear_weights("main", weights(1), now=0.0)
    lg.hear_weights("exploiter", weights(7, updates=700), now=0.0)
    for o in (1, 1, -1):
        lg.record("exploiter", "main", o)
    assert lg.reset_due("exploiter", 1.0) == "win_rate"
    assert lg.tick(1.0) == [("reset", "exploiter", "exploiter-g0-s1", "win_rate")]
    e = lg.players["exploiter"]
    assert e.generation == 1 and lg.since_rate("exploiter") == (0.0, 0)
    assert not lg.available("exploiter")
    # the old learner's late broadcast is ignored; the fresh learner's (few updates) is taken
    assert not lg.hear_weights("exploiter", weights(8, updates=720), now=2.0)
    assert lg.hear_weights("exploiter", weights(1, updates=0), now=3.0)
    assert lg.hear_weights("exploiter", weights(2, updates=20), now=4.0)
    # matches of the old generation count in the table, not towards the rules
    assert not lg.record("exploiter", "main", 1, generation=0)
    assert lg.record("exploiter", "main", 1, generation=1)
    assert lg.since_rate("exploiter") == (1.0, 1)
    assert lg.payoff.wdl("exploiter", "main") == (4, 0, 1)
    # the snapshot is a frozen player of main's PFSP pool
    assert "exploiter-g0-s1" in lg.distribution("main")


def test_exploiter_reset_by_timer():
    lg = League(cfg(exploiter_reset_s=60, exploiter_snapshot_on_timeout=True), now=0.0)
    lg.hear_weights("exploiter", weights(2), now=0.0)
    assert lg.reset_due("exploiter", 59.0) is None
    assert lg.tick(60.0) == [("reset", "exploiter", "exploiter-g0-s1", "timer")]
    lg2 = League(cfg(exploiter_reset_s=60, exploiter_snapshot_on_timeout=False), now=0.0)
    lg2.hear_weights("exploiter", weights(2), now=0.0)
    assert lg2.tick(60.0) == [("reset", "exploiter", None, "timer")]


def test_served_weights_of_a_learner_refresh_at_most_every_live_refresh_s():
    lg = League(cfg(live_refresh_s=30), now=0.0)
    lg.hear_weights("main", weights(1), now=0.0)
    lg.hear_weights("main", weights(2), now=10.0)
    assert lg.weights_of("main").version == 1 and lg.live["main"].version == 2
    assert not lg.hear_weights("main", weights(2), now=40.0)  # not newer
    lg.hear_weights("main", weights(3), now=40.0)
    assert lg.weights_of("main").version == 3 and lg.players["main"].version == 3
    assert lg.weights_of("cheese") is None


def test_oldest_snapshot_leaves_with_its_rows():
    lg = League(cfg(max_snapshots=2), now=0.0)
    for v in (1, 2, 3):
        lg.hear_weights("main", weights(v), now=float(v) * 100)
        sid = lg.add_snapshot("main", now=float(v) * 100)
        lg.record("main", sid, 1)
    snaps = [p.id for p in lg.players.values() if p.kind == SNAPSHOT]
    assert snaps == ["main-s2", "main-s3"]
    assert ("main", "main-s1") not in lg.payoff.counts and "main-s1" not in lg.weights


def test_state_round_trip_through_json():
    c = cfg()
    lg = League(c, now=0.0)
    lg.hear_weights("main", weights(4), now=0.0)
    lg.hear_weights("exploiter", weights(2), now=0.0)
    for o in (1, -1, 0, 1):
        lg.record("main", "cheese", o)
    sid = lg.add_snapshot("main", now=5.0)
    lg.record("exploiter", "main", 1)
    lg.reset("exploiter", now=6.0, reason="timer")
    state = json.loads(json.dumps(lg.to_state()))
    back = League.from_state(c, state, dict(lg.weights), now=7.0)
    assert list(back.players) == list(lg.players)
    assert back.players["exploiter"].generation == 1
    assert back.payoff.counts == lg.payoff.counts
    assert back.payoff.decayed == lg.payoff.decayed  # floats survive JSON exactly
    assert back.since == lg.since and back.results_total == lg.results_total
    assert back.weights_of(sid).version == 4
    # the old exploiter learner is still told apart after the restart
    assert not back.hear_weights("exploiter", weights(3, updates=20), now=8.0)
    # learning agents serve nothing until heard again; the distribution is the same otherwise
    assert not back.available("main")
    back.hear_weights("main", weights(5), now=8.0)
    lg.hear_weights("main", weights(5), now=100.0)
    assert back.distribution("main") == pytest.approx(lg.distribution("main"))
    # a snapshot whose weights file is gone is dropped with its rows
    gone = League.from_state(c, state, {}, now=7.0)
    assert sid not in gone.players and all(sid not in k for k in gone.payoff.counts)
    with pytest.raises(ValueError, match="format"):
        League.from_state(c, {"format": 99}, {}, now=0.0)


def test_league_config_is_checked():
    with pytest.raises(ValueError, match="exactly one agent with role main"):
        LeagueConfig(agents={"a": {"role": "exploiter"}})
    with pytest.raises(ValueError, match="share a player id"):
        LeagueConfig(bots=["main"])
    with pytest.raises(ValueError, match="league.player"):
        LeagueConfig(player="nobody")
    c = load_config(None, ["league.enabled=true", "league.pfsp_weighting=var"])
    assert c.league.main_id == "main" and c.league.pfsp_weighting == "var"
    kinds = {p.kind for p in League(c.league, 0.0).players.values()}
    assert kinds == {BOT, LEARNER}


def test_frozen_files_are_players_and_leave_with_the_config():
    c = cfg()
    lg = League(c, now=0.0, frozen=["champ"])
    assert lg.players["champ"].kind == "frozen" and lg.available("champ") and lg.weights_of("champ") is None
    assert set(lg.distribution("main")) == {"cheese", "teriyaki", "champ"}
    lg.record("main", "champ", 1)
    state = json.loads(json.dumps(lg.to_state()))
    kept = League.from_state(c, state, {}, now=1.0, frozen=["champ"])
    assert kept.payoff.wdl("main", "champ") == (1, 0, 0)
    gone = League.from_state(cfg(bots=["cheese"]), state, {}, now=1.0)
    assert "champ" not in gone.players and "teriyaki" not in gone.players
    assert ("main", "champ") not in gone.payoff.counts


def test_timers_skip_the_time_the_league_was_down():
    c = cfg(snapshot_interval_s=100, exploiter_reset_s=200)
    lg = League(c, now=0.0)
    lg.hear_weights("main", weights(1), now=0.0)
    lg.hear_weights("exploiter", weights(1), now=0.0)
    state = json.loads(json.dumps(lg.to_state(now=60.0)))  # saved 60 s in, then down for 1000 s
    back = League.from_state(c, state, {}, now=1060.0)
    back.hear_weights("main", weights(2), now=1060.0)
    back.hear_weights("exploiter", weights(2), now=1060.0)
    assert back.snapshot_due("main", 1099.0) is None and back.snapshot_due("main", 1100.0) == "timer"
    assert back.reset_due("exploiter", 1199.0) is None and back.reset_due("exploiter", 1200.0) == "timer"
