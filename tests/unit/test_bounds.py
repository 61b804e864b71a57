"""Bounds on everything a peer declares (issue #32, items 1, 3, 4), by class rather than by
example: integer fields at the edges of their types, shapes whose product overflows or that hide
huge dimensions behind a zero, compressed arrays whose declared size is a lie or does not fit
the receiver's spec, frame ids at the edge of int64. Decoding any of them raises ProtocolError or
accepts cleanly; the replay's ingest rejects them by reason and never counts an internal error;
the ingest queue and the decoded data it holds are bounded in bytes; the quarantine's memory is
bounded and it never stops quarantining; a stalled ingest thread is what the health check sees."""

from __future__ import annotations

import math
import queue
import threading
import time

import lz4.block
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.quarantine import MAX_LINE, Quarantine, SourceLedger, TopCounter
from zenrl.common.roles import Supervisor
from zenrl.health import judge
from zenrl.replay.checks import ChunkChecker, ObsRule
from zenrl.replay.service import ReplayService

from tests.unit.inbox_fake import FakeInbox

B = 8
#: what msgpack can carry: -2^63 .. 2^64-1, with the edges of every integer type
EDGE_INTS = st.one_of(
    st.sampled_from([-(1 << 63), -(1 << 62), -(1 << 31) - 1, -2, -1, 0, 1, 2, (1 << 31) - 1, 1 << 31, 1 << 32,
                     (1 << 62) - 1, 1 << 62, (1 << 63) - 1, 1 << 63, (1 << 64) - 1]),
    st.integers(-(1 << 63), (1 << 64) - 1))
FAST = settings(max_examples=150, deadline=None, database=None, derandomize=True,
                suppress_health_check=list(HealthCheck))


def _f32(*shape):
    return np.zeros(shape, np.float32)


def _samples() -> dict[str, P.Message]:
    """One valid message of each type (A3C gradients, IMPALA unrolls, R2D2 sequences travel as
    transitions too, frame-mode chunks)."""
    T = 3
    seq = {"obs": _f32(B, 5, 4), "action": np.zeros((B, 4), np.int64), "reward": _f32(B, 4),
           "terminated": np.zeros((B, 4), bool), "truncated": np.zeros((B, 4), bool), "mask": np.ones((B, 4), bool),
           "first": np.zeros(B, bool), "h": _f32(B, 2), "c": _f32(B, 2)}
    frames_data = {"obs": np.arange(B, dtype=np.int64), "next_obs": np.arange(1, B + 1, dtype=np.int64),
                   "action": np.zeros(B, np.int64), "reward": _f32(B), "n": np.ones(B, np.uint8),
                   "terminated": np.zeros(B, bool), "truncated": np.zeros(B, bool)}
    return {
        "transitions": P.TransitionBatch("a0", 3, 4, _plain()),
        "sequences": P.TransitionBatch("a0", 3, 4, seq, np.ones(B, np.float32)),
        "frames": P.TransitionBatch("a0", 3, 4, frames_data, frames={"obs": np.zeros((B + 1, 3, 3), np.uint8)},
                                    frame_base=0),
        "sample_request": P.SampleRequest(1, 32, 0.4),
        "sample_reply": P.SampleReply(1, "ok", "", 10, np.arange(2, dtype=np.int64), np.ones(2), np.ones(2, np.float32),
                                      {"x": _f32(2, 3)}),
        "priorities": P.PriorityUpdate(np.arange(3, dtype=np.int64), np.ones(3, np.float32)),
        "weights": P.Weights(5, "learner", "arch", 7, {"w": _f32(2, 2)}),
        "gradients": P.Gradients("w0", 5, 20, {"w": _f32(2, 2)}),
        "episodes": P.EpisodeStats("a0", 0, 0.1, 5, 100, _f32(2), np.ones(2, np.int64)),
        "eval": P.EvalResult(5, 7, _f32(2), np.zeros(2, np.int8)),
        "stats": P.Stats("replay", "replay", 1.0, {"n": 3, "s": "x"}),
        "unroll": P.Unroll("a0", 2, 9, {"obs": _f32(T + 1, 4)}, np.zeros(T, np.int64), np.full(T, -0.5, np.float32),
                           _f32(T), np.zeros(T, bool), np.zeros(T, bool), None, _f32(T, 2)),
        "opponent_request": P.OpponentRequest("main", "a0"),
        "opponent_reply": P.OpponentReply("ok", "main", 1, "cheese", "bot", -1, ""),
        "player_weights_request": P.PlayerWeightsRequest("main", 3),
        "player_weights": P.PlayerWeights("ok", "main-s1", 3, 10, "arch", "", {"w": _f32(2, 2)}),
        "match_result": P.MatchResult("a0", "main", 0, 3, "cheese", -1, 1, 2, 1),
    }


