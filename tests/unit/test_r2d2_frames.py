"""Frame mode for R2D2 sequences (issue #34): image observations leave the actor as frame ids,
each frame sent once (actor/frame_ids.py, actor/sequences.py), and the replay stores each frame
once and rebuilds the sequences' observations when sampled (replay/frames.py, the
SequenceChecker's frame rules in replay/checks.py), also with lz4-compressed frames."""

import numpy as np
import pytest

from zenrl.actor.sequences import SequenceBuilder
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.replay.checks import ObsRule, SequenceChecker
from zenrl.replay.service import ReplayService

E, M, N, H, A, HW = 3, 6, 2, 4, 2, (4, 4)


def _play(frame_stack, steps=90, seed=0):
    """The blocks of a full-observation builder and of a frame-mode one fed the same steps:
    each env's frames are distinct random images, stacks of ``frame_stack`` (oldest first,
    padded at a reset with the reset frame, as FrameStackObservation does); episodes end at
    random (terminated or truncated). Returns (full blocks, frame blocks, frames generated)."""
    rng = np.random.default_rng(seed)
    k = frame_stack
    kw = dict(num_envs=E, length=M, n_step=N, gamma=0.9, burn_in=2, block_steps=4)
    full, framed = SequenceBuilder(**kw), SequenceBuilder(**kw, frame_stack=k)
    made = 0

    def frame():
        nonlocal made
        made += 1
        return rng.integers(0, 256, HW, dtype=np.uint8)

    hist = [[frame()] * max(k, 1) for _ in range(E)]

    def observe(h):
        return np.stack(h) if k else h[-1]

    out_full, out_framed = [], []
    for _ in range(steps):
        obs = {"obs": np.stack([observe(h) for h in hist])}
        term, trunc = rng.random(E) < 0.08, rng.random(E) < 0.04
        nxt = []
        for e in range(E):
            hist[e] = (hist[e] + [frame()])[-max(k, 1):]
            nxt.append(observe(hist[e]))
        next_obs = {"obs": np.stack(nxt)}
        q = rng.normal(size=(E, A)).astype(np.float32)
        state = (np.zeros((E, H), np.float32), np.zeros((E, H), np.float32))
        act, rew = rng.integers(0, A, E), rng.normal(size=E).astype(np.float32)
        fq = lambda idx: np.ones((len(idx), A), np.float32)  # noqa: E731
        bf = full.add(obs, q, state, act, rew, next_obs, term, trunc, fq)
        bi = framed.add(obs, q, state, act, rew, next_obs, term, trunc, fq)
        assert (bf is None) == (bi is None)
        if bf is not None:
            out_full.append(bf)
            out_framed.append(bi)
        for e in np.flatnonzero(term | trunc):  # auto-reset: a new episode's first frame
            hist[e] = [frame()] * max(k, 1)
    return out_full, out_framed, made


@pytest.mark.parametrize("stack", [0, 3])
def test_frame_ids_name_the_observations_and_each_frame_travels_once(stack):
    full, framed, made = _play(stack)
    table, n_sent = {}, 0
    for bf, bi in zip(full, framed):
        f = bi.frames["obs"]
        assert bi.frame_base == n_sent, "frame ids are consecutive across blocks"
        for i in range(len(f)):
            table[bi.frame_base + i] = f[i]
        n_sent += len(f)
        ids = bi.data["obs"]
        assert ids.dtype == np.int64 and ids.shape == ((len(bi), M + 1, stack) if stack else (len(bi), M + 1))
        assert ids.max() < n_sent, "every id names a frame sent in this block or an earlier one"
        decoded = np.stack([table[int(i)] for i in ids.reshape(-1)]).reshape(*ids.shape, *HW)
        valid = np.arange(M + 1)[None, :] <= bi.length[:, None]
        np.testing.assert_array_equal(decoded[valid], bf.data["obs"][valid])
        # padding names s_len's frames (ones the replay holds), full mode pads with zeros
        pad_ids = np.where(valid.reshape(*valid.shape, *([1] * (ids.ndim - 2))), -1, ids)
        s_len = ids[np.arange(len(bi)), bi.length]
        for s in range(len(bi)):
            assert np.isin(pad_ids[s][pad_ids[s] >= 0], s_len[s]).all()
        for name in bf.data:
            if name != "obs":
                np.testing.assert_array_equal(bi.data[name], bf.data[name])
        np.testing.assert_array_equal(bi.priorities, bf.priorities)
    # each frame generated is sent at most once (frames of open sequences wait for a later block)
    assert len(table) == n_sent <= made
    assert n_sent >= made - E * (M + 4) * max(stack, 1)


def _replay(stack, capacity=1000):
    svc = ReplayService(load_config(None, [f"replay.capacity={capacity}", "replay.min_size=1",
                                           "replay.frames_per_item=8"], environ={}), node=None, run_id="r")
    shape = (stack, *HW) if stack else HW
    svc.checker = SequenceChecker({"obs": ObsRule("uint8", shape)}, n_actions=A, length=M, lstm_size=H,
                                  max_abs_reward=1e6, max_priority=1e9, frame_stack=stack)
    svc.ingestor.limits = P.DecodeLimits(svc.rcfg.max_decoded_bytes, svc.checker.packed_shapes())
    return svc


