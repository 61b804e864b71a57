"""The replay service in its own OS process, behind a real router, fed by two publisher
processes; a client samples and updates priorities; then malformed messages."""

import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.errors import NotReady
from zenrl.common.replay_client import ZenohReplayClient
from zenrl.common.transport import Node
from tests.conftest import replay_stats_reader, wait_until

pytestmark = pytest.mark.integration


def test_ingest_sample_update_and_reject(router, run_id, procs):
    keys = P.Keys(run_id)
    procs.zenrl("replay", ["replay", "--router", router, "--run-id", run_id,
                           "--set", "replay.min_size=1500", "--set", "replay.stats_interval_s=0.3",
                           "--set", "replay.capacity=5000",
                           # the publishers tag rewards with their seed (1e6 apart)
                           "--set", "replay.max_abs_reward=1e8"])
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        stats = replay_stats_reader(node, keys)
        client = ZenohReplayClient(node, keys, "learner", timeout_s=5.0)
        # not ready yet: answered at once, never a hang
        with pytest.raises(NotReady, match="min_size"):
            client.sample(32, 0.4)

        pubs = [procs.start(f"pub{i}", ["tests/integration/procs.py", "publish", "--router", router, "--run", run_id,
                                        "--actor", f"a{i}", "--chunks", "20", "--chunk", "50", "--seed", str(i + 1)])
                for i in range(2)]
        for p in pubs:
            assert p.wait(timeout=60) == 0
        # BLOCK congestion control: all 2 x 20 x 50 transitions arrive
        s = wait_until(lambda: (v := stats()) and v["inserted_total"] == 2000 and v, 30, "2000 inserted transitions")
        assert s["size"] == 2000 and s["rejected_total"] == 0

        b = client.sample(256, 0.5)
        assert b.keys.shape == (256,) and b.weights.shape == (256,) and b.replay_size == 2000
        assert b.data["obs"].shape == (256, 4) and b.data["meta/policy_version"].shape == (256,)
        assert (b.weights > 0).all() and abs(b.weights.max() - 1.0) < 1e-6
        assert np.all(b.probabilities > 0)
        rewards = b.data["reward"]
        assert set((rewards // 1_000_000).astype(int)) <= {1, 2}   # came from the two publishers

        # push one key's priority far up; it must then dominate sampling
        hot = int(b.keys[0])
        client.update_priorities(np.array([hot]), np.array([1e6], np.float32))

        def hot_dominates():
            s2 = client.sample(256, 0.5)
            return (s2.keys == hot).mean() > 0.5

        wait_until(hot_dominates, 10, "the updated priority to take effect")

        # a burst of malformed messages on every key the service listens to
        raw = node.publisher(keys.transitions("evil"))
        good = P.TransitionBatch("evil", 0, 0, {"obs": np.zeros((2, 4), np.float32)}).encode()
        bad_payloads = [
            b"\x00garbage",
            msgpack.packb({"v": 99, "t": "transitions"}),
            msgpack.packb({**msgpack.unpackb(good), "seq": -3}),
            P.TransitionBatch("evil", 0, 0, {"obs": np.zeros((2, 4), np.float32)}).encode(),  # wrong spec
            P.TransitionBatch("evil", 0, 0, {"obs": np.full((3, 4), np.nan, np.float32),
                                             "action": np.zeros(3, np.int64), "reward": np.zeros(3, np.float32),
                                             "next_obs": np.zeros((3, 4), np.float32), "terminated": np.zeros(3, bool),
                                             "n": np.ones(3, np.uint8)}).encode(),
            b"x" * (6 * 1024 * 1024),  # above replay.max_chunk_bytes (4 MiB), under twice it: refused, counted
        ]
        for payload in bad_payloads:
            raw.put(payload)
        node.publisher(keys.priorities).put(b"not msgpack")
        bad_req = node.query(keys.sample, b"\x93\x01\x02", 5.0)
        assert P.SampleReply.decode(bad_req).status == "not_ready"

        s = wait_until(lambda: (v := stats()) and v["rejected_total"] >= 8 and v, 30, "8 rejections in the stats")
        for reason in ("malformed", "version", "field", "spec", "nonfinite", "size"):
            assert s.get(f"rejected_{reason}", 0) >= 1, (reason, s)
        # ... and it still serves everyone else
        assert client.sample(64, 0.4).keys.shape == (64,)
        assert s["size"] == 2000
    assert "rejected message" in procs.log("replay")


def _honest(seq, b=16):
    data = {"obs": np.zeros((b, 4), np.float32), "action": np.ones(b, np.int64), "reward": np.ones(b, np.float32),
            "next_obs": np.zeros((b, 4), np.float32), "terminated": np.zeros(b, bool), "n": np.ones(b, np.uint8)}
    return P.TransitionBatch("a0", 1, seq, data).encode()


def test_a_message_that_raises_costs_only_itself(router, run_id, procs):
    """Messages the protocol admits but that raise something else between receipt and insert
    (an int64 column for a policy version of 2**64-1; a shape mixing a zero with dimensions whose
    product overflows) are counted as rejected; the ingest thread goes on with the next honest
    chunk, the replay reports no stalled thread and its health probe stays green."""
    from tests.integration.test_health import _health

    keys = P.Keys(run_id)
    procs.zenrl("replay", ["replay", "--router", router, "--run-id", run_id, "--set", "replay.stats_interval_s=0.3",
                           "--set", "replay.min_size=1"])
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        stats = replay_stats_reader(node, keys)
        evil, honest = node.publisher(keys.transitions("evil")), node.publisher(keys.transitions("a0"))
        huge_version = msgpack.packb({**msgpack.unpackb(_honest(0)), "policy_version": 2**64 - 1})
        m = msgpack.unpackb(_honest(0))
        m["data"]["obs"] = {"dtype": "float32", "shape": [2**32, 2**32, 0], "data": b""}
        evil.put(huge_version)
        evil.put(msgpack.packb(m))
        honest.put(_honest(1))
        s = wait_until(lambda: (v := stats()) and v["inserted_total"] == 16 and v["rejected_total"] == 2 and v, 30,
                       "the honest chunk inserted after two that raise")
        assert s["rejected_from/evil"] == 2 and s["stalled"] == "" and s["errors_total"] == 0, s
        honest.put(_honest(2))
        wait_until(lambda: (v := stats()) and v["inserted_total"] == 32, 30, "the next honest chunk inserted too")
        rc, out = _health(router, run_id, "--role", "replay", "--id", "replay", "--stats-within-s", "5")
        assert rc == 0, out