def _plain(b=B, rng=None):
    rng = rng or np.random.default_rng(0)
    return {"obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32), "action": rng.integers(0, 2, b),
            "reward": np.ones(b, np.float32), "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
            "terminated": np.zeros(b, bool), "n": np.ones(b, np.uint8)}


def _int_fields(msg: P.Message) -> list[str]:
    return [n for n, k in msg.SCHEMA.items() if k.rstrip("?") in ("int", "uint")]


SAMPLES = _samples()
INT_CASES = [(name, f) for name, m in SAMPLES.items() for f in _int_fields(m)]


def test_every_message_type_with_integers_is_covered():
    covered = {type(m) for m in SAMPLES.values()}
    assert {c for c in P._REGISTRY.values() if any(k.rstrip("?") in ("int", "uint") for k in c.SCHEMA.values())} <= covered
    assert len(INT_CASES) >= 15


@pytest.mark.parametrize("name,field", INT_CASES)
@FAST
@given(v=EDGE_INTS)
def test_integer_fields_at_type_edges(name, field, v):
    """Every integer field of every message type: a value outside its declared range (int64 at
    most) is a ProtocolError naming the field; inside, the message decodes (or another rule of
    that message refuses it, still as a ProtocolError)."""
    msg = SAMPLES[name]
    env = msgpack.unpackb(msg.encode(), raw=False)
    env[field] = v
    lo, hi = type(msg).RANGES.get(field) or P.INT_RANGES[msg.SCHEMA[field].rstrip("?")]
    assert -(1 << 63) <= lo and hi <= (1 << 63) - 1
    try:
        out = type(msg).decode(msgpack.packb(env, use_bin_type=True))
    except P.ProtocolError as e:
        if lo <= v <= hi:  # another rule of the message (e.g. frame_base + frames), never the range
            assert "must be an integer in" not in str(e), (e, v)
        else:
            assert e.field == field and "must be an integer in" in str(e), (e, v)
        return
    assert lo <= v <= hi and getattr(out, field) == v


def _shape_ok(shape) -> bool:
    return (isinstance(shape, list) and len(shape) <= P.MAX_NDIM
            and all(type(d) is int and 0 <= d <= P.MAX_DIM for d in shape)
            and math.prod(max(d, 1) for d in shape) <= P.MAX_ELEMENTS)


SHAPES = st.lists(st.one_of(st.sampled_from([0, 1, 2, 3, 7, 1 << 15, 1 << 30, (1 << 30) + 1, 1 << 31, 1 << 32,
                                             1 << 62, (1 << 64) - 1, -1]),
                            st.integers(0, 64)), max_size=10)


@FAST
@given(shape=SHAPES, dtype=st.sampled_from(["uint8", "float32", "int64", "bool"]), extra=st.integers(-2, 2))
def test_random_shapes_decode_or_refuse(shape, dtype, extra):
    """A raw array of any declared shape: accepted only when the shape is bounded and its bytes
    are exactly there (no exception but ProtocolError, no allocation from the shape)."""
    itemsize = np.dtype(dtype).itemsize
    n = math.prod(shape) * itemsize if _shape_ok(shape) else 0
    if n > 1 << 16:
        n = 16  # a few bytes against a huge declared shape
    data = bytes(max(0, n + extra))
    try:
        a = P.decode_array("x", {"dtype": dtype, "shape": shape, "data": data})
    except P.ProtocolError:
        return
    assert _shape_ok(shape) and list(a.shape) == shape and a.nbytes == len(data)


