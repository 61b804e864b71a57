"""Hostile and buggy actors against a real replay and a real Ape-X learner (separate OS
processes behind a real router): targeted semantic attacks, a flood from one source, and
hypothesis-driven mutations of valid chunks. Pass: nothing crashes, every weights message the
learner publishes is finite, the flooder is quarantined (visible in the replay's stats and as a
liveliness token) while an honest publisher's data keeps flowing and the learner keeps
training."""

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zenrl.common import protocol as P
from zenrl.common.transport import Node
from tests.conftest import wait_until

pytestmark = pytest.mark.integration

B = 16


def _valid(rng):
    return {
        "obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32),
        "action": rng.integers(0, 2, B),
        "reward": rng.uniform(-1, 1, B).astype(np.float32),
        "next_obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32),
        "terminated": np.zeros(B, bool),
        "n": np.full(B, 3, np.uint8),
    }, rng.uniform(0.1, 1, B).astype(np.float32)


def _attacks(rng):
    """(actor id, data, priorities, the reason the replay must give)."""
    out = []

    def add(who, reason, **change):
        d, p = _valid(rng)
        for k, (row, v) in change.items():
            if k == "prio":
                p[row] = v
            else:
                d[k][row] = v
        out.append((who, d, p, reason))

    add("evil-action", "action_range", action=(3, 7))
    add("evil-reward", "reward_bound", reward=(0, 3e38))
    add("evil-obs", "obs_bounds", obs=((2, 2), 0.9))
    add("evil-n0", "n_range", n=(1, 0))
    add("evil-n9", "n_range", n=(1, 9))
    add("evil-prio", "priority_bound", prio=(5, 1e30))
    d, p = _valid(rng)
    d["obs"] = d["obs"].astype(np.float64)
    out.append(("evil-dtype", d, p, "spec"))  # differs from the storage (allocated from the env spec)
    return out


def _stats(node, keys, role, ident):
    latest = node.subscribe_latest(keys.stats(role, ident))
    last = {}

    def get():
        raw = latest.take()
        if raw is not None:
            last.clear()
            last.update(P.Stats.decode(raw).values)
        return dict(last)

    return get


_FIELDS = ["obs", "action", "reward", "next_obs", "terminated", "n", "priorities"]


@st.composite
def mutations(draw):
    """One mutation of a valid chunk: a value written into one field, or the encoded payload's
    bytes altered."""
    kind = draw(st.sampled_from(["value", "value", "bytes", "truncate", "envelope"]))
    if kind == "value":
        field = draw(st.sampled_from(_FIELDS))
        row = draw(st.integers(0, B - 1))
        v = draw(st.one_of(st.integers(-2**63, 2**63 - 1), st.floats(width=32), st.booleans()))
        return kind, (field, row, v)
    if kind == "bytes":
        return kind, (draw(st.integers(0, 10_000)), draw(st.integers(0, 255)))
    if kind == "truncate":
        return kind, draw(st.integers(0, 10_000))
    key = draw(st.sampled_from(["actor_id", "policy_version", "seq", "data", "priorities", "v", "t"]))
    v = draw(st.one_of(st.none(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=20),
                       st.binary(max_size=20), st.lists(st.integers(-2**63, 2**64 - 1), max_size=3)))
    return kind, (key, v)


def _mutated_payload(rng, mutation):
    d, p = _valid(rng)
    kind, arg = mutation
    if kind == "value":
        field, row, v = arg
        target = p if field == "priorities" else d[field]
        with np.errstate(all="ignore"):
            try:
                target[(row,) + (0,) * (target.ndim - 1)] = v
            except (OverflowError, ValueError):  # not representable in that dtype: keep it valid
                pass
    payload = P.TransitionBatch("fuzz", 0, 0, d, p).encode()
    if kind == "bytes":
        i, b = arg
        payload = payload[:i % len(payload)] + bytes([b]) + payload[i % len(payload) + 1:]
    elif kind == "truncate":
        payload = payload[:arg % len(payload)]
    elif kind == "envelope":
        env = msgpack.unpackb(payload, raw=False)
        env[arg[0]] = arg[1]
        payload = msgpack.packb(env, use_bin_type=True)
    return payload


