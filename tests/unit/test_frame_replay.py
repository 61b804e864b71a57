"""FrameReplay (frames stored once) against a brute-force reference.

A simulated actor steps E envs with random episode lengths ending in termination or truncation,
builds n-step transitions over k-frame stacks (reset padding repeats the first frame, as
gymnasium's FrameStackObservation does) and sends chunks of new frames + frame ids. Every frame
is unique, so a wrong frame anywhere is seen. The reference keeps the full obs/next_obs arrays of
every transition and decides by brute force which transitions must be stored: those whose ids
resolved when they arrived, minus the ring's FIFO eviction (the transition capacity, and every
transition at or before one that references an overwritten frame).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from zenrl.common.errors import SpecMismatch
from zenrl.common.specs import ArraySpec
from zenrl.replay.frames import FrameChunk, FrameReplay, InsertResult

CAM = (2, 3)


class Counter:
    def __init__(self) -> None:
        self.u = 0

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        self.u += 1
        u = self.u
        cam = np.frombuffer(np.array([u], "<u4").tobytes() + bytes([u % 7, u % 11]), np.uint8).reshape(CAM)
        return cam, np.array([u, u + 0.5], np.float32)


class SimActor:
    """One actor: E envs stepped together; chunks every ``chunk_steps`` steps."""

    def __init__(self, name: str, rng: np.random.Generator, counter: Counter, E: int, n: int, k: int,
                 chunk_steps: int, max_len: int) -> None:
        self.name, self.rng, self.c = name, rng, counter
        self.E, self.n, self.k, self.chunk_steps, self.max_len = E, n, k, chunk_steps, max_len
        self.next_id = 0
        self.frames: list[tuple[np.ndarray, np.ndarray]] = []  # by id
        self.sent = 0  # frames sent so far (ids < sent)
        self.envs = [self._reset() for _ in range(E)]
        self.pending: list[dict] = []
        self.t = 0

    def _new(self) -> int:
        self.frames.append(self.c.frame())
        self.next_id += 1
        return self.next_id - 1

    def _reset(self) -> dict:
        f = self._new()
        length = int(self.rng.integers(1, self.max_len + 1))
        return {"stacks": [[f] * max(self.k, 1)], "len": length, "term": bool(self.rng.random() < 0.5),
                "acts": [], "rews": []}

    def _stack(self, ids: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ids_a = np.array(ids, np.int64)
        cam = np.stack([self.frames[i][0] for i in ids])
        vec = np.stack([self.frames[i][1] for i in ids])
        if not self.k:
            return ids_a[0], cam[0], vec[0]
        return ids_a, cam, vec

    def step(self) -> None:
        for e in range(self.E):
            env = self.envs[e]
            env["acts"].append(int(self.rng.integers(0, 5)))
            env["rews"].append(float(self.rng.integers(-3, 4)))
            f = self._new()
            env["stacks"].append(env["stacks"][-1][1:] + [f] if self.k else [f])
            steps = len(env["acts"])
            done = steps == env["len"]
            # every start j whose window of min(n, len - j) steps is complete
            for j in range(steps):
                m = min(self.n, env["len"] - j)
                if j + m == steps and j not in env.setdefault("emitted", set()):
                    env["emitted"].add(j)
                    ended = j + m == env["len"]
                    self.pending.append({"obs": env["stacks"][j], "next": env["stacks"][j + m],
                                         "action": env["acts"][j], "reward": sum(env["rews"][j:j + m]),
                                         "terminated": ended and env["term"], "truncated": ended and not env["term"]})
            if done:
                self.envs[e] = self._reset()
        self.t += 1

    def chunk(self) -> dict | None:
        """New frames since the last chunk and the transitions completed since."""
        if self.t % self.chunk_steps:
            return None
        base = self.sent
        ids = range(base, self.next_id)
        self.sent = self.next_id
        trs, self.pending = self.pending, []
        B = len(trs)
        frames = {"obs/cam": np.array([self.frames[i][0] for i in ids], np.uint8).reshape((len(ids), *CAM)),
                  "obs/vec": np.array([self.frames[i][1] for i in ids], np.float32).reshape((len(ids), 2))}
        refs, naive = {}, {}
        for field, key in (("obs", "obs"), ("next_obs", "next")):
            st_ = [self._stack(t[key]) for t in trs]
            shape_ids = (B, self.k) if self.k else (B,)
            refs[f"{field}/cam"] = np.array([s[0] for s in st_], np.int64).reshape(shape_ids)
            refs[f"{field}/vec"] = refs[f"{field}/cam"].copy()
            cam_shape = (B, self.k, *CAM) if self.k else (B, *CAM)
            vec_shape = (B, self.k, 2) if self.k else (B, 2)
            naive[f"{field}/cam"] = np.array([s[1] for s in st_], np.uint8).reshape(cam_shape)
            naive[f"{field}/vec"] = np.array([s[2] for s in st_], np.float32).reshape(vec_shape)
        batch = {"action": np.array([t["action"] for t in trs], np.int64).reshape(B),
                 "reward": np.array([t["reward"] for t in trs], np.float32).reshape(B),
                 "terminated": np.array([t["terminated"] for t in trs], bool).reshape(B),
                 "truncated": np.array([t["truncated"] for t in trs], bool).reshape(B)}
        return {"stream": self.name, "base": base, "frames": frames, "refs": refs, "batch": batch,
                "naive": {**batch, **naive}}


def make_store(k: int, capacity: int, frames_per_item: float, uniform: bool = True) -> FrameReplay:
    item = {"action": ArraySpec((), "int64"), "reward": ArraySpec((), "float32"),
            "terminated": ArraySpec((), "bool"), "truncated": ArraySpec((), "bool")}
    frames = {"obs/cam": ArraySpec(CAM, "uint8"), "obs/vec": ArraySpec((2,), "float32")}
    refs = {f: k for f in ("obs/cam", "next_obs/cam", "obs/vec", "next_obs/vec")}
    return FrameReplay(item, frames, refs, capacity, frames_per_item=frames_per_item, uniform=uniform, seed=0)


class Reference:
    """Brute force: every transition ever stored with its global frame keys and full data."""

    def __init__(self, capacity: int, fcap: int) -> None:
        self.cap, self.fcap = capacity, fcap
        self.frames_total = 0
        self.chunks: dict[str, list[tuple[int, int, int]]] = {}  # stream -> (base, count, gbase)
        self.items: list[tuple[list[int], dict]] = []  # by key: (global frame keys, data)
        self.dropped = 0

    def insert(self, c: dict) -> None:
        F = c["frames"]["obs/cam"].shape[0]
        hist = self.chunks.setdefault(c["stream"], [])
        if F:
            hist.append((c["base"], F, self.frames_total))
            self.frames_total += F
        floor = self.frames_total - self.fcap

        def glob(i: int) -> int | None:
            for base, cnt, gb in hist:
                if base <= i < base + cnt and gb + i - base >= floor:
                    return gb + i - base
            return None

        B = c["batch"]["action"].shape[0]
        for r in range(B):
            ids = [int(x) for f in ("obs/cam", "next_obs/cam") for x in np.atleast_1d(c["refs"][f][r])]
            g = [glob(i) for i in ids]
            if any(x is None for x in g):
                self.dropped += 1
                continue
            self.items.append((g, {k: v[r] for k, v in c["naive"].items()}))

    def live(self) -> dict[int, dict]:
        total = len(self.items)
        lo = max(0, total - self.cap)
        floor = self.frames_total - self.fcap
        for key, (g, _) in enumerate(self.items):
            if min(g) < floor:
                lo = max(lo, key + 1)
        return {key: self.items[key][1] for key in range(lo, total)}


def run_stream(seed: int, n_actors: int, E: int, n: int, k: int, chunk_steps: int, max_len: int, steps: int,
               capacity: int, frames_per_item: float, lose: float = 0.0, check_every: int = 1,
               max_group: int = 1) -> tuple[FrameReplay, Reference]:
    """``max_group`` > 1: chunks go in through ``insert_many`` in groups of 1..max_group (as the
    service's ingest batches them), against the same one-chunk-at-a-time reference."""
    rng = np.random.default_rng(seed)
    counter = Counter()
    actors = [SimActor(f"a{i}", rng, counter, E, n, k, chunk_steps, max_len) for i in range(n_actors)]
    store = make_store(k, capacity, frames_per_item)
    ref = Reference(store.capacity, store.frame_capacity)
    inserted = 0
    pending: list[dict] = []
    want = 1

    def flush() -> None:
        nonlocal inserted, want
        if max_group == 1:
            c = pending[0]
            try:
                results = [store.insert(c["stream"], c["base"], c["frames"], c["batch"], c["refs"])]
            except SpecMismatch as e:
                results = [e]
        else:
            # with the ids' bounds given, as the service's ingest gives the decode's (found here
            # by plain Python, not numpy); one chunk at a time, the replay finds them itself
            results = store.insert_many([FrameChunk(c["stream"], c["base"], c["frames"], c["batch"], c["refs"],
                                                    bounds={f: (min(v.flat), max(v.flat)) for f, v in c["refs"].items() if v.size})
                                         for c in pending])
        assert len(results) == len(pending)
        for c, res in zip(pending, results):
            if c["frames"]["obs/cam"].shape[0] > store.frame_capacity:
                assert isinstance(res, SpecMismatch) and "does not fit" in str(res)
                continue  # refused whole, as if lost
            assert isinstance(res, InsertResult), res
            before, first = ref.dropped, len(ref.items)
            ref.insert(c)
            inserted += 1
            assert res.dropped == ref.dropped - before
            assert res.keys.tolist() == list(range(first, len(ref.items)))  # a key is a reference item index
            if inserted % check_every == 0 and max_group == 1:
                check_equal(store, ref, rng)
        assert store.unresolved == ref.dropped
        pending.clear()
        want = int(rng.integers(1, max_group + 1))
        if max_group > 1:
            check_equal(store, ref, rng)

    for _ in range(steps):
        for a in rng.permutation(n_actors):  # actors interleave in random order
            actors[a].step()
            c = actors[a].chunk()
            if c is None:
                continue
            if lose and rng.random() < lose:
                continue  # lost on the way: later chunks' references into it must not resolve
            pending.append(c)
            if len(pending) >= want:
                flush()
    if pending:
        flush()
    check_equal(store, ref, rng)
    return store, ref


def check_equal(store: FrameReplay, ref: Reference, rng: np.random.Generator) -> None:
    live = ref.live()
    assert store.size == len(live)
    all_keys = np.arange(len(ref.items), dtype=np.int64)
    stored = ~np.isnan(store.priorities_of(all_keys))
    assert set(all_keys[stored].tolist()) == set(live)
    if not live:
        return
    s = store.sample(64, 0.4, rng)
    for i, key in enumerate(s.keys.tolist()):
        want = live[key]
        for f, v in want.items():
            np.testing.assert_array_equal(s.data[f][i], v, err_msg=f"key {key} field {f}")


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31), n_actors=st.integers(1, 3), E=st.integers(1, 3), n=st.integers(1, 4),
       k=st.sampled_from([0, 1, 4]), chunk_steps=st.integers(1, 5), max_len=st.integers(1, 12),
       capacity=st.integers(4, 60), fpi=st.sampled_from([0.6, 1.0, 1.5, 3.0]), lose=st.sampled_from([0.0, 0.2]))
