"""The sharded replay's sampler (common/replay_client.py ShardedReplayClient) against one replay.

The shards are real replay samplers (replay/sampling.py over replay/buffer.py, the code each
``zenrl replay --shard k`` runs), reached through an in-process node that routes each shard's
keys to its sampler; the reference is one InMemoryReplay holding every item with the same
priorities. The client must draw each item as often as the single replay would, with its global
probability and IS weight; a client that picked shards uniformly (or by size) fails the
chi-square test below.
"""

from __future__ import annotations

import logging
import math
import threading

import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import ReplayConfig
from zenrl.common.errors import NotReady, RemoteTimeout
from zenrl.common.metrics import RejectCounter
from zenrl.common.replay_client import SamplePrefetcher, Sampled, ShardedReplayClient
from zenrl.common.specs import ArraySpec
from zenrl.replay.buffer import InMemoryReplay
from zenrl.replay.sampling import Sampler

RUN = "shards"
ALPHA, EPS = 0.6, 1e-6
#: items carry their global id, and a [T, 2] field as R2D2's sequences do
SPEC = {"id": ArraySpec((), "int64"), "seq": ArraySpec((5, 2), "float32")}


class ShardNode:
    """Routes shard k's sample queries and priority updates to its :class:`Sampler`, answering
    at once on the caller's thread. ``silent``: shards that never answer (down: the query ends
    with no reply, as Zenoh's does when nothing serves the key)."""

    def __init__(self, samplers: list[Sampler]) -> None:
        self.samplers = samplers
        self.silent: set[int] = set()
        self.queries = [0] * len(samplers)
        self.lock = threading.Lock()

    def _shard(self, key: str, what: str) -> int:
        for k in range(len(self.samplers)):
            if key == getattr(P.Keys(RUN, k), what):
                return k
        raise AssertionError(f"{key} is no shard's {what} key")

    def query_async(self, key, payload, timeout_s, on_reply) -> None:
        k = self._shard(key, "sample")
        with self.lock:
            self.queries[k] += 1
        on_reply(None if k in self.silent else self.samplers[k].on_sample(payload))

    def publisher(self, key: str):
        k = self._shard(key, "priorities")
        sampler = self.samplers[k]

        class Pub:
            def put(self, payload: bytes) -> None:
                sampler.on_priorities(key, payload)

        return Pub()


def _buffer(ids: np.ndarray, prios: np.ndarray, seed: int) -> InMemoryReplay:
    rb = InMemoryReplay(SPEC, capacity=1024, alpha=ALPHA, eps=EPS, seed=seed)
    if ids.size:
        seq = np.repeat(ids[:, None, None], 10, 1).reshape(-1, 5, 2).astype(np.float32)
        rb.insert({"id": ids.astype(np.int64), "seq": seq}, prios)
    return rb


def _sampler(rb: InMemoryReplay | None, k: int, rcfg: ReplayConfig) -> Sampler:
    return Sampler(rcfg, seed=100 + k, max_bytes=P.DEFAULT_MAX_MESSAGE_BYTES, lock=threading.Lock(),
                   buffer=lambda: rb, rejects=RejectCounter(logging.getLogger("test"), "test"),
                   sample_key=P.Keys(RUN, k).sample, check_priorities=False)


def world(split: list[np.ndarray], prios: np.ndarray, min_size: int = 1):
    """Shards holding the items of ``split`` (ids into ``prios``), their node and client."""
    rcfg = ReplayConfig(min_size=min_size)
    bufs = [_buffer(ids, prios[ids], seed=k) for k, ids in enumerate(split)]
    node = ShardNode([_sampler(b, k, rcfg) for k, b in enumerate(bufs)])
    client = ShardedReplayClient(node, RUN, len(split), "learner", timeout_s=1.0, seed=7)
    return bufs, node, client


def _priorities(m: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.05, 3.0, m)


#: 60 items over 3 shards of unequal mass: shard 0 takes the 10 highest priorities, shard 2
#: the 30 lowest, shard 1 the rest
M = 60