@FAST
@given(shape=SHAPES, size=EDGE_INTS, payload=st.sampled_from([b"", b"\x00" * 8, lz4.block.compress(bytes(4096), store_size=False),
                                                             lz4.block.compress(bytes(1 << 20), store_size=False)]),
       cap=st.sampled_from([1 << 10, 1 << 16, 1 << 22]))
def test_random_compressed_declared_sizes(monkeypatch, shape, size, payload, cap):
    """A compressed array with any declared shape and size, under a per-message decoded-bytes
    cap: a ProtocolError, or a clean accept within the cap; nothing is decompressed unless the
    declared numbers are consistent, lz4 could produce them and they fit the cap."""
    calls = []
    real = lz4.block.decompress
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: calls.append(k) or real(*a, **k))
    env = msgpack.unpackb(P.TransitionBatch("a0", 0, 0, _plain()).encode(), raw=False)
    env["data"]["obs"] = {"dtype": "uint8", "shape": shape, "codec": "lz4", "size": size, "data": payload}
    try:
        P.TransitionBatch.decode(msgpack.packb(env, use_bin_type=True), limits=P.DecodeLimits(cap))
    except P.ProtocolError:
        pass
    for k in calls:
        assert k["uncompressed_size"] <= cap and _shape_ok(shape) and k["uncompressed_size"] == math.prod(shape)
        assert k["uncompressed_size"] <= P.LZ4_MAX_RATIO * len(payload) + 64


def test_decoded_cap_counts_all_compressed_arrays_of_a_message(monkeypatch):
    called = []
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: called.append(1))
    img = np.zeros((B, 64, 64), np.uint8)
    data = {**_plain(), "obs": img, "next_obs": img}
    payload = P.TransitionBatch("a0", 0, 0, data).encode(codec="lz4")
    with pytest.raises(P.ProtocolError, match="refused unread") as e:
        P.TransitionBatch.decode(payload, limits=P.DecodeLimits(max_decoded_bytes=B * 64 * 64 + 10))
    assert e.value.reason == "size" and not called


def test_compressed_arrays_against_the_receivers_spec(monkeypatch):
    """With a spec, a compressed array must be one of its uint8 fields with its item shape:
    otherwise refused before decompressing (reason spec)."""
    called = []
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: called.append(1))
    img = np.zeros((B, 64, 64), np.uint8)
    spec = P.DecodeLimits(packed={"data.obs": ((64, 64),), "data.next_obs": ((64, 64),)})
    wrong = P.TransitionBatch("a0", 0, 0, {**_plain(), "obs": np.zeros((B, 128, 64), np.uint8), "next_obs": img})
    extra = P.TransitionBatch("a0", 0, 0, {**_plain(), "obs": img, "next_obs": img, "junk": img})
    for msg, what in ((wrong, "rows of"), (extra, "no uint8 field")):
        with pytest.raises(P.ProtocolError, match=what) as e:
            P.TransitionBatch.decode(msg.encode(codec="lz4"), limits=spec)
        assert e.value.reason == "spec"
    assert not called


@FAST
@given(base=EDGE_INTS, shift=EDGE_INTS)
def test_frame_ids_at_the_edge_of_int64(base, shift):
    """frame_base and frame ids anywhere in msgpack's range: a ProtocolError, or ids and
    frame_base + F inside 0..2^62."""
    msg = SAMPLES["frames"]
    env = msgpack.unpackb(msg.encode(), raw=False)
    env["frame_base"] = base
    ids = np.clip(np.arange(B, dtype=object) + shift, -(1 << 63), (1 << 63) - 1).astype(np.int64)
    env["data"]["obs"] = P.encode_array(ids)
    env["data"]["obs"]["data"] = bytes(env["data"]["obs"]["data"])
    try:
        out = P.TransitionBatch.decode(msgpack.packb(env, use_bin_type=True))
    except P.ProtocolError:
        return
    assert 0 <= out.frame_base and out.frame_base + B + 1 <= P.MAX_FRAME_ID
    assert out.data["obs"].min() >= 0 and out.data["obs"].max() < out.frame_base + B + 1


