"""InMemoryReplay: storage, FIFO keys, priorities, stratified sampling, IS weights, state."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from zenrl.common.errors import SpecMismatch
from zenrl.common.specs import ArraySpec, flatten, spec_nbytes
from zenrl.replay.buffer import InMemoryReplay, ReplayEmpty, SampleBatch

SETTINGS = settings(derandomize=True, max_examples=40, deadline=None)


# ---------------------------------------------------------------- helpers
def cartpole_spec() -> dict[str, ArraySpec]:
    return {
        "obs": ArraySpec((4,), "float32"),
        "action": ArraySpec((), "int64"),
        "reward": ArraySpec((), "float32"),
        "next_obs": ArraySpec((4,), "float32"),
        "terminated": ArraySpec((), "bool"),
        "n": ArraySpec((), "uint8"),
    }


def image_spec() -> dict[str, ArraySpec]:
    return {
        "obs": ArraySpec((84, 84, 4), "uint8"),
        "action": ArraySpec((), "int64"),
        "reward": ArraySpec((), "float32"),
        "next_obs": ArraySpec((84, 84, 4), "uint8"),
        "terminated": ArraySpec((), "bool"),
    }


def dict_obs_spec() -> dict[str, ArraySpec]:
    return flatten(
        {
            "obs": {"lidar": ArraySpec((360,), "float32"), "pose": ArraySpec((4,), "float32")},
            "action": ArraySpec((2,), "float32"),
            "reward": ArraySpec((), "float32"),
            "next_obs": {"lidar": ArraySpec((360,), "float32"), "pose": ArraySpec((4,), "float32")},
            "terminated": ArraySpec((), "bool"),
        }
    )


def make_batch(spec, ids: np.ndarray) -> dict[str, np.ndarray]:
    """A batch whose every field encodes the row id, so gathered rows can be checked."""
    out = {}
    for name, s in spec.items():
        dt = np.dtype(s.dtype)
        vals = ids if dt != np.bool_ else (ids % 2 == 1)
        if dt == np.uint8:
            vals = ids % 251
        out[name] = np.broadcast_to(vals.astype(dt).reshape((-1,) + (1,) * len(s.shape)), (len(ids), *s.shape)).copy()
    return out


def cp_batch(ids) -> dict[str, np.ndarray]:
    return make_batch(cartpole_spec(), np.asarray(ids, dtype=np.int64))


# ---------------------------------------------------------------- construction
def test_construction_and_properties():
    rb = InMemoryReplay(cartpole_spec(), 100, seed=0)
    assert rb.capacity == 100 and rb.size == 0 and len(rb) == 0
    assert rb.bytes_per_item == spec_nbytes(cartpole_spec()) == 16 + 8 + 4 + 16 + 1 + 1
    assert rb.nbytes == 0 and rb.inserts_total == 0 and rb.max_priority == 1.0
    assert rb.spec == cartpole_spec()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"capacity": 0}, "capacity"),
        ({"capacity": -5}, "-5"),
        ({"capacity": 2.5}, "2.5"),
        ({"capacity": True}, "capacity"),
        ({"capacity": 10, "alpha": -0.1}, "alpha"),
        ({"capacity": 10, "alpha": float("nan")}, "alpha"),
        ({"capacity": 10, "eps": -1.0}, "eps"),
        ({"capacity": 10, "max_bytes": -1}, "max_bytes"),
        ({"capacity": 10, "max_bytes": 10}, "max_bytes=10"),
        ({"capacity": 10, "uniform": "yes"}, "uniform"),
        ({"capacity": 10, "seed": 1.5}, "seed"),
    ],
)
def test_constructor_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        InMemoryReplay(cartpole_spec(), **kwargs)


def test_constructor_rejects_bad_spec():
    with pytest.raises(ValueError):
        InMemoryReplay({}, 10)
    with pytest.raises(ValueError):
        InMemoryReplay({"obs": (4,)}, 10)  # type: ignore[dict-item]


def test_byte_cap_limits_capacity_and_nbytes():
    spec = image_spec()
    bpi = spec_nbytes(spec)
    assert bpi == 2 * 84 * 84 * 4 + 8 + 4 + 1
    rb = InMemoryReplay(spec, 1000, max_bytes=10 * bpi + bpi - 1)
    assert rb.capacity == 10 and rb.bytes_per_item == bpi
    rb.insert(make_batch(spec, np.arange(3)))
    assert rb.nbytes == 3 * bpi
    rb.insert(make_batch(spec, np.arange(3, 20)))
    assert rb.size == 10 and rb.nbytes == 10 * bpi
    assert InMemoryReplay(spec, 4, max_bytes=10**12).capacity == 4


# ---------------------------------------------------------------- insert / FIFO
def test_fifo_eviction_and_keys():
    rb = InMemoryReplay(cartpole_spec(), 5, seed=0)
    k1 = rb.insert(cp_batch([0, 1, 2]))
    k2 = rb.insert(cp_batch([3, 4, 5, 6]))
    np.testing.assert_array_equal(k1, [0, 1, 2])
    np.testing.assert_array_equal(k2, [3, 4, 5, 6])
    assert k1.dtype == np.int64
    assert rb.size == 5 and rb.inserts_total == 7
    # slot = key % capacity; keys 0 and 1 were evicted
    s = rb.state_dict()
    np.testing.assert_array_equal(s["keys"], [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(s["data"]["action"], [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(s["data"]["obs"][:, 0], [5, 6, 2, 3, 4])


def test_batch_larger_than_capacity_keeps_last_items():
    rb = InMemoryReplay(cartpole_spec(), 5, seed=0)
    rb.insert(cp_batch([100]))
    keys = rb.insert(cp_batch(np.arange(12)), priorities=np.arange(12, dtype=np.float64))
    np.testing.assert_array_equal(keys, np.arange(1, 13))
    assert rb.size == 5 and rb.inserts_total == 13
    s = rb.state_dict()
    # keys 8..12 (rows 7..11) stored at slots key % 5
    np.testing.assert_array_equal(np.sort(s["keys"]), np.arange(8, 13))
    np.testing.assert_array_equal(s["data"]["action"][s["keys"] % 5], s["keys"] - 1)
    assert rb.update_priorities(keys[:7], np.ones(7)) == 0  # stale from the start
    assert rb.stale_updates == 7
    assert rb.max_priority == 1.0  # priorities that come with inserted items do not move it


def test_empty_batch_is_noop():
    rb = InMemoryReplay(cartpole_spec(), 5)
    keys = rb.insert(cp_batch(np.arange(0)))
    assert keys.shape == (0,) and rb.size == 0 and rb.inserts_total == 0


@SETTINGS
@given(st.integers(1, 40), st.lists(st.integers(0, 60), min_size=1, max_size=12), st.booleans())
def test_ring_matches_reference_deque(capacity, chunks, with_prio):
    """Random chunk sizes (wrap-around, oversize chunks) against a deque of (key, prio)."""
    rb = InMemoryReplay(cartpole_spec(), capacity, alpha=1.0, eps=0.0, seed=0)
    ref: deque = deque(maxlen=capacity)
    nxt = 0
    maxp = 1.0
    for c in chunks:
        ids = np.arange(nxt, nxt + c)
        prio = (ids % 7 + 1).astype(np.float64) if with_prio else None
        keys = rb.insert(cp_batch(ids), priorities=prio)
        np.testing.assert_array_equal(keys, ids)
        if with_prio and c:
            maxp = max(maxp, float(prio.max()))
        for j, i in enumerate(ids):
            ref.append((int(i), float(prio[j]) if with_prio else maxp))
        nxt += c
    assert rb.size == len(ref) and rb.inserts_total == nxt
    s = rb.state_dict()
    ref_keys = np.array([k for k, _ in ref], dtype=np.int64)
    np.testing.assert_array_equal(np.sort(s["keys"]), ref_keys)
    np.testing.assert_array_equal(s["data"]["action"], s["keys"])  # rows match their keys
    np.testing.assert_array_equal(s["keys"] % capacity, np.arange(rb.size))
    np.testing.assert_array_equal(rb.priorities_of(ref_keys), [p for _, p in ref])
    assert rb._tree is not None and rb._tree.total == sum(p for _, p in ref)


# ---------------------------------------------------------------- validation of batches
@pytest.mark.parametrize(
    "mutate",
    [
        lambda b: b.pop("reward"),
        lambda b: b.__setitem__("extra", np.zeros(3, np.float32)),
        lambda b: b.__setitem__("obs", b["obs"].astype(np.float64)),
        lambda b: b.__setitem__("obs", b["obs"][:, :3]),
        lambda b: b.__setitem__("action", b["action"][:, None]),
        lambda b: b.__setitem__("reward", b["reward"][:2]),
        lambda b: b.__setitem__("terminated", [True, False, True]),
    ],
)
def test_insert_rejects_spec_mismatch(mutate):
    rb = InMemoryReplay(cartpole_spec(), 10)
    b = cp_batch([0, 1, 2])
    mutate(b)
    with pytest.raises(SpecMismatch):
        rb.insert(b)
    assert rb.size == 0 and rb.inserts_total == 0
    assert issubclass(SpecMismatch, ValueError)


@pytest.mark.parametrize("prio", [[1.0, np.nan, 1.0], [1.0, np.inf, 1.0], [1.0, -0.5, 1.0], [1.0, 2.0], [[1.0, 2.0, 3.0]]])
def test_insert_rejects_bad_priorities(prio):
    rb = InMemoryReplay(cartpole_spec(), 10)
    with pytest.raises(ValueError):
        rb.insert(cp_batch([0, 1, 2]), priorities=np.array(prio))
    assert rb.size == 0


# ---------------------------------------------------------------- priorities
def test_new_items_get_the_recent_learner_max_priority():
    rb = InMemoryReplay(cartpole_spec(), 10, alpha=1.0, eps=0.0)
    k0 = rb.insert(cp_batch([0]))
    assert rb.priorities_of(k0)[0] == 1.0
    k1 = rb.insert(cp_batch([1, 2]), priorities=np.array([0.5, 3.0]))
    k2 = rb.insert(cp_batch([3]))
    assert rb.max_priority == 1.0  # an inserted chunk's own priorities do not move it
    np.testing.assert_array_equal(rb.priorities_of(np.concatenate([k1, k2])), [0.5, 3.0, 1.0])
    assert rb.update_priorities(k0, np.array([7.0])) == 1
    assert rb.max_priority == 7.0
    assert rb.priorities_of(rb.insert(cp_batch([4])))[0] == 7.0


def test_one_chunk_cannot_pin_the_new_item_priority():
    """A chunk inserted at a huge priority leaves it alone; one huge learner priority among many
    is outside the 0.99 quantile; a window of them moves it only while they are the latest."""
    rb = InMemoryReplay(cartpole_spec(), 300, alpha=1.0, eps=0.0, recent_window=200, recent_quantile=0.99)
    rb.insert(cp_batch(np.arange(64)), priorities=np.full(64, 1e9))
    assert rb.max_priority == 1.0
    honest = rb.insert(cp_batch(np.arange(199)))
    rb.update_priorities(honest, np.linspace(0.5, 2.0, 199))
    rb.update_priorities(np.array([0]), np.array([1e9]))  # the chunk's first item, sampled once
    # ring: 199 honest values and 1e9; the 0.99 quantile of 200 is the 198th smallest, an honest one
    expected = np.linspace(0.5, 2.0, 199)[197]
    assert rb.max_priority == expected
    assert rb.priorities_of(rb.insert(cp_batch([5])))[0] == expected
    # a full window of huge values moves it, and it comes back once they are no longer the latest
    rb.update_priorities(np.arange(64), np.full(64, 1e9))
    rb.update_priorities(np.repeat(np.arange(64), 4)[:200], np.full(200, 1e9))
    assert rb.max_priority == 1e9
    rb.update_priorities(honest, np.full(199, 0.25))
    rb.update_priorities(honest[:1], np.array([0.25]))
    assert rb.max_priority == 0.25


def test_removed_items_are_never_sampled_and_stay_removed():
    rb = InMemoryReplay(cartpole_spec(), 8, alpha=1.0, eps=0.0)
    keys = rb.insert(cp_batch(np.arange(8)), priorities=np.full(8, 1.0))
    hit = rb.remove(np.array([2, 5, 5, 99, -1]))
    np.testing.assert_array_equal(hit, [True, True, False, False, False])
    assert rb.removed_total == 2 and rb.removed_live == 2 and rb._tree.total == 6.0
    assert not rb.remove(np.array([2])).any()  # already removed
    # a priority update that was in flight does not bring it back; the others apply
    assert rb.update_priorities(np.array([2, 3]), np.array([9.0, 4.0])) == 1
    np.testing.assert_array_equal(rb.priorities_of(keys[[2, 3, 5]]), [0.0, 4.0, 0.0])
    assert rb.max_priority == 4.0  # the removed item's priority did not count either
    s = rb.sample(512, 0.4, np.random.default_rng(0))
    assert not np.isin(s.keys, [2, 5]).any()
    # the ring overwrites the slot: the new item there is live
    k = rb.insert(cp_batch([8, 9, 10]))
    assert k[2] == 10 and rb.priorities_of(k[2:])[0] == 4.0 and rb.removed_live == 1


def test_removed_items_are_skipped_in_uniform_mode():
    rb = InMemoryReplay(cartpole_spec(), 8, uniform=True, seed=0)
    rb.insert(cp_batch(np.arange(8)))
    rb.remove(np.arange(7))
    s = rb.sample(64, 0.4)
    np.testing.assert_array_equal(s.keys, np.full(64, 7))
    rb.remove(np.array([7]))
    with pytest.raises(ReplayEmpty):
        rb.sample(4, 0.4)


def test_alpha_and_eps_applied_to_stored_priorities():
    rb = InMemoryReplay(cartpole_spec(), 10, alpha=0.5, eps=0.01)
    keys = rb.insert(cp_batch([0, 1]), priorities=np.array([0.0, 4.0]))
    np.testing.assert_allclose(rb.priorities_of(keys), [0.01**0.5, 4.01**0.5])


def test_stale_updates_ignored_and_counted():
    rb = InMemoryReplay(cartpole_spec(), 4, alpha=1.0, eps=0.0)
    old = rb.insert(cp_batch([0, 1, 2, 3]))
    new = rb.insert(cp_batch([4, 5]))  # evicts keys 0, 1
    before_total = rb._tree.total
    applied = rb.update_priorities(np.array([0, 1, 2, 5, 99, -1]), np.array([9.0, 9.0, 2.0, 3.0, 9.0, 9.0]))
    assert applied == 2 and rb.stale_updates == 4
    np.testing.assert_array_equal(rb.priorities_of(old), [np.nan, np.nan, 2.0, 1.0])
    np.testing.assert_array_equal(rb.priorities_of(new), [1.0, 3.0])
    assert rb._tree.total == before_total + 1.0 + 2.0  # key 2: 1 -> 2, key 5: 1 -> 3
    assert rb.max_priority == 3.0  # stale priorities do not raise the max
    assert rb.update_priorities(np.array([], dtype=np.int64), np.array([])) == 0


def test_update_duplicates_last_wins():
    rb = InMemoryReplay(cartpole_spec(), 4, alpha=1.0, eps=0.0)
    k = rb.insert(cp_batch([0, 1]))
    assert rb.update_priorities(np.array([k[0], k[1], k[0]]), np.array([5.0, 2.0, 0.25])) == 3
    np.testing.assert_array_equal(rb.priorities_of(k), [0.25, 2.0])


@pytest.mark.parametrize(
    "keys, prio",
    [
        ([0], [np.nan]),
        ([0], [-1.0]),
        ([0], [np.inf]),
        ([0, 1], [1.0]),
        ([0.0], [1.0]),
        ([[0]], [1.0]),
    ],
)
def test_update_priorities_validation(keys, prio):
    rb = InMemoryReplay(cartpole_spec(), 4)
    rb.insert(cp_batch([0, 1]))
    with pytest.raises(ValueError):
        rb.update_priorities(np.array(keys), np.array(prio))


# ---------------------------------------------------------------- sampling
def test_sample_empty_raises():
    rb = InMemoryReplay(cartpole_spec(), 4)
    with pytest.raises(ReplayEmpty, match="empty"):
        rb.sample(2, 0.4)
    rbu = InMemoryReplay(cartpole_spec(), 4, uniform=True)
    with pytest.raises(ReplayEmpty):
        rbu.sample(2, 0.4)
    rb0 = InMemoryReplay(cartpole_spec(), 4, eps=0.0)
    rb0.insert(cp_batch([0]), priorities=np.zeros(1))
    with pytest.raises(ReplayEmpty, match="priority"):
        rb0.sample(1, 0.4)


@pytest.mark.parametrize("bs, beta", [(0, 0.4), (-1, 0.4), (2.0, 0.4), (2, -0.1), (2, float("nan"))])
def test_sample_argument_validation(bs, beta):
    rb = InMemoryReplay(cartpole_spec(), 4)
    rb.insert(cp_batch([0]))
    with pytest.raises(ValueError):
        rb.sample(bs, beta)


def test_sample_data_matches_keys_and_is_a_copy():
    rb = InMemoryReplay(cartpole_spec(), 50, seed=3)
    rb.insert(cp_batch(np.arange(80)), priorities=np.linspace(0.1, 5, 80))
    s = rb.sample(64, 0.5)
    assert isinstance(s, SampleBatch) and len(s) == 64
    assert s.keys.dtype == np.int64 and s.probabilities.dtype == np.float64 and s.weights.dtype == np.float32
    np.testing.assert_array_equal(s.data["action"], s.keys)
    np.testing.assert_array_equal(s.data["obs"], np.repeat(s.keys[:, None], 4, 1).astype(np.float32))
    assert s.data["obs"].shape == (64, 4) and s.data["terminated"].dtype == np.bool_
    assert np.all(s.keys >= 30)
    s.data["action"][:] = -7
    assert rb.sample(64, 0.5).data["action"].min() >= 30


def test_stratification_one_sample_per_segment():
    """16 equal items, B=4: segment j covers exactly items 4j..4j+3."""
    rb = InMemoryReplay(cartpole_spec(), 16, alpha=1.0, eps=0.0)
    rb.insert(cp_batch(np.arange(16)), priorities=np.full(16, 2.0))
    for seed in range(50):
        s = rb.sample(4, 0.4, rng=np.random.default_rng(seed))
        np.testing.assert_array_equal(s.keys // 4, np.arange(4))
    # Unequal priorities: segments of total/3 = 10 each: items {0}, {1,2}, {3}
    rb2 = InMemoryReplay(cartpole_spec(), 4, alpha=1.0, eps=0.0)
    rb2.insert(cp_batch(np.arange(4)), priorities=np.array([10.0, 4.0, 6.0, 10.0]))
    seen = set()
    for seed in range(100):
        s = rb2.sample(3, 0.0, rng=np.random.default_rng(seed))
        assert s.keys[0] == 0 and s.keys[1] in (1, 2) and s.keys[2] == 3
        seen.add(int(s.keys[1]))
    assert seen == {1, 2}


def test_probabilities_and_is_weights_by_hand():
    alpha, beta, eps = 0.7, 0.5, 0.0
    raw = np.array([1.0, 2.0, 3.0, 4.0])
    rb = InMemoryReplay(cartpole_spec(), 10, alpha=alpha, eps=eps)
    rb.insert(cp_batch(np.arange(4)), priorities=raw)
    s = rb.sample(8, beta, rng=np.random.default_rng(0))
    p_alpha = raw**alpha
    P = p_alpha / p_alpha.sum()
    np.testing.assert_allclose(s.probabilities, P[s.keys], rtol=1e-12)
    w = (4 * P[s.keys]) ** -beta
    np.testing.assert_allclose(s.weights, (w / w.max()).astype(np.float32), rtol=1e-6)
    assert s.weights.max() == 1.0
    assert np.all(rb.sample(8, 0.0, rng=np.random.default_rng(0)).weights == 1.0)


def test_sample_proportions_with_fixed_seed():
    rb = InMemoryReplay(cartpole_spec(), 8, alpha=0.5, eps=0.0, seed=0)
    raw = np.array([1.0, 4.0, 9.0, 16.0, 0.0, 25.0, 1.0, 4.0])
    rb.insert(cp_batch(np.arange(8)), priorities=raw)
    counts = np.zeros(8)
    rng = np.random.default_rng(7)
    for _ in range(500):
        counts += np.bincount(rb.sample(128, 0.4, rng=rng).keys, minlength=8)
    freq = counts / counts.sum()
    expected = np.sqrt(raw) / np.sqrt(raw).sum()
    np.testing.assert_allclose(freq, expected, atol=3e-3)
    assert counts[4] == 0


def test_uniform_mode():
    rb = InMemoryReplay(cartpole_spec(), 10, uniform=True, seed=0)
    keys = rb.insert(cp_batch(np.arange(13)), priorities=np.arange(13, dtype=np.float64))
    s = rb.sample(1000, 0.4)
    assert np.all((s.keys >= 3) & (s.keys < 13))
    np.testing.assert_array_equal(s.probabilities, np.full(1000, 0.1))
    np.testing.assert_array_equal(s.weights, np.ones(1000, np.float32))
    counts = np.bincount(s.keys - 3, minlength=10)
    assert counts.min() > 60 and counts.max() < 140
    assert rb.update_priorities(keys, np.ones(13)) == 10 and rb.stale_updates == 3
    np.testing.assert_array_equal(s.data["action"], s.keys)


def test_default_rng_is_seeded():
    a = InMemoryReplay(cartpole_spec(), 20, seed=5)
    b = InMemoryReplay(cartpole_spec(), 20, seed=5)
    for rb in (a, b):
        rb.insert(cp_batch(np.arange(20)), priorities=np.arange(20, dtype=np.float64))
    np.testing.assert_array_equal(a.sample(16, 0.4).keys, b.sample(16, 0.4).keys)


# ---------------------------------------------------------------- other specs
def test_uint8_image_spec():
    spec = image_spec()
    rb = InMemoryReplay(spec, 6, seed=0)
    rb.insert(make_batch(spec, np.arange(9)))
    s = rb.sample(5, 0.4)
    assert s.data["obs"].shape == (5, 84, 84, 4) and s.data["obs"].dtype == np.uint8
    np.testing.assert_array_equal(s.data["obs"][:, 0, 0, 0], s.keys % 251)
    np.testing.assert_array_equal(s.data["next_obs"][:, 83, 83, 3], s.keys % 251)
    assert s.data["obs"].flags.c_contiguous


def test_dict_obs_spec():
    spec = dict_obs_spec()
    assert {"obs/lidar", "obs/pose", "next_obs/lidar", "next_obs/pose"} <= set(spec)
    rb = InMemoryReplay(spec, 32, seed=0)
    rb.insert(make_batch(spec, np.arange(40)))
    s = rb.sample(8, 0.4)
    assert set(s.data) == set(spec)
    assert s.data["obs/lidar"].shape == (8, 360) and s.data["next_obs/pose"].shape == (8, 4)
    np.testing.assert_array_equal(s.data["obs/pose"][:, 2], s.keys.astype(np.float32))


# ---------------------------------------------------------------- state
def _check_plain(value, path="state"):
    if isinstance(value, dict):
        for k, v in value.items():
            assert isinstance(k, str), path
            _check_plain(v, f"{path}.{k}")
    else:
        assert isinstance(value, (np.ndarray, int, float, str, bool)), (path, type(value))
        if isinstance(value, np.ndarray):
            assert value.dtype != object, path


def _assert_same_sample(a: SampleBatch, b: SampleBatch):
    np.testing.assert_array_equal(a.keys, b.keys)
    assert a.probabilities.tobytes() == b.probabilities.tobytes()
    assert a.weights.tobytes() == b.weights.tobytes()
    assert a.data.keys() == b.data.keys()
    for k in a.data:
        assert a.data[k].tobytes() == b.data[k].tobytes()


@pytest.mark.parametrize("uniform", [False, True])
def test_state_dict_round_trip(uniform):
    spec = cartpole_spec()
    rng = np.random.default_rng(0)
    src = InMemoryReplay(spec, 37, alpha=0.6, uniform=uniform, seed=11)
    for i in range(6):
        ids = np.arange(i * 10, i * 10 + 10)
        b = cp_batch(ids)
        b["obs"] = rng.standard_normal((10, 4)).astype(np.float32)
        src.insert(b, priorities=rng.random(10) * 3)
        s = src.sample(16, 0.4, rng=rng)
        src.update_priorities(s.keys, rng.random(16) * 2)
    src.update_priorities(np.array([0, 1]), np.array([1.0, 1.0]))  # stale
    state = src.state_dict()
    _check_plain(state)

    dst = InMemoryReplay(spec, 37, alpha=0.6, uniform=uniform, seed=999)
    dst.load_state_dict(state)
    assert (dst.size, dst.inserts_total, dst.max_priority, dst.stale_updates) == (
        src.size, src.inserts_total, src.max_priority, src.stale_updates)
    if not uniform:
        assert src._tree.nodes().tobytes() == dst._tree.nodes().tobytes()
    for step in range(5):
        _assert_same_sample(src.sample(32, 0.5, rng=np.random.default_rng(step)),
                            dst.sample(32, 0.5, rng=np.random.default_rng(step)))
        _assert_same_sample(src.sample(32, 0.5), dst.sample(32, 0.5))  # internal rng restored
        ids = np.arange(100 + step * 3, 103 + step * 3)
        for rb in (src, dst):
            k = rb.insert(cp_batch(ids))
            rb.update_priorities(k, np.array([0.5, 1.5, 2.5]))
    # the state is a snapshot, not a view
    assert state["inserts_total"] == 60


def test_state_dict_of_empty_buffer():
    src = InMemoryReplay(image_spec(), 3, seed=1)
    dst = InMemoryReplay(image_spec(), 3)
    dst.insert(make_batch(image_spec(), np.arange(2)))
    dst.load_state_dict(src.state_dict())
    assert dst.size == 0 and dst.inserts_total == 0
    with pytest.raises(ReplayEmpty):
        dst.sample(1, 0.4)


def test_load_state_dict_incompatible():
    src = InMemoryReplay(cartpole_spec(), 8, alpha=0.6)
    src.insert(cp_batch(np.arange(3)))
    state = src.state_dict()
    other_spec = dict(cartpole_spec(), obs=ArraySpec((5,), "float32"))
    with pytest.raises(SpecMismatch):
        InMemoryReplay(other_spec, 8).load_state_dict(state)
    with pytest.raises(ValueError, match="capacity"):
        InMemoryReplay(cartpole_spec(), 9).load_state_dict(state)
    with pytest.raises(ValueError, match="alpha"):
        InMemoryReplay(cartpole_spec(), 8, alpha=0.5).load_state_dict(state)
    with pytest.raises(ValueError, match="uniform"):
        InMemoryReplay(cartpole_spec(), 8, uniform=True).load_state_dict(state)
    with pytest.raises(ValueError, match="format"):
        InMemoryReplay(cartpole_spec(), 8).load_state_dict(dict(state, format="nope"))
    bad = dict(state, data=dict(state["data"], obs=state["data"]["obs"][:2]))
    dst = InMemoryReplay(cartpole_spec(), 8)
    with pytest.raises(SpecMismatch):
        dst.load_state_dict(bad)
    assert dst.size == 0  # untouched on failure


def test_sample_into_preallocated_out():
    spec = image_spec()
    rb = InMemoryReplay(spec, 8, seed=0)
    rb.insert(make_batch(spec, np.arange(8)), priorities=np.arange(1, 9, dtype=np.float64))
    out = {k: np.empty((5, *s.shape), s.dtype) for k, s in spec.items()}
    ref = rb.sample(5, 0.4, rng=np.random.default_rng(3))
    got = rb.sample(5, 0.4, rng=np.random.default_rng(3), out=out)
    _assert_same_sample(ref, got)
    assert all(got.data[k] is out[k] for k in spec)
    bad = dict(out, obs=np.empty((4, 84, 84, 4), np.uint8))
    with pytest.raises(SpecMismatch):
        rb.sample(5, 0.4, out=bad)
    with pytest.raises(SpecMismatch):
        rb.sample(5, 0.4, out=dict(out, reward=np.empty(5, np.float64)))
    with pytest.raises(SpecMismatch):
        rb.sample(5, 0.4, out={"obs": out["obs"]})