def _split(prios: np.ndarray) -> list[np.ndarray]:
    order = np.argsort(-prios)
    return [np.sort(order[:10]), np.sort(order[10:30]), np.sort(order[30:])]


def _chi2_bound(df: int, z: float = 4.0) -> float:
    """Upper tail bound of chi-square(df) at ~3e-5 (Wilson-Hilferty)."""
    return df * (1 - 2 / (9 * df) + z * math.sqrt(2 / (9 * df))) ** 3


def test_sharded_draws_match_one_replay_in_frequency_probability_and_weight():
    prios = _priorities(M)
    split = _split(prios)
    _, node, client = world(split, prios)
    big = _buffer(np.arange(M), prios, seed=99)
    leaf = (prios + EPS) ** ALPHA
    p_ref = leaf / leaf.sum()
    masses = [leaf[ids].sum() for ids in split]
    assert max(masses) > 1.5 * min(masses)  # unequal masses: a uniform pick of shards is wrong

    # the single replay's own probabilities are the reference's
    ref = big.sample(64, 0.5, np.random.default_rng(1))
    np.testing.assert_allclose(ref.probabilities, p_ref[ref.data["id"]], rtol=1e-9)

    counts = np.zeros(M)
    B, T, beta = 32, 1500, 0.6
    for _ in range(T):
        s = client.sample(B, beta)
        ids = s.data["id"]
        assert s.keys.shape == (B,) and s.data["seq"].shape == (B, 5, 2)
        np.testing.assert_array_equal(s.data["seq"][:, 0, 0], ids)  # rows stay together across shards
        # global probabilities and IS weights: what the single replay gives the same items
        np.testing.assert_allclose(s.probabilities, p_ref[ids], rtol=1e-9)
        w_ref = (p_ref[ids].min() / p_ref[ids]) ** beta  # (N P_i)^-beta over its max, one replay's rule
        np.testing.assert_allclose(s.weights, w_ref, rtol=1e-6)
        counts += np.bincount(ids, minlength=M)
    assert s.replay_size == M
    expected = B * T * p_ref
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < _chi2_bound(M - 1), (chi2, _chi2_bound(M - 1))
    # and per shard: its share of the draws is its share of the mass
    share = np.array([counts[ids].sum() for ids in split]) / (B * T)
    np.testing.assert_allclose(share, np.array(masses) / sum(masses), atol=0.01)
    v = client.values()
    assert v["replay_shards_up"] == 3 and sum(v[f"replay{k}_items"] for k in range(3)) == B * T


