"""V-trace (learner/vtrace.py) against numpy references written out as loops: eq. 1 of the IMPALA
paper as a literal double sum, n-step and lambda-returns on-policy, per-decision
importance-weighted returns without clipping, a 2-step example computed by hand, and episode
ends (terminations and truncations) inside an unroll."""

import math

import numpy as np
import pytest
import torch

from zenrl.learner.vtrace import vtrace

G = 0.9


def _run(log_rhos, r, v, boot, term, trunc, final_v, gamma=G, **kw):
    t = lambda x: torch.as_tensor(np.asarray(x, np.float64))  # noqa: E731
    out = vtrace(t(log_rhos), t(r), t(v), t(boot), torch.as_tensor(term), torch.as_tensor(trunc),
                 None if final_v is None else t(final_v), gamma, **kw)
    return out.vs.numpy(), out.pg_advantages.numpy(), out.q_estimates.numpy()


def _next_value(s, b, v, boot, term, trunc, final_v):
    """V of the observation after step s (0 after a termination, the final observation's value
    after a truncation, the bootstrap after the last step), and whether the episode goes on."""
    T = v.shape[0]
    if term[s, b]:
        return 0.0, False
    if trunc[s, b]:
        return final_v[s, b], False
    return (v[s + 1, b] if s + 1 < T else boot[b]), s + 1 < T


def ref_eq1(log_rhos, r, v, boot, term, trunc, final_v, gamma=G, lam=1.0, rho_bar=1.0, c_bar=1.0, rho_pg_bar=None):
    """Eq. 1 literally: v_s = V(x_s) + sum_t gamma^(t-s) (prod_{i<t} c_i) delta_t, summed over the
    steps of x_s's episode inside the unroll; then the pg advantages from v_{s+1}."""
    T, B = r.shape
    rho = np.exp(log_rhos)
    rho_pg_bar = rho_bar if rho_pg_bar is None else rho_pg_bar
    vs = np.zeros((T, B))
    adv = np.zeros((T, B))
    for b in range(B):
        for s in range(T):
            total = v[s, b]
            prod_c = 1.0
            t = s
            while True:
                nv, goes_on = _next_value(t, b, v, boot, term, trunc, final_v)
                delta = min(rho_bar, rho[t, b]) * (r[t, b] + gamma * nv - v[t, b])
                total += gamma ** (t - s) * prod_c * delta
                if not goes_on:
                    break
                prod_c *= lam * min(c_bar, rho[t, b])
                t += 1
            vs[s, b] = total
    for b in range(B):
        for s in range(T):
            if term[s, b]:
                nxt = 0.0
            elif trunc[s, b]:
                nxt = final_v[s, b]
            else:
                nxt = vs[s + 1, b] if s + 1 < T else boot[b]
            adv[s, b] = min(rho_pg_bar, rho[s, b]) * (r[s, b] + gamma * nxt - v[s, b])
    return vs, adv


def _segment(s, b, T, term, trunc):
    """Steps s..e-1 of x_s's episode inside the unroll (e exclusive)."""
    e = s
    while True:
        e += 1
        if term[e - 1, b] or trunc[e - 1, b] or e == T:
            return e


def ref_nstep(r, v, boot, term, trunc, final_v, gamma=G):
    """On-policy, lambda = 1: the discounted rewards to the episode's or the unroll's end plus
    the discounted value there (0 after a termination)."""
    T, B = r.shape
    out = np.zeros((T, B))
    for b in range(B):
        for s in range(T):
            e = _segment(s, b, T, term, trunc)
            ret = sum(gamma ** (k - s) * r[k, b] for k in range(s, e))
            tail, _ = _next_value(e - 1, b, v, boot, term, trunc, final_v)
            out[s, b] = ret + gamma ** (e - s) * tail
    return out


def ref_lambda_return(r, v, boot, term, trunc, final_v, lam, gamma=G):
    """On-policy: the lambda-return as the weighted average of n-step returns
    (1-lam) sum_{n<N} lam^(n-1) G^(n) + lam^(N-1) G^(N), N = steps left in the segment."""
    T, B = r.shape
    out = np.zeros((T, B))
    for b in range(B):
        for s in range(T):
            e = _segment(s, b, T, term, trunc)
            N = e - s

            def g(n):
                ret = sum(gamma ** k * r[s + k, b] for k in range(n))
                tail = v[s + n, b] if n < N else _next_value(e - 1, b, v, boot, term, trunc, final_v)[0]
                return ret + gamma ** n * tail

            out[s, b] = (1 - lam) * sum(lam ** (n - 1) * g(n) for n in range(1, N)) + lam ** (N - 1) * g(N)
    return out


