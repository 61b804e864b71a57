"""An actor's chunk over the replay's cap (``replay.max_chunk_bytes``, which the replay would
drop) is sent as halves, in order and whole; where it cannot be split (frame mode, one item) it is
counted and not sent."""

from types import SimpleNamespace

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.replay_client import ZenohReplayClient


class Pub:
    matching_status = SimpleNamespace(matching=True)

    def __init__(self) -> None:
        self.puts: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.puts.append(payload)


class Node:
    def __init__(self) -> None:
        self.pub = Pub()

    def publisher(self, key: str, **_kw) -> Pub:
        return self.pub


def _batch(n: int, rng) -> dict:
    return {"obs": rng.normal(size=(n, 64)).astype(np.float32), "next_obs": rng.normal(size=(n, 64)).astype(np.float32),
            "action": np.arange(n, dtype=np.int64), "reward": np.ones(n, np.float32),
            "n": np.full(n, 3, np.uint8), "terminated": np.zeros(n, bool)}


def test_oversized_chunk_goes_as_ordered_halves():
    rng = np.random.default_rng(0)
    one = len(P.TransitionBatch(actor_id="a", policy_version=1, seq=0, data=_batch(40, rng)).encode())
    node = Node()
    client = ZenohReplayClient(node, P.Keys("unit"), "a", max_message_bytes=one)  # 40 items fit, 100 do not
    b, pr = _batch(100, rng), rng.random(100).astype(np.float32)
    client.insert(b, pr, policy_version=7)
    msgs = [P.TransitionBatch.decode(p) for p in node.pub.puts]
    assert [len(m.data["action"]) for m in msgs] == [25, 25, 25, 25]
    assert all(len(p) <= one for p in node.pub.puts)
    np.testing.assert_array_equal(np.concatenate([m.data["action"] for m in msgs]), b["action"])
    np.testing.assert_array_equal(np.concatenate([m.data["obs"] for m in msgs]), b["obs"])
    np.testing.assert_array_equal(np.concatenate([m.priorities for m in msgs]), pr)
    assert {m.policy_version for m in msgs} == {7}
    assert (client.split_chunks, client.oversized_chunks, client.undelivered_chunks, client.sent_chunks) == (3, 0, 0, 4)


def test_a_chunk_that_cannot_be_split_is_counted_not_sent():
    rng = np.random.default_rng(1)
    node = Node()
    client = ZenohReplayClient(node, P.Keys("unit"), "a", max_message_bytes=300)
    client.insert(_batch(1, rng))  # one item over the cap
    frames = {"obs": rng.integers(0, 255, size=(4, 84, 84), dtype=np.uint8)}
    data = {"obs": np.zeros((2, 4), np.int64), "next_obs": np.ones((2, 4), np.int64), "action": np.zeros(2, np.int64),
            "reward": np.zeros(2, np.float32), "n": np.ones(2, np.uint8), "terminated": np.zeros(2, bool)}
    client.insert(data, frames=frames, frame_base=0)  # frame mode: items refer to the chunk's frames
    assert node.pub.puts == []
    assert (client.split_chunks, client.oversized_chunks, client.undelivered_chunks) == (0, 2, 2)
