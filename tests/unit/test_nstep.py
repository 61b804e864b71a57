"""n-step blocks against hand-computed and brute-force returns and priorities."""

import numpy as np
import pytest

from zenrl.actor.nstep import NStepBlocks
from zenrl.common.exploration import apex_epsilon, env_epsilons


def _obs(x):
    return {"obs": np.asarray(x, np.float32).reshape(-1, 1)}


def _no_values(obs):
    raise AssertionError("no truncated window expected")


def _step(b, t, q, reward, nxt, term=False, trunc=False, value_fn=_no_values):
    return b.add(_obs([t]), np.asarray(q, np.float64).reshape(1, -1), np.array([0]), np.array([reward]),
                 _obs([nxt]), np.array([term]), np.array([trunc]), value_fn)


def test_hand_computed_mid_episode():
    """One env, n = 3, gamma 0.5, blocks of 2 steps: the first block comes out at step 5
    (starts 0 and 1 need steps up to 3 and V(s_4))."""
    b = NStepBlocks(1, 3, 0.5, block_steps=2)
    outs = [_step(b, t, [10.0 * t, 0.0], 1.0 * (t + 1), t + 1) for t in range(5)]
    assert [o is None for o in outs] == [True, True, True, True, False]
    blk = outs[4]
    assert len(blk) == 2 and list(blk.data["obs"][:, 0]) == [0, 1] and list(blk.data["next_obs"][:, 0]) == [3, 4]
    R0, R1 = 1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3 + 0.25 * 4
    np.testing.assert_allclose(blk.data["reward"], [R0, R1])
    assert list(blk.data["n"]) == [3, 3] and not blk.data["terminated"].any() and not blk.data["truncated"].any()
    # priority |R + gamma^3 V(s_{j+3}) - Q(s_j, a_j)|, V(s_t) = 10 t, Q(s_j, 0) = 10 j
    np.testing.assert_allclose(blk.priorities, [abs(R0 + 0.125 * 30 - 0), abs(R1 + 0.125 * 40 - 10)], rtol=1e-6)


@pytest.mark.parametrize("terminated", [True, False])
def test_episode_shorter_than_n(terminated):
    """An episode of two steps with n = 5: both starts stop at its end, bootstrap from the final
    observation only when truncated, and the next episode's steps are not mixed in."""
    asked = []

    def values(obs):
        asked.append(obs["obs"][:, 0].tolist())
        return np.full(len(obs["obs"]), 7.0)

    b = NStepBlocks(1, 5, 0.9, block_steps=2)
    _step(b, 0, [0.5, 0.0], 1.0, 1, value_fn=values)
    _step(b, 1, [0.0, 0.0], 2.0, 99, term=terminated, trunc=not terminated, value_fn=values)
    outs = [_step(b, t, [0.0, 0.0], 100.0, t + 1, value_fn=values) for t in range(2, 7)]
    blk = outs[-1]
    assert blk is not None and list(blk.data["obs"][:, 0]) == [0, 1]
    np.testing.assert_allclose(blk.data["reward"], [1 + 0.9 * 2, 2])
    assert list(blk.data["n"]) == [2, 1]
    assert (blk.data["next_obs"][:, 0] == 99).all()   # the final observation
    assert (blk.data["terminated"] == terminated).all() and (blk.data["truncated"] == (not terminated)).all()
    boot = 0.0 if terminated else 7.0
    np.testing.assert_allclose(blk.priorities, [abs(2.8 + 0.81 * boot - 0.5), abs(2 + 0.9 * boot)], rtol=1e-6)
    assert asked == ([] if terminated else [[99.0, 99.0]])


