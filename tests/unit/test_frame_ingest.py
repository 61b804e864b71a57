"""Frame-mode chunks through the replay service's ingest path (no network): what an actor's
n-step builder sends in frame mode is sampled back exactly as plain mode would have stored it,
survives a durable restore, and bad frame chunks are rejected and counted alone."""

import numpy as np
import pytest

from zenrl.actor.nstep import NStepBlocks
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.replay.service import ReplayService
from zenrl.replay.store import POLICY_VERSION_FIELD


def _stream(k, steps, seed=0, E=2, n=3, cut=False):
    """(plain block, frame block) pairs of one simulated actor over unique 3x3 frames (``cut``:
    both builders with ``cut_non_greedy``; about half the random actions are not greedy)."""
    rng = np.random.default_rng(seed)
    plain = NStepBlocks(E, n, 0.9, block_steps=4, cut_non_greedy=cut)
    framed = NStepBlocks(E, n, 0.9, block_steps=4, frame_stack=k, cut_non_greedy=cut)
    u = [0]

    def frame():
        u[0] += 1
        return np.full((3, 3), u[0] % 251, np.uint8) + np.eye(3, dtype=np.uint8) * (u[0] // 251)

    stacks = [[frame()] * max(k, 1) for _ in range(E)]
    left = rng.integers(2, 12, E)
    out = []
    for _ in range(steps):
        obs = {"obs": np.stack([np.stack(s) if k else s[0] for s in stacks])}
        nxt = [s[1:] + [frame()] for s in stacks]
        left -= 1
        done = left == 0
        final = {"obs": np.stack([np.stack(s) if k else s[-1] for s in nxt])}
        for e in np.flatnonzero(done):
            nxt[e] = [frame()] * max(k, 1)
            left[e] = rng.integers(2, 12)
        stacks = nxt
        args = (rng.random((E, 2)).astype(np.float32), rng.integers(0, 2, E), rng.random(E), final,
                done & (rng.random(E) < 0.5), np.zeros(E, bool), lambda o: np.zeros(len(o["obs"])))
        term = args[4]
        args = args[:5] + (done & ~term,) + args[6:]
        bp, bf = plain.add(obs, *args), framed.add(obs, *args)
        if bp is not None:
            out.append((bp, bf))
    return out


def _service(tmp_path=None, **over):
    # synthetic 3x3 frames match no registered env: the env checks are tested with a checker
    # of their spec below
    sets = {"capacity": 500, "min_size": 1, "check_semantics": False, **over}
    if tmp_path is not None:
        sets.update({"durable": True, "segment_items": 50, "log_dir": str(tmp_path / "log")})
    return ReplayService(load_config(None, [f"replay.{k}={v}" for k, v in sets.items()], environ={}), node=None, run_id="r")


def _framed_payload(bf, seq, actor="a0"):
    return P.TransitionBatch(actor, seq, seq, bf.data, bf.priorities, frames=bf.frames, frame_base=bf.frame_base).encode()


def _check_samples(svc, plain_by_key):
    s = svc.buffer.sample(128, 0.4, np.random.default_rng(1))
    for i, key in enumerate(s.keys.tolist()):
        for f, v in plain_by_key[key].items():
            np.testing.assert_array_equal(s.data[f][i], v, err_msg=f"key {key} {f}")


@pytest.mark.parametrize("cut", [False, True])
@pytest.mark.parametrize("k", [0, 4])
def test_frame_chunks_sample_back_like_plain_ones(k, cut):
    svc = _service()
    plain_by_key = {}
    pairs = _stream(k, 60, cut=cut)
    if cut:  # windows cut inside the episode (n < 3, neither terminated nor truncated)
        assert any(((bp.data["n"] < 3) & ~bp.data["terminated"] & ~bp.data["truncated"]).any() for bp, _ in pairs)
    for seq, (bp, bf) in enumerate(pairs):
        first = svc.buffer.inserts_total if svc.buffer is not None else 0
        assert svc.ingest(_framed_payload(bf, seq)) == len(bp)
        for r in range(len(bp)):
            plain_by_key[first + r] = {**{f: v[r] for f, v in bp.data.items()}, POLICY_VERSION_FIELD: seq}
    assert svc.buffer.size == len(plain_by_key)
    _check_samples(svc, plain_by_key)
    # each frame stored once: far fewer frames than 2 obs per transition (2k frames when stacked)
    assert svc.buffer.frames_stored < 1.3 * svc.buffer.size
    assert svc.stats_values()["frames_stored"] == svc.buffer.frames_stored


def test_durable_restore_of_frame_chunks(tmp_path):
    a = _service(tmp_path)
    plain_by_key = {}
    for seq, (bp, bf) in enumerate(_stream(4, 50, seed=3)):
        first = a.buffer.inserts_total if a.buffer is not None else 0
        a.ingest(_framed_payload(bf, seq))
        for r in range(len(bp)):
            plain_by_key[first + r] = {f: v[r] for f, v in bp.data.items()}
    a.close()
    b = _service(tmp_path)
    assert b.buffer.inserts_total == a.buffer.inserts_total and b.buffer.size == a.buffer.size
    _check_samples(b, plain_by_key)


def test_bad_frame_chunks_are_rejected_alone():
    svc = _service()
    pairs = _stream(0, 20)
    _, bf = pairs[0]
    bad_id = dict(bf.data, next_obs=bf.data["next_obs"] + 10_000)  # names frames never sent
    with pytest.raises(P.ProtocolError, match="frame ids must be in"):
        P.TransitionBatch.decode(P.TransitionBatch("a0", 0, 0, bad_id, frames=bf.frames, frame_base=bf.frame_base).encode())
    with pytest.raises(P.ProtocolError, match="frames and frame_base"):
        P.TransitionBatch.decode(P.TransitionBatch("a0", 0, 0, bf.data, frames=bf.frames).encode())
    # a full-observation chunk sent to a frame-mode replay is refused with a reason
    assert svc.ingest(_framed_payload(bf, 0)) == len(pairs[0][0])
    assert svc.ingest(P.TransitionBatch("a1", 0, 0, pairs[1][0].data).encode()) == 0
    assert svc.rejects.as_values().get("rejected_spec", 0) == 1
    # a later chunk whose earlier chunk was lost: its transitions referring back are dropped, counted
    n = svc.ingest(_framed_payload(pairs[2][1], 2))
    assert n < len(pairs[2][0]) and svc.buffer.unresolved == len(pairs[2][0]) - n
    assert svc.ingest(_framed_payload(pairs[3][1], 3)) == len(pairs[3][0])


def test_frame_chunks_are_checked_against_the_env_spec():
    """Frame mode is no way around the semantic checks: actions, n, rewards and the frames'
    dtype and shape are checked before anything is stored, and a bad chunk costs only itself."""
    from zenrl.replay.checks import ChunkChecker, ObsRule

    svc = _service()
    svc.checker = ChunkChecker({"obs": ObsRule("uint8", (3, 3))}, n_actions=2, n_step=3, max_abs_reward=1e6,
                               max_priority=1e9)
    stream = _stream(0, 40)
    good = [bf for _, bf in stream]
    assert svc.ingest(_framed_payload(good[0], 0)) == good[0].data["action"].shape[0]
    bad_action = good[1].data.copy()
    bad_action["action"] = np.full_like(good[1].data["action"], 7)
    bad_n = good[1].data.copy()
    bad_n["n"] = np.full_like(good[1].data["n"], 9)
    for data, frames, reason in ((bad_action, good[1].frames, "action_range"), (bad_n, good[1].frames, "n_range"),
                                 (good[1].data, {"obs": good[1].frames["obs"].astype(np.float32)}, "fields")):
        payload = P.TransitionBatch("evil", 1, 1, data, good[1].priorities, frames=frames,
                                    frame_base=good[1].frame_base).encode()
        assert svc.ingest(payload, "zenrl/r/transitions/evil") == 0
        assert svc.rejects.counts[reason] >= 1, (reason, dict(svc.rejects.counts))
    assert svc.rejected_by_source["evil"] == 3
    # the honest actor's next chunk still goes in
    assert svc.ingest(_framed_payload(good[1], 1)) == good[1].data["action"].shape[0]


def test_frame_chunks_queued_together_store_what_one_at_a_time_stores(tmp_path):
    """The ingest thread takes every queued chunk at once (``ingest_many``): two actors' frame
    chunks interleaved, a chunk of another frame shape, one with a NaN priority and one that
    refers back to a lost chunk in the same batch are each rejected or dropped alone, and the
    store (keys, samples, what the log restores) is that of one ingest per chunk."""
    a_pairs, b_pairs = _stream(4, 40, seed=5), _stream(4, 40, seed=6)
    payloads = []
    for i in range(min(len(a_pairs), len(b_pairs))):
        payloads.append((_framed_payload(a_pairs[i][1], i, "a0"), "zenrl/r/transitions/a0"))
        if i != 3:  # b1's chunk 3 is lost: b1's chunk 4 refers back into it
            payloads.append((_framed_payload(b_pairs[i][1], i, "b1"), "zenrl/r/transitions/b1"))
    bf = a_pairs[0][1]
    wrong_shape = P.TransitionBatch("c2", 0, 0, bf.data, bf.priorities, frames={"obs": bf.frames["obs"][:, :, :2]},
                                    frame_base=0).encode()
    nan_prio = P.TransitionBatch("c3", 0, 0, bf.data, np.full_like(bf.priorities, np.nan), frames=bf.frames,
                                 frame_base=0).encode()
    payloads[6:6] = [(wrong_shape, "zenrl/r/transitions/c2"), (nan_prio, "zenrl/r/transitions/c3")]

    one = _service()
    for p, src in payloads:
        first = one.buffer.inserts_total if one.buffer is not None else 0
        got = one.ingest(p, src)
        if src.endswith(("c2", "c3")):
            assert got == 0
            continue
        msg = P.TransitionBatch.decode(p)
        if got == msg.batch_size:  # stored whole: with the priorities it was sent with
            keys = np.arange(first, first + got, dtype=np.int64)
            buf = one.buffer
            want = (msg.priorities.astype(np.float64) + buf._inner.eps) ** buf._inner.alpha  # the tree's values
            np.testing.assert_allclose(buf.priorities_of(keys), want, rtol=1e-6)
    many = _service(tmp_path)
    inserted = sum(many.ingest_many(payloads[i:i + 16]) for i in range(0, len(payloads), 16))

    assert inserted == one.inserted.total == many.inserted.total
    assert many.buffer.inserts_total == one.buffer.inserts_total and many.buffer.size == one.buffer.size
    assert many.buffer.unresolved == one.buffer.unresolved > 0
    assert dict(many.rejects.counts) == dict(one.rejects.counts)
    assert many.rejected_by_source["c2"] == 1 and many.rejected_by_source["c3"] == 1
    keys = np.arange(one.buffer.inserts_total, dtype=np.int64)
    np.testing.assert_array_equal(many.buffer.priorities_of(keys), one.buffer.priorities_of(keys))
    s = many.buffer.sample(64, 0.4, np.random.default_rng(2))
    sampled = {int(k): s.data["obs"][i] for i, k in enumerate(s.keys)}
    for key, img in sampled.items():  # a stack sampled from the batched store is the one-at-a-time one
        np.testing.assert_array_equal(img, _obs_of(one, key))
    many.close()
    restored = _service(tmp_path)
    assert restored.buffer.inserts_total == many.buffer.inserts_total and restored.buffer.size == many.buffer.size
    for key, img in sampled.items():
        np.testing.assert_array_equal(_obs_of(restored, key), img)


def _obs_of(svc, key):
    """The stored obs stack of transition ``key`` (through the frame keys column)."""
    from zenrl.replay.frames import GKEY_PREFIX

    inner = svc.buffer._inner
    slot = key % inner.capacity
    assert inner._keys[slot] == key, f"key {key} is not stored"
    g = inner._data[GKEY_PREFIX + "obs"][slot]
    ring = svc.buffer._frames["obs"]
    return ring[g % svc.buffer.frame_capacity]
