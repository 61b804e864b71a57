"""Frame-mode unrolls (frame-stacked image envs): each distinct frame of an unroll travels once,
the stacks as int64 frame ids, lz4-compressed when asked. Round trips against the plain unroll
(terminations, truncations with their final observations, reset padding), the ids reusing
exactly the shared frames, and the declared sizes of a lying sender (against the env's spec,
lz4's expansion bound, the rebuilt stacks' total) refused before anything is decompressed."""

import lz4.block
import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P

T, K, H = 6, 4, 32
SPEC = {"obs/image": ("uint8", (K, H, H)), "obs/v": ("float32", (2,))}


def _stack(hist):
    """The last K frames of an episode, padded with its first (FrameStackObservation's reset padding)."""
    h = hist[-K:]
    return np.stack([h[0]] * (K - len(h)) + h)


def _stacked_unroll(seed=0):
    """T steps over a stream of distinct frames: step 2 terminates, step 4 is truncated (its
    final stack in final_obs), each followed by a reset; 8 distinct frames are needed."""
    rng = np.random.default_rng(seed)
    stream = iter(rng.integers(0, 255, (64, H, H), dtype=np.uint8))
    hist = [next(stream)]
    obs, fin = [_stack(hist)], []
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    for t in range(T):
        hist.append(next(stream))
        if t == 2:
            term[t] = True
            hist = [next(stream)]
        elif t == 4:
            trunc[t] = True
            fin.append(_stack(hist))
            hist = [next(stream)]
        obs.append(_stack(hist))
    v = rng.normal(size=(T + 1, 2)).astype(np.float32)
    return P.Unroll(actor_id="a0", policy_version=3, seq=1, obs={"obs/image": np.stack(obs), "obs/v": v},
                    action=rng.integers(0, 3, T).astype(np.int64), behaviour_logp=np.full(T, -1.1, np.float32),
                    reward=np.ones(T, np.float32), terminated=term, truncated=trunc,
                    final_obs={"obs/image": np.stack(fin), "obs/v": np.zeros((1, 2), np.float32)})


def _assert_same(a, b):
    for k in ("action", "behaviour_logp", "reward", "terminated", "truncated"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    for group in ("obs", "final_obs"):
        x, y = getattr(a, group), getattr(b, group)
        assert x.keys() == y.keys()
        for k in x:
            assert x[k].dtype == y[k].dtype and x[k].shape == y[k].shape, k
            np.testing.assert_array_equal(x[k], y[k])


@pytest.mark.parametrize("codec", [None, "lz4"])
def test_frame_mode_round_trip_equals_the_plain_unroll(codec):
    u = _stacked_unroll()
    f = u.framed(["obs/image"])
    # 3 frames of the first episode, the reset after the termination and its next frame, the
    # truncated episode's last frame (final_obs), the next reset and its next frame
    assert f.frames["obs/image"].shape == (8, H, H)
    np.testing.assert_array_equal(f.obs["obs/image"], [[0, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 2], [3, 3, 3, 3],
                                                       [3, 3, 3, 4], [6, 6, 6, 6], [6, 6, 6, 7]])
    np.testing.assert_array_equal(f.final_obs["obs/image"], [[3, 3, 4, 5]])
    assert f.obs["obs/v"] is u.obs["obs/v"]  # fields that are not stacks stay arrays
    payload = f.encode(codec=codec)
    env = msgpack.unpackb(payload, raw=False)
    assert (env["frames"]["obs/image"].get("codec") == "lz4") == (codec == "lz4")
    d = P.Unroll.decode(payload, spec=SPEC)
    assert d.frames is not None and d.obs["obs/image"].shape == (T + 1, K)
    _assert_same(d.resolved(), u)
    # each frame once: ~T + K frames instead of (T + 1 + 1) * K
    assert len(payload) < len(u.encode()) / 2


def test_plain_unrolls_are_unchanged_by_frame_mode_helpers():
    u = _stacked_unroll()
    assert u.resolved() is u and u.framed([]) is u and u.framed(["obs/missing"]) is u
    assert "frames" not in msgpack.unpackb(u.encode(), raw=False)  # the plain wire form is as before
    with pytest.raises(ValueError):
        u.framed(["obs/v"])  # not a stack of frames


def test_lz4_shrinks_rendered_frames():
    u = _stacked_unroll()
    flat = {**u.obs, "obs/image": np.zeros_like(u.obs["obs/image"])}  # a flat image compresses many times
    f = P.Unroll(**{**u.__dict__, "obs": flat, "final_obs": {**u.final_obs, "obs/image": np.zeros((1, K, H, H), np.uint8)}})
    f = f.framed(["obs/image"])
    assert len(f.encode(codec="lz4")) < len(f.encode()) / 5
    np.testing.assert_array_equal(P.Unroll.decode(f.encode(codec="lz4"), spec=SPEC).resolved().obs["obs/image"], flat["obs/image"])


def _framed_env(codec="lz4"):
    return msgpack.unpackb(_stacked_unroll().framed(["obs/image"]).encode(codec=codec), raw=False)


def _no_decompress(monkeypatch):
    called = []
    real = lz4.block.decompress
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: called.append(1) or real(*a, **k))
    return called


