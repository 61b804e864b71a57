"""The R2D2 sequence builder against a brute-force reference: boundaries for episodes shorter and
longer than m, overlap m/2, no sequence across episodes, the stored state, padding and mask, and
the initial priorities recomputed with loops."""

import numpy as np
import pytest

from zenrl.actor.sequences import SequenceBuilder
from zenrl.common.recurrent import inverse_value_rescale, value_rescale

M, P, N, GAMMA, A, H, K = 6, 3, 2, 0.9, 3, 4, 2
#: per env: episode lengths, in order; an episode ends truncated when its index is odd
EPISODES = [[2, 6, 7, 13, 3, 99], [3, 4, 12, 1, 9, 99], [20, 5, 6, 99], [1, 1, 8, 24, 99]]
STEPS = 37


def _run(builder_kw=None, block_steps=1):
    """Drive the builder with scripted episodes; obs = (env, episode, step) and an image whose
    pixels are the step; returns the blocks and the record of what the actor saw."""
    rng = np.random.default_rng(0)
    E = len(EPISODES)
    b = SequenceBuilder(E, M, N, GAMMA, block_steps=block_steps, **(builder_kw or {"burn_in": K}))
    epi, step = np.zeros(E, int), np.zeros(E, int)
    rec = {}          # (env, episode, step) -> dict(q, h, c, action, reward)
    finals = {}       # (env, episode) -> q of the final observation (truncated episodes)
    blocks, calls = [], []

    def obs_of(e_idx, ep_idx, st):
        return {"obs": np.stack([e_idx, ep_idx, st], 1).astype(np.float32),
                "obs/img": np.repeat(np.asarray(st, np.uint8)[:, None, None], 2, 1).repeat(2, 2)}

    for i in range(STEPS):
        envs = np.arange(E)
        obs = obs_of(envs, epi, step)
        q = rng.normal(size=(E, A)).astype(np.float32) * 3
        h = np.where((step == 0)[:, None], 0.0, rng.normal(size=(E, H))).astype(np.float32)
        c = np.where((step == 0)[:, None], 0.0, rng.normal(size=(E, H))).astype(np.float32)
        act = rng.integers(0, A, E)
        rew = rng.normal(size=E).astype(np.float32)
        lengths = np.array([EPISODES[e][epi[e]] for e in range(E)])
        done = step + 1 == lengths
        term = done & (epi % 2 == 0)
        trunc = done & (epi % 2 == 1)
        for e in range(E):
            rec[e, epi[e], step[e]] = dict(q=q[e], h=h[e], c=c[e], action=act[e], reward=rew[e])
        next_obs = obs_of(envs, epi, step + 1)  # the final observation where the episode ended

        def final_q(idx, epi=epi.copy()):
            calls.append(idx.tolist())
            out = rng.normal(size=(len(idx), A)).astype(np.float32)
            for i, e in enumerate(idx):
                finals[e, epi[e]] = out[i]
            return out

        blk = b.add(obs, q, (h, c), act, rew, next_obs, term, trunc, final_q)
        if blk is not None:
            assert (i + 1) % block_steps == 0
            blocks.append(blk)
        epi, step = np.where(done, epi + 1, epi), np.where(done, 0, step + 1)
    last = b.flush()
    if last is not None:
        blocks.append(last)
    assert b.flush() is None
    return blocks, rec, finals, calls, (epi, step)


def _expected(end_state):
    """(env, episode, start, length) of every sequence that should have been emitted: starts
    every P steps, at most M steps, cut at the episode's end; a sequence whose steps all lie in an
    earlier one is dropped; an unfinished episode only has its sequences with s_M recorded."""
    epi_now, step_now = end_state
    out = set()
    for e, eps in enumerate(EPISODES):
        for i, L in enumerate(eps[:epi_now[e] + 1]):
            finished = i < epi_now[e]
            seen = L if finished else step_now[e]
            cands = [(s, min(s + M, L)) for s in range(0, L, P)]
            for j, (s, end) in enumerate(cands):
                if any(end2 >= end for _, end2 in cands[:j]):
                    continue
                if (end - s == M and s + M < seen) or (finished and end == L):
                    out.add((e, i, s, end - s))
    return out


@pytest.mark.parametrize("block_steps", [1, 5])
def test_boundaries_overlap_and_episodes(block_steps):
    blocks, rec, _, _, end_state = _run(block_steps=block_steps)
    got = []
    for blk in blocks:
        for i in range(len(blk)):
            o = blk.data["obs"][i]
            L = int(blk.length[i])
            assert blk.data["mask"][i].tolist() == [t < L for t in range(M)]
            ep_ids = set(o[:L + 1, 1].tolist())
            assert len(ep_ids) == 1, "a sequence spans two episodes"
            assert o[:L + 1, 0].tolist() == [blk.env[i]] * (L + 1)
            assert o[:L + 1, 2].tolist() == list(range(blk.start[i], blk.start[i] + L + 1))
            got.append((int(blk.env[i]), int(o[0, 1]), int(blk.start[i]), L))
    assert sorted(got) == sorted(_expected(end_state))
    assert len(got) == len(set(got))
    # neighbours inside an episode overlap by exactly m/2 and reach its end
    by_ep = {}
    for e, ep, s, L in got:
        by_ep.setdefault((e, ep), []).append((s, L))
    for (e, ep), seqs in by_ep.items():
        seqs.sort()
        assert seqs[0][0] == 0
        for (s, L), (s2, _) in zip(seqs, seqs[1:]):
            assert s2 - s == P and L == M and s + L - s2 == M // 2
        if ep < end_state[0][e]:
            assert seqs[-1][0] + seqs[-1][1] == EPISODES[e][ep]
    lengths = {L for *_, L in got}
    assert {1, 2, 3, 4, M} <= lengths      # episodes and tails shorter than m, and full ones