def _chunks(blocks, codec=None):
    out = []
    for i, b in enumerate(blocks):
        out.append(P.TransitionBatch("a0", 0, i, dict(b.data), b.priorities, frames=b.frames,
                                     frame_base=b.frame_base).encode(codec=codec))
    return out


@pytest.mark.parametrize("stack,codec", [(0, None), (3, "lz4")])
def test_the_replay_stores_each_frame_once_and_samples_the_sequences(stack, codec):
    full, framed, _ = _play(stack, steps=120, seed=1)
    svc = _replay(stack)
    n = sum(len(b) for b in framed)
    assert sum(svc.ingest(p, "zenrl/r/transitions/a0") for p in _chunks(framed, codec)) == n
    v = svc.stats_values()
    assert v["size"] == n and v["frames_stored"] == sum(len(b.frames["obs"]) for b in framed)
    expected = {k: bf for k, bf in enumerate(s for b in full for s in _split(b))}
    s = svc.buffer.sample(16, 0.4, np.random.default_rng(0))
    assert s.data["obs"].shape == ((16, M + 1, stack, *HW) if stack else (16, M + 1, *HW))
    for j, key in enumerate(s.keys.tolist()):
        want_obs, length, act = expected[key]
        valid = np.arange(M + 1) <= length
        np.testing.assert_array_equal(s.data["obs"][j][valid], want_obs[valid])
        np.testing.assert_array_equal(s.data["action"][j], act)


def _split(b):
    return [(b.data["obs"][i], int(b.length[i]), b.data["action"][i]) for i in range(len(b))]


def test_frame_chunks_that_break_the_layout_are_rejected_and_a_lost_frame_drops_only_its_sequences():
    _, framed, _ = _play(0, steps=60, seed=2)
    svc = _replay(0)
    b = framed[0]
    key = "zenrl/r/transitions/a0"
    wrong = dict(b.data, obs=b.data["obs"][:, :M])  # ids for m observations, not m+1
    assert svc.ingest(P.TransitionBatch("a0", 0, 0, wrong, b.priorities, frames=b.frames, frame_base=0).encode(), key) == 0
    assert svc.stats_values()["rejected_spec"] == 1
    stacked = {"obs": np.zeros((len(b.frames["obs"]), 2, *HW), np.uint8)}  # stacks, but the env's frames are single
    assert svc.ingest(P.TransitionBatch("a0", 0, 0, dict(b.data), b.priorities, frames=stacked, frame_base=0).encode(), key) == 0
    # the first block's frames never arrive: sequences naming them are dropped, later ones kept
    later = _chunks(framed[1:])
    stored = sum(svc.ingest(p, key) for p in later)
    first_ids = set(range(len(b.frames["obs"])))
    keep = sum(int(not np.isin(bl.data["obs"][i], list(first_ids)).any()) for bl in framed[1:] for i in range(len(bl)))
    assert stored == keep and keep < sum(len(bl) for bl in framed[1:])
    assert svc.stats_values()["frames_unresolved_items"] == sum(len(bl) for bl in framed[1:]) - keep


def test_the_actor_on_a_camera_env_sends_frame_chunks_the_replay_stores(tmp_path):
    """The R2D2 actor on Burger War's camera (a uint8 image): its chunks carry frames and frame
    ids (with ``actor.compress=lz4``), and a replay built from the same config stores every sequence."""
    import json

    from tests.unit.actor_fakes import FakeNode
    from zenrl.actor.r2d2 import R2D2Actor
    from zenrl.replay.service import make_checker

    match = {"match_time": 3.0, "sudden_death_time": 1.0, "control_hz": 5, "opponents": ["cheese"], "side": "random",
             "reward": "zero_sum", "render_size": 96, "image_size": 16}
    cfg = load_config(None, [f"runs_dir={tmp_path}", "algo=r2d2", "env.id=zenrl/BurgerWarImage-v0",
                             f"env.kwargs={json.dumps(match)}", "network.hidden=[16]", "actor.envs_per_actor=2",
                             "actor.chunk_size=8", "actor.compress=lz4", "r2d2.sequence_length=4", "r2d2.burn_in=2",
                             "r2d2.n_step=2", "r2d2.lstm_size=8", "r2d2.block_steps=2", "replay.min_size=1",
                             "replay.frames_per_item=8"], environ={})
    node = FakeNode(None)
    actor = R2D2Actor(cfg, node, "t", "a0", slot=0, num_slots=1)
    actor.start(node)
    for _ in range(24):
        actor.step(0.05)
    actor.close()
    payloads = node.sent(P.Keys("t").transitions("a0"))
    msgs = [P.TransitionBatch.decode(p) for p in payloads]
    assert msgs and all(m.frames is not None for m in msgs)
    n_frames = sum(len(next(iter(m.frames.values()))) for m in msgs)
    n_seq = sum(m.batch_size for m in msgs)
    assert n_frames < n_seq * (4 + 1), "overlapping sequences share their frames"
    svc = ReplayService(cfg, None, "t")
    svc.checker = make_checker(cfg)
    svc.ingestor.limits = P.DecodeLimits(svc.rcfg.max_decoded_bytes, svc.checker.packed_shapes())
    assert sum(svc.ingest(p, "zenrl/t/transitions/a0") for p in payloads) == n_seq
    assert svc.stats_values()["frames_stored"] == n_frames