def _decode(env, spec=SPEC):
    return P.Unroll.decode(msgpack.packb(env, use_bin_type=True), spec=spec)


def _frames_shape(shape):
    def edit(e):
        e["frames"]["obs/image"].update(shape=shape, size=int(np.prod(shape)))
    return edit


def _ids(a):
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


LIES = {
    # declared against the env's spec, refused unread
    "frames bigger than the spec's frame": (_frames_shape([8, 4 * H, 4 * H]), "spec"),
    "frames of another dtype": (lambda e: e["frames"]["obs/image"].update(dtype="float32"), "spec"),
    "ids of a deeper stack": (lambda e: e["obs"]["obs/image"].update(shape=[T + 1, K + 1]), "spec"),
    "plain image bigger than the spec": (lambda e: (e.pop("frames"), e["obs"].update({"obs/image": {
        "dtype": "uint8", "shape": [T + 1, K, 4 * H, H], "codec": "lz4", "size": (T + 1) * K * 4 * H * H,
        "data": lz4.block.compress(bytes((T + 1) * K * 4 * H * H), store_size=False)}})), "spec"),
    "frames of a field the env lacks": (lambda e: e["frames"].update({"obs/other": e["frames"]["obs/image"]}), "spec"),
    # lz4's own numbers
    "declared size not the shape's": (lambda e: e["frames"]["obs/image"].update(size=8 * H * H + 1), "shape"),
    "bomb": (lambda e: e["frames"]["obs/image"].update(data=e["frames"]["obs/image"]["data"][:16]), "bomb"),
}


@pytest.mark.parametrize("case", sorted(LIES))
def test_lying_declared_sizes_are_refused_before_decompressing(monkeypatch, case):
    edit, reason = LIES[case]
    env = _framed_env()
    edit(env)
    called = _no_decompress(monkeypatch)
    with pytest.raises(P.ProtocolError) as e:
        _decode(env)
    assert e.value.reason == reason, str(e.value)
    assert not called


def test_rebuilt_size_counts_against_the_unroll_cap(monkeypatch):
    """Ids declaring 2^20-deep stacks of 1 KiB frames (a rebuilt TiB) are refused from the declared
    numbers, without a spec and before decompressing."""
    env = _framed_env()
    env["obs"]["obs/image"] = {"dtype": "int64", "shape": [T + 1, 1 << 20], "data": b""}
    called = _no_decompress(monkeypatch)
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.reason == "size" and not called


BAD_IDS = {
    "id past the frames": (lambda e: e["obs"].update({"obs/image": _ids(np.full((T + 1, K), 8, np.int64))}), "field"),
    "negative id": (lambda e: e["obs"].update({"obs/image": _ids(np.full((T + 1, K), -1, np.int64))}), "field"),
    "final id past the frames": (lambda e: e["final_obs"].update({"obs/image": _ids(np.full((1, K), 99, np.int64))}), "field"),
    "ids int32": (lambda e: e["obs"].update({"obs/image": _ids(np.zeros((T + 1, K), np.int32))}), "dtype"),
    "ids 1-D": (lambda e: e["obs"].update({"obs/image": _ids(np.zeros(T + 1, np.int64))}), "shape"),
    "frames of no obs field": (lambda e: e["frames"].update({"obs/x": e["frames"]["obs/image"]}), "field"),
}


@pytest.mark.parametrize("case", sorted(BAD_IDS))
def test_bad_frame_ids_are_refused(case):
    edit, reason = BAD_IDS[case]
    env = _framed_env(codec=None)
    edit(env)
    with pytest.raises(P.ProtocolError) as e:
        P.Unroll.decode(msgpack.packb(env, use_bin_type=True))  # the form alone, no spec
    assert e.value.reason == reason, str(e.value)