@pytest.mark.parametrize("block_steps", [1, 5])
def test_fields_state_and_padding(block_steps):
    blocks, rec, finals, _, _ = _run(block_steps=block_steps)
    for blk in blocks:
        d = blk.data
        assert d["obs"].shape[1:] == (M + 1, 3) and d["obs/img"].shape[1:] == (M + 1, 2, 2)
        assert d["action"].dtype == np.int64 and d["reward"].dtype == np.float32
        for i in range(len(blk)):
            e, ep, s, L = int(blk.env[i]), int(d["obs"][i, 0, 1]), int(blk.start[i]), int(blk.length[i])
            r0 = rec[e, ep, s]
            np.testing.assert_array_equal(d["h"][i], r0["h"])      # the state the actor acted on s_0 with
            np.testing.assert_array_equal(d["c"][i], r0["c"])
            assert d["first"][i] == (s == 0)
            for t in range(L):
                r = rec[e, ep, s + t]
                assert d["action"][i, t] == r["action"] and d["reward"][i, t] == r["reward"]
                np.testing.assert_array_equal(blk.q[i, t], r["q"])
                assert (d["obs/img"][i, t] == s + t).all()
            ended = s + L == EPISODES[e][ep]
            term, trunc = ended and ep % 2 == 0, ended and ep % 2 == 1
            assert d["terminated"][i].tolist() == [term and t == L - 1 for t in range(M)]
            assert d["truncated"][i].tolist() == [trunc and t == L - 1 for t in range(M)]
            want_q = finals[e, ep] if trunc else (np.zeros(A) if term else rec[e, ep, s + L]["q"])
            np.testing.assert_array_equal(blk.q[i, L], want_q)
            # padding is zero everywhere
            assert not d["obs"][i, L + 1:].any() and not d["obs/img"][i, L + 1:].any()
            assert not blk.q[i, L + 1:].any()
            for f in ("action", "reward", "terminated", "truncated"):
                assert not d[f][i, L:].any()


def test_final_q_fn_only_for_truncations():
    blocks, _, finals, calls, _ = _run()
    assert calls and all(len(c) >= 1 for c in calls)
    n_trunc = sum(int(b.data["truncated"].any(1).sum()) for b in blocks)
    assert sum(len(c) for c in calls) == n_trunc == len(finals)


@pytest.mark.parametrize("burn_in,block_steps", [(0, 1), (K, 1), (K, 4)])
def test_initial_priorities_match_loops(burn_in, block_steps):
    blocks, *_ = _run({"burn_in": burn_in}, block_steps)
    for blk in blocks:
        d = blk.data
        for i in range(len(blk)):
            L, first = int(blk.length[i]), bool(d["first"][i])
            deltas = []
            for t in range(L):
                if t < burn_in and not first:
                    continue
                j = min(N, L - t)
                ret = sum(GAMMA ** k * float(d["reward"][i, t + k]) for k in range(j))
                if t + j == L and d["terminated"][i, L - 1]:
                    boot = 0.0
                else:
                    boot = float(inverse_value_rescale(np.float64(blk.q[i, t + j].max())))
                y = value_rescale(ret + GAMMA ** j * boot)
                deltas.append(abs(float(blk.q[i, t, d["action"][i, t]]) - y))
            want = 0.9 * max(deltas) + 0.1 * np.mean(deltas) if deltas else 0.0
            assert blk.priorities[i] == pytest.approx(want, rel=1e-5, abs=1e-6)
    assert any(p > 0 for b in blocks for p in b.priorities)


def test_rejects_bad_lengths():
    with pytest.raises(ValueError):
        SequenceBuilder(2, 5, 1, 0.9)
    with pytest.raises(ValueError):
        SequenceBuilder(2, 6, 1, 0.9, burn_in=4)


def test_a_step_both_terminated_and_truncated_is_terminal():
    """A time limit reached on the step the episode terminates (gymnasium sets both flags): the
    sequence is terminal, as the learner's loss reads it: no final Q asked, none bootstrapped."""
    b = SequenceBuilder(1, M, N, GAMMA, burn_in=0)
    calls = []

    def final_q(idx):
        calls.append(idx.tolist())
        return np.full((len(idx), A), 50.0, np.float32)

    obs = {"obs": np.zeros((1, 2), np.float32)}
    q = np.ones((1, A), np.float32)
    state = (np.zeros((1, H), np.float32), np.zeros((1, H), np.float32))
    blk = None
    for t in range(3):
        done = np.array([t == 2])
        blk = b.add(obs, q, state, np.zeros(1, np.int64), np.ones(1, np.float32), obs, done, done, final_q)
    assert calls == [] and blk is not None and len(blk) == 1
    assert (blk.q[0, 3] == 0).all()  # the bootstrap row: zero, as after any terminal step
    y = []
    for t in range(3):  # Q = 1 everywhere: V = 1 where the bootstrap is inside, 0 at the terminal s_3
        j = min(N, 3 - t)
        v = inverse_value_rescale(1.0) if t + j < 3 else 0.0
        y.append(value_rescale(sum(GAMMA ** i for i in range(j)) + GAMMA ** j * v))
    want = np.abs(1.0 - np.array(y))
    np.testing.assert_allclose(blk.priorities[0], 0.9 * want.max() + 0.1 * want.mean(), rtol=1e-5)
