"""The per-source fair queue of the A3C learner's gradients: bounded, a flooding source only
evicts its own messages, sources served round-robin; and the learner's checks of what a gradient
claims (its sender, its env steps)."""

import threading

import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.learner.a3c import APPLIED, A3CLearner
from zenrl.learner.fair_queue import FairQueue


def _drain(q):
    out = []
    while (item := q.get(0.0)) is not None:
        out.append(item)
    return out


def test_round_robin_across_sources_fifo_within():
    q = FairQueue(100)
    for i in range(5):
        q.put("flood", ("flood", i))
    q.put("a", ("a", 0))
    q.put("b", ("b", 0))
    q.put("a", ("a", 1))
    got = [item for _, item in _drain(q)]
    assert got == [("flood", 0), ("a", 0), ("b", 0), ("flood", 1), ("a", 1), ("flood", 2), ("flood", 3), ("flood", 4)]
    assert len(q) == 0 and q.counters["taken"] == 8


def test_a_flood_evicts_only_its_own_messages():
    q = FairQueue(10)
    honest = []
    for i in range(1000):
        q.put("flood", i)
        if i % 250 == 0:  # 4 in all: below its fair share of the 10 places
            q.put("honest", i)
            honest.append(i)
    assert len(q) == 10
    got = _drain(q)
    assert [v for s, v in got if s == "honest"] == honest  # every honest message survived, in order
    assert q.counters["evicted"] == 1000 + len(honest) - 10
    assert q.evicted_values() == {"queue_dropped_from/flood": q.counters["evicted"]}


def test_brute_force_reference_of_eviction_and_order():
    """Random puts and gets against a plain reference model of the same rules, turns waited
    included (counted from the sequence of takes)."""
    rng = np.random.default_rng(0)
    q, ref, turn = FairQueue(7), {}, []
    takes, put_at, wait_max = [], {}, {}  # sources in take order; step -> (len(takes), ahead)
    for step in range(3000):
        if rng.random() < 0.7:
            src = f"s{int(rng.integers(0, 4))}"
            if sum(map(len, ref.values())) >= 7:
                mine = len(ref.get(src, []))
                best = max(ref, key=lambda s: len(ref[s]))
                victim = src if mine and mine >= len(ref[best]) else best
                ref[victim].pop(0)
                if not ref[victim]:
                    del ref[victim]
                    turn.remove(victim)
            if src not in ref:
                ref[src] = []
                turn.append(src)
            put_at[step] = (len(takes), len(ref[src]))
            ref[src].append(step)
            q.put(src, step)
        else:
            got = q.get(0.0)
            if not ref:
                assert got is None
                continue
            src = turn.pop(0)
            turn.append(src)
            want = (src, ref[src].pop(0))
            since, ahead = put_at[want[1]]
            others = sum(s != src for s in takes[since:])
            wait_max[src] = max(wait_max.get(src, 0.0), others / (ahead + 1))
            takes.append(src)
            if not ref[src]:
                del ref[src]
                turn.remove(src)
            assert got == want, step
        assert q.sizes() == {s: len(v) for s, v in ref.items()}
    want = {f"queue_wait_turns_max_from/{s}": round(v, 3) for s, v in wait_max.items()}
    assert q.wait_values() == want
    # round-robin: no message waited more than one turn of each of the 3 other sources per own ahead
    assert max(want.values()) <= 3 and max(want.values()) >= 1


def test_turns_waited_do_not_grow_with_a_flood():
    """A quiet source's message waits one turn of the flood per message of its own ahead, however
    deep the flood's backlog; a FIFO would have made it wait the whole backlog."""
    q = FairQueue(100)
    for i in range(90):
        q.put("flood", i)
    q.put("honest", 0)
    q.put("honest", 1)
    q.put("third", 0)
    _drain(q)
    w = q.wait_values()
    # honest 0: flood 0 ahead of it (1 turn, nothing of its own); honest 1: flood 0, third 0,
    # flood 1 (3 turns, 1 of its own ahead: 1.5); third: flood 0 and honest 0 (2 turns)
    assert w["queue_wait_turns_max_from/honest"] == 1.5
    assert w["queue_wait_turns_max_from/third"] == 2.0
    # flood 1: honest 0 and third 0 ahead, behind 1 of its own (1.0); flood 2: those and honest 1,
    # behind 2 of its own (1.0); later ones waited behind the same 3 and more of their own
    assert w["queue_wait_turns_max_from/flood"] == 1.0


