"""The IMPALA learner's unroll queue (learner/unroll_queue.py): bounds in count and bytes,
eviction that spares slow sources, round-robin takes, policy-lag drops, timeouts, many threads
putting while one takes; and batching into time-major tensors."""

import threading

import numpy as np
import pytest
import torch

from zenrl.common import protocol as P
from zenrl.learner.unroll_queue import UnrollQueue, batch_unrolls

T = 3


def _u(actor="a", version=0, seq=0, obs_dim=2, trunc_at=(), term_at=(), logits=False):
    term = np.zeros(T, bool)
    trunc = np.zeros(T, bool)
    trunc[list(trunc_at)] = True
    term[list(term_at)] = True
    K = int((trunc & ~term).sum())
    obs = np.full((T + 1, obs_dim), seq, np.float32)
    obs[:, 0] = np.arange(T + 1)
    return P.Unroll(actor, version, seq, {"obs": obs}, np.full(T, seq % 2, np.int64), np.full(T, -0.5, np.float32),
                    np.full(T, float(seq), np.float32), term, trunc,
                    {"obs": np.full((K, obs_dim), 100.0 + seq, np.float32)} if K else None,
                    np.zeros((T, 2), np.float32) if logits else None)


NBYTES = _u().nbytes


def test_fifo_within_a_source_and_count_bound():
    q = UnrollQueue(max_unrolls=3, max_bytes=10**9, max_policy_lag=10)
    for s in range(5):
        assert q.put(_u(seq=s)) == "queued"
    assert len(q) == 3 and q.counters["evicted"] == 2  # the oldest went
    assert [u.seq for u in q.take(3, timeout=0)] == [2, 3, 4]
    assert len(q) == 0 and q.nbytes == 0


def test_byte_bound_and_too_large():
    q = UnrollQueue(max_unrolls=100, max_bytes=int(2.5 * NBYTES), max_policy_lag=10)
    for s in range(4):
        q.put(_u(seq=s))
        assert q.nbytes <= q.max_bytes
    assert len(q) == 2 and q.nbytes == 2 * NBYTES and q.counters["evicted"] == 2
    big = _u(obs_dim=200)
    assert big.nbytes > q.max_bytes
    assert q.put(big) == "too_large" and q.counters["too_large_dropped"] == 1 and len(q) == 2


def test_fast_source_cannot_push_out_a_slow_one():
    q = UnrollQueue(max_unrolls=6, max_bytes=10**9, max_policy_lag=10)
    q.put(_u("slow", seq=0))
    q.put(_u("slow", seq=1))
    for s in range(100):
        q.put(_u("fast", seq=s))
    assert q.sizes() == {"slow": 2, "fast": 4}
    # the fast source's newest survive
    got = q.take(6, timeout=0)
    assert sorted(u.seq for u in got if u.actor_id == "fast") == [96, 97, 98, 99]


def test_a_new_source_gets_room_from_the_biggest():
    q = UnrollQueue(max_unrolls=4, max_bytes=10**9, max_policy_lag=10)
    for s in range(4):
        q.put(_u("a", seq=s))
    q.put(_u("b", seq=0))
    q.put(_u("c", seq=0))
    assert q.sizes() == {"a": 2, "b": 1, "c": 1}
    q.put(_u("b", seq=1))  # b holds fewer than a: a's oldest goes, not b's
    assert q.sizes() == {"a": 1, "b": 2, "c": 1}
    q.put(_u("b", seq=2))  # b now holds the most: it evicts its own oldest
    assert q.sizes() == {"a": 1, "b": 2, "c": 1}
    assert [u.seq for u in q.take(4, timeout=0) if u.actor_id == "b"] == [1, 2]


def test_on_a_tie_the_putter_evicts_its_own():
    q = UnrollQueue(max_unrolls=4, max_bytes=10**9, max_policy_lag=10)
    for s in range(2):
        q.put(_u("a", seq=s))
    for s in range(3):
        q.put(_u("b", seq=s))
    assert q.sizes() == {"a": 2, "b": 2}
    assert [u.seq for u in q.take(4, timeout=0) if u.actor_id == "b"] == [1, 2]


def test_take_is_round_robin_across_sources():
    q = UnrollQueue(max_unrolls=100, max_bytes=10**9, max_policy_lag=10)
    for s in range(10):
        q.put(_u("fast", seq=s))
    q.put(_u("slow1", seq=0))
    q.put(_u("slow2", seq=0))
    first = q.take(3, timeout=0)
    assert sorted(u.actor_id for u in first) == ["fast", "slow1", "slow2"]
    rest = q.take(9, timeout=0)
    assert [u.seq for u in rest] == list(range(1, 10))


