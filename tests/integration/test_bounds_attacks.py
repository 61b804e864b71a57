"""Issue #32 against real processes (a router, the replay service, an honest actor, a hostile
publisher that knows only docs/protocol.md): integers at the edges of their types, shapes that
overflow or hide huge dimensions behind a zero, compressed arrays whose declared sizes lie or
do not fit the env spec, frame-mode chunks at int64's edge or naming another actor. Every honest
transition is inserted, a sample query is answered, each attack is counted by its reason and
none as an internal error, and the replay's health stays true. Then a barrage of the largest
messages the checks admit (and a few beyond the message cap), from names invented for each
message: the replay's peak RSS (VmHWM) stays within 2x of its steady state (VmRSS with its
storage full)."""

from __future__ import annotations

import lz4.block
import msgpack
import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.replay_client import ZenohReplayClient
from zenrl.common.transport import Node
from tests.conftest import replay_stats_reader, wait_until
from tests.integration.test_health import _health

pytestmark = pytest.mark.integration

B = 16
#: replay.max_chunk_bytes at its default: what the barrage's messages are sized to (the replay's
#: session takes no larger message; the memory bound scales with it, see docs/architecture.md)
MAX_MESSAGE = 4 * 1024 * 1024


def _chunk(b, rng, bad_action=False):
    d = {"obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32), "action": rng.integers(0, 2, b),
         "reward": rng.uniform(-1, 1, b).astype(np.float32), "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
         "terminated": np.zeros(b, bool), "n": np.full(b, 3, np.uint8)}
    if bad_action:
        d["action"][-1] = 2  # found only by the last step: the checks read every byte first
    return d


def _env(rng):
    return msgpack.unpackb(P.TransitionBatch("x", 0, 0, _chunk(B, rng)).encode(), raw=False)


def _attacks(rng):
    """(reason the replay must count, payload), one per class; each from a name of its own."""
    out = []

    def env_with(**fields):
        e = _env(rng)
        e.update(fields)
        return e

    # integer fields at the edges of their types
    out.append(("field", env_with(policy_version=2**63)))
    out.append(("field", env_with(seq=2**64 - 1)))
    out.append(("field", env_with(seq=-1)))
    # shapes: a product that overflows behind a zero, too many dimensions, a dimension past MAX_DIM
    e = _env(rng)
    e["data"]["obs"] = {"dtype": "float32", "shape": [2**32, 2**32, 0], "data": b""}
    out.append(("shape", e))
    e = _env(rng)
    e["data"]["obs"] = {"dtype": "float32", "shape": [1] * 9 + [B], "data": bytes(64)}
    out.append(("shape", e))
    e = _env(rng)
    e["data"]["terminated"] = {"dtype": "bool", "shape": [B, 2**40], "data": b""}
    out.append(("shape", e))
    # compressed arrays: a bomb (more than lz4 can expand), a lie about the size, a field the env
    # spec has as float32, a declared size past the per-chunk decoded cap on a field it allows
    blob = lz4.block.compress(bytes(1 << 20), store_size=False)
    e = _env(rng)
    e["data"]["n"] = {"dtype": "uint8", "shape": [1 << 30], "codec": "lz4", "size": 1 << 30, "data": blob}
    out.append(("bomb", e))
    e = _env(rng)
    e["data"]["n"] = {"dtype": "uint8", "shape": [B], "codec": "lz4", "size": 2**31, "data": blob}
    out.append(("shape", e))
    e = _env(rng)
    e["data"]["obs"] = {"dtype": "uint8", "shape": [B, 16], "codec": "lz4", "size": B * 16,
                        "data": lz4.block.compress(bytes(B * 16), store_size=False)}
    out.append(("spec", e))
    zeros = lz4.block.compress(bytes(100 << 20), store_size=False)
    big = min(100 << 20, P.LZ4_MAX_RATIO * len(zeros))  # what lz4 could expand it to: not a bomb
    assert big > 64 << 20  # but past replay.max_decoded_bytes
    e = _env(rng)
    e["data"]["n"] = {"dtype": "uint8", "shape": [big], "codec": "lz4", "size": big, "data": zeros}
    out.append(("size", e))
    # frame mode at int64's edge, ids of a wrong type, and a chunk naming another actor
    fb = P.TransitionBatch("x", 0, 0, {**_chunk(B, rng), "obs": np.arange(B, dtype=np.int64),
                                       "next_obs": np.arange(1, B + 1, dtype=np.int64)},
                           frames={"obs": rng.uniform(-0.4, 0.4, (B + 1, 4)).astype(np.float32)}, frame_base=0)
    e = msgpack.unpackb(fb.encode(), raw=False)
    e["frame_base"] = 2**63 - 1
    out.append(("field", e))
    e = msgpack.unpackb(fb.encode(), raw=False)
    e["data"]["obs"] = {**e["data"]["obs"], "dtype": "uint64"}
    out.append(("dtype", e))
    e = msgpack.unpackb(fb.encode(), raw=False)
    e["actor_id"] = "honest"
    out.append(("source", e))
    return [(reason, msgpack.packb(e, use_bin_type=True)) for reason, e in out]


def _mem(pid):
    v = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            k, _, rest = line.partition(":")
            if k in ("VmRSS", "VmHWM"):
                v[k] = int(rest.split()[0]) * 1024
    return v