def test_frame_ids_must_be_int64():
    msg = SAMPLES["frames"]
    data = dict(msg.data, obs=msg.data["obs"].astype(np.uint64))
    with pytest.raises(P.ProtocolError, match="int64"):
        P.TransitionBatch.decode(P.TransitionBatch("a0", 0, 0, data, frames=msg.frames, frame_base=0).encode())


def test_stats_maps_are_bounded():
    for values in ({"x": 1 << 63}, {"x": (1 << 64) - 1}, {"k" * 300: 1}):
        with pytest.raises(P.ProtocolError):
            P.Stats.decode(P.Stats("replay", "r", 1.0, values).encode())


# -- the replay's ingest: no input reaches an internal error ------------------------------------
def _service(checker=True, **over):
    sets = {"capacity": 1000, "min_size": 1, "check_semantics": False, **over}
    svc = ReplayService(load_config(None, [f"replay.{k}={v}" for k, v in sets.items()], environ={}), node=None, run_id="r")
    if checker:
        svc.checker = ChunkChecker({"obs": ObsRule("float32", (4,), np.full(4, -1, np.float32), np.full(4, 1, np.float32))},
                                   n_actions=2, n_step=3, max_abs_reward=1e3, max_priority=1e6)
        svc.ingestor.limits = P.DecodeLimits(svc.rcfg.max_decoded_bytes, svc.checker.packed_shapes())
    return svc


ENV_FIELDS = ["policy_version", "seq", "frame_base"]


@FAST
@given(field=st.sampled_from(ENV_FIELDS + ["action", "n", "shape", "size"]), v=EDGE_INTS, row=st.integers(0, B - 1))
def test_ingest_counts_no_internal_error_for_integer_and_shape_attacks(field, v, row):
    """The classes of the issue sent through the replay's whole ingest path, between honest
    chunks: each is rejected by reason or stored, none raises anything else (rejected_internal
    stays absent), and the honest chunks are all stored."""
    svc = _service()
    d = _plain()
    env = msgpack.unpackb(P.TransitionBatch("evil", 0, 0, d).encode(), raw=False)
    if field in ENV_FIELDS:
        env[field] = v
    elif field == "shape":
        env["data"]["obs"]["shape"] = [v % (1 << 64) >> (v % 61), 0] if v >= 0 else [v]
        env["data"]["obs"]["data"] = b""
    elif field == "size":
        env["data"]["obs"] = {"dtype": "uint8", "shape": [B, 16], "codec": "lz4", "size": v,
                              "data": lz4.block.compress(bytes(B * 16), store_size=False)}
    else:
        a = np.array(env["data"][field]["shape"] and np.frombuffer(env["data"][field]["data"], env["data"][field]["dtype"]))
        a = a.copy()
        a[row] = np.array(v).astype(a.dtype) if -(1 << 63) <= v < (1 << 63) else a[row]
        env["data"][field]["data"] = a.tobytes()
    evil = msgpack.packb(env, use_bin_type=True)
    honest = [P.TransitionBatch("a0", 0, i, _plain(rng=np.random.default_rng(i))).encode() for i in range(2)]
    n = svc.ingest_many([(honest[0], "zenrl/r/transitions/a0"), (evil, "zenrl/r/transitions/evil"),
                         (honest[1], "zenrl/r/transitions/a0")])
    v_ = svc.stats_values()
    assert "rejected_internal" not in v_, v_
    assert n in (2 * B, 3 * B) and v_.get("rejected_total", 0) == (3 * B - n) // B


# -- memory: the inbox and each batch in bytes, the decoded data held at once --------------------
TX = "zenrl/r/transitions/a0"


