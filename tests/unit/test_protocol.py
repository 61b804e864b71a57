"""Wire protocol: round trip of every message type, and every rejection path."""

import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.errors import ProtocolError


def _batch(b=5):
    return {
        "obs/lidar": np.random.default_rng(0).random((b, 360), dtype=np.float32),
        "obs/image": np.zeros((b, 8, 8, 3), np.uint8),
        "action": np.arange(b, dtype=np.int64),
        "reward": np.linspace(-1, 1, b).astype(np.float32),
        "terminated": np.array([True, False, False, True, False][:b]),
    }


MESSAGES = [
    P.TransitionBatch("actor-1", 7, 3, _batch(), np.ones(5, np.float32)),
    P.TransitionBatch("actor-1", -1, 0, _batch(), None),
    P.SampleRequest(4, 512, 0.4),
    P.SampleReply(4, "not_ready", "min_size 10 > size 3", 3),
    P.SampleReply(4, "ok", "", 100, np.arange(5, dtype=np.int64), np.full(5, 0.01), np.ones(5, np.float32), _batch()),
    P.PriorityUpdate(np.arange(3, dtype=np.int64), np.array([0.5, 1.0, 2.0], np.float32)),
    P.Weights(3, "learner", "mlp:4-64-2", 99, {"w": np.ones((2, 3), np.float32), "b": np.zeros(3, np.float32)}),
    P.Gradients("w0", 2, 40, {"w": np.ones((2, 3), np.float32)}),
    P.EpisodeStats("a0", 1, 0.1, 3, 1000, np.array([1.5, 2.0], np.float32), np.array([10, 20], np.int32)),
    P.EvalResult(3, 100, np.array([500.0], np.float32)),
    P.EvalResult(3, 100, np.array([7.0, -2.0, 0.0], np.float32), np.array([1, -1, 0], np.int8)),
    P.Stats("replay", "r0", 12.5, {"size": 3, "rate": 1.5, "name": "x"}),
]


def _eq(a, b):
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_eq(a[k], b[k]) for k in a)
    return a == b


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: m.TYPE)
def test_round_trip(msg):
    out = type(msg).decode(msg.encode())
    for f in msg.__dataclass_fields__:
        assert _eq(getattr(msg, f), getattr(out, f)), f
    assert type(P.decode_any(msg.encode())) is type(msg)


def _big_batch(b=5):
    """``_batch`` with an image large enough to be read in place (P.VIEW_MIN_BYTES)."""
    return {**_batch(b), "obs/image": np.random.default_rng(1).integers(0, 256, (b, 128, 128, 3), dtype=np.uint8)}


#: messages long enough for the view reader (a large uint8 array in each array map)
BIG_MESSAGES = [
    P.TransitionBatch("actor-1", 7, 3, _big_batch(), np.ones(5, np.float32)),
    P.TransitionBatch("actor-1", 7, 3, {"obs": np.arange(5, dtype=np.int64), "action": np.zeros(5, np.int64),
                                        "reward": np.zeros(5, np.float32)}, np.ones(5, np.float32),
                      frames={"obs": np.zeros((6, 96, 96, 3), np.uint8)}, frame_base=10),
    P.SampleReply(4, "ok", "", 100, np.arange(5, dtype=np.int64), np.full(5, 0.01), np.ones(5, np.float32), _big_batch()),
    P.Gradients("w0", 2, 40, {"w": np.ones((2, 3), np.float32), "img": np.zeros(70000, np.uint8)}),
]


def test_large_uint8_arrays_are_views_on_the_payload_and_the_rest_aligned_copies():
    for msg in BIG_MESSAGES[:3]:
        payload = msg.encode()
        assert len(payload) >= P.VIEW_MIN_BYTES
        out = type(msg).decode(payload)
        whole = np.frombuffer(payload, np.uint8)
        arrays = {**out.data, **(getattr(out, "frames", None) or {})}
        for k, a in arrays.items():
            assert not a.flags.writeable, k
            big = a.dtype == np.uint8 and a.nbytes >= P.VIEW_MIN_BYTES
            assert np.shares_memory(a, whole) == big, f"{k}: {'copied' if big else 'a view'}"
            assert a.flags.aligned, k
    small = P.TransitionBatch.decode(MESSAGES[0].encode())
    assert not small.data["obs/lidar"].flags.writeable


