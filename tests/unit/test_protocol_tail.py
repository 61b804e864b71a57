"""Large arrays in the message's tail (docs/protocol.md, "Large arrays"): they round-trip, the
receiver reads them in place (no copy), small arrays stay in the map, and every declared number
about the tail is checked."""

import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P


def _chunk(b=16):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (b + 3, 64, 64, 3), dtype=np.uint8)  # 233 KB: in the tail
    data = {"obs": np.arange(b, dtype=np.int64), "next_obs": np.arange(b, dtype=np.int64) + 3,
            "action": rng.integers(0, 5, b).astype(np.int64), "reward": rng.random(b).astype(np.float32),
            "terminated": np.zeros(b, bool), "truncated": np.zeros(b, bool), "n": np.full(b, 3, np.uint8),
            "big": rng.random((b, 2048)).astype(np.float32)}  # 128 KB float: in the tail too
    return P.TransitionBatch("a0", 2, 7, data, rng.random(b).astype(np.float32) + 0.1,
                             frames={"obs": frames}, frame_base=0)


def _split(payload):
    u = msgpack.Unpacker(raw=False)
    u.feed(payload)
    env = u.unpack()
    return env, payload[u.tell():]


def test_tail_round_trip_is_read_in_place():
    msg = _chunk()
    plain, tailed = msg.encode(), msg.encode(tail=True)
    assert tailed[1:6] == b"\xa4tail" and abs(len(tailed) - len(plain)) < 64
    env, tail = _split(tailed)
    assert env["tail"] == len(tail) == msg.frames["obs"].nbytes + msg.data["big"].nbytes
    assert set(env["frames"]["obs"]) == {"dtype", "shape", "at"} and set(env["data"]["big"]) == {"dtype", "shape", "at"}
    assert "data" in env["data"]["reward"]  # small arrays stay in the map
    got = P.TransitionBatch.decode(tailed)
    for k, v in msg.data.items():
        np.testing.assert_array_equal(got.data[k], v)
    np.testing.assert_array_equal(got.frames["obs"], msg.frames["obs"])
    np.testing.assert_array_equal(got.priorities, msg.priorities)
    # the frames are a view of the received payload: no copy was made
    assert np.shares_memory(got.frames["obs"], np.frombuffer(tailed, np.uint8))
    assert not got.frames["obs"].flags.writeable
    # decode_any takes the same path; a message without big arrays has no tail at all
    assert P.decode_any(tailed).seq == 7
    small = P.SampleRequest(1, 32, 0.4)
    assert small.encode(tail=True) == small.encode()


def test_tail_with_compression_and_sample_replies():
    msg = _chunk()
    packed = msg.encode(codec="lz4", tail=True)  # compressed arrays stay in the map
    env, tail = _split(packed)
    assert env["frames"]["obs"]["codec"] == "lz4" and env["data"]["big"]["at"] == 0
    np.testing.assert_array_equal(P.TransitionBatch.decode(packed).frames["obs"], msg.frames["obs"])
    b = 8
    reply = P.SampleReply(3, "ok", "", 100, np.arange(b, dtype=np.int64), np.full(b, 0.1), np.ones(b, np.float32),
                          {"obs": np.ones((b, 84, 84, 4), np.uint8), "action": np.zeros(b, np.int64)})
    got = P.SampleReply.decode(reply.encode(tail=True))
    np.testing.assert_array_equal(got.data["obs"], reply.data["obs"])


def _tampered(mutate):
    env, tail = _split(_chunk().encode(tail=True))
    tail = mutate(env, tail)
    out = msgpack.packb(env, use_bin_type=True) + tail
    assert out[1:6] == b"\xa4tail"
    return out


@pytest.mark.parametrize("mutate, field, reason", [
    (lambda e, t: t[:-1], "tail", "size"),                                        # truncated
    (lambda e, t: t + b"x", "tail", "size"),                                      # extra bytes
    (lambda e, t: (e.__setitem__("tail", len(t) + 5), t)[1], "tail", "size"),    # wrong declared length
    (lambda e, t: (e["frames"]["obs"].__setitem__("at", len(t) - 10), t)[1], "frames.obs.at", "shape"),
    (lambda e, t: (e["frames"]["obs"].__setitem__("at", -1), t)[1], "frames.obs.at", "shape"),
    (lambda e, t: (e["frames"]["obs"].__setitem__("at", "0"), t)[1], "frames.obs.at", "shape"),
    (lambda e, t: (e["frames"]["obs"].__setitem__("shape", [10 ** 6, 64, 64, 3]), t)[1], "frames.obs.at", "shape"),
    (lambda e, t: (e["frames"]["obs"].__setitem__("dtype", "object"), t)[1], "frames.obs.dtype", "dtype"),
])
def test_bad_tails_are_refused_by_name(mutate, field, reason):
    with pytest.raises(P.ProtocolError) as e:
        P.TransitionBatch.decode(_tampered(mutate))
    assert e.value.field == field and e.value.reason == reason, str(e.value)


def test_an_array_in_the_tail_of_a_message_without_one_is_refused():
    env, _ = _split(_chunk().encode(tail=True))
    del env["tail"]  # a plain map now: "at" names nothing
    with pytest.raises(P.ProtocolError, match="has no tail") as e:
        P.TransitionBatch.decode(msgpack.packb(env, use_bin_type=True))
    assert e.value.field in ("data.big", "frames.obs")
    with pytest.raises(P.ProtocolError) as e:  # garbage after the map of a plain message
        P.TransitionBatch.decode(_chunk(2).encode() + b"\x00" * 10)
    assert e.value.reason == "malformed"