def test_the_inbox_holds_what_queue_max_bytes_takes_of_the_largest_chunks():
    assert _service(checker=False, queue_max_bytes=100_000, max_chunk_bytes=30_000).ingestor.inbox_capacity == 3
    assert _service(checker=False, queue_max_bytes=100_000, max_chunk_bytes=200_000).ingestor.inbox_capacity == 1
    assert _service(checker=False, queue_size=2, queue_max_bytes=100_000, max_chunk_bytes=1024).ingestor.inbox_capacity == 2
    assert _service(checker=False).ingestor.inbox_capacity == 64  # the defaults: 256 MiB over 4 MiB
    # the transport's cap, when lower, is the chunk cap
    svc = ReplayService(load_config(None, ["replay.queue_max_bytes=100000", "replay.max_chunk_bytes=200000",
                                           "transport.max_message_bytes=50000"], environ={}), node=None, run_id="r")
    assert svc.ingestor.inbox_capacity == 2


def test_a_batch_takes_at_most_queue_max_bytes_and_the_first_chunk_always():
    svc = _service(checker=False, capacity=10_000, queue_max_bytes=100_000)
    ing = svc.ingestor
    ing.inbox = FakeInbox(TX, 10)  # more than the service's own inbox holds: the batch bound is the one tested
    big = [P.TransitionBatch("a0", 0, i, _plain(b=1000)).encode() for i in range(5)]
    assert 40_000 < len(big[0]) < 50_000
    for p in big:
        ing.inbox.put(TX, p)
    assert ing.unit() == 3 * 1000  # 3 chunks reach 100,000 bytes: the rest wait for the next batch
    assert ing.inbox.qsize() == 2 and ing.pending() == 0
    assert ing.unit() == 2 * 1000
    # one chunk larger than the bound is still taken (alone)
    svc = _service(checker=False, queue_max_bytes=1024)
    svc.ingestor.inbox = FakeInbox(TX, 10)
    for i in range(2):
        svc.ingestor.inbox.put(TX, P.TransitionBatch("a0", 0, i, _plain(b=200)).encode())
    assert svc.ingestor.unit() == 200 and svc.ingestor.inbox.qsize() == 1


def test_a_chunk_over_the_cap_is_refused_unread():
    svc = _service(checker=False, max_chunk_bytes=20_000)
    ing = svc.ingestor
    ing.inbox = FakeInbox(TX, 4)
    big = ing.inbox.put(TX, P.TransitionBatch("a0", 0, 0, _plain(b=1500)).encode())
    ok = ing.inbox.put(TX, P.TransitionBatch("a0", 0, 1, _plain()).encode())
    assert big.nbytes > 20_000
    assert ing.unit() == B and big.copied == 0 and ok.copied == 1
    assert svc.stats_values()["rejected_size"] == 1


def test_a_stuck_ingest_thread_has_what_waits_dropped_and_counted():
    """The ingest thread stuck on a batch (here on the storage lock, as a stuck insert or disk would
    leave it) while chunks arrive: after replay.drop_after_s the relief thread drops and counts
    what waits in the inbox, so that Zenoh's receive thread (``put``) never waits into the 5 s fuse;
    once the thread moves again, every chunk is either stored or counted as dropped."""
    svc = _service(checker=False, queue_max_bytes=2 * 4096, max_chunk_bytes=4096, drop_after_s=0.4)
    node, sup = _Node(), Supervisor()
    svc.start(node, sup)
    inbox = node.inboxes[svc.keys.transitions_all]
    assert inbox.capacity == 2
    try:
        inbox.put(TX, P.TransitionBatch("a0", 0, 0, _plain()).encode())
        _until(lambda: svc.buffer is not None and svc.buffer.inserts_total == B)
        with svc._lock:
            inbox.put(TX, P.TransitionBatch("a0", 0, 1, _plain()).encode())
            _until(lambda: svc.ingestor.pending() == 1)  # taken, stuck on the lock
            t0 = time.monotonic()
            for i in range(2, 8):  # 6 more: the inbox (2) fills, the receive thread waits, is relieved
                inbox.put(TX, P.TransitionBatch("a0", 0, i, _plain()).encode(), timeout=3.0)
            assert 0.3 < time.monotonic() - t0 < 3.0
            _until(lambda: svc.ingestor.dropped_queue_full >= 4)
        _until(lambda: svc.ingestor.pending() == 0 and inbox.qsize() == 0 and svc.buffer.inserts_total > 2 * B)
        dropped = svc.ingestor.dropped_queue_full
        v = svc.stats_values()
        assert v["rejected_queue_full"] == dropped and v["dropped_queue_full"] == dropped
        assert svc.buffer.inserts_total == (8 - dropped) * B
    finally:
        svc.close()