@pytest.mark.slow
def test_each_attack_class_is_counted_and_memory_stays_bounded(router, run_id, procs, tmp_path):
    keys = P.Keys(run_id)
    capacity = 2_000_000  # Ape-X's replay size
    replay = procs.zenrl("replay", ["replay", "--router", router, "--run-id", run_id, "--set", f"runs_dir={tmp_path}",
                                    "--set", "replay.stats_interval_s=0.3", "--set", "replay.min_size=1",
                                    "--set", f"replay.capacity={capacity}", "--set", "replay.quarantine_rejections=5"])
    rng = np.random.default_rng(0)
    honest_chunks = 150
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        stats = replay_stats_reader(node, keys)
        last = {}

        def latest():
            v = stats()
            if v:
                last.clear()
                last.update(v)
            return dict(last)

        good = procs.start("honest", ["tests/integration/procs.py", "publish", "--router", router, "--run", run_id,
                                      "--actor", "honest", "--chunks", str(honest_chunks), "--chunk", "64", "--seed", "3",
                                      "--plain", "--pause-s", "0.01"])
        attacks = _attacks(rng)
        for i, (reason, payload) in enumerate(attacks):
            node.publisher(keys.transitions(f"evil{i}")).put(payload)

        want: dict[str, int] = {}
        for reason, _ in attacks:
            want[reason] = want.get(reason, 0) + 1

        def counted():
            v = latest()
            return v if all(v.get(f"rejected_{r}", 0) >= n for r, n in want.items()) else None

        try:
            s = wait_until(counted, 60, "every attack counted by its reason")
        except AssertionError:
            raise AssertionError(f"want {want}, replay stats: {latest()}") from None
        assert good.wait(120) == 0
        s = wait_until(lambda: (v := latest()).get("inserted_total") == honest_chunks * 64 and v, 30,
                       "every honest transition inserted")
        assert s["rejected_total"] == len(attacks) and "rejected_internal" not in s, s
        assert all(s[f"rejected_{r}"] == n for r, n in want.items()), (want, s)
        assert s["stalled"] == "" and s["errors_total"] == 0
        # a sample query is answered
        got = ZenohReplayClient(node, keys, "learner-probe", timeout_s=10.0).sample(32, 0.4)
        assert got.keys.shape == (32,) and got.data["obs"].shape == (32, 4)
        assert _health(router, run_id, "--role", "replay", "--id", "replay", "--stats-within-s", "5")[0] == 0

        # -- memory: fill the storage, then a barrage of the largest messages the checks admit --
        cap = MAX_MESSAGE
        rows = (cap - 4096) // 46  # 46 bytes a transition
        filler = node.publisher(keys.transitions("filler"))
        parts = -(-capacity // rows)  # chunks under the cap that fill the storage
        per = -(-capacity // parts)
        full = P.TransitionBatch("filler", 0, 0, _chunk(per, rng)).encode(cap)
        for i in range(parts):  # one at a time: none is dropped by a full queue on a loaded machine
            filler.put(full)
            wait_until(lambda: latest().get("inserted_total", 0) >= honest_chunks * 64 + (i + 1) * per,
                       60, f"filler chunk {i + 1} inserted")
        s = wait_until(lambda: (v := latest()).get("size") == capacity and v, 30, "the storage full")
        steady = _mem(replay.pid)["VmRSS"]
        with open(f"/proc/{replay.pid}/clear_refs", "w") as f:
            f.write("5")  # the peak starts again from here
        bad = P.TransitionBatch("x", 0, 0, _chunk(rows, rng, bad_action=True)).encode(cap)
        good_big = P.TransitionBatch("x", 0, 0, _chunk(rows, rng)).encode(cap)
        assert len(bad) > cap * 0.99
        n_bad, n_good = 12, 4
        base = latest()
        over = bytes(cap + cap // 2)  # past the cap, within Zenoh's: refused unqueued, counted
        junk = bytes(6 * cap)  # past twice the message cap: Zenoh drops it as its fragments arrive
        for i in range(n_bad + n_good):  # a new name for each: no quarantine spares the checks
            node.publisher(keys.transitions(f"big{i}")).put(bad if i % 4 else good_big)
            if i % 8 == 0:
                node.publisher(keys.transitions(f"huge{i}")).put(junk)
                node.publisher(keys.transitions(f"over{i}")).put(over)

        def barrage_done():
            v = latest()
            handled = (v.get("rejected_action_range", 0) - base.get("rejected_action_range", 0)
                       + v.get("dropped_queue_full", 0) - base.get("dropped_queue_full", 0))
            stored = (v.get("inserted_total", 0) - base["inserted_total"]) // rows
            oversized = v.get("rejected_size", 0) - base.get("rejected_size", 0)
            return v if handled + stored >= n_bad + n_good and oversized == 2 else None

        try:
            s = wait_until(barrage_done, 180, "the barrage handled")
        except AssertionError:
            raise AssertionError(f"replay stats: {latest()}") from None
        peak = _mem(replay.pid)["VmHWM"]
        assert "rejected_internal" not in s and s["stalled"] == ""
        assert peak <= 2 * steady, f"peak RSS {peak >> 20} MiB over 2x the steady {steady >> 20} MiB"
        assert _health(router, run_id, "--role", "replay", "--id", "replay", "--stats-within-s", "5")[0] == 0
        assert replay.poll() is None
    assert "Traceback" not in procs.log("replay")
