"""n-step builder against hand-computed and brute-force returns."""

import numpy as np
import pytest

from zenrl.actor.nstep import NStepBuilder
from zenrl.common.exploration import apex_epsilon, env_epsilons


def _obs(x):
    return {"obs": np.asarray(x, np.float32).reshape(-1, 1)}


def test_hand_computed_mid_episode():
    b = NStepBuilder(1, 3, 0.5)
    outs = []
    for t in range(4):
        outs.append(b.add(_obs([t]), np.array([t]), np.array([1.0 * (t + 1)]), np.array([0.0]),
                          _obs([t + 1]), np.array([False]), np.array([False])))
    assert [len(o) for o in outs] == [0, 0, 1, 1]
    e = outs[2]
    assert e.data["obs"][0, 0] == 0 and e.data["action"][0] == 0
    assert e.data["reward"][0] == pytest.approx(1 + 0.5 * 2 + 0.25 * 3)
    assert e.data["next_obs"][0, 0] == 3 and e.data["n"][0] == 3
    assert not e.data["terminated"][0] and e.pending[0]
    assert outs[3].data["reward"][0] == pytest.approx(2 + 0.5 * 3 + 0.25 * 4)


@pytest.mark.parametrize("terminated", [True, False])
def test_episode_shorter_than_n(terminated):
    b = NStepBuilder(1, 5, 0.9)
    b.add(_obs([0]), np.array([0]), np.array([1.0]), np.array([0.0]), _obs([1]), np.array([False]), np.array([False]))
    e = b.add(_obs([1]), np.array([1]), np.array([2.0]), np.array([0.0]), _obs([99]),
              np.array([terminated]), np.array([not terminated]))
    assert len(e) == 2
    by_start = {int(o): i for i, o in enumerate(e.data["obs"][:, 0])}
    i0, i1 = by_start[0], by_start[1]
    assert e.data["reward"][i0] == pytest.approx(1 + 0.9 * 2) and e.data["n"][i0] == 2
    assert e.data["reward"][i1] == pytest.approx(2) and e.data["n"][i1] == 1
    assert (e.data["next_obs"][:, 0] == 99).all()   # the final observation
    assert (e.data["terminated"] == terminated).all() and (e.data["truncated"] == (not terminated)).all()
    assert not e.pending.any()
    # the next episode starts clean
    e = b.add(_obs([5]), np.array([0]), np.array([1.0]), np.array([0.0]), _obs([6]), np.array([False]), np.array([False]))
    assert len(e) == 0


def _reference(obs, act, rew, term, trunc, n, gamma):
    """Brute force, one env: every start j, summing until n steps or the episode end."""
    out = []
    T = len(rew)
    ep_end = [t for t in range(T) if term[t] or trunc[t]]
    for j in range(T):
        end = next((t for t in ep_end if t >= j), None)
        last = min(j + n - 1, end if end is not None else T + 10)
        if last >= T:
            continue  # not emitted yet
        m = last - j + 1
        R = sum(gamma ** k * rew[j + k] for k in range(m))
        done_here = end is not None and last == end
        out.append((obs[j], act[j], round(R, 4), obs[last + 1], m, bool(term[last]) if done_here else False))
    return sorted(out)


def test_against_brute_force_many_envs():
    rng = np.random.default_rng(0)
    E, T, n, gamma = 4, 60, 3, 0.9
    rew = rng.normal(size=(T, E))
    term = rng.random((T, E)) < 0.08
    trunc = (rng.random((T, E)) < 0.05) & ~term
    # observation ids: unique per (t, env); "final" observations are distinct ids
    obs_id = np.arange(T + 1)[:, None] * 10 + np.arange(E)[None, :]
    final_id = 100000 + obs_id
    b = NStepBuilder(E, n, gamma)
    got = [[] for _ in range(E)]
    for t in range(T):
        done = term[t] | trunc[t]
        nxt = np.where(done, final_id[t + 1], obs_id[t + 1])
        e = b.add(_obs(obs_id[t]), obs_id[t] % 7, rew[t], np.zeros(E), _obs(nxt), term[t], trunc[t])
        for k in range(len(e)):
            got[e.env[k]].append((int(e.data["obs"][k, 0]), int(e.data["action"][k]), round(float(e.data["reward"][k]), 4),
                                  int(e.data["next_obs"][k, 0]), int(e.data["n"][k]), bool(e.data["terminated"][k])))
    for env in range(E):
        done = term[:, env] | trunc[:, env]
        nxt_seq = np.where(np.r_[done, False], np.r_[final_id[1:, env], 0], np.r_[obs_id[1:, env], 0])
        # reference next_obs of a transition ending at step `last` is the obs after `last`
        seq_obs = list(obs_id[:T, env])
        ref = _reference(seq_obs + [None], [o % 7 for o in seq_obs], rew[:, env], term[:, env], trunc[:, env], n, gamma)
        ref = [(o, a, R, int(nxt_seq[o // 10 + m - 1]), m, te) for (o, a, R, _, m, te) in ref]
        got_f = sorted((o, a, round(R, 4), nx, m, te) for (o, a, R, nx, m, te) in got[env])
        assert [(g[0], g[4], g[5], g[3]) for g in got_f] == [(r[0], r[4], r[5], r[3]) for r in ref]
        np.testing.assert_allclose([g[2] for g in got_f], [r[2] for r in ref], atol=1e-3)


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