def test_hostile_actors_cannot_crash_or_poison(router, run_id, procs, tmp_path):
    keys = P.Keys(run_id)
    common = ["--router", router, "--run-id", run_id, "--set", f"runs_dir={tmp_path}"]
    replay = procs.zenrl("replay", ["replay", *common, "--set", "replay.min_size=200",
                                    "--set", "replay.stats_interval_s=0.3", "--set", "replay.capacity=20000",
                                    "--set", "replay.max_abs_reward=1e3", "--set", "replay.max_priority=1e4",
                                    "--set", "replay.quarantine_rejections=5", "--set", "replay.quarantine_s=60"])
    learner = procs.zenrl("learner", ["learner", *common, "--set", "learner.batch_size=32",
                                      "--set", "network.hidden=[32]", "--set", "learner.publish_every_updates=5",
                                      "--set", "learner.log_interval_s=0.3", "--set", "learner.requests_in_flight=2"])
    with Node(router, 10.0) as node:
        weights: list[bytes] = []
        node.subscribe(keys.weights, lambda _k, payload: weights.append(payload))
        replay_stats = _stats(node, keys, "replay", "replay")
        learner_stats = _stats(node, keys, "learner", "learner")
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay's liveliness token")
        good = procs.start("good", ["tests/integration/procs.py", "publish", "--router", router, "--run", run_id,
                                    "--actor", "honest", "--chunks", "100000", "--chunk", "64", "--seed", "7",
                                    "--plain", "--pause-s", "0.02"])
        wait_until(lambda: learner_stats().get("updates", 0) >= 20, 90, "the learner's first 20 updates")

        rng = np.random.default_rng(0)
        pubs = {}

        def put(who, payload):
            if who not in pubs:
                pubs[who] = node.publisher(keys.transitions(who))
            pubs[who].put(payload)

        # targeted semantic attacks, each from its own id
        attacks = _attacks(rng)
        for who, d, p, _ in attacks:
            put(who, P.TransitionBatch(who, 0, 0, d, p).encode())
        # a flood of out-of-range actions from one source: quarantined after 5
        for _ in range(40):
            d, p = _valid(rng)
            d["action"][:] = 7
            put("flooder", P.TransitionBatch("flooder", 0, 0, d, p).encode())
        # absurd priority updates on the learner's key
        node.publisher(keys.priorities).put(P.PriorityUpdate(np.arange(10, dtype=np.int64),
                                                             np.full(10, 1e30, np.float32)).encode())

        # hypothesis: mutations of valid chunks from a few fuzzing ids
        sent = [0]

        @settings(max_examples=150, deadline=None, database=None, derandomize=True,
                  suppress_health_check=list(HealthCheck))
        @given(m=mutations())
        def fuzz(m):
            # a new id every 4 examples: below the quarantine threshold, so every mutation is read
            put(f"fuzz{sent[0] // 4}", _mutated_payload(rng, m))
            sent[0] += 1

        fuzz()
        assert sent[0] == 150

        def all_counted():
            s = replay_stats()
            return s if all(s.get(f"rejected_{r}", 0) >= 1 for *_, r in attacks) and s.get("quarantined", 0) >= 1 else None

        try:
            s = wait_until(all_counted, 30, "every attack counted and the flooder quarantined")
        except AssertionError:
            raise AssertionError(f"replay stats: {replay_stats()}") from None
        assert not any(k.startswith("fuzz") for k in s["quarantined_sources"].split("; "))
        assert "flooder (action_range" in s["quarantined_sources"], s["quarantined_sources"]
        assert s["rejected_from/flooder"] >= 5  # the most rejected sources are listed by name
        assert node.alive_now(keys.quarantined("flooder"), 2.0)  # frees its slot (see actor.slots)
        assert not node.alive_now(keys.quarantined("honest"), 1.0)
        # from now on the flooder's chunks are dropped unread
        rej0, drop0 = s["rejected_from/flooder"], s["dropped_quarantined"]
        for _ in range(10):
            put("flooder", P.TransitionBatch("flooder", 0, 0, *_valid(rng)).encode())
        s = wait_until(lambda: (v := replay_stats()).get("dropped_quarantined", 0) >= drop0 + 10 and v, 20,
                       "the quarantined flooder's chunks dropped")
        assert s["rejected_from/flooder"] == rej0

        # the honest publisher's data keeps coming in and the learner keeps training on it
        ins0, upd0 = s["inserted_total"], learner_stats()["updates"]
        wait_until(lambda: replay_stats().get("inserted_total", 0) >= ins0 + 640, 30, "10 more honest chunks")
        wait_until(lambda: learner_stats().get("updates", 0) >= upd0 + 50, 60, "50 more learner updates")
        wait_until(lambda: len(weights) >= 5, 30, "weights broadcasts")

        assert replay.poll() is None and learner.poll() is None and good.poll() is None
        n_weights = len(weights)
        for raw in list(weights):
            w = P.Weights.decode(raw)  # raises on NaN/Inf
            assert all(np.isfinite(a).all() for a in w.params.values())
        assert n_weights >= 5
    assert "Traceback" not in procs.log("replay") and "Traceback" not in procs.log("learner")