def test_stale_unrolls_dropped_on_put_and_on_take():
    q = UnrollQueue(max_unrolls=100, max_bytes=10**9, max_policy_lag=2)
    q.set_version(5)
    assert q.put(_u(version=2)) == "stale"
    assert q.put(_u(version=3, seq=1)) == "queued"  # lag 2: still allowed
    assert q.put(_u(version=5, seq=2)) == "queued"
    assert q.put(_u(version=7, seq=3)) == "queued" and q.counters["future_version"] == 1
    q.set_version(6)  # the version-3 unroll is now 3 behind
    got = q.take(2, timeout=0)
    assert [u.seq for u in got] == [2, 3]
    assert q.counters["stale_dropped"] == 2 and len(q) == 0


def test_take_times_out_and_takes_nothing():
    q = UnrollQueue(max_unrolls=10, max_bytes=10**9, max_policy_lag=10)
    q.put(_u())
    assert q.take(2, timeout=0.05) is None
    assert len(q) == 1
    with pytest.raises(ValueError, match="at most 10"):
        q.take(11, timeout=0)


def test_take_wakes_when_enough_arrive():
    q = UnrollQueue(max_unrolls=10, max_bytes=10**9, max_policy_lag=10)
    got = []
    th = threading.Thread(target=lambda: got.append(q.take(2, timeout=120)), daemon=True)
    th.start()
    q.put(_u(seq=0))
    q.put(_u(seq=1))
    th.join(timeout=30)  # woken by the put, long before its own timeout
    assert not th.is_alive() and [u.seq for u in got[0]] == [0, 1]


def test_many_producers_one_consumer_conserve_unrolls():
    q = UnrollQueue(max_unrolls=8, max_bytes=10**9, max_policy_lag=1000)
    N, P_ = 300, 4
    taken = []
    done = threading.Event()

    def consume():
        while not (done.is_set() and len(q) < 4):
            b = q.take(4, timeout=0.05)
            if b:
                taken.extend(b)

    producers = [threading.Thread(target=lambda a=a: [q.put(_u(f"p{a}", seq=s)) for s in range(N)]) for a in range(P_)]
    cons = threading.Thread(target=consume)
    cons.start()
    for p in producers:
        p.start()
    for p in producers:
        p.join(timeout=60)
    done.set()
    cons.join(timeout=60)
    assert not cons.is_alive()
    c = q.counters
    assert c["queued"] == N * P_ and c["taken"] == len(taken)
    assert c["queued"] == c["taken"] + c["evicted"] + len(q)
    for a in range(P_):  # within a source, taken in order
        seqs = [u.seq for u in taken if u.actor_id == f"p{a}"]
        assert seqs == sorted(seqs)


def test_drop_source():
    q = UnrollQueue(max_unrolls=10, max_bytes=10**9, max_policy_lag=10)
    q.put(_u("a"))
    q.put(_u("a", seq=1))
    q.put(_u("b"))
    assert q.drop_source("a") == 2 and q.sizes() == {"b": 1} and q.nbytes == NBYTES


def test_batch_unrolls_time_major_with_final_observations():
    us = [_u("a", version=1, seq=0, trunc_at=[2]), _u("b", version=2, seq=1), _u("c", version=3, seq=2, trunc_at=[0, 1], term_at=[1])]
    b = batch_unrolls(us)
    B = 3
    assert b.shape == (T, B) and b.obs["obs"].shape == (T + 1, B, 2)
    assert b.action.dtype == torch.int64 and b.terminated.dtype == torch.bool and b.reward.dtype == torch.float32
    for i, u in enumerate(us):
        np.testing.assert_array_equal(b.obs["obs"][:, i].numpy(), u.obs["obs"])
        np.testing.assert_array_equal(b.reward[:, i].numpy(), u.reward)
        np.testing.assert_array_equal(b.truncated[:, i].numpy(), u.truncated)
    # unroll a truncated at t=2, unroll c at t=0 (t=1 is also terminated: no final observation)
    assert b.final_index.tolist() == [2 * B + 0, 0 * B + 2]
    np.testing.assert_array_equal(b.final_obs["obs"][:, 0].numpy(), [100.0, 102.0])
    assert b.policy_version.tolist() == [1, 2, 3] and b.behaviour_logits is None
    flat = torch.zeros(T * B)
    flat[b.final_index] = 1.0
    assert flat.view(T, B).bool().equal(b.truncated & ~b.terminated)


def test_batch_unrolls_logits_and_no_truncation():
    b = batch_unrolls([_u(logits=True), _u(seq=1, logits=True)])
    assert b.behaviour_logits.shape == (T, 2, 2) and b.final_obs["obs"].shape == (0, 2) and b.final_index.numel() == 0
    with pytest.raises(ValueError, match="differ"):
        batch_unrolls([_u(), _u(obs_dim=3)])