def _reference(T, E, n, gamma, rew, term, trunc, q, act, final_value, cut=False):
    """Brute force, per env and start j < T - n: (obs id, action, R, next obs id, m,
    terminated, truncated, priority). Obs id of s_t of env e is 10 t + e; a final observation
    after step t is 100000 + 10 (t + 1) + e. ``cut``: a window stops before a later step whose
    action is not argmax q, and bootstraps from that step's observation."""
    out = []
    for e in range(E):
        for j in range(T - n):
            R, m, end = 0.0, 0, None
            for k in range(n):
                if cut and k > 0 and act[j + k, e] != q[j + k, e].argmax():
                    break
                R += gamma ** k * rew[j + k, e]
                m += 1
                if term[j + k, e] or trunc[j + k, e]:
                    end = j + k
                    break
            te = bool(end is not None and term[end, e])
            tr = bool(end is not None and trunc[end, e] and not te)
            if end is None:
                nxt, boot = 10 * (j + m) + e, q[j + m, e].max()
            else:
                nxt = 100000 + 10 * (end + 1) + e
                boot = 0.0 if te else final_value(nxt)
            prio = abs(R + gamma ** m * boot - q[j, e, act[j, e]])
            out.append((10 * j + e, int(act[j, e]), R, nxt, m, te, tr, prio))
    return sorted(out)


@pytest.mark.parametrize("cut", [False, True])
@pytest.mark.parametrize("E,T,n,K,A", [(4, 60, 3, 5, 3), (3, 41, 1, 1, 3), (2, 50, 5, 16, 2), (5, 30, 3, 64, 3),
                                         (3, 40, 4, 8, 20)])