def _outcome(fn):
    try:
        return ("ok", fn())
    except ProtocolError as e:
        return ("rejected", e.field, e.reason)


def _read_by_msgpack(cls, payload):
    """The decode as it was before array data became views: msgpack reads the envelope."""
    env = P._unpack(payload, P.DEFAULT_MAX_MESSAGE_BYTES)
    if env["t"] != cls.TYPE:
        raise ProtocolError("t", "another type", "type")
    return cls._from_envelope(env)


_ODD = [None, True, 1, -1, 2**63, 1.5, float("nan"), "x", b"ab", [], [1, 2], {}, {"a": 1}, {1: 2}, [{2: 1}],
        msgpack.ExtType(5, b"x"), {"dtype": "uint8", "shape": [2], "data": b"ab"},
        {"dtype": "uint8", "shape": [2], "data": "ab"}, {"dtype": "uint8", "shape": [2.0], "data": b"ab"},
        {"dtype": "uint8", "shape": [2], "data": b"ab", "codec": "lz4", "size": 2}]


def test_the_view_reader_accepts_and_refuses_exactly_what_msgpack_s_reader_does():
    """Every message type, mutated at random (a field replaced by a value of another form, a key
    of an array map changed, a field dropped, a byte flipped): decode gives the same message or
    the same rejection (field and reason) as reading the envelope with msgpack."""
    rng = np.random.default_rng(0)
    corpus = BIG_MESSAGES * 3 + MESSAGES  # half of the draws long enough for the view reader
    viewed = 0
    for _ in range(4000):
        msg = corpus[rng.integers(len(corpus))]
        env = msgpack.unpackb(msg.encode(), raw=False)
        op = rng.random()
        if op < 0.1:
            pass  # as sent
        elif op < 0.45:
            env[[*env, "extra"][rng.integers(len(env) + 1)]] = _ODD[rng.integers(len(_ODD))]
        elif op < 0.8:
            maps = [v for v in env.values() if isinstance(v, dict) and v]
            if maps:
                m = maps[rng.integers(len(maps))]
                m = m if "dtype" in m else m[[*m][rng.integers(len(m))]]
                if isinstance(m, dict):
                    m[[*m, "codec", "size", "zz"][rng.integers(len(m) + 3)]] = _ODD[rng.integers(len(_ODD))]
        else:
            env.pop([*env][rng.integers(len(env))])
        payload = msgpack.packb(env, use_bin_type=True)
        if rng.random() < 0.1:
            b = bytearray(payload)
            b[rng.integers(len(b))] = rng.integers(256)
            payload = bytes(b)
        cls = type(msg)
        want, got = _outcome(lambda: _read_by_msgpack(cls, payload)), _outcome(lambda: cls.decode(payload))
        assert want[0] == got[0], (want, got, env)
        if want[0] == "rejected":
            assert want[1:] == got[1:], (want, got, env)
        else:
            for f in msg.__dataclass_fields__:
                assert _eq(getattr(want[1], f), getattr(got[1], f)), (f, env)
            whole = np.frombuffer(payload, np.uint8)
            viewed += any(isinstance(v, dict) and any(np.shares_memory(a, whole) for a in v.values())
                          for v in vars(got[1]).values())
    assert viewed > 120, f"the view reader read only {viewed} messages"


