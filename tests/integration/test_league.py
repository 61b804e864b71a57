"""The league service between real OS processes (a real router, `zenrl league`, two `zenrl
actor`s playing real pybullet matches): every finished match is reported and counted in the
payoff table, the exploiter plays the main agent's weights fetched from the league, the league
answers PFSP-weighted opponents (empirical frequencies against its distribution), a hostile
result (a forged or replayed ticket among them) is counted and rejected without changing the
table, and a restarted league comes back with its state."""

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from tests.conftest import ROOT, wait_until
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.networks import QNetwork, arch_fingerprint, num_actions, obs_spec, params_to_arrays
from zenrl.common.recurrent import RecurrentQNetwork

pytestmark = pytest.mark.integration

# 6 s matches plus 2 s of sudden death at 5 decisions/s: at most 40 steps each
MATCH = {"opponents": {"cheese": 1}, "side": "random", "reward": "zero_sum", "control_hz": 5, "action_set": "rich",
         "match_time": 6.0, "sudden_death_time": 2.0}


def config(tmp_path, run_id, algo="apex"):
    doc = {"algo": algo, "seed": 3, "runs_dir": str(tmp_path / "runs"),
           "env": {"id": "zenrl/BurgerWar-v0", "kwargs": MATCH},
           "network": {"hidden": [32]},
           "actor": {"num_actors": 1, "envs_per_actor": 4, "chunk_size": 64, "episode_report_s": 1.0},
           "league": {"enabled": True, "bots": ["cheese", "teriyaki"], "decay": 1.0, "selfplay_share": 0.3,
                      "live_refresh_s": 1.0, "min_games": 100000, "snapshot_interval_s": 100000,
                      "exploiter_reset_s": 100000, "stats_interval_s": 0.5, "save_interval_s": 1.0,
                      # 8 s matches end faster than the rate meant for real ones (tests/unit has the rate)
                      "ticket_rate_per_s": 10000, "ticket_burst": 10000,
                      "agents": {"main": {"role": "main"}, "exploiter": {"role": "exploiter"}}}}
    path = tmp_path / "league.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def start_league(tmp_path, router, run_id, procs, algo="apex"):
    """`zenrl league` and one `zenrl actor` per agent (main, exploiter) of :func:`config`'s
    league, as real processes; returns (the config, the common CLI arguments)."""
    path = config(tmp_path, run_id, algo)
    common = ["--config", str(path), "--router", router]
    procs.zenrl("league", ["league", *common, "--run-id", run_id])
    for aid in ("main", "exploiter"):
        procs.zenrl(f"{aid}-actor", ["actor", *common, "--run-id", f"{run_id}.{aid}", "--id", f"{aid}-a0", "--slot", "0",
                                     "--set", f"league.run_id={run_id}", "--set", f"league.player={aid}"])
    return load_config(path), common


def table(node, run_id):
    return P.LeagueTable.decode(node.query(P.LeagueKeys(run_id).table, None, 5.0))


def wdl(t, a, b):
    return t.counts[t.ids[a], t.ids[b]].tolist()


def league_stats(latest):
    raw = latest.take()
    return None if raw is None else P.Stats.decode(raw).values