def test_against_brute_force(E, T, n, K, A, cut):
    """Every start that has its n steps recorded comes out exactly once (blocks while running,
    the rest at flush), equal to the brute force, priorities included; with ``cut_non_greedy``
    too (about half the actions greedy, so that windows are cut at every offset)."""
    rng = np.random.default_rng(E * 1000 + T)
    gamma = 0.9
    rew = rng.normal(size=(T, E))
    term = rng.random((T, E)) < 0.08
    trunc = (rng.random((T, E)) < 0.05) & ~term
    q = rng.normal(size=(T + 1, E, A))
    act = rng.integers(0, A, (T, E))
    if cut:
        greedy = rng.random((T, E)) < 0.5
        act = np.where(greedy, q[:T].argmax(2), act)
    obs_id = np.arange(T + 1)[:, None] * 10 + np.arange(E)[None, :]
    final_value = lambda ids: np.asarray(ids, np.float64) * 1e-5  # noqa: E731
    b = NStepBlocks(E, n, gamma, block_steps=K, cut_non_greedy=cut)
    blocks = []
    for t in range(T):
        nxt = np.where(term[t] | trunc[t], 100000 + obs_id[t + 1], -1)
        blk = b.add(_obs(obs_id[t]), q[t], act[t], rew[t], _obs(nxt), term[t], trunc[t],
                    lambda o: final_value(o["obs"][:, 0]))
        if blk is not None:
            assert len(blk) == K * E
            blocks.append(blk)
    blk = b.flush(lambda o: final_value(o["obs"][:, 0]))
    if blk is not None:
        blocks.append(blk)
    got = []
    for blk in blocks:
        d = blk.data
        for i in range(len(blk)):
            assert blk.env[i] == int(d["obs"][i, 0]) % 10
            got.append((int(d["obs"][i, 0]), int(d["action"][i]), float(d["reward"][i]), int(d["next_obs"][i, 0]),
                        int(d["n"][i]), bool(d["terminated"][i]), bool(d["truncated"][i]), float(blk.priorities[i])))
    got.sort()
    ref = _reference(T, E, n, gamma, rew, term, trunc, q, act, final_value, cut)
    if cut and n > 1:
        assert any(r[4] < n and not (r[5] or r[6]) for r in ref), "no window was cut: the test does not test the cut"
    assert [g[:2] + g[3:7] for g in got] == [r[:2] + r[3:7] for r in ref]
    np.testing.assert_allclose([g[2] for g in got], [r[2] for r in ref], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose([g[7] for g in got], [r[7] for r in ref], rtol=1e-5, atol=1e-5)


def test_dict_observations_and_dtypes():
    """Several observation keys (e.g. the match env's lidar + image) each get obs/next_obs."""
    E, n = 2, 2
    b = NStepBlocks(E, n, 0.99, block_steps=1)
    out = None
    for t in range(3):
        obs = {"obs/lidar": np.full((E, 4), t, np.float32), "obs/image": np.full((E, 2, 2, 3), t, np.uint8)}
        out = b.add(obs, np.zeros((E, 2)), np.zeros(E, np.int64), np.ones(E, np.float32), obs,
                    np.zeros(E, bool), np.zeros(E, bool), _no_values)
    assert set(out.data) == {"obs/lidar", "obs/image", "next_obs/lidar", "next_obs/image", "action", "reward",
                             "terminated", "truncated", "n"}
    assert out.data["obs/image"].dtype == np.uint8 and out.data["obs/image"].shape == (E, 2, 2, 3)
    assert (out.data["next_obs/image"] == 2).all() and (out.data["obs/lidar"] == 0).all()
    assert out.data["n"].dtype == np.uint8 and out.data["reward"].dtype == np.float32
    assert out.priorities.dtype == np.float32


def test_bad_arguments():
    with pytest.raises(ValueError, match="n_step"):
        NStepBlocks(1, 0, 0.9, 4)
    with pytest.raises(ValueError, match="block_steps"):
        NStepBlocks(1, 3, 0.9, 0)


def test_epsilon_ladder():
    assert apex_epsilon(0, 1) == 0.4
    assert apex_epsilon(0, 8) == pytest.approx(0.4)
    assert apex_epsilon(7, 8) == pytest.approx(0.4 ** 8)
    assert apex_epsilon(3, 8) == pytest.approx(0.4 ** (1 + 7 * 3 / 7))
    eps = [apex_epsilon(i, 8) for i in range(8)]
    assert all(a > b for a, b in zip(eps, eps[1:]))
    assert apex_epsilon(8, 8) == apex_epsilon(0, 8)  # wraps
    np.testing.assert_allclose(env_epsilons(1, 2, 4), [apex_epsilon(4 + k, 8) for k in range(4)])
    with pytest.raises(ValueError):
        apex_epsilon(0, 0)


def test_step_pacer_caps_the_rate_without_bursting():
    from zenrl.actor.pacing import StepPacer

    now = [100.0]
    p = StepPacer(max_steps_per_s=80.0, envs=8, clock=lambda: now[0])  # 10 batched steps/s
    assert p.delay() == pytest.approx(0.1)          # the first step waits one period
    now[0] += 0.1
    now[0] += 0.03                                   # the step itself took 30 ms
    assert p.delay() == pytest.approx(0.07)          # only the rest of the period
    now[0] += 0.07
    now[0] += 0.5                                    # a slow step: far behind schedule
    assert p.delay() == 0.0                          # no wait ...
    assert p.delay() == pytest.approx(0.1)           # ... and no burst afterwards
    assert StepPacer(None, 8, clock=lambda: now[0]).delay() == 0.0


def test_epsilon_greedy_per_env_rates():
    """Env i explores with probability eps[i]: greedy where eps is 0, uniform where it is 1,
    and in between the greedy action's frequency is 1 - eps + eps / A (within 5 standard
    errors over 20 k steps)."""
    from zenrl.common.exploration import EpsilonGreedy

    eps = np.array([0.0, 1.0, 0.3])
    A, T = 4, 20_000
    pick = EpsilonGreedy(eps, A, np.random.default_rng(0))
    q = np.array([[0.0, 0.0, 1.0, 0.0]] * 3)  # greedy action 2
    acts = np.stack([pick(q) for _ in range(T)])
    assert acts.dtype == np.int64 and acts.shape == (T, 3)
    assert (acts[:, 0] == 2).all()
    counts = np.bincount(acts[:, 1], minlength=A) / T
    assert np.all(np.abs(counts - 0.25) < 5 * np.sqrt(0.25 * 0.75 / T))
    p = 1 - 0.3 + 0.3 / A
    assert abs((acts[:, 2] == 2).mean() - p) < 5 * np.sqrt(p * (1 - p) / T)
    # the same seed gives the same actions
    again = EpsilonGreedy(eps, A, np.random.default_rng(0))
    assert np.array_equal(np.stack([again(q) for _ in range(T)]), acts)


class _StackEnvs:
    """E envs whose observations are k-frame stacks (reset padding repeats the first frame, as
    gymnasium's FrameStackObservation does) of unique 2x2 uint8 frames, plus a float vector."""

    def __init__(self, E, k, rng):
        self.E, self.k, self.rng, self.u = E, k, rng, 0
        self.stacks = [self._reset() for _ in range(E)]
        self.left = rng.integers(1, 9, E)

    def _frame(self):
        self.u += 1
        return (np.frombuffer(np.array([self.u], "<u4").tobytes(), np.uint8).reshape(2, 2), np.float32(self.u))

    def _reset(self):
        f = self._frame()
        return [f] * max(self.k, 1)

    def obs(self, stacks):
        img = np.stack([np.stack([f[0] for f in s]) for s in stacks])
        vec = np.stack([np.stack([[f[1]] for f in s]) for s in stacks])
        if not self.k:
            img, vec = img[:, 0], vec[:, 0]
        return {"obs/img": img, "obs/vec": vec}

    def step(self):
        nxt = [s[1:] + [self._frame()] if self.k else [self._frame()] for s in self.stacks]
        self.left -= 1
        done = self.left == 0
        term = done & (self.rng.random(self.E) < 0.5)
        final = self.obs(nxt)
        for e in np.flatnonzero(done):
            nxt[e] = self._reset()
            self.left[e] = self.rng.integers(1, 9)
        self.stacks = nxt
        return final, term, done & ~term


@pytest.mark.parametrize("k", [0, 1, 4])
def test_frame_mode_matches_plain_mode(k):
    """Frame mode emits the same transitions as plain mode, obs as frame ids that resolve, over
    the frames sent in this and earlier blocks, to exactly the plain arrays; and it sends about
    one frame per transition (not 2k)."""
    rng = np.random.default_rng(k)
    E, n = 3, 3
    envs = _StackEnvs(E, k, rng)
    plain = NStepBlocks(E, n, 0.9, block_steps=4)
    framed = NStepBlocks(E, n, 0.9, block_steps=4, frame_stack=k)
    frames = {"obs/img": [], "obs/vec": []}
    transitions = frames_sent = 0
    values = lambda o: o["obs/vec"].reshape(len(o["obs/vec"]), -1).sum(1)  # noqa: E731
    for t in range(120):
        obs = envs.obs(envs.stacks)
        q = rng.random((E, 2)).astype(np.float32)
        a, r = rng.integers(0, 2, E), rng.random(E)
        final, term, trunc = envs.step()
        bp = plain.add(obs, q, a, r, final, term, trunc, values)
        bf = framed.add(obs, q, a, r, final, term, trunc, values)
        assert (bp is None) == (bf is None)
        if bp is None:
            continue
        assert bf.frame_base == frames_sent
        for f, v in bf.frames.items():
            frames[f].extend(v)
        frames_sent += len(bf.frames["obs/img"])
        transitions += len(bp)
        np.testing.assert_allclose(bf.priorities, bp.priorities, rtol=1e-6)
        for key, v in bp.data.items():
            got = bf.data[key]
            if key.split("/")[0] in ("obs", "next_obs"):
                table = np.stack(frames["obs/" + key.split("/", 1)[1]])
                assert got.shape == ((len(bp),) if not k else (len(bp), k))
                got = table[got]
            np.testing.assert_array_equal(got, v, err_msg=key)
    assert transitions > 200
    assert frames_sent <= 1.2 * transitions + (n + 4) * E  # ~1 + 1/episode length per transition