def test_the_view_reader_s_plain_arrays_are_what_the_array_check_makes_of_them():
    """The view reader turns a plain wire array straight into an array; every shape and length
    it must not take that way (negative, empty, too many dimensions, bytes that do not match,
    an unknown dtype, a compressed map) goes to the array check and gets its rejection."""
    frames = np.zeros((6, 96, 96, 3), np.uint8)
    msg = P.TransitionBatch("actor-1", 7, 3, {"obs": np.arange(6, dtype=np.int64), "r": np.zeros(6, np.float32)},
                            np.ones(6, np.float32), frames={"obs": frames}, frame_base=10)
    edits = [("shape", [6, 96, 96, -3]), ("shape", [6, 96, 96, 3, 1, 1, 1, 1, 1]), ("shape", [0, 96, 96, 3]),
             ("shape", [6, 96, 96, 2]), ("shape", [6 * 96, 96 * 3]), ("dtype", "uint9"), ("dtype", "float32"),
             ("data", b"\0" * 10), ("size", 6 * 96 * 96 * 3), (None, None)]
    for key, value in edits:
        env = msgpack.unpackb(msg.encode(), raw=False)
        if key is not None:
            env["frames"]["obs"][key] = value
        payload = msgpack.packb(env, use_bin_type=True)
        assert len(payload) >= P.VIEW_MIN_BYTES or key == "data"
        want, got = _outcome(lambda: _read_by_msgpack(P.TransitionBatch, payload)), _outcome(lambda: P.TransitionBatch.decode(payload))
        assert want[0] == got[0], (key, value, want, got)
        if want[0] == "rejected":
            assert want[1:] == got[1:], (key, value, want, got)
        else:
            assert got[1].frames["obs"].shape == tuple(env["frames"]["obs"]["shape"]), (key, value)
            assert np.shares_memory(got[1].frames["obs"], np.frombuffer(payload, np.uint8)), (key, value)
    assert _outcome(lambda: P.TransitionBatch.decode(msg.encode()))[0] == "ok"


def _frame_chunk(big: bool) -> P.TransitionBatch:
    rng = np.random.default_rng(5)
    side = 84 if big else 8
    obs = np.arange(6, dtype=np.int64)[:, None] + np.arange(4)
    return P.TransitionBatch("actor-1", 7, 3, {"obs": obs, "next_obs": obs + 3, "action": np.arange(6, dtype=np.int64),
                                               "reward": rng.random(6).astype(np.float32), "terminated": np.zeros(6, bool)},
                             np.ones(6, np.float32), frames={"obs": rng.integers(0, 256, (12, side, side), dtype=np.uint8)},
                             frame_base=20)


