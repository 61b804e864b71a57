"""The verdict of ``python -m zenrl.health`` from what it saw (zenrl/health.judge): a token, the
newest stats, and the threads those stats call stalled. The probe itself against real processes
is tests/integration/test_health.py."""

from zenrl.health import judge

TOKEN = "zenrl/r/alive/replay/replay"


def test_no_token_is_unhealthy_whatever_the_stats():
    ok, why = judge("replay", TOKEN, "replay", [], {"replay": {"stalled": ""}}, 5.0)
    assert not ok and why == f"no liveliness token {TOKEN} at the router"


def test_token_alone_when_stats_are_not_asked_for():
    assert judge("replay", TOKEN, "replay", ["replay"], {}, None) == (True, "alive")


def test_stats_must_come_from_the_process_itself():
    ok, why = judge("replay", TOKEN, "replay", ["replay"], {"replay-2": {"stalled": ""}}, 5.0)
    assert not ok and "published no stats within 5.0 s" in why


def test_stalled_thread_fails_with_its_name():
    ok, why = judge("replay", TOKEN, "replay", ["replay"], {"replay": {"stalled": "replay-ingest", "size": 10}}, 5.0)
    assert not ok and "replay-ingest" in why and "stalled" in why and "\n" not in why


def test_fresh_stats_without_a_stall_are_healthy():
    # roles outside the role loop publish no ``stalled`` at all; an empty one means none stalled
    for values in ({"stalled": ""}, {"size": 3}):
        assert judge("replay", TOKEN, "replay", ["replay"], {"replay": values}, 5.0) == (True, "alive and publishing stats")


def test_any_matching_process_that_stalls_fails_the_probe():
    stats = {"actor-h-1": {"stalled": ""}, "actor-h-2": {"stalled": "sender,prefetch"}}
    ok, why = judge("actor", "zenrl/r/alive/actor/actor-h-*", "actor-h-*", ["actor-h-1", "actor-h-2"], stats, 5.0)
    assert not ok and "actor-h-2" in why and "sender,prefetch" in why
