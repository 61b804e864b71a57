"""The Unroll wire message (IMPALA actor -> learner): round trips (plain, dict and image
observations, lz4, truncations with final observations, behaviour logits) and every malformed
field refused at decode with its reason tag, including well-formed lies (T mismatches, huge
declared shapes, out-of-range integers) refused before anything is decompressed."""

import dataclasses
import lz4.block
import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P

T = 5


def _unroll(T=T, obs=None, **over):
    rng = np.random.default_rng(0)
    kw = dict(actor_id="a0", policy_version=7, seq=3,
              obs=obs if obs is not None else {"obs": rng.normal(size=(T + 1, 4)).astype(np.float32)},
              action=rng.integers(0, 2, T).astype(np.int64),
              behaviour_logp=np.log(rng.uniform(0.1, 1.0, T)).astype(np.float32),
              reward=np.ones(T, np.float32), terminated=np.zeros(T, bool), truncated=np.zeros(T, bool))
    kw.update(over)
    return P.Unroll(**kw)


def _truncated_unroll():
    term = np.zeros(T, bool)
    trunc = np.zeros(T, bool)
    trunc[1] = trunc[3] = True
    term[3] = True  # terminated and truncated: no final observation needed (termination wins)
    term[4] = True
    final = {"obs": np.full((1, 4), 9.0, np.float32)}
    logits = np.random.default_rng(1).normal(size=(T, 2)).astype(np.float32)
    return _unroll(terminated=term, truncated=trunc, final_obs=final, behaviour_logits=logits)


def _assert_same(a, b):
    assert (a.actor_id, a.policy_version, a.seq) == (b.actor_id, b.policy_version, b.seq)
    for k in ("action", "behaviour_logp", "reward", "terminated", "truncated", "behaviour_logits"):
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None) == (y is None)
        if x is not None:
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
    for group in ("obs", "final_obs"):
        x, y = getattr(a, group), getattr(b, group)
        assert (x is None) == (y is None)
        for k in x or {}:
            assert x[k].dtype == y[k].dtype
            np.testing.assert_array_equal(x[k], y[k])


def test_round_trip_plain():
    u = _unroll()
    d = P.Unroll.decode(u.encode())
    _assert_same(u, d)
    assert d.steps == T and d.final_obs is None and d.behaviour_logits is None
    assert d.nbytes == (T + 1) * 16 + T * (8 + 4 + 4 + 1 + 1)
    assert isinstance(P.decode_any(u.encode()), P.Unroll)


def test_round_trip_truncations_and_logits():
    u = _truncated_unroll()
    d = P.Unroll.decode(u.encode())
    _assert_same(u, d)
    assert d.cut.tolist() == [False, True, False, False, False]


def test_round_trip_images_lz4_and_dict_obs():
    img = np.zeros((T + 1, 84, 84), np.uint8)
    img[:, 10:20, 30:60] = 200
    obs = {"obs/image": img, "obs/pose": np.zeros((T + 1, 3), np.float32)}
    trunc = np.zeros(T, bool)
    trunc[2] = True
    u = _unroll(obs=obs, truncated=trunc,
                final_obs={"obs/image": np.full((1, 84, 84), 7, np.uint8), "obs/pose": np.ones((1, 3), np.float32)})
    raw, packed = u.encode(), u.encode(codec="lz4")
    assert len(packed) < len(raw) / 10
    env = msgpack.unpackb(packed)
    assert env["obs"]["obs/image"]["codec"] == "lz4" and "codec" not in env["obs"]["obs/pose"]
    for payload in (raw, packed):
        _assert_same(u, P.Unroll.decode(payload))


def test_final_obs_may_be_empty_arrays_when_nothing_is_truncated():
    u = _unroll(final_obs={"obs": np.zeros((0, 4), np.float32)})
    assert P.Unroll.decode(u.encode()).final_obs["obs"].shape == (0, 4)


def test_keys():
    k = P.Keys("run1")
    assert k.unrolls("a-0") == "zenrl/run1/unrolls/a-0" and k.unrolls_all == "zenrl/run1/unrolls/*"
    with pytest.raises(P.ProtocolError):
        k.unrolls("bad/id")


# --------------------------------------------------------------------------------------------
# malformed: each case edits one part of a valid envelope
# --------------------------------------------------------------------------------------------
def _arr(a):
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


def _env(u=None):
    return msgpack.unpackb((u or _truncated_unroll()).encode(), raw=False)