def test_get_waits_for_a_put_and_times_out():
    q = FairQueue(3)
    assert q.get(0.01) is None
    t = threading.Timer(0.05, q.put, ("a", 1))
    t.start()
    assert q.get(5.0) == ("a", 1)
    t.join()
    with pytest.raises(ValueError):
        FairQueue(0)


def _learner(tmp_path, *sets):
    cfg = load_config(None, [f"runs_dir={tmp_path}", "algo=a3c", "network.hidden=[8]", "actor.envs_per_actor=4",
                             "a3c.t_max=5", *sets], environ={})
    svc = A3CLearner(cfg, node=None, run_id="fq")
    svc.applier.next_version()
    return svc


def _grads(svc, steps, worker="w0", scale=0.01):
    g = {k: np.full(p.shape, scale, np.float32) for k, p in svc.net.named_parameters()}
    return P.Gradients(worker_id=worker, version=svc.applier.version, steps=steps, grads=g).encode()


def test_steps_are_bounded_by_one_rollout(tmp_path):
    svc = _learner(tmp_path)
    assert svc.max_steps == 20
    assert svc.handle("run/gradients/w0", _grads(svc, 20)) == APPLIED and svc.env_steps_trained == 20
    for steps in (21, 2**40, 2**64 - 1):
        assert svc.handle("run/gradients/w0", _grads(svc, steps)) is None
    # 2**64 - 1 is outside the field's declared range: the decoder refuses it first ("field")
    assert svc.rejects.counts["steps"] == 2 and svc.rejects.counts["field"] == 1
    assert svc.env_steps_trained == 20 and svc.applier.updates == 1
    assert _learner(tmp_path, "a3c.max_gradient_steps=64").max_steps == 64


def test_a_gradient_sent_under_another_workers_name_is_rejected(tmp_path):
    svc = _learner(tmp_path)
    assert svc.handle("run/gradients/w1", _grads(svc, 5, worker="w0")) is None
    assert svc.rejects.counts["source"] == 1 and svc.applier.updates == 0


def test_the_learner_serves_a_quiet_worker_between_a_floods_messages(tmp_path):
    svc = _learner(tmp_path)
    for _ in range(200):
        svc._on_gradients("run/gradients/flood", _grads(svc, 20, worker="flood"))
    svc._on_gradients("run/gradients/honest", _grads(svc, 20, worker="honest"))
    assert svc.queue_dropped == 200 + 1 - svc._q.max_items
    first = [svc._q.get(0.0)[0] for _ in range(2)]
    assert "honest" in first  # served within one round, not after the flood


def test_future_version_claims_move_the_version_boundedly(tmp_path):
    """A worker claiming versions ahead of the learner's (legitimate only after a restart from an
    older checkpoint) makes it resync at most once per max_staleness + 1 applied gradients and
    never beyond MAX_RESYNC_AHEAD past where it started."""
    from zenrl.learner.a3c import MAX_RESYNC_AHEAD

    svc = _learner(tmp_path, "a3c.max_staleness=2")
    ap = svc.applier
    assert ap.resync(ap.version + 5) and ap.version == 8
    for _ in range(50):  # a flood of future claims: no further jump until 3 gradients are applied
        assert not ap.resync(ap.version + 1)
    for _ in range(3):
        assert svc.handle("run/gradients/w0", _grads(svc, 20)) == APPLIED
    assert not ap.resync(MAX_RESYNC_AHEAD + 1)  # past the ceiling: never
    assert ap.resync(MAX_RESYNC_AHEAD) and ap.version == MAX_RESYNC_AHEAD + 2
    for _ in range(3):
        assert svc.handle("run/gradients/w0", _grads(svc, 20)) == APPLIED
    assert not ap.resync(ap.version + 1) and ap.version < MAX_RESYNC_AHEAD + 10