def test_matches_brute_force(seed, n_actors, E, n, k, chunk_steps, max_len, capacity, fpi, lose):
    run_stream(seed, n_actors, E, n, k, chunk_steps, max_len, steps=40, capacity=capacity,
               frames_per_item=fpi, lose=lose)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31), n_actors=st.integers(1, 3), E=st.integers(1, 3), n=st.integers(1, 4),
       k=st.sampled_from([0, 1, 4]), chunk_steps=st.integers(1, 5), max_len=st.integers(1, 12),
       capacity=st.integers(4, 60), fpi=st.sampled_from([0.6, 1.0, 1.5, 3.0]), lose=st.sampled_from([0.0, 0.2]),
       max_group=st.integers(2, 12))
def test_insert_many_matches_one_at_a_time(seed, n_actors, E, n, k, chunk_steps, max_len, capacity, fpi, lose, max_group):
    """Groups of chunks (in tiny rings: later chunks of a group overwrite frames that earlier
    ones reference) give the keys, drops and stored transitions of one insert per chunk."""
    run_stream(seed, n_actors, E, n, k, chunk_steps, max_len, steps=40, capacity=capacity,
               frames_per_item=fpi, lose=lose, max_group=max_group)


def test_insert_many_wraps_many_times_and_stays_exact():
    store, ref = run_stream(4, 3, 2, 3, 4, chunk_steps=1, max_len=9, steps=300, capacity=50,
                            frames_per_item=1.2, max_group=16)
    assert store.inserts_total > 10 * store.capacity and store.evicted_by_frames > 0