def _random_case(seed, T=6, B=5, ends=True):
    rng = np.random.default_rng(seed)
    r = rng.normal(size=(T, B))
    v = rng.normal(size=(T, B))
    boot = rng.normal(size=B)
    log_rhos = rng.normal(scale=0.7, size=(T, B))
    term = np.zeros((T, B), bool)
    trunc = np.zeros((T, B), bool)
    final_v = np.zeros((T, B))
    if ends:
        term[1, 1] = True
        trunc[2, 2] = True
        term[4, 3] = trunc[4, 3] = True  # termination wins
        trunc[T - 1, 4] = True  # truncated on the last step: the final value, not the bootstrap
        term[0, 0] = True
        trunc[3, 0] = True
        final_v[trunc] = rng.normal(size=int(trunc.sum())) * 3
    return log_rhos, r, v, boot, term, trunc, final_v


def test_hand_example():
    """T=2, B=1, gamma=0.9, pi/mu = (2, 0.5), rho_bar = c_bar = 1:
    rho = c = (1, 0.5); delta_1 = 0.5 (2 + 0.9*2 - 1) = 1.4, v_1 = 1 + 1.4 = 2.4;
    delta_0 = 1 (1 + 0.9*1 - 0.5) = 1.4, v_0 = 0.5 + 1.4 + 0.9*1*1.4 = 3.16;
    A_0 = 1 (1 + 0.9*2.4 - 0.5) = 2.66, A_1 = 0.5 (2 + 0.9*2 - 1) = 1.4."""
    log_rhos = np.log([[2.0], [0.5]])
    vs, adv, q = _run(log_rhos, [[1.0], [2.0]], [[0.5], [1.0]], [2.0], np.zeros((2, 1), bool), np.zeros((2, 1), bool), None)
    np.testing.assert_allclose(vs[:, 0], [3.16, 2.4], rtol=1e-12)
    np.testing.assert_allclose(adv[:, 0], [2.66, 1.4], rtol=1e-12)
    np.testing.assert_allclose(q[:, 0], [1 + 0.9 * 2.4, 2 + 0.9 * 2.0], rtol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_on_policy_is_nstep_returns(seed):
    _, r, v, boot, term, trunc, final_v = _random_case(seed)
    vs, adv, _ = _run(np.zeros_like(r), r, v, boot, term, trunc, final_v)
    ref = ref_nstep(r, v, boot, term, trunc, final_v)
    np.testing.assert_allclose(vs, ref, rtol=1e-10, atol=1e-12)
    # on-policy the advantage is the one-step target from v_{s+1} minus V(x_s)
    _, ref_adv = ref_eq1(np.zeros_like(r), r, v, boot, term, trunc, final_v)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("lam", [0.0, 0.5, 0.95])
def test_on_policy_with_lambda_is_lambda_return(lam):
    _, r, v, boot, term, trunc, final_v = _random_case(3)
    vs, _, _ = _run(np.zeros_like(r), r, v, boot, term, trunc, final_v, lam=lam)
    np.testing.assert_allclose(vs, ref_lambda_return(r, v, boot, term, trunc, final_v, lam), rtol=1e-10, atol=1e-12)


def test_lambda_zero_is_one_step_td():
    _, r, v, boot, term, trunc, final_v = _random_case(4)
    vs, _, _ = _run(np.zeros_like(r), r, v, boot, term, trunc, final_v, lam=0.0)
    T, B = r.shape
    for b in range(B):
        for s in range(T):
            nv, _ = _next_value(s, b, v, boot, term, trunc, final_v)
            assert vs[s, b] == pytest.approx(r[s, b] + G * nv, rel=1e-12, abs=1e-12)


def test_no_clipping_zero_values_is_per_decision_importance_weighted_return():
    """rho_bar = c_bar = inf and V = 0 (no baseline): v_s = sum_t gamma^(t-s) (prod_{i=s}^t rho_i) r_t."""
    log_rhos, r, _, _, term, trunc, _ = _random_case(5)
    T, B = r.shape
    zeros = np.zeros((T, B))
    vs, _, _ = _run(log_rhos, r, zeros, np.zeros(B), term, trunc, zeros, rho_bar=math.inf, c_bar=math.inf)
    rho = np.exp(log_rhos)
    for b in range(B):
        for s in range(T):
            e = _segment(s, b, T, term, trunc)
            ref = 0.0
            for t in range(s, e):
                w = 1.0
                for i in range(s, t + 1):
                    w *= rho[i, b]
                ref += G ** (t - s) * w * r[t, b]
            assert vs[s, b] == pytest.approx(ref, rel=1e-10, abs=1e-12)


def test_no_clipping_with_values_is_importance_weighted_return_with_control_variates():
    """rho_bar = c_bar = inf, no episode end: v_s = sum_t gamma^(t-s) rho_{s:t} r_t
    + gamma^(T-s) rho_{s:T-1} V(x_T) + sum_{t=s}^{T-1} gamma^(t-s) (rho_{s:t-1} - rho_{s:t}) V(x_t),
    with rho_{s:t} = prod_{i=s}^t rho_i (an empty product is 1)."""
    log_rhos, r, v, boot, term, trunc, final_v = _random_case(6, ends=False)
    vs, _, _ = _run(log_rhos, r, v, boot, term, trunc, None, rho_bar=math.inf, c_bar=math.inf)
    rho = np.exp(log_rhos)
    T, B = r.shape
    for b in range(B):
        for s in range(T):
            def w(a, z):  # prod of rho_a..rho_z
                out = 1.0
                for i in range(a, z + 1):
                    out *= rho[i, b]
                return out
            ref = sum(G ** (t - s) * w(s, t) * r[t, b] for t in range(s, T))
            ref += G ** (T - s) * w(s, T - 1) * boot[b]
            ref += sum(G ** (t - s) * (w(s, t - 1) - w(s, t)) * v[t, b] for t in range(s, T))
            assert vs[s, b] == pytest.approx(ref, rel=1e-10, abs=1e-12)


@pytest.mark.parametrize("kw", [dict(), dict(lam=0.8, c_bar=0.9), dict(rho_bar=2.0, c_bar=0.5, rho_pg_bar=0.7),
                                dict(rho_bar=math.inf, c_bar=math.inf, lam=0.9)])
def test_clipped_matches_eq1(kw):
    case = _random_case(7)
    vs, adv, _ = _run(*case, **kw)
    ref_vs, ref_adv = ref_eq1(*case, **kw)
    np.testing.assert_allclose(vs, ref_vs, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-10, atol=1e-12)


def test_truncation_bootstraps_from_final_observation_and_never_leaks_next_episode():
    """Env truncated at s = 2 of T = 5: targets up to s use V(final obs); nothing of the next
    episode (its rewards, values, the unroll's bootstrap) reaches them."""
    log_rhos, r, v, boot, term, trunc, final_v = _random_case(8, T=5, B=1, ends=False)
    trunc[2, 0] = True
    final_v[2, 0] = 5.0
    vs, adv, _ = _run(log_rhos, r, v, boot, term, trunc, final_v)
    r2, v2, boot2 = r.copy(), v.copy(), boot + 100.0
    r2[3:] += 50.0
    v2[3:] -= 30.0  # the next episode's first observation is x_3
    vs2, adv2, _ = _run(log_rhos, r2, v2, boot2, term, trunc, final_v)
    np.testing.assert_array_equal(vs[:3], vs2[:3])
    np.testing.assert_array_equal(adv[:3], adv2[:3])
    assert not np.allclose(vs[3:], vs2[3:])
    # on-policy the truncated step's target is r + gamma V(final obs)
    vs_on, _, _ = _run(np.zeros_like(r), r, v, boot, term, trunc, final_v)
    assert vs_on[2, 0] == pytest.approx(r[2, 0] + G * 5.0)
    fv = final_v.copy()
    fv[2, 0] = -5.0
    vs3, _, _ = _run(log_rhos, r, v, boot, term, trunc, fv)
    assert not np.allclose(vs3[:3], vs[:3])


def test_termination_stops_bootstrapping():
    log_rhos, r, v, boot, term, trunc, final_v = _random_case(9, T=4, B=1, ends=False)
    term[1, 0] = True
    vs, _, _ = _run(np.zeros_like(r), r, v, boot, term, trunc, final_v)
    assert vs[1, 0] == pytest.approx(r[1, 0])
    assert vs[0, 0] == pytest.approx(r[0, 0] + G * r[1, 0])
    # a final value given at a terminated (and truncated) step is ignored
    trunc[1, 0] = True
    final_v[1, 0] = 1e6
    vs2, _, _ = _run(log_rhos, r, v, boot, term, trunc, final_v)
    vs1, _, _ = _run(log_rhos, r, v, boot, term, np.zeros_like(trunc), np.zeros_like(final_v))
    np.testing.assert_array_equal(vs2, vs1)


def test_targets_carry_no_gradient_and_keep_dtype():
    T, B = 3, 2
    v = torch.zeros(T, B, requires_grad=True)
    out = vtrace(torch.zeros(T, B), torch.ones(T, B), v, torch.zeros(B), torch.zeros(T, B, dtype=torch.bool),
                 torch.zeros(T, B, dtype=torch.bool), None, G)
    assert not out.vs.requires_grad and out.vs.dtype == torch.float32 and out.vs.shape == (T, B)
    trunc = torch.zeros(T, B, dtype=torch.bool)
    trunc[1, 0] = True
    with pytest.raises(ValueError, match="truncated_values"):
        vtrace(torch.zeros(T, B), torch.ones(T, B), v, torch.zeros(B), torch.zeros(T, B, dtype=torch.bool), trunc, None, G)
    with pytest.raises(ValueError, match="bootstrap_value"):
        vtrace(torch.zeros(T, B), torch.ones(T, B), v, torch.zeros(T), torch.zeros(T, B, dtype=torch.bool),
               torch.zeros(T, B, dtype=torch.bool), None, G)
