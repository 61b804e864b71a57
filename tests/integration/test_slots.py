"""Elastic exploration slots claimed through liveliness tokens, across real processes."""

import re
import signal

import numpy as np
import pytest

from zenrl.common.exploration import elastic_env_epsilons, van_der_corput
from tests.conftest import wait_until

pytestmark = pytest.mark.integration


def _slot(procs, name):
    m = re.search(r"SLOT (\d+)", procs.log(name))
    return int(m.group(1)) if m else None


def test_concurrent_claims_get_distinct_slots_and_freed_slots_are_reused(router, run_id, procs):
    def start(name):
        return procs.start(name, ["tests/integration/procs.py", "claim", "--router", router, "--run", run_id, "--actor", name])

    ps = {n: start(n) for n in ("a", "b", "c")}
    slots = {n: wait_until(lambda n=n: _slot(procs, n) is not None and _slot(procs, n) + 1, 60, f"{n}'s slot") - 1 for n in ps}
    assert sorted(slots.values()) == [0, 1, 2], slots

    victim = next(n for n, s in slots.items() if s == 1)
    ps[victim].send_signal(signal.SIGKILL)
    ps[victim].wait(timeout=10)
    start("d")
    # a SIGKILLed process's token disappears at once, so the newcomer takes the freed slot
    assert wait_until(lambda: _slot(procs, "d") is not None and _slot(procs, "d") + 1, 60, "d's slot") - 1 == 1


def test_elastic_ladder_covers_the_range_for_any_n():
    assert [van_der_corput(k) for k in range(4)] == [0.0, 0.5, 0.25, 0.75]
    for n in (1, 2, 3, 5, 8):
        eps = np.concatenate([elastic_env_epsilons(s, 4) for s in range(n)])
        expo = np.log(eps) / np.log(0.4) - 1.0        # = 7 * vdc(rung) in [0, 7)
        pos = np.sort(expo / 7.0)
        assert pos[0] == 0.0
        assert np.max(np.diff(np.r_[pos, 1.0])) <= 2.0 / len(pos) + 1e-9   # no big gap anywhere


def test_a_quarantined_actors_slot_goes_to_a_newcomer(router, run_id, procs):
    """The replay quarantines an actor that keeps sending bad chunks; its slot then counts as
    free, so the next actor to claim takes it although the bad actor is still connected."""
    from zenrl.common import protocol as P
    from zenrl.common.transport import Node

    keys = P.Keys(run_id)
    procs.zenrl("replay", ["replay", "--router", router, "--run-id", run_id,
                           "--set", "replay.stats_interval_s=0.2", "--set", "replay.quarantine_rejections=3"])

    def start(name):
        return procs.start(name, ["tests/integration/procs.py", "claim", "--router", router, "--run", run_id, "--actor", name])

    start("bad")
    assert wait_until(lambda: _slot(procs, "bad") is not None and _slot(procs, "bad") + 1, 60, "bad's slot") - 1 == 0
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        pub = node.publisher(keys.transitions("bad"))
        b = 4
        chunk = {"obs": np.zeros((b, 4), np.float32), "action": np.full(b, 9), "reward": np.zeros(b, np.float32),
                 "next_obs": np.zeros((b, 4), np.float32), "terminated": np.zeros(b, bool), "n": np.ones(b, np.uint8)}

        def quarantined():
            pub.put(P.TransitionBatch("bad", 0, 0, chunk).encode())  # action 9 in a 2-action env
            return node.alive_now(keys.quarantined("bad"), 0.5)

        wait_until(quarantined, 30, "the replay to quarantine 'bad'", interval_s=0.2)
        start("good")
        assert wait_until(lambda: _slot(procs, "good") is not None and _slot(procs, "good") + 1, 60, "good's slot") - 1 == 0