def test_insert_many_refuses_only_the_bad_chunk():
    store = make_store(0, 100, 2.0)
    cam = np.zeros((2, *CAM), np.uint8)
    vec = np.zeros((2, 2), np.float32)
    one = {"action": np.zeros(1, np.int64), "reward": np.zeros(1, np.float32),
           "terminated": np.zeros(1, bool), "truncated": np.zeros(1, bool)}
    refs = {"obs/cam": np.array([0]), "next_obs/cam": np.array([1]), "obs/vec": np.array([0]), "next_obs/vec": np.array([1])}
    good = FrameChunk("a", 0, {"obs/cam": cam, "obs/vec": vec}, one, refs)
    bad_dtype = FrameChunk("b", 0, {"obs/cam": cam, "obs/vec": vec}, {**one, "reward": np.zeros(1, np.float64)}, refs)
    bad_prio = FrameChunk("c", 0, {"obs/cam": cam, "obs/vec": vec}, one, refs, np.array([np.nan]))
    bad_base = FrameChunk("d", -1, {"obs/cam": cam, "obs/vec": vec}, one, refs)
    later = FrameChunk("a", 2, {"obs/cam": cam, "obs/vec": vec}, one, {f: v + 2 for f, v in refs.items()})
    res = store.insert_many([good, bad_dtype, bad_prio, bad_base, later])
    assert isinstance(res[1], SpecMismatch) and "reward" in str(res[1])
    assert isinstance(res[2], ValueError) and "finite" in str(res[2])
    assert isinstance(res[3], ValueError) and "frame_base" in str(res[3])
    assert res[0].keys.tolist() == [0] and res[4].keys.tolist() == [1]
    assert store.frames_total == 4 and store.size == 2  # the refused chunks stored no frame


