"""Sample replies gathered straight into their payload (:class:`zenrl.common.protocol.Rows`):
the bytes are those of the same reply with its arrays gathered first, and the replay writes the
rows while it holds its lock (the ingest would overwrite a frame ring's oldest slots)."""

from __future__ import annotations

import logging
import threading

import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.config import ReplayConfig
from zenrl.common.metrics import RejectCounter
from zenrl.common.specs import ArraySpec
from zenrl.replay.buffer import InMemoryReplay
from zenrl.replay.frames import FrameReplay
from zenrl.replay.sampling import Sampler


def _reply(data: dict, b: int) -> P.SampleReply:
    return P.SampleReply(9, "ok", "", 1000, np.arange(b, dtype=np.int64), np.full(b, 0.25), np.ones(b, np.float32),
                         data, mass=3.5)


def _gathered(data: dict) -> dict:
    return {k: v.array() if isinstance(v, P.Rows) else v for k, v in data.items()}


@pytest.mark.parametrize("seed", range(6))
def test_rows_pack_the_bytes_of_the_gathered_arrays(seed):
    """Rows of every wire dtype and of sizes on each side of msgpack's bin8 / bin16 / bin32
    headers, beside plain arrays, in maps of up to 20 fields (fixmap and map16): the payload
    is byte for byte the one the gathered arrays give, and decodes to them."""
    rng = np.random.default_rng(seed)
    b = int(rng.integers(1, 40))
    data: dict = {}
    for i in range(int(rng.integers(1, 21))):
        dtype = rng.choice(["uint8", "float32", "int64", "bool", "float64"])
        row = tuple(int(d) for d in rng.integers(1, 9, size=int(rng.integers(0, 3))))
        if rng.random() < 0.3:
            row = (int(rng.choice([1, 100, 300, 70000])),)  # rows of a few bytes up to a bin32 payload
        source = (rng.random((50, *row)) * 100).astype(dtype)
        idx = rng.integers(0, 50, size=b).astype(np.int64)
        if rng.random() < 0.7:
            lead = (b,) if rng.random() < 0.5 or not row else (b, 1)
            data[f"f{i}"] = P.Rows(source, idx, (*lead, *row))
        else:
            data[f"f{i}"] = source[idx]
    lazy, eager = _reply(data, b), _reply(_gathered(data), b)
    want = eager.encode()
    got = lazy.encode()
    assert bytes(got) == want
    back = P.SampleReply.decode(bytes(got))
    for k, v in _gathered(data).items():
        np.testing.assert_array_equal(back.data[k], v)
        assert back.data[k].dtype == v.dtype and back.data[k].shape == v.shape


def test_rows_with_a_codec_or_no_rows_are_gathered_first():
    rng = np.random.default_rng(1)
    src = rng.integers(0, 4, (30, 84, 84), dtype=np.uint8)
    idx = rng.integers(0, 30, 8).astype(np.int64)
    empty = P.Rows(src, idx[:0], (0, 84, 84))
    assert _reply({"obs": empty}, 8).encode() == _reply({"obs": src[idx[:0]]}, 8).encode()
    lazy = _reply({"obs": P.Rows(src, idx, (8, 84, 84))}, 8)
    eager = _reply({"obs": src[idx]}, 8)
    assert lazy.encode(codec="lz4") == eager.encode(codec="lz4")
    assert msgpack.unpackb(lazy.encode(codec="lz4"))["data"]["obs"]["codec"] == "lz4"


def test_rows_refuse_a_shape_their_rows_do_not_make():
    src = np.zeros((10, 4, 4), np.uint8)
    with pytest.raises(ValueError, match="do not make"):
        P.Rows(src, np.arange(3, dtype=np.int64), (3, 4, 5))
    assert P.Rows(src, np.arange(4, dtype=np.int64), (2, 2, 4, 4)).nbytes == 4 * 16


def _sampler(buf) -> Sampler:
    rcfg = ReplayConfig(min_size=1)
    return Sampler(rcfg, seed=3, max_bytes=P.DEFAULT_MAX_MESSAGE_BYTES, lock=threading.Lock(), buffer=lambda: buf,
                   rejects=RejectCounter(logging.getLogger("test"), "test"), sample_key="zenrl/t/replay/sample",
                   check_priorities=False)


def _frame_replay() -> FrameReplay:
    rng = np.random.default_rng(0)
    item = {"action": ArraySpec((), "int64"), "reward": ArraySpec((), "float32")}
    fr = FrameReplay(item, {"obs": ArraySpec((84, 84), "uint8")}, {"obs": 4, "next_obs": 4}, 200,
                     frames_per_item=1.2, seed=0)
    base = 0
    for _ in range(5):
        ids = np.arange(20)[:, None] + np.arange(4) + base
        fr.insert("a0", base, {"obs": rng.integers(0, 256, (26, 84, 84), dtype=np.uint8)},
                  {"action": rng.integers(0, 6, 20), "reward": rng.random(20).astype(np.float32)},
                  {"obs": ids, "next_obs": ids + 3}, rng.random(20) + 0.1)
        base += 26
    return fr


def _plain_replay() -> InMemoryReplay:
    rng = np.random.default_rng(0)
    spec = {"obs": ArraySpec((4, 64, 64), "uint8"), "small": ArraySpec((3,), "float32"), "action": ArraySpec((), "int64")}
    rb = InMemoryReplay(spec, 300, seed=0)
    rb.insert({"obs": rng.integers(0, 256, (100, 4, 64, 64), dtype=np.uint8), "small": rng.random((100, 3), dtype=np.float32),
               "action": rng.integers(0, 6, 100)}, rng.random(100) + 0.1)
    return rb


@pytest.mark.parametrize("make", [_frame_replay, _plain_replay], ids=["frames", "plain"])
def test_the_replay_s_reply_is_the_gathered_reply_written_under_its_lock(make, monkeypatch):
    buf = make()
    a, b = _sampler(buf), _sampler(buf)
    wrote = []

    def write(self, out, _orig=P.Rows.write):
        wrote.append(a.lock.locked())
        _orig(self, out)

    monkeypatch.setattr(P.Rows, "write", write)
    req = P.SampleRequest(1, 64, 0.4)
    for _ in range(3):
        got = a.on_sample(req.encode())
        want = b.reply(req).encode()
        assert bytes(got) == want
        assert P.SampleReply.decode(bytes(got)).status == "ok"
    assert wrote and all(wrote), "the rows were not written, or written without the replay's lock"
    assert a.sampled.total == b.sampled.total == 3