def _chunk_edits():
    """Edits of a chunk's envelope, each one rule of the general decoder's (or none)."""
    arr = lambda dtype, shape, data: {"dtype": dtype, "shape": shape, "data": data}  # noqa: E731
    ids = lambda a: arr("int64", list(a.shape), a.astype(np.int64).tobytes())  # noqa: E731
    obs = np.arange(6)[:, None] + np.arange(4)
    return [
        ("v", 2), ("v", "1"), ("v", 1.0), ("t", "sample_reply"), ("actor_id", "bad name!"), ("actor_id", ""),
        ("actor_id", "a" * 65), ("actor_id", "ok\n"), ("actor_id", 5), ("policy_version", 2**63),
        ("policy_version", -(2**63)), ("policy_version", True), ("policy_version", 1.0), ("seq", -1), ("seq", 2**63 - 1),
        ("seq", 2**64 - 1), ("frame_base", -1), ("frame_base", P.MAX_FRAME_ID), ("frame_base", None), ("frame_base", 0),
        ("frames", None), ("frames", {}), ("priorities", None), ("priorities", arr("float32", [5], b"\0" * 20)),
        ("priorities", arr("float32", [6], np.full(6, -1, np.float32).tobytes())),
        ("priorities", arr("float64", [6], np.full(6, np.nan).tobytes())), ("priorities", arr("float32", [6, 1], b"\0" * 24)),
        ("priorities", arr("int64", [6], b"\0" * 48)), ("extra", 1), ("data", {}), ("data", 5),
        ("data.bad key!", arr("int64", [6], b"\0" * 48)), ("data." + "k" * 129, arr("int64", [6], b"\0" * 48)),
        ("data.x", arr("uint9", [6], b"\0" * 6)), ("data.x", arr("int64", [-6], b"")), ("data.x", arr("int64", [6], b"\0" * 47)),
        ("data.x", arr("int64", [6, True], b"\0" * 48)), ("data.x", arr("float32", [6], np.full(6, np.inf, np.float32).tobytes())),
        ("data.x", arr("int64", [0], b"")), ("data.x", arr("int64", [0, 2**40], b"")), ("frames.obs", arr("uint8", [0, 2**40], b"")), ("data.x", arr("int64", [7], b"\0" * 56)), ("data.x", {**arr("int64", [6], b"\0" * 48), "zz": 1}),
        ("data.x", arr("int64", [6], "text")), ("data.x", arr("int64", [1] * 9, b"\0" * 8)), ("data.x", arr("int64", [6], b"\0" * 48)),
        ("data.obs", ids(obs + 100)), ("data.obs", ids(obs - 30)), ("data.obs", arr("int32", [6, 4], obs.astype(np.int32).tobytes())),
        ("data.obs", ids(obs[:, :1].reshape(6))), ("data.next_obs", ids(np.zeros((6, 1, 1, 1), np.int64))),
        ("frames.obs", arr("uint8", [11, 8, 8], b"\0" * 704)), ("frames.next", arr("uint8", [12, 8, 8], b"\0" * 768)),
        ("frames.obs", arr("float32", [12, 1], np.full(12, np.nan, np.float32).tobytes())),
        ("frames.obs", {"dtype": "uint8", "shape": [12, 8, 8], "data": b"\0" * 9, "codec": "lz4", "size": 768}),
    ]


@pytest.mark.parametrize("big", [False, True], ids=["small", "views"])
def test_the_chunk_short_way_accepts_and_refuses_as_the_general_way(big):
    """:func:`_decode_transitions_plain` (the short way every honest chunk takes) against the
    envelope read by msgpack and checked by the general decoder, on edits that each break one
    rule: it gives the same message, the same rejection, or leaves the chunk to the general way
    (None); ``TransitionBatch.decode`` then agrees with the general decoder on every edit. And an
    honest chunk does take it."""
    msg = _frame_chunk(big)
    assert P._decode_transitions_plain(msg.encode(), P.DEFAULT_MAX_MESSAGE_BYTES) is not None
    short_ok = 0
    for key, value in [(None, None), *_chunk_edits()]:
        env = msgpack.unpackb(msg.encode(), raw=False)
        if key is not None:
            where, _, name = key.partition(".")
            target = env if not name else env.setdefault(where, {}) if isinstance(env.get(where), dict) else env
            if not name:
                env[where] = value
            elif isinstance(target, dict):
                target[name] = value
        payload = msgpack.packb(env, use_bin_type=True)
        want = _outcome(lambda: _read_by_msgpack(P.TransitionBatch, payload))
        short = _outcome(lambda: P._decode_transitions_plain(payload, P.DEFAULT_MAX_MESSAGE_BYTES))
        got = _outcome(lambda: P.TransitionBatch.decode(payload))
        assert want[0] == got[0] and (want[0] == "ok" or want[1:] == got[1:]), (key, value, want, got)
        if short[0] == "rejected":
            assert want[1:] == short[1:], (key, value, want, short)
        elif short[1] is not None:
            short_ok += 1
            assert want[0] == "ok", (key, value, want)
            for f in msg.__dataclass_fields__:
                assert _eq(getattr(want[1], f), getattr(short[1], f)), (key, f)
        if want[0] == "ok":
            for f in msg.__dataclass_fields__:
                assert _eq(getattr(want[1], f), getattr(got[1], f)), (key, f)
    assert short_ok >= 5, "the short way took almost none of the well-formed chunks"


