"""Optional lz4 compression of uint8 arrays on the wire: round trip, raw and compressed both
accepted, and every declared number checked before a byte is decompressed (no bombs)."""

import lz4.block
import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.replay.service import ReplayService


def _frames(b=8):
    a = np.zeros((b, 84, 84), np.uint8)
    a[:, 20:30, 10:70] = np.arange(b, dtype=np.uint8)[:, None, None] + 100
    return a


def _batch(frames):
    b = frames.shape[0]
    return {"obs": frames, "action": np.zeros(b, np.int64), "reward": np.ones(b, np.float32),
            "next_obs": frames[::-1].copy(), "terminated": np.zeros(b, bool), "n": np.full(b, 3, np.uint8)}


def test_round_trip_and_size():
    data = _batch(_frames())
    raw = P.TransitionBatch("a0", 1, 0, data).encode()
    packed = P.TransitionBatch("a0", 1, 0, data).encode(codec="lz4")
    assert len(packed) < len(raw) / 10
    env = msgpack.unpackb(packed)
    assert env["data"]["obs"]["codec"] == "lz4" and env["data"]["obs"]["size"] == 8 * 84 * 84
    assert "codec" not in env["data"]["reward"]  # only uint8 arrays are compressed
    for payload in (raw, packed):
        msg = P.TransitionBatch.decode(payload)
        for k, v in data.items():
            np.testing.assert_array_equal(msg.data[k], v)


def _packed_env(**over):
    frames = _frames()
    env = msgpack.unpackb(P.TransitionBatch("a0", 1, 0, _batch(frames)).encode(codec="lz4"))
    env["data"]["obs"].update(over)
    return msgpack.packb(env, use_bin_type=True)


def test_bomb_is_refused_before_decompressing(monkeypatch):
    """A few hundred bytes that claim to expand to 1 GiB: refused from the declared numbers alone
    (decompression is never called), with a one-line reason, and counted by the replay."""
    called = []
    real = lz4.block.decompress
    monkeypatch.setattr(lz4.block, "decompress", lambda *a, **k: called.append(1) or real(*a, **k))
    bomb_data = lz4.block.compress(bytes(1 << 20), store_size=False)  # ~4 KB of zeros' worth
    shape = [1 << 14, 256, 256]  # 1 GiB of uint8, consistent with the declared size
    payload = _packed_env(shape=shape, size=1 << 30, data=bomb_data)
    with pytest.raises(P.ProtocolError, match="refused unread") as e:
        P.TransitionBatch.decode(payload)
    assert e.value.reason == "bomb" and not called
    svc = ReplayService(load_config(None, ["replay.capacity=100", "replay.check_semantics=false"], environ={}),  # no env to check against
                        node=None, run_id="r")
    assert svc.ingest(payload, "bad-actor") == 0
    assert svc.rejects.as_values()["rejected_bomb"] == 1 and not called
    # the replay keeps serving everyone else
    assert svc.ingest(P.TransitionBatch("a0", 1, 0, _batch(_frames())).encode(codec="lz4")) == 8


@pytest.mark.parametrize("over, match", [
    ({"size": 8 * 84 * 84 + 1}, "needs"),                 # size disagrees with the shape
    ({"size": "lots"}, "needs"),
    ({"codec": "zip"}, "not one of"),
    ({"dtype": "float32"}, "must be uint8"),
    ({"data": b"\x00garbage"}, "refused unread|not valid lz4"),
])
def test_bad_compressed_arrays_are_refused(monkeypatch, over, match):
    with pytest.raises(P.ProtocolError, match=match):
        P.TransitionBatch.decode(_packed_env(**over))


def test_declared_size_larger_than_the_data_gives():
    """Valid lz4 of fewer bytes than declared (lz4 alone would return the short result)."""
    short = lz4.block.compress(bytes(8 * 84 * 84 - 84), store_size=False)
    with pytest.raises(P.ProtocolError, match="decompresses to|not valid lz4"):
        P.TransitionBatch.decode(_packed_env(data=short))
