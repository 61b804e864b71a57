"""SumTree against a brute-force numpy reference (property-based, deterministic)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from zenrl.replay.sumtree import SumTree

SETTINGS = settings(derandomize=True, max_examples=40, deadline=None)

#: top_levels values exercising pure descent (0), a mix (3) and pure searchsorted (64)
TOPS = pytest.mark.parametrize("top", [0, 3, 64])


def _apply_reference(leaves: np.ndarray, idx: list[int], vals: list[float]) -> None:
    for i, v in zip(idx, vals):  # sequential: last write wins
        leaves[i] = v


@st.composite
def tree_and_updates(draw, max_capacity: int = 300, integer: bool = True):
    cap = draw(st.integers(1, max_capacity))
    n_batches = draw(st.integers(1, 6))
    batches = []
    for _ in range(n_batches):
        k = draw(st.integers(0, 40))
        idx = draw(st.lists(st.integers(0, cap - 1), min_size=k, max_size=k))
        if integer:
            vals = draw(st.lists(st.integers(0, 100).map(float), min_size=k, max_size=k))
        else:
            vals = draw(st.lists(st.floats(0.0, 1e3, allow_nan=False), min_size=k, max_size=k))
        batches.append((idx, vals))
    return cap, batches


@TOPS
@SETTINGS
@given(tree_and_updates())
def test_batched_updates_match_reference(top, case):
    cap, batches = case
    tree = SumTree(cap, top_levels=top)
    ref = np.zeros(cap)
    for idx, vals in batches:
        tree.update(np.array(idx, dtype=np.int64), np.array(vals, dtype=np.float64))
        _apply_reference(ref, idx, vals)
        # integer-valued leaves: every partial sum is exact
        assert tree.total == ref.sum()
        np.testing.assert_array_equal(tree.leaves, ref)
    if cap > 0:
        np.testing.assert_array_equal(tree.get(np.arange(cap)), ref)


@TOPS
@SETTINGS
@given(tree_and_updates(integer=False))
def test_tree_is_pure_function_of_leaves(top, case):
    """Incremental updates and a rebuild from the leaves give bitwise the same nodes."""
    cap, batches = case
    tree = SumTree(cap, top_levels=top)
    for idx, vals in batches:
        tree.update(np.array(idx, dtype=np.int64), np.array(vals, dtype=np.float64))
    rebuilt = SumTree(cap, top_levels=top)
    rebuilt.set_leaves(tree.leaves.copy())
    np.testing.assert_array_equal(tree.nodes(), rebuilt.nodes())
    assert tree.total == rebuilt.total
    np.testing.assert_allclose(tree.total, np.sum(tree.leaves), rtol=1e-12)


@TOPS
@SETTINGS
@given(st.integers(1, 200), st.integers(0, 199), st.integers(0, 50), st.integers(0, 2**31 - 1))
def test_set_range_equals_update(top, cap, start, n, seed):
    start = start % cap
    n = min(n, cap - start)
    rng = np.random.default_rng(seed)
    base = rng.random(cap)
    vals = rng.random(n)
    a, b = SumTree(cap, top_levels=top), SumTree(cap, top_levels=0)
    a.set_leaves(base)
    b.set_leaves(base)
    a.set_range(start, vals)
    b.update(np.arange(start, start + n), vals)
    np.testing.assert_array_equal(a.nodes(), b.nodes())


@TOPS
@SETTINGS
@given(tree_and_updates(), st.lists(st.floats(-10.0, 1e5, allow_nan=False), min_size=1, max_size=64))
def test_find_prefix_sum_matches_searchsorted(top, case, raw_targets):
    cap, batches = case
    tree = SumTree(cap, top_levels=top)
    ref = np.zeros(cap)
    for idx, vals in batches:
        tree.update(np.array(idx, dtype=np.int64), np.array(vals, dtype=np.float64))
        _apply_reference(ref, idx, vals)
    if ref.sum() == 0:
        with pytest.raises(ValueError):
            tree.find_prefix_sum(np.array(raw_targets))
        return
    total = ref.sum()
    targets = np.array(raw_targets) % (total * 1.25)  # includes targets >= total (clipped)
    got = tree.find_prefix_sum(targets)
    clipped = np.clip(targets, 0.0, np.nextafter(total, -np.inf))
    expected = np.searchsorted(np.cumsum(ref), clipped, side="right")
    np.testing.assert_array_equal(got, expected)
    assert got.dtype == np.int64
    assert np.all(ref[got] > 0)  # never a zero leaf


@TOPS
@SETTINGS
@given(tree_and_updates(integer=False), st.integers(0, 2**31 - 1))
def test_find_prefix_sum_float_leaves_within_rounding(top, case, seed):
    cap, batches = case
    tree = SumTree(cap, top_levels=top)
    for idx, vals in batches:
        tree.update(np.array(idx, dtype=np.int64), np.array(vals, dtype=np.float64))
    leaves = tree.leaves.copy()
    if tree.total == 0:
        return
    rng = np.random.default_rng(seed)
    targets = np.concatenate([rng.random(100) * tree.total, [0.0, tree.total, np.nextafter(tree.total, 0)]])
    got = tree.find_prefix_sum(targets)
    assert np.all((got >= 0) & (got < cap))
    assert np.all(leaves[got] > 0)
    cs = np.cumsum(leaves)
    before = np.where(got > 0, cs[np.maximum(got - 1, 0)], 0.0)
    tol = 1e-9 * tree.total
    t = np.clip(targets, 0.0, np.nextafter(tree.total, -np.inf))
    assert np.all(before - tol <= t) and np.all(t < cs[got] + tol)


def test_guarded_descent_skips_zero_subtrees():
    tree = SumTree(10, top_levels=1)  # padded to 16 leaves
    tree.update(np.array([0, 3, 7]), np.array([1.0, 0.0, 2.0]))
    # Targets past the total would walk into padding without the guard.
    got = tree._guarded_descent(np.array([0.0, 0.5, 1.0, 2.9, 3.0, 100.0]))
    np.testing.assert_array_equal(got, [0, 0, 7, 7, 7, 7])
    np.testing.assert_array_equal(tree.find_prefix_sum(np.array([100.0, 3.0, -1.0])), [7, 7, 0])


@TOPS
def test_zero_leaves_never_returned(top):
    tree = SumTree(7, top_levels=top)
    tree.update(np.arange(7), np.array([0.0, 3.0, 0.0, 0.0, 2.0, 0.0, 0.0]))
    t = np.linspace(0, 5, 1001)
    got = tree.find_prefix_sum(t)
    assert set(np.unique(got).tolist()) == {1, 4}
    np.testing.assert_array_equal(got, np.where(t < 3.0, 1, 4))


@TOPS
def test_sampling_proportions(top):
    rng = np.random.default_rng(1234)
    p = np.array([1.0, 2.0, 3.0, 4.0, 0.0, 10.0])
    tree = SumTree(len(p), top_levels=top)
    tree.update(np.arange(len(p)), p)
    n = 200_000
    idx = tree.find_prefix_sum(rng.random(n) * tree.total)
    freq = np.bincount(idx, minlength=len(p)) / n
    expected = p / p.sum()
    # standard error <= sqrt(.25/n) ~ 1.1e-3; 5 sigma
    np.testing.assert_allclose(freq, expected, atol=6e-3)
    assert freq[4] == 0
    chi2 = np.sum((freq[p > 0] - expected[p > 0]) ** 2 / expected[p > 0]) * n
    assert chi2 < 25.0  # 4 dof; p-value ~ 5e-5


def test_capacity_one_and_power_of_two():
    t1 = SumTree(1)
    t1.update(np.array([0]), np.array([2.5]))
    assert t1.total == 2.5 and t1.depth == 0
    np.testing.assert_array_equal(t1.find_prefix_sum(np.array([0.0, 2.4, 9.0])), [0, 0, 0])
    t8 = SumTree(8)
    assert t8.depth == 3
    t8.update(np.arange(8), np.ones(8))
    np.testing.assert_array_equal(t8.find_prefix_sum(np.arange(8) + 0.5), np.arange(8))


def test_duplicates_last_write_wins():
    tree = SumTree(4)
    tree.update(np.array([1, 2, 1, 1, 2]), np.array([5.0, 6.0, 7.0, 8.0, 0.5]))
    np.testing.assert_array_equal(tree.leaves, [0.0, 8.0, 0.5, 0.0])
    assert tree.total == 8.5
    tree.update(np.array([3]), 2.0)  # scalar broadcast
    assert tree.get(3) == 2.0 and tree.total == 10.5


def test_validation():
    for bad in (0, -3, 1.5, True, "4"):
        with pytest.raises(ValueError):
            SumTree(bad)  # type: ignore[arg-type]
    for bad in (-1, 2.0, None):
        with pytest.raises(ValueError, match="top_levels"):
            SumTree(4, top_levels=bad)  # type: ignore[arg-type]
    tree = SumTree(4)
    with pytest.raises(IndexError):
        tree.update(np.array([4]), np.array([1.0]))
    with pytest.raises(IndexError):
        tree.update(np.array([-1]), np.array([1.0]))
    for v in (-1.0, np.nan, np.inf):
        with pytest.raises(ValueError):
            tree.update(np.array([0]), np.array([v]))
    with pytest.raises(ValueError, match="total is 0"):
        tree.find_prefix_sum(np.array([0.0]))
    with pytest.raises(IndexError):
        tree.get(7)
    with pytest.raises(ValueError):
        tree.set_leaves(np.ones(3))
    with pytest.raises(IndexError):
        tree.set_range(3, np.ones(2))
    tree.update(np.array([], dtype=np.int64), np.array([]))  # no-op
    assert tree.total == 0.0


def test_large_tree_against_reference():
    """A 2**16-leaf tree with random float updates, default top_levels (mixed path)."""
    rng = np.random.default_rng(5)
    cap = 50_000
    tree = SumTree(cap)
    ref = np.zeros(cap)
    for _ in range(20):
        idx = rng.integers(0, cap, 2000)
        vals = rng.integers(0, 1000, 2000).astype(np.float64)
        tree.update(idx, vals)
        uniq, first = np.unique(idx[::-1], return_index=True)
        ref[uniq] = vals[::-1][first]
    start = 49_000
    tree.set_range(start, np.arange(1000, dtype=np.float64))
    ref[start:] = np.arange(1000)
    assert tree.total == ref.sum()
    rebuilt = SumTree(cap)
    rebuilt.set_leaves(ref)
    np.testing.assert_array_equal(tree.nodes(), rebuilt.nodes())
    t = rng.random(4096) * tree.total
    np.testing.assert_array_equal(tree.find_prefix_sum(t), np.searchsorted(np.cumsum(ref), t, side="right"))