def _until(cond, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def test_decoded_chunks_held_at_once_are_bounded(monkeypatch):
    svc = _service(checker=False, max_decoded_bytes=4096)
    seen = []
    real = type(svc.ingestor)._store_batch

    def store(self, chunks):
        seen.append(sum(c.nbytes for c in chunks))
        return real(self, chunks)

    monkeypatch.setattr(type(svc.ingestor), "_store_batch", store)
    items = [(P.TransitionBatch("a0", 0, i, _plain(b=16)).encode(), "a0") for i in range(20)]
    per = svc.ingestor._decode(items[0][0], "a0").nbytes
    assert svc.ingest_many(items) == 20 * 16
    assert len(seen) > 3 and max(seen) < 4096 + per


# -- frame mode: layout from the env spec, the stream bound to the key --------------------------
def _frame_checker(stack):
    return ChunkChecker({"obs": ObsRule("uint8", (2, 3, 3) if stack else (3, 3))}, n_actions=2, n_step=3,
                        max_abs_reward=1e6, max_priority=1e9, frame_stack=stack)


def _frame_chunk(base, stack, n_f=None, b=4, extra=None, drop=None):
    n_f = b + 1 if n_f is None else n_f
    ids = base + np.arange(b, dtype=np.int64)
    data = {"obs": np.stack([ids, ids + 1], 1) if stack else ids, "next_obs": np.stack([ids + 1, ids + 1], 1) if stack else ids + 1,
            "action": np.zeros(b, np.int64), "reward": np.zeros(b, np.float32), "n": np.ones(b, np.uint8),
            "terminated": np.zeros(b, bool), "truncated": np.zeros(b, bool), **(extra or {})}
    for k in drop or ():
        del data[k]
    return data, {"obs": np.full((n_f, 3, 3), base % 200, np.uint8)}


@pytest.mark.parametrize("stack", [0, 2])
def test_frame_layout_is_the_env_specs(stack):
    svc = _service(checker=False)
    svc.checker = _frame_checker(stack)
    key = "zenrl/r/transitions/a0"
    bad = [_frame_chunk(0, stack, extra={"junk": np.zeros(4, np.float32)}), _frame_chunk(0, stack, drop=["truncated"]),
           _frame_chunk(0, stack, drop=["next_obs"]), _frame_chunk(0, 2 - stack)]
    for data, frames in bad:
        payload = P.TransitionBatch("a0", 0, 0, data, frames=frames, frame_base=0).encode()
        assert svc.ingest(payload, key) == 0
    assert svc.buffer is None, "no storage allocated from a chunk that is not the env's layout"
    assert svc.rejects.counts["spec"] + svc.rejects.counts["fields"] == 4
    data, frames = _frame_chunk(0, stack)
    assert svc.ingest(P.TransitionBatch("a0", 0, 0, data, frames=frames, frame_base=0).encode(), key) == 4
    item, frame_spec, ref_stack = svc.buffer.wire_spec
    assert set(item) == {"action", "reward", "n", "terminated", "truncated", "meta/policy_version"}
    assert ref_stack == {"obs": stack, "next_obs": stack}


def test_a_frame_stream_is_bound_to_its_key():
    """A chunk naming actor a0 sent on evil's key is rejected (source); one on evil's own key
    starts evil's stream, leaving a0's frame history whole."""
    svc = _service(checker=False)
    a0 = "zenrl/r/transitions/a0"
    d, f = _frame_chunk(0, 0)
    assert svc.ingest(P.TransitionBatch("a0", 0, 0, d, frames=f, frame_base=0).encode(), a0) == 4
    d, f = _frame_chunk(0, 0)
    assert svc.ingest(P.TransitionBatch("a0", 0, 0, d, frames=f, frame_base=0).encode(), "zenrl/r/transitions/evil") == 0
    assert svc.rejects.counts["source"] == 1
    assert svc.ingest(P.TransitionBatch("evil", 0, 0, d, frames=f, frame_base=0).encode(), "zenrl/r/transitions/evil") == 4
    # a0's next chunk refers back to a frame of its first one: still resolved
    d, f = _frame_chunk(5, 0)
    d["obs"][0] = 4
    assert svc.ingest(P.TransitionBatch("a0", 0, 1, d, frames=f, frame_base=5).encode(), a0) == 4
    assert svc.buffer.unresolved == 0


def test_packed_shapes_of_an_image_env():
    c = _frame_checker(2)
    assert c.packed_shapes()["data.obs"] == ((2, 3, 3),) and c.packed_shapes()["frames.obs"] == ((3, 3),)
    assert c.packed_shapes()["data.n"] == ((),)


# -- quarantine ---------------------------------------------------------------------------------
@FAST
@given(stream=st.lists(st.integers(0, 200), min_size=1, max_size=2000), cap=st.integers(1, 40))
def test_top_counter_keeps_the_heavy_hitters(stream, cap):
    c = TopCounter(cap)
    true: dict[str, int] = {}
    for x in stream:
        c.add(str(x))
        true[str(x)] = true.get(str(x), 0) + 1
    assert len(c) <= cap and c.total == len(stream)
    for k, n in true.items():
        if n > len(stream) / cap:
            assert k in c, "a key counted more than total / capacity times is always held"
        if k in c:
            assert n <= c[k] <= n + c.error(k)


def test_a_failing_source_stays_tracked_among_invented_names():
    """Least recently rejected first: a flooder interleaved with a stream of one-off names
    (more than max_sources of them) is still quarantined; memory stays bounded."""
    q = Quarantine(5, 60.0, 60.0, clock=lambda: 0.0, max_sources=100)
    led = SourceLedger(q, max_sources=200)
    for i in range(5 * 90):
        if i % 90 == 0:
            led.rejected("flooder", "action_range")
        led.rejected(f"x{i}", "action_range")
    assert q.is_quarantined("flooder") and len(q._recent) <= 100 and len(led.by_source) <= 200
    assert led.by_source["flooder"] >= 5  # more than total / capacity rejections: always held


def test_quarantines_are_capped_and_new_offenders_still_quarantined():
    t = [0.0]
    q = Quarantine(1, 60.0, 60.0, clock=lambda: t[0], max_sources=10)
    for i in range(30):
        t[0] = float(i)
        assert q.record(f"s{i}", "spec") is True
    assert len(q.active) == 10 and q.is_quarantined("s29") and not q.is_quarantined("s0")
    line = q.describe(3)
    assert line.count("(spec") == 3 and line.endswith("and 7 more")


def test_the_status_line_stays_bounded():
    q = Quarantine(1, 60.0, 60.0, clock=lambda: 0.0, max_sources=5000)
    for i in range(5000):
        q.record("n" * 60 + str(i), "spec")
    led = SourceLedger(q)
    v = led.values(100)
    assert len(v["quarantined_sources"]) <= MAX_LINE
    P.Stats.decode(P.Stats("replay", "replay", 1.0, v).encode())


# -- health: a stalled ingest thread ------------------------------------------------------------
class _Node:
    def __init__(self):
        self.subs, self.inboxes = {}, {}

    def inbox(self, key, capacity):
        self.inboxes[key] = FakeInbox(key, capacity)
        return self.inboxes[key]

    def subscribe(self, key, cb):
        self.subs[key] = cb
        return key

    def queryable(self, key, cb):
        return key

    def withdraw(self, x):
        if x in self.inboxes:
            self.inboxes[x].close()


def test_health_fails_while_the_ingest_thread_makes_no_progress_with_input_waiting():
    """The real ingest thread, blocked (here on the storage lock, as a stuck insert would leave
    it) while chunks wait: the supervisor reports it stalled and the health verdict fails; once
    it moves again the verdict recovers."""
    svc = _service(checker=False, queue_max_bytes=4 * 4096, max_chunk_bytes=4096)
    node, sup = _Node(), Supervisor(stall_s=0.3)
    svc.start(node, sup)
    key = "zenrl/r/transitions/a0"
    node.cb = node.inboxes[svc.keys.transitions_all].put
    try:
        node.cb(key, P.TransitionBatch("a0", 0, 0, _plain()).encode())
        deadline = time.monotonic() + 10
        while (svc.buffer is None or svc.buffer.inserts_total < B) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert judge("replay", "tok", "replay", ["replay"], {"replay": sup.values()}, 5.0)[0]
        with svc._lock:
            for i in range(3):
                node.cb(key, P.TransitionBatch("a0", 0, i + 1, _plain()).encode())
            deadline = time.monotonic() + 10
            while not sup.values()["stalled"] and time.monotonic() < deadline:
                time.sleep(0.02)
            ok, why = judge("replay", "tok", "replay", ["replay"], {"replay": sup.values()}, 5.0)
            assert not ok and "replay-ingest" in why and "stalled" in why
        deadline = time.monotonic() + 10
        while svc.buffer.inserts_total < 4 * B and time.monotonic() < deadline:
            time.sleep(0.01)
        assert svc.buffer.inserts_total == 4 * B
        assert judge("replay", "tok", "replay", ["replay"], {"replay": sup.values()}, 5.0)[0]
    finally:
        svc.close()


def test_status_shows_the_top_rejected_sources():
    from zenrl.launcher.status_client import _detail

    row = {"role": "replay", "size": 10, "capacity": 100, "rejected_total": 14, "rejected_from/evil": 9,
           "rejected_from/fuzz1": 3, "rejected_from/fuzz2": 1, "rejected_from/fuzz3": 1, "quarantined": 1,
           "quarantined_sources": "evil (action_range, 4 dropped, 50 s left)"}
    line = _detail(row, None)
    assert line.startswith("size 10 / 100; rejected 14 (top: evil 9, fuzz1 3, ")
    assert "quarantined 1: evil (action_range" in line and line.count("fuzz") == 2
    assert _detail({"role": "replay", "size": 1, "capacity": 2}, None) == "size 1 / 2"


def test_unroll_decode_limits_from_the_env_spec(monkeypatch):
    """An IMPALA learner decoding with its checker's limits refuses a compressed observation of
    another item shape, or of a float field, before decompressing it."""
    from zenrl.common.unroll_checks import UnrollChecker

    called = []
    real = lz4.block.decompress
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: called.append(1) or real(*a, **k))
    chk = UnrollChecker({"obs": ObsRule("uint8", (32, 32))}, n_actions=2, max_abs_reward=10.0)
    T = 4
    args = (np.zeros(T, np.int64), np.full(T, -0.7, np.float32), np.zeros(T, np.float32), np.zeros(T, bool), np.zeros(T, bool))
    good = P.Unroll("a0", 0, 0, {"obs": np.zeros((T + 1, 32, 32), np.uint8)}, *args).encode(codec="lz4")
    assert P.Unroll.decode(good, limits=chk.decode_limits()).obs["obs"].shape == (T + 1, 32, 32) and called
    called.clear()
    bad = P.Unroll("a0", 0, 0, {"obs": np.zeros((T + 1, 64, 32), np.uint8)}, *args).encode(codec="lz4")
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(bad, limits=chk.decode_limits())
    assert e.value.reason == "spec" and not called