def test_ring_wraps_many_times_and_stays_exact():
    store, ref = run_stream(1, 2, 4, 3, 4, chunk_steps=2, max_len=9, steps=300, capacity=50,
                            frames_per_item=1.2, check_every=7)
    assert store.inserts_total > 10 * store.capacity
    assert store.frames_total > 10 * store.frame_capacity


def test_frames_stored_once():
    """With a stack of 4 and n = 3 each transition costs about one frame, not eight."""
    store, ref = run_stream(2, 2, 4, 3, 4, chunk_steps=4, max_len=200, steps=200, capacity=100_000,
                            frames_per_item=1.0, check_every=50)
    assert store.frames_total < 1.05 * store.inserts_total + 2 * 2 * 4 * 3


def test_too_small_frame_ring_bounds_the_store():
    store, ref = run_stream(3, 1, 2, 3, 4, chunk_steps=2, max_len=3, steps=100, capacity=40,
                            frames_per_item=0.5, check_every=5)
    assert store.evicted_by_frames > 0 and 0 < store.size < store.capacity


def test_actor_restart_ids_go_backwards():
    store = make_store(0, 100, 2.0)
    cam = np.zeros((3, *CAM), np.uint8)
    cam[:, 0, 0] = [1, 2, 3]
    vec = np.zeros((3, 2), np.float32)
    one = {"action": np.zeros(1, np.int64), "reward": np.zeros(1, np.float32),
           "terminated": np.zeros(1, bool), "truncated": np.zeros(1, bool)}
    refs = {"obs/cam": np.array([0]), "next_obs/cam": np.array([2]), "obs/vec": np.array([0]), "next_obs/vec": np.array([2])}
    store.insert("a", 0, {"obs/cam": cam, "obs/vec": vec}, one, refs)
    # the restarted actor numbers from 0 again; its id 5 must not resolve into the old chunk
    cam2 = cam.copy()
    cam2[:, 0, 0] = [7, 8, 9]
    late = {f: np.array([5]) for f in refs}
    r = store.insert("a", 0, {"obs/cam": cam2, "obs/vec": vec}, one, {**refs, "next_obs/cam": np.array([5])})
    assert r.dropped == 1 and store.unresolved == 1
    r = store.insert("a", 3, {"obs/cam": cam2, "obs/vec": vec}, one, refs)  # ids 0 and 2 of the new run
    assert r.keys.tolist() == [1]
    s = store.sample(64, 0.4, np.random.default_rng(0))
    got = {int(k): (int(o[0, 0]), int(x[0, 0])) for k, o, x in zip(s.keys, s.data["obs/cam"], s.data["next_obs/cam"])}
    assert got == {0: (1, 3), 1: (7, 9)}
    # ids of another actor are never looked up
    r = store.insert("b", 0, {"obs/cam": cam[:0], "obs/vec": vec[:0]}, one, late)
    assert r.dropped == 1