def _set(path, value):
    def edit(env):
        node = env
        for p in path[:-1]:
            node = node[p]
        if value is _DELETE:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return edit


_DELETE = object()
_nan_logp = np.zeros(T, np.float32)
_nan_logp[2] = np.nan
_inf_reward = np.ones(T, np.float32)
_inf_reward[0] = np.inf
_nan_obs = np.zeros((T + 1, 4), np.float32)
_nan_obs[3, 1] = np.nan

MALFORMED = {
    # envelope and scalars
    "version": (lambda e: e.update(v=2), "version"),
    "missing action": (_set(["action"], _DELETE), "field"),
    "unknown field": (lambda e: e.update(extra=1), "field"),
    "bad actor id": (_set(["actor_id"], "a/b"), "name"),
    "policy_version below -1": (_set(["policy_version"], -2), "field"),
    "policy_version beyond int63": (_set(["policy_version"], 1 << 63), "field"),
    "seq beyond int63": (_set(["seq"], (1 << 64) - 1), "field"),
    "negative seq": (_set(["seq"], -1), "field"),
    "seq not an int": (_set(["seq"], 1.5), "field"),
    # per-step arrays
    "action int32": (_set(["action"], _arr(np.zeros(T, np.int32))), "dtype"),
    "action 2-D": (_set(["action"], _arr(np.zeros((T, 1), np.int64))), "shape"),
    "empty unroll": (lambda e: e.update(action=_arr(np.zeros(0, np.int64))), "batch"),
    # continuous actions: float32[T, d] only
    "continuous actions float64": (_set(["action"], _arr(np.zeros((T, 2), np.float64))), "shape"),
    "continuous actions of no dimension": (_set(["action"], _arr(np.zeros((T, 0), np.float32))), "shape"),
    "continuous actions NaN": (_set(["action"], _arr(np.full((T, 2), np.nan, np.float32))), "nonfinite"),
    "continuous actions Inf": (_set(["action"], _arr(np.full((T, 1), -np.inf, np.float32))), "nonfinite"),
    "continuous actions 3-D": (_set(["action"], _arr(np.zeros((T, 2, 2), np.float32))), "shape"),
    "continuous actions one step short": (_set(["action"], _arr(np.zeros((T - 1, 2), np.float32))), "batch"),
    "float actions 1-D": (_set(["action"], _arr(np.zeros(T, np.float32))), "dtype"),
    "reward one step short": (_set(["reward"], _arr(np.ones(T - 1, np.float32))), "batch"),
    "logp one step long": (_set(["behaviour_logp"], _arr(np.zeros(T + 1, np.float32))), "batch"),
    "logp float64": (_set(["behaviour_logp"], _arr(np.zeros(T, np.float64))), "dtype"),
    "logp NaN": (_set(["behaviour_logp"], _arr(_nan_logp)), "nonfinite"),
    "reward Inf": (_set(["reward"], _arr(_inf_reward)), "nonfinite"),
    "terminated uint8": (_set(["terminated"], _arr(np.zeros(T, np.uint8))), "dtype"),
    "truncated missing": (_set(["truncated"], _DELETE), "field"),
    "dtype not on the wire": (_set(["reward", "dtype"], "complex64"), "dtype"),
    "bytes do not match shape": (_set(["reward", "data"], b"\0" * 3), "shape"),
    "negative dimension": (_set(["reward", "shape"], [-T]), "shape"),
    # observations
    "obs T rows not T+1": (_set(["obs", "obs"], _arr(np.zeros((T, 4), np.float32))), "batch"),
    "obs T+2 rows": (_set(["obs", "obs"], _arr(np.zeros((T + 2, 4), np.float32))), "batch"),
    "obs scalar": (_set(["obs", "obs"], _arr(np.float32(1.0))), "batch"),
    "obs NaN": (_set(["obs", "obs"], _arr(_nan_obs)), "nonfinite"),
    "obs misnamed": (lambda e: e.update(obs={"state": e["obs"]["obs"]}), "field"),
    "obs empty map": (_set(["obs"], {}), "array"),
    # final observations
    "final_obs missing": (_set(["final_obs"], _DELETE), "field"),
    "final_obs two rows for one truncation": (_set(["final_obs", "obs"], _arr(np.zeros((2, 4), np.float32))), "batch"),
    "final_obs wrong dtype": (_set(["final_obs", "obs"], _arr(np.zeros((1, 4), np.float64))), "dtype"),
    "final_obs wrong item shape": (_set(["final_obs", "obs"], _arr(np.zeros((1, 5), np.float32))), "shape"),
    "final_obs other fields": (lambda e: e.update(final_obs={"obs/x": e["final_obs"]["obs"]}), "field"),
    "final_obs Inf": (_set(["final_obs", "obs"], _arr(np.full((1, 4), np.inf, np.float32))), "nonfinite"),
    # behaviour logits
    "logits T mismatch": (_set(["behaviour_logits"], _arr(np.zeros((T - 1, 2), np.float32))), "batch"),
    "logits 1-D": (_set(["behaviour_logits"], _arr(np.zeros(T, np.float32))), "batch"),
    "logits no actions": (_set(["behaviour_logits"], _arr(np.zeros((T, 0), np.float32))), "shape"),
    "logits float64": (_set(["behaviour_logits"], _arr(np.zeros((T, 2), np.float64))), "dtype"),
    "logits NaN": (_set(["behaviour_logits"], _arr(np.full((T, 2), np.nan, np.float32))), "nonfinite"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_is_refused_with_reason(case):
    edit, reason = MALFORMED[case]
    env = _env()
    edit(env)
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == reason, str(e.value)


def test_continuous_actions_round_trip():
    """float32[T, d] actions (a Box normalised to [-1, 1], samples outside it included) decode
    as sent, and T is read from their first axis."""
    u = _truncated_unroll()
    act = np.linspace(-3, 3, T * 2, dtype=np.float32).reshape(T, 2)
    d = P.Unroll.decode(dataclasses.replace(u, action=act).encode())
    assert d.steps == T and d.action.dtype == np.float32 and np.array_equal(d.action, act)


def test_continuous_actions_declaring_too_many_steps_are_refused_unread():
    env = _env()
    env["action"] = {"dtype": "float32", "shape": [P.MAX_UNROLL_STEPS + 1, 2], "data": b""}
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "size"


def test_empty_unroll_refused_by_constructor_path_too():
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(_unroll(T=0).encode())
    assert e.value.reason == "batch"


def test_too_many_steps_refused():
    env = _env(_unroll(T=P.MAX_UNROLL_STEPS + 1))
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "size"


def _no_decompress(monkeypatch):
    called = []
    real = lz4.block.decompress
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: called.append(1) or real(*a, **k))
    return called


def test_huge_declared_steps_refused_unread(monkeypatch):
    """action claims 2^20 steps in a few bytes: refused from the shape alone."""
    called = _no_decompress(monkeypatch)
    env = _env()
    env["action"]["shape"] = [1 << 20]  # within MAX_DIM, past MAX_UNROLL_STEPS
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "size" and not called


def test_compressed_obs_with_wrong_rows_refused_before_decompressing(monkeypatch):
    img = np.zeros((T + 1, 84, 84), np.uint8)
    env = msgpack.unpackb(_unroll(obs={"obs": img}).encode(codec="lz4"), raw=False)
    assert env["obs"]["obs"]["codec"] == "lz4"
    env["obs"]["obs"]["shape"] = [T + 2, 84, 84]
    env["obs"]["obs"]["size"] = (T + 2) * 84 * 84
    called = _no_decompress(monkeypatch)
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "batch" and "rows" in str(e.value) and not called


def test_huge_declared_total_refused_before_decompressing(monkeypatch):
    """Each array within lz4's expansion bound but together over MAX_UNROLL_BYTES: refused from
    the declared numbers before any array is decompressed."""
    rows = T + 1
    per = 200 * 1024 * 1024 // rows  # two tables of ~200 MiB each
    blob = lz4.block.compress(bytes(rows * per), store_size=False)
    m = {"dtype": "uint8", "shape": [rows, per], "codec": "lz4", "size": rows * per, "data": blob}
    env = _env(_unroll())
    env["obs"] = {"obs/a": m, "obs/b": dict(m)}
    del env["final_obs"]
    env["truncated"] = _arr(np.zeros(T, bool))
    called = _no_decompress(monkeypatch)
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "size" and "refused unread" in str(e.value) and not called


def test_bomb_in_obs_refused(monkeypatch):
    img = np.zeros((T + 1, 84, 84), np.uint8)
    env = msgpack.unpackb(_unroll(obs={"obs": img}).encode(codec="lz4"), raw=False)
    side = 1 << 12
    env["obs"]["obs"].update(shape=[T + 1, side, side], size=(T + 1) * side * side)  # 96 MiB from a few KB
    called = _no_decompress(monkeypatch)
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "bomb" and not called