def test_uniform_choice_of_shards_fails_the_same_chi_square():
    """The test above can fail: the same items drawn with each shard picked uniformly (each
    shard's own sampling unchanged) is far outside the bound."""
    prios = _priorities(M)
    split = _split(prios)
    leaf = (prios + EPS) ** ALPHA
    p_ref = leaf / leaf.sum()
    B, T = 32, 1500
    rng = np.random.default_rng(3)
    counts = np.zeros(M)
    for ids in split:  # E[count] under a uniform pick of shards: B*T/3 draws per shard
        p_in = leaf[ids] / leaf[ids].sum()
        counts[ids] += rng.multinomial(B * T // 3, p_in)
    expected = B * T * p_ref
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 > 10 * _chi2_bound(M - 1)


def test_priorities_go_back_to_the_shard_of_each_item():
    prios = _priorities(M)
    split = _split(prios)
    bufs, node, client = world(split, prios)
    s = client.sample(48, 0.4)
    shard, local = client.shard_of(s.keys)
    assert set(shard.tolist()) == {0, 1, 2}  # 48 draws over these masses reach every shard
    new = np.linspace(0.1, 9.0, len(s.keys)).astype(np.float32)
    # the last item is reported poisonous: removed from its own shard only
    client.update_priorities(s.keys[:-1], new[:-1], poisoned=s.keys[-1:])
    for k, rb in enumerate(bufs):
        mine = shard[:-1] == k
        # each shard holds the new priority of its items (the last update of a key named twice wins)
        want = {int(key): p for key, p in zip(local[:-1][mine], new[:-1][mine])}
        if k == shard[-1]:
            want.pop(int(local[-1]), None)  # the poisoned item takes no priority after
        got = rb.priorities_of(np.array(sorted(want), np.int64))
        np.testing.assert_allclose(got, [(want[x] + EPS) ** ALPHA for x in sorted(want)], rtol=1e-5)
        assert node.samplers[k].priority_keys == int(mine.sum())
    k_bad, key_bad = int(shard[-1]), int(local[-1])
    assert node.samplers[k_bad].poison_removed == 1
    assert bufs[k_bad].priorities_of(np.array([key_bad]))[0] == 0.0
    assert sum(node.samplers[k].poison_removed for k in range(3)) == 1
    assert sum(client.values()[f"replay{k}_priority_keys"] for k in range(3)) == len(s.keys) - 1


def test_an_empty_shard_is_skipped_and_counted():
    prios = _priorities(M)
    split = [np.arange(30), np.arange(0), np.arange(30, M)]
    _, node, client = world(split, prios)
    leaf = (prios + EPS) ** ALPHA
    for _ in range(20):
        s = client.sample(16, 0.4)
        assert s.keys.shape == (16,)
        np.testing.assert_allclose(s.probabilities, leaf[s.data["id"]] / leaf.sum(), rtol=1e-9)
    st = client.state[1]
    assert not st.up and "min_size" in st.reason and st.mass == 0.0
    assert client.values()["replay1_items"] == 0


def test_a_shard_that_goes_down_costs_one_batch_then_the_others_serve():
    prios = _priorities(M)
    split = _split(prios)
    _, node, client = world(split, prios)
    client.refresh()
    assert all(st.up for st in client.state)
    node.silent.add(0)  # shard 0 (the largest mass) stops answering
    got: list = []
    client.sample_async(32, 0.4, got.append)
    assert isinstance(got[0], RemoteTimeout) and "shard 0" in str(got[0])
    assert client.state[0].failed == 1 and not client.state[0].up and client.dropped_batches == 1
    leaf = (prios + EPS) ** ALPHA
    rest = np.concatenate(split[1:])
    for _ in range(10):  # drawn from shards 1 and 2 alone, with their union's probabilities
        s = client.sample(32, 0.4)
        assert set(client.shard_of(s.keys)[0].tolist()) <= {1, 2}
        np.testing.assert_allclose(s.probabilities, leaf[s.data["id"]] / leaf[rest].sum(), rtol=1e-9)
    node.silent.clear()
    client.refresh()  # the next probe brings it back
    assert client.state[0].up


def test_with_no_shard_ready_the_request_fails_at_once_naming_each():
    prios = _priorities(M)
    _, node, client = world([np.arange(3), np.arange(3, 6)], prios, min_size=100)
    with pytest.raises(NotReady, match="shard 0: .*min_size 100 > size 3.*shard 1"):
        client.sample(8, 0.4)


def test_prefetcher_over_shards_hands_out_whole_batches():
    prios = _priorities(M)
    split = _split(prios)
    _, node, client = world(split, prios)
    pf = SamplePrefetcher(client, 8, lambda: 0.4, in_flight=2, backoff_s=0.01, batches_per_request=2, seed=0).start()
    try:
        got = [pf.get(timeout_s=2.0) for _ in range(6)]
    finally:
        pf.stop()
    assert all(isinstance(s, Sampled) and s.keys.shape == (8,) for s in got)
    assert pf.errors == 0 and pf.timeouts == 0


def test_a_shard_reply_with_the_wrong_count_or_fields_is_refused_not_raised():
    prios = _priorities(M)
    split = _split(prios)
    _, node, client = world(split, prios)
    client.refresh()
    real = node.query_async

    def lying(key, payload, timeout_s, on_reply):  # shard 2 answers with one item more than asked
        if key == P.Keys(RUN, 2).sample:
            req = P.SampleRequest.decode(payload)
            payload = P.SampleRequest(request_id=req.request_id, batch_size=req.batch_size + 1, beta=req.beta).encode()
        real(key, payload, timeout_s, on_reply)

    node.query_async = lying
    results: list = []
    for _ in range(20):
        client.sample_async(64, 0.4, results.append)
    bad = [r for r in results if isinstance(r, P.ProtocolError)]
    assert bad and all("shard 2" in str(r) for r in bad)
    assert client.state[2].failed >= 1


def test_shard_keys_are_apart_from_each_other_and_from_the_unsharded_ones():
    import zenoh

    one, s0, s1 = P.Keys(RUN), P.Keys(RUN, 0), P.Keys(RUN, 1)
    assert (one.sample, one.priorities, one.transitions("a0")) == (
        f"zenrl/{RUN}/replay/sample", f"zenrl/{RUN}/replay/priorities", f"zenrl/{RUN}/transitions/a0")
    assert (s1.sample, s1.priorities, s1.transitions("a0"), s1.transitions_all) == (
        f"zenrl/{RUN}/replay/1/sample", f"zenrl/{RUN}/replay/1/priorities", f"zenrl/{RUN}/transitions/1/a0",
        f"zenrl/{RUN}/transitions/1/*")
    assert s1.weights == one.weights and s1.stats("replay", "replay-1") == one.stats("replay", "replay-1")
    # each replay's subscription takes its own actors' chunks and no other replay's
    for sub, mine in ((one, one), (s0, s0), (s1, s1)):
        for other in (one, s0, s1):
            hit = zenoh.KeyExpr(sub.transitions_all).intersects(zenoh.KeyExpr(other.transitions("a0")))
            assert hit == (other is mine), (sub.transitions_all, other.transitions("a0"))
    with pytest.raises(P.ProtocolError, match="replay_shard"):
        P.Keys(RUN, P.MAX_REPLAY_SHARDS)


def test_which_shard_a_replay_and_an_actor_take():
    from zenrl.common.errors import ConfigError

    assert P.replay_shard(None, 1) is None and P.replay_shard(0, 1) is None  # unsharded keys
    assert P.replay_shard(2, 3) == 2
    for bad, n in ((2, 2), (-1, 2), (1, 1)):
        with pytest.raises(ConfigError, match=f"replay shard {bad} is not in 0..{n - 1}"):
            P.replay_shard(bad, n)
    with pytest.raises(ConfigError, match="replay.shards=2: give this replay its shard"):
        P.replay_shard(None, 2)
    assert P.actor_shard(5, 1) is None
    assert [P.actor_shard(i, 3) for i in range(7)] == [0, 1, 2, 0, 1, 2, 0]  # slots fill the shards in turn


def test_the_launcher_display_and_zenrl_status_show_each_shard():
    from zenrl.launcher.display import Progress
    from zenrl.launcher.status_client import _detail

    p = Progress()
    for sid, size in (("replay-0", 700), ("replay-1", 300)):
        p.on_message("k", P.Stats(role="replay", id=sid, time=0.0,
                                  values={"size": size, "capacity": 1000, "inserted_total": 2 * size,
                                          "priority_mass": size / 10, "durable_degraded": False}).encode())
    assert set(p.replays) == {"replay-0", "replay-1"} and p.replays["replay-1"]["size"] == 300
    assert p.replay["size"] == 1000 and p.replay["capacity"] == 2000 and p.replay["shards"] == 2
    assert p.status_line()["replay_size"] == 1000
    row = {"role": "replay", "id": "replay-1", **p.replays["replay-1"]}
    assert _detail(row, None).startswith("size 300 / 1,000, priority mass 30")
    learner = {"role": "learner", "policy_lag": 2.0, "replay_shards_up": 1, "replay0_items": 1200, "replay1_items": 34,
               "replay0_mass": 5.0, "replay1_mass": 0.0}
    assert _detail(learner, None) == "policy lag 2.0; replay shards up 1/2, items drawn 0: 1,200, 1: 34"
    assert _detail({"role": "learner", "policy_lag": 2.0}, None) == "policy lag 2.0"  # one replay: as before
