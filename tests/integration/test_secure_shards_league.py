"""The secured router (deploy/zenoh/router-secure.json5, in-process with certificates from
gen-certs.sh: the `secure_router` fixture of test_secure_router.py) on the sharded replay's keys
and the league's keys, with each role's committed client login:

* an actor publishes transitions to its replay shard (transitions/<k>/<its id>) and the replay
  gets them; it can neither publish to a shard as another actor, nor send a shard priorities, nor
  answer a shard's sample queries (the learner's query gets the replay's answer alone);
* an actor asks the league login's opponent and weights queryables; it cannot publish a match
  result as another actor nor answer the league's queries; the monitor reads the league table;
  the league hears a learning agent's weights broadcast (run <league-run>.<agent>)."""

from __future__ import annotations

import uuid

import pytest

from tests.conftest import wait_until
from tests.integration.test_secure_router import Inbox, client_config_file, secure_router  # noqa: F401 (fixture)

pytestmark = pytest.mark.integration


def _answers(node, key: str) -> list[bytes]:
    import zenoh

    replies = node.session.get(key, timeout=3.0, consolidation=zenoh.ConsolidationMode.NONE)
    return sorted(r.ok.payload.to_bytes() for r in replies if r.ok is not None)


def _nodes(ep, certs, tmp_path, *logins):
    from zenrl.common.transport import Node

    return [Node(ep, connect_timeout_s=5.0, config_file=str(client_config_file(u, certs, tmp_path))) for u in logins]


def test_shard_keys_actor_publishes_only_as_itself_and_only_the_replay_answers(secure_router, tmp_path):
    from zenrl.common.protocol import Keys

    ep, certs = secure_router
    run = f"shards-{uuid.uuid4().hex[:8]}"
    k1 = Keys(run, replay_shard=1)
    replay, learner, actor, other = _nodes(ep, certs, tmp_path, "replay", "learner", "actor-0", "actor-1")
    try:
        at_replay = Inbox()
        replay.subscribe(k1.transitions_all, at_replay)
        replay.subscribe(k1.priorities, at_replay)
        replay.queryable(k1.sample, lambda _req: b"from-replay")
        actor.queryable(k1.sample, lambda _req: b"from-actor")

        # (a) actor-0's transitions to shard 1 under its own id reach the replay of shard 1
        wait_until(lambda: actor.put(k1.transitions("actor-0"), b"warm-up") or at_replay.has("transitions/1/actor-0"),
                   10, "actor-0's shard-1 transitions at the replay", 0.2)
        # the learner's priorities to shard 1 reach the replay
        wait_until(lambda: learner.put(k1.priorities, b"learner-prio") or at_replay.has("replay/1/priorities"),
                   10, "the learner's shard-1 priorities at the replay", 0.2)
        # actor-1's own shard transitions get through too (it is not a rule for actor-0 alone)
        wait_until(lambda: other.put(k1.transitions("actor-1"), b"own") or at_replay.has("transitions/1/actor-1", b"own"),
                   10, "actor-1's shard-1 transitions at the replay", 0.2)

        # (b) actor-0 publishes to shard 1 as actor-1, and priorities; then (same session, same
        # priority: in order on one link) its own transitions: once those arrived, the forged would have
        actor.put(k1.transitions("actor-1"), b"forged")
        actor.put(k1.priorities, b"forged")
        actor.put(k1.transitions("actor-0"), b"sentinel")
        wait_until(lambda: at_replay.has("transitions/1/actor-0", b"sentinel"), 10, "actor-0's sentinel")
        forged = [key for key, p in at_replay.items if p == b"forged"]
        assert not forged, f"actor-0's login published {forged} on shard keys"

        # only the replay answers shard 1's sample queries (actor-0 declared a queryable too)
        assert _answers(learner, k1.sample) == [b"from-replay"]
        # and an actor cannot sample a shard
        assert _answers(other, k1.sample) == []
    finally:
        for n in (replay, learner, actor, other):
            n.close()


def test_league_keys_only_the_league_serves_and_actors_report_as_themselves(secure_router, tmp_path):
    from zenrl.common.protocol import Keys, LeagueKeys

    ep, certs = secure_router
    lrun = f"lg-{uuid.uuid4().hex[:8]}"
    lk = LeagueKeys(lrun)
    agent = Keys(f"{lrun}.main")
    league, learner, actor, other, monitor = _nodes(ep, certs, tmp_path, "league", "learner", "actor-0", "actor-1",
                                                    "monitor")
    try:
        at_league = Inbox()
        league.subscribe(lk.results_all, at_league)
        league.subscribe(agent.weights, at_league)
        league.queryable(lk.opponent, lambda _req: b"opponent-from-league")
        league.queryable(lk.weights, lambda _req: b"weights-from-league")
        league.queryable(lk.table, lambda _req: b"table-from-league")
        # an actor tries to answer the league's queries as well
        actor.queryable(lk.opponent, lambda _req: b"opponent-from-actor")
        actor.queryable(lk.table, lambda _req: b"table-from-actor")

        # (c) actors ask the league's opponent and weights; the monitor reads the table
        wait_until(lambda: _answers(other, lk.opponent) == [b"opponent-from-league"], 10,
                   "the league's opponent answer, alone, at actor-1", 0.2)
        assert _answers(actor, lk.weights) == [b"weights-from-league"]
        assert _answers(monitor, lk.table) == [b"table-from-league"]
        assert _answers(other, lk.table) == [], "an actor read the league table"
        # the league hears the learning agent's weights broadcast
        wait_until(lambda: learner.put(agent.weights, b"agent-weights") or at_league.has("weights", b"agent-weights"),
                   10, "the agent's weights at the league", 0.2)

        # actor-1's own result gets through; actor-0 reports as actor-1, then its own sentinel
        wait_until(lambda: other.put(lk.results("actor-1"), b"own") or at_league.has("league/results/actor-1", b"own"),
                   10, "actor-1's result at the league", 0.2)
        actor.put(lk.results("actor-1"), b"forged")
        actor.put(agent.weights, b"forged")
        actor.put(lk.results("actor-0"), b"sentinel")
        wait_until(lambda: at_league.has("league/results/actor-0", b"sentinel"), 10, "actor-0's own result")
        forged = [key for key, p in at_league.items if p == b"forged"]
        assert not forged, f"actor-0's login published {forged}"
    finally:
        for n in (league, learner, actor, other, monitor):
            n.close()