def test_rejects_mismatched_chunks_without_storing():
    store = make_store(4, 10, 1.0)
    one = {"action": np.zeros(1, np.int64), "reward": np.zeros(1, np.float32),
           "terminated": np.zeros(1, bool), "truncated": np.zeros(1, bool)}
    frames = {"obs/cam": np.zeros((1, *CAM), np.uint8), "obs/vec": np.zeros((1, 2), np.float32)}
    refs = {f: np.zeros((1, 4), np.int64) for f in ("obs/cam", "next_obs/cam", "obs/vec", "next_obs/vec")}
    with pytest.raises(SpecMismatch, match="frame ids obs/cam"):
        store.insert("a", 0, frames, one, {**refs, "obs/cam": np.zeros((1, 3), np.int64)})
    with pytest.raises(SpecMismatch, match="frames obs/cam"):
        store.insert("a", 0, {**frames, "obs/cam": np.zeros((1, 3, 3), np.uint8)}, one, refs)
    with pytest.raises(SpecMismatch, match="does not fit"):
        store.insert("a", 0, {k: np.concatenate([v] * 11) for k, v in frames.items()}, one, refs)
    with pytest.raises(ValueError, match="priorities"):
        store.insert("a", 0, frames, one, refs, priorities=np.array([-1.0]))
    assert store.frames_total == 0 and store.size == 0
    store.insert("a", 0, frames, one, refs)
    assert store.size == 1


def test_the_columns_fast_check_refuses_what_the_full_check_does_with_its_words():
    """A chunk's columns are compared without building the gkey columns its ids become; every
    way a chunk can be wrong there is refused with the full check's message, and a good chunk
    gets its batch size."""
    store = make_store(4, 10, 1.0)
    one = {"action": np.zeros(2, np.int64), "reward": np.zeros(2, np.float32),
           "terminated": np.zeros(2, bool), "truncated": np.zeros(2, bool)}
    refs = {f: np.zeros((2, 4), np.int64) for f in ("obs/cam", "next_obs/cam", "obs/vec", "next_obs/vec")}
    assert store._batch_size(one, refs) == 2
    wrong = [
        ({**one, "reward": np.zeros(2, np.float64)}, refs, "field 'reward' has dtype float64"),
        ({**one, "reward": np.zeros((2, 1), np.float32)}, refs, "field 'reward' has shape (2, 1)"),
        ({**one, "reward": [0.0, 0.0]}, refs, "field 'reward' must be a numpy array"),
        ({**one, "reward": np.zeros(3, np.float32)}, refs, "field 'reward' has batch size 3"),
        ({k: v for k, v in one.items() if k != "reward"}, refs, "missing ['reward']"),
        ({**one, "extra": np.zeros(2)}, refs, "unexpected ['extra']"),
        (one, {**refs, "next_obs/vec": np.zeros((3, 4), np.int64)}, "field 'frame_keys/next_obs/vec' has batch size 3"),
    ]
    for batch, r, words in wrong:
        with pytest.raises(SpecMismatch) as fast:
            store._batch_size(batch, r)
        with pytest.raises(SpecMismatch) as full:
            store._full_batch_size(batch, r)
        assert str(fast.value) == str(full.value) and words in str(fast.value), (str(fast.value), words)
