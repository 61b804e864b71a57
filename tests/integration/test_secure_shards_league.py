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


def _delivered(sender, key: str, payload: bytes, inbox, suffix: str, what: str) -> None:
    """Put ``payload`` on ``key`` until ``inbox`` holds it (under its short key ``suffix``)."""
    wait_until(lambda: sender.put(key, payload) or inbox.has(suffix, payload), 10, what, 0.2)


def _forgeries_dropped(sender, forged_keys, sentinel_key: str, inbox, sentinel_suffix: str) -> None:
    """``sender`` puts b"forged" on each of ``forged_keys``, then b"sentinel" on its own key
    (same session, same priority: in order on one link); once the sentinel arrived the forged
    ones would have, and none may have."""
    for key in forged_keys:
        sender.put(key, b"forged")
    sender.put(sentinel_key, b"sentinel")
    wait_until(lambda: inbox.has(sentinel_suffix, b"sentinel"), 10, "the sender's own sentinel")
    forged = [key for key, p in inbox.items if p == b"forged"]
    assert not forged, f"the login published {forged}"


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
        _delivered(actor, k1.transitions("actor-0"), b"warm-up", at_replay, "transitions/1/actor-0",
                   "actor-0's shard-1 transitions at the replay")
        # the learner's priorities to shard 1 reach the replay
        _delivered(learner, k1.priorities, b"learner-prio", at_replay, "replay/1/priorities",
                   "the learner's shard-1 priorities at the replay")
        # actor-1's own shard transitions get through too (it is not a rule for actor-0 alone)
        _delivered(other, k1.transitions("actor-1"), b"own", at_replay, "transitions/1/actor-1",
                   "actor-1's shard-1 transitions at the replay")

        # (b) actor-0 publishes to shard 1 as actor-1, and priorities; then its own transitions
        _forgeries_dropped(actor, [k1.transitions("actor-1"), k1.priorities], k1.transitions("actor-0"), at_replay,
                           "transitions/1/actor-0")

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
        _delivered(learner, agent.weights, b"agent-weights", at_league, "weights", "the agent's weights at the league")

        # actor-1's own result gets through; actor-0 reports as actor-1, then its own sentinel
        _delivered(other, lk.results("actor-1"), b"own", at_league, "league/results/actor-1",
                   "actor-1's result at the league")
        _forgeries_dropped(actor, [lk.results("actor-1"), agent.weights], lk.results("actor-0"), at_league,
                           "league/results/actor-0")
    finally:
        for n in (league, learner, actor, other, monitor):
            n.close()