def test_frame_id_bounds_are_the_ids_extremes_decoded_or_built():
    """The decode's id check records each frame-id field's smallest and largest id (the replay's
    insert reads them instead of reducing the ids again); a message built here finds the same."""
    rng = np.random.default_rng(3)
    frames = np.zeros((40, 84, 84), np.uint8)
    obs = rng.integers(10, 50, (8, 4)).astype(np.int64)
    nxt = np.array([12, 49, 30, 11, 10, 33, 48, 20], np.int64)
    msg = P.TransitionBatch("actor-1", 7, 3, {"obs": obs, "next_obs": nxt, "r": np.zeros(8, np.float32)},
                            np.ones(8, np.float32), frames={"obs": frames}, frame_base=10)
    want = {"obs": (min(obs.flat), max(obs.flat)), "next_obs": (10, 49)}
    got = P.TransitionBatch.decode(msg.encode())
    assert got.frame_id_bounds() == want
    assert msg.frame_id_bounds() == want
    got.frame_id_bounds()["obs"] = (0, 0)  # a copy: the message's own stay
    assert got.frame_id_bounds() == want


def test_types_whose_precheck_reads_array_maps_get_maps_from_the_view_reader():
    """A type that reads its envelope's array maps before the checks (an unroll's declared
    steps) must see maps: only types with the base ``_precheck`` take arrays already made."""
    direct = {t for t, cls in P._REGISTRY.items() if cls.DIRECT_ARRAYS}
    assert {"transitions", "sample_reply"} <= direct
    for t in direct:
        assert P._REGISTRY[t]._precheck is P.Message._precheck, t
    assert not P.Unroll.DIRECT_ARRAYS


def _env(**over):
    env = msgpack.unpackb(MESSAGES[0].encode(), raw=False)
    env.update(over)
    return env


def _raises(payload, field, reason=None, cls=P.TransitionBatch):
    with pytest.raises(ProtocolError) as ei:
        cls.decode(payload if isinstance(payload, bytes) else msgpack.packb(payload, use_bin_type=True))
    assert ei.value.field == field, str(ei.value)
    assert field in str(ei.value)
    if reason:
        assert ei.value.reason == reason
    return ei.value


def test_garbage_and_non_map():
    _raises(b"\xc1\xff garbage", "payload", "malformed")
    _raises(msgpack.packb([1, 2, 3]), "payload", "malformed")
    with pytest.raises(ProtocolError):
        P.TransitionBatch.decode("not bytes")  # type: ignore[arg-type]


def test_version_and_type():
    _raises(_env(v=2), "v", "version")
    _raises({k: v for k, v in _env().items() if k != "v"}, "v", "version")
    _raises(_env(t="weights"), "t", "type")
    with pytest.raises(ProtocolError) as ei:
        P.decode_any(msgpack.packb(_env(t="nope")))
    assert ei.value.field == "t"


def test_missing_and_unknown_fields():
    env = _env()
    del env["actor_id"]
    _raises(env, "actor_id", "field")
    _raises(_env(extra=1), "extra", "field")


def test_bad_scalars():
    _raises(_env(seq=-1), "seq", "field")
    _raises(_env(policy_version="x"), "policy_version", "field")
    _raises(_env(actor_id="a/b*"), "actor_id", "name")
    _raises(msgpack.packb({"v": 1, "t": "sample_request", "request_id": 1, "batch_size": 0, "beta": 0.4}), "batch_size", cls=P.SampleRequest)
    _raises(msgpack.packb({"v": 1, "t": "sample_request", "request_id": 1, "batch_size": 8, "beta": float("nan")}), "beta", "nonfinite", cls=P.SampleRequest)


def test_bad_arrays():
    env = _env()
    env["data"]["action"]["dtype"] = "object"
    _raises(env, "data.action.dtype", "dtype")
    env = _env()
    env["data"]["action"]["shape"] = [6]
    _raises(env, "data.action.data", "shape")
    env = _env()
    env["data"]["action"]["shape"] = [-5]
    _raises(env, "data.action.shape", "shape")
    env = _env()
    env["data"]["action"] = {"dtype": "int64", "shape": [5]}
    _raises(env, "data.action", "array")