def test_league_service_with_real_matches(tmp_path, router, run_id, procs):
    from zenrl.common.env_factory import make_env
    from zenrl.common.transport import Node

    cfg, common = start_league(tmp_path, router, run_id, procs)
    env = make_env(cfg.env)
    net = QNetwork(obs_spec(env.observation_space), num_actions(env.action_space), cfg.network)
    env.close()
    weights = P.Weights(version=7, learner_id="learner", arch=arch_fingerprint(net), updates=70,
                        params=params_to_arrays(net)).encode()
    with Node(router, 10.0) as node:
        stats = node.subscribe_latest(P.Keys(run_id).stats("league", "league"))
        heard = node.subscribe_latest(P.LeagueKeys(run_id).results_all)  # the actors' own results, to replay one
        wait_until(lambda: node.alive_now(P.Keys(run_id).alive_role("league"), 1.0), 60, "the league's token")
        main_weights = P.Keys(f"{run_id}.main").weights

        def matches_played():
            node.put(main_weights, weights, low_priority=True)  # what main's learner would broadcast
            t = table(node, run_id)
            return t if (sum(wdl(t, "main", b)[i] for b in ("cheese", "teriyaki") for i in range(3)) >= 6
                         and sum(wdl(t, "exploiter", "main")) >= 3 and sum(wdl(t, "main", "main")) >= 1) else None

        t = wait_until(matches_played, 120, "matches of both actors in the payoff table", interval_s=0.5)
        # both sides of each pair hold the same matches
        assert wdl(t, "main", "cheese") == wdl(t, "cheese", "main")[::-1]
        assert wdl(t, "exploiter", "main") == wdl(t, "main", "exploiter")[::-1]
        # zenrl league status, as a user runs it
        out = subprocess.run([sys.executable, "-m", "zenrl.cli", "league", "status", "--run-id", run_id, "--router",
                              router, "--json"], capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert out.returncode == 0, out.stderr[-2000:]
        shown = {r["id"]: r for r in json.loads(out.stdout.strip().splitlines()[-1])["players"]}
        assert set(shown) == {"cheese", "teriyaki", "main", "exploiter"}
        assert shown["main"]["games"] >= 7 and "elo" in shown["main"] and shown["exploiter"]["vs_main"]
        assert sum(r["pfsp"] for r in shown.values()) == pytest.approx(1.0)
        for name in ("main-actor", "exploiter-actor"):
            p = next(p for n, p in procs.procs if n == name)
            p.terminate()
            p.wait(30)
        exploiter_log = procs.log("exploiter-actor")
        assert "Traceback" not in exploiter_log, exploiter_log[-3000:]

        # a hostile sender: garbage, an unknown opponent, an absurd score, a result without an
        # assignment (a made-up ticket), a real actor's result sent again; counted and rejected
        before = table(node, run_id)
        replayed = heard.take()
        assert replayed is not None and P.MatchResult.decode(replayed).ticket > 0
        bad_key = P.LeagueKeys(run_id).results("evil")
        node.put(bad_key, b"\x00not msgpack")
        node.put(bad_key, P.MatchResult("evil", "main", 0, 1, "nobody", -1, 1).encode())
        node.put(bad_key, P.MatchResult("evil", "main", 0, 1, "cheese", -1, 1, my_score=10**6).encode())
        node.put(bad_key, P.MatchResult("evil", "main", 0, 1, "cheese", 3, 1).encode())
        node.put(bad_key, P.MatchResult("evil", "main", 0, 1, "cheese", -1, 1, ticket=123456789).encode())
        node.put(P.LeagueKeys(run_id).results(P.MatchResult.decode(replayed).actor_id), replayed)

        def rejected():
            v = league_stats(stats)
            return v if v and v.get("rejected_total", 0) >= 6 else None

        v = wait_until(rejected, 30, "the league's stats counting 6 rejections")
        assert v["rejected_malformed"] == 1 and v["rejected_unknown_opponent"] == 1
        assert v["rejected_field"] == 1 and v["rejected_opponent_version"] == 1
        assert v["rejected_ticket_unknown"] == 2
        after = table(node, run_id)
        assert np.array_equal(before.counts, after.counts)

        # PFSP: main wins every match against cheese (published as a third actor would: it asks
        # for assignments and reports a win for each cheese one), so cheese must be drawn rarely;
        # the empirical frequencies follow the league's distribution
        # (each cheese assignment answered as it comes: an actor id holds at most
        # league.open_tickets_per_actor unanswered, the oldest dropped, and where main beat
        # cheese in the real matches above it takes hundreds of assignments to draw 40 of it)
        ask = P.OpponentRequest("main", "a9").encode()
        cheese = 0
        while cheese < 40:
            rep = P.OpponentReply.decode(node.query(P.LeagueKeys(run_id).opponent, ask, 5.0))
            if rep.opponent == "cheese":
                cheese += 1
                node.put(P.LeagueKeys(run_id).results("a9"),
                         P.MatchResult("a9", "main", 0, 7, "cheese", -1, 1, ticket=rep.ticket).encode())
        wait_until(lambda: sum(wdl(table(node, run_id), "main", "cheese")) >= sum(wdl(after, "main", "cheese")) + 40,
                   30, "the 40 results counted")
        t = table(node, run_id)
        dist = dict(t.main_pfsp)
        x = {}
        for b in ("cheese", "teriyaki"):  # decay 1: win rate from the raw counts, prior 0.5 worth 1 match
            w, d, l_ = wdl(t, "main", b)
            x[b] = (w + 0.5 * d + 0.5) / (w + d + l_ + 1)
        f = {b: (1 - x[b]) ** 2 for b in x}
        for b in x:
            assert dist[b] == pytest.approx(0.7 * f[b] / sum(f.values()), rel=1e-6)
        assert dist["main"] == pytest.approx(0.3)
        n = 600
        req = P.OpponentRequest("main", "probe").encode()
        got = [P.OpponentReply.decode(node.query(P.LeagueKeys(run_id).opponent, req, 5.0)).opponent for _ in range(n)]
        for k, p in dist.items():
            tol = 4 * np.sqrt(p * (1 - p) / n) + 1e-3
            assert abs(got.count(k) / n - p) <= tol, (k, got.count(k) / n, p)

        # restart: the same players and table
        league = next(p for nm, p in procs.procs if nm == "league")
        league.terminate()
        assert league.wait(30) == 0
        procs.zenrl("league-2", ["league", *common, "--run-id", run_id])

        def back():
            try:
                return table(node, run_id)
            except Exception:  # noqa: BLE001 - not up yet
                return None

        t2 = wait_until(back, 60, "the restarted league's table")
        assert t2.ids == t.ids and np.array_equal(t2.counts, t.counts)
        assert t2.values["results_total"] == t.values["results_total"]
    assert "restored" in procs.log("league-2")


def test_r2d2_actors_play_the_leagues_recurrent_opponents(tmp_path, router, run_id, procs):
    """The same league with R2D2 actor processes: the exploiter plays main's recurrent
    Q-network, fetched from the league and built by the actor, and both actors' matches reach
    the payoff table (every algorithm's actors take their opponents from the league)."""
    from zenrl.common.env_factory import make_env
    from zenrl.common.transport import Node

    cfg, _ = start_league(tmp_path, router, run_id, procs, "r2d2")
    env = make_env(cfg.env)
    net = RecurrentQNetwork(obs_spec(env.observation_space), num_actions(env.action_space), cfg.network,
                            cfg.r2d2.lstm_size)
    env.close()
    weights = P.Weights(version=4, learner_id="learner", arch=arch_fingerprint(net), updates=40,
                        params=params_to_arrays(net)).encode()
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(P.Keys(run_id).alive_role("league"), 1.0), 60, "the league's token")

        def matches_played():
            node.put(P.Keys(f"{run_id}.main").weights, weights, low_priority=True)  # main's learner's broadcast
            t = table(node, run_id)
            return t if (sum(wdl(t, "exploiter", "main")) >= 2
                         and sum(wdl(t, "main", b)[i] for b in ("cheese", "teriyaki") for i in range(3)) >= 2) else None

        t = wait_until(matches_played, 120, "R2D2 actors' matches in the payoff table", interval_s=0.5)
        assert wdl(t, "exploiter", "main") == wdl(t, "main", "exploiter")[::-1]
    for name in ("main-actor", "exploiter-actor"):
        log = procs.log(name)
        assert "Traceback" not in log, log[-3000:]
    assert "league weights for main@4 not used" not in procs.log("exploiter-actor")