def test_inconsistent_batch():
    b = _batch()
    b["action"] = np.arange(4, dtype=np.int64)
    _raises(P.TransitionBatch("a", 0, 0, b).encode(), "data.action", "batch")
    _raises(P.TransitionBatch("a", 0, 0, _batch(), np.ones(4, np.float32)).encode(), "priorities", "batch")


def test_nonfinite_rewards_and_priorities():
    b = _batch()
    b["reward"] = b["reward"].copy()
    b["reward"][2] = np.nan
    _raises(P.TransitionBatch("a", 0, 0, b).encode(), "data.reward", "nonfinite")
    _raises(P.TransitionBatch("a", 0, 0, _batch(), np.array([1, 1, np.inf, 1, 1], np.float32)).encode(), "priorities", "nonfinite")
    _raises(P.TransitionBatch("a", 0, 0, _batch(), np.array([1, 1, -1, 1, 1], np.float32)).encode(), "priorities", "negative")
    g = P.Gradients("w", 0, 1, {"w": np.array([np.nan], np.float32)}).encode()
    _raises(g, "grads.w", "nonfinite", cls=P.Gradients)


def test_eval_outcomes_checked():
    rets = np.zeros(2, np.float32)
    _raises(P.EvalResult(1, 1, rets, np.array([1, 2], np.int8)).encode(), "outcomes", "field", cls=P.EvalResult)
    _raises(P.EvalResult(1, 1, rets, np.array([1], np.int8)).encode(), "outcomes", "batch", cls=P.EvalResult)
    _raises(P.EvalResult(1, 1, rets, np.array([1.0, 0.0], np.float32)).encode(), "outcomes", "dtype", cls=P.EvalResult)


def test_size_caps():
    big = P.TransitionBatch("a", 0, 0, {"x": np.zeros((1000, 100), np.float32)})
    with pytest.raises(ProtocolError) as ei:
        big.encode(max_bytes=10_000)
    assert ei.value.reason == "size"
    payload = big.encode()
    with pytest.raises(ProtocolError) as ei:
        P.TransitionBatch.decode(payload, max_bytes=10_000)
    assert ei.value.field == "payload" and ei.value.reason == "size"


def test_keys():
    k = P.Keys("run1")
    assert k.transitions("a0") == "zenrl/run1/transitions/a0"
    assert k.alive("actor", "a0") == "zenrl/run1/alive/actor/a0"
    assert k.parse_alive("zenrl/run1/alive/actor/a0") == ("actor", "a0")
    assert k.slot_token(3, "a0") == "zenrl/run1/slots/3/a0"
    assert k.parse_slot("zenrl/run1/slots/3/a0") == (3, "a0")
    for bad in ["", "a/b", "a*", "x" * 65, "$x"]:
        with pytest.raises(ProtocolError):
            P.Keys(bad)
        with pytest.raises(ProtocolError):
            k.transitions(bad)


@pytest.mark.parametrize("order", ["<", ">", "="])
@pytest.mark.parametrize("name", sorted(P.ALLOWED_DTYPES))
def test_arrays_of_every_wire_dtype_and_byte_order_round_trip_little_endian(name, order):
    a = np.arange(6).astype(np.dtype(name).newbyteorder(order)).reshape(2, 3)
    m = P.encode_array(a)
    assert m["dtype"] == name and m["shape"] == [2, 3]
    back = P.decode_array("x", {**m, "data": bytes(m["data"])})
    assert back.dtype == np.dtype(name) and np.array_equal(back, a)


@pytest.mark.parametrize("dtype", [object, "U3", np.complex64, "datetime64[s]"])
def test_encode_names_an_array_dtype_the_wire_does_not_carry(dtype):
    with pytest.raises(ProtocolError, match="not a wire dtype"):
        P.encode_array(np.zeros(2, dtype))
