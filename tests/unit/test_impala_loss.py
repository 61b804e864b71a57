"""One IMPALA / APPO learner step against numpy by hand: a tiny ActorCritic (one tanh layer,
linear policy and value heads), a fixed batch of unrolls with a termination and truncations; the
forward pass, the V-trace targets (tests/unit/test_vtrace.py's eq. 1 reference), the loss and its
gradient w.r.t. every parameter written out in numpy (softmax, entropy and clipped-surrogate
derivatives, backprop through tanh), compared with what one SGD step did to the parameters."""

import numpy as np
import pytest
import torch

from tests.unit.test_vtrace import ref_eq1
from zenrl.common import protocol as P
from zenrl.common.config import NetworkConfig
from zenrl.common.networks import LOG_STD_MIN, ActorCritic, BoxActions
from zenrl.common.specs import ArraySpec
from zenrl.learner.impala_loss import LossParams, forward_unrolls, impala_loss, learner_step
from zenrl.learner.unroll_queue import batch_unrolls

T, B, D, H, A = 4, 3, 3, 5, 3
LR = 0.1


def _net():
    torch.manual_seed(0)
    cfg = NetworkConfig(hidden=[H], activation="tanh", orthogonal_init=False, shared_torso=True, dueling=False)
    return ActorCritic({"obs": ArraySpec((D,), "float32")}, A, cfg)


def _params(net):
    return {k: v.detach().numpy().astype(np.float64).copy() for k, v in net.named_parameters()}


def _np_forward(w, x):
    h = np.tanh(x @ w["trunk.0.weight"].T + w["trunk.0.bias"])
    return h, h @ w["policy.weight"].T + w["policy.bias"], (h @ w["value.weight"].T + w["value.bias"])[:, 0]


def _log_softmax(z):
    z = z - z.max(axis=1, keepdims=True)
    return z - np.log(np.exp(z).sum(axis=1, keepdims=True))


def _categorical_draw(rng, w, obs):
    """Actions of the first T observations and their behaviour log-probs (the net's own plus noise)."""
    act = rng.integers(0, A, T).astype(np.int64)
    _, z, _ = _np_forward(w, obs[:T].astype(np.float64))
    return act, _log_softmax(z)[np.arange(T), act] + rng.normal(scale=0.4, size=T)


def _unrolls(net, draw=_categorical_draw, seed=1):
    """B unrolls: 0 plain, 1 truncated at t=1 and terminated at t=3, 2 truncated at t=0 and
    t=2; actions and behaviour log-probs from ``draw`` (ratios on both sides of 1)."""
    rng = np.random.default_rng(seed)
    w = _params(net)
    out = []
    for b in range(B):
        obs = rng.normal(size=(T + 1, D)).astype(np.float32)
        act, logp = draw(rng, w, obs)
        term, trunc = np.zeros(T, bool), np.zeros(T, bool)
        if b == 1:
            trunc[1], term[3] = True, True
        if b == 2:
            trunc[0] = trunc[2] = True
        K = int((trunc & ~term).sum())
        final = {"obs": rng.normal(size=(K, D)).astype(np.float32)} if K else None
        out.append(P.Unroll(f"a{b}", 3, b, {"obs": obs}, act, logp.astype(np.float32),
                            rng.normal(size=T).astype(np.float32), term, trunc, final))
    return out


def _batch(w, us, p: LossParams):
    """The batch's arrays by hand: observations x [T+1, B, D], hidden h [N, H], policy head
    outputs [N, A], values v [T, B], bootstrap values [B], actions, behaviour log-probs, rewards
    (scaled), terminations, truncations and the truncated steps' final values [T, B]."""
    N = T * B
    x = np.stack([u.obs["obs"] for u in us], axis=1).astype(np.float64)  # [T+1, B, D]
    h_all, z_all, v_all = _np_forward(w, x.reshape((T + 1) * B, D))
    act = np.stack([u.action for u in us], axis=1)
    mu_logp = np.stack([u.behaviour_logp for u in us], axis=1).astype(np.float64)
    r = np.stack([u.reward for u in us], axis=1).astype(np.float64) * p.reward_scale
    term = np.stack([u.terminated for u in us], axis=1)
    trunc = np.stack([u.truncated for u in us], axis=1)
    final_v = np.zeros((T, B))
    for b, u in enumerate(us):
        if u.final_obs is not None:
            final_v[np.flatnonzero(u.cut), b] = _np_forward(w, u.final_obs["obs"].astype(np.float64))[2]
    return x, h_all[:N], z_all[:N], v_all[:N].reshape(T, B), v_all[N:].copy(), act, mu_logp, r, term, trunc, final_v


def _policy_loss(logp, log_rhos, vs, pg_adv, r, v, boot, term, trunc, final_v, p: LossParams):
    """IMPALA's or APPO's policy loss and its derivative w.r.t. each sample's log pi, by hand."""
    N = T * B
    if p.clip_eps is None:
        adv = pg_adv.reshape(N)
        return -np.mean(adv * logp), -adv / N
    q = np.zeros((T, B))
    for b in range(B):
        for s in range(T):
            nxt = 0.0 if term[s, b] else final_v[s, b] if trunc[s, b] else vs[s + 1, b] if s + 1 < T else boot[b]
            q[s, b] = r[s, b] + p.gamma * nxt
    adv = (q - v).reshape(N)
    if p.normalize_advantages:
        adv = (adv - adv.mean()) / (adv.std(ddof=1) + 1e-8)
    ratio = np.exp(log_rhos.reshape(N))
    clipped = np.clip(ratio, 1 - p.clip_eps, 1 + p.clip_eps)
    # the unclipped term is the min (or equal to it inside the clip range): gradient flows
    active = (ratio * adv <= clipped * adv) | (np.abs(ratio - 1) <= p.clip_eps)
    return -np.mean(np.minimum(ratio * adv, clipped * adv)), -(active * adv * ratio) / N


def _grads(w, x, h, du, dv, extra=None):
    """d loss / d parameter from d loss / d policy head output ``du`` [N, A] and d loss / d value ``dv`` [N]."""
    N = T * B
    dh = du @ w["policy.weight"] + dv[:, None] @ w["value.weight"]
    dpre = dh * (1 - h ** 2)
    x_rows = x.reshape((T + 1) * B, D)[:N]
    return {"policy.weight": du.T @ h, "policy.bias": du.sum(0),
            "value.weight": dv[None, :] @ h, "value.bias": np.array([dv.sum()]),
            "trunk.0.weight": dpre.T @ x_rows, "trunk.0.bias": dpre.sum(0), **(extra or {})}


def _np_step(w, us, p: LossParams):
    """Loss statistics and d loss / d parameter, by hand."""
    N = T * B
    x, h, z, v, boot, act, mu_logp, r, term, trunc, final_v = _batch(w, us, p)
    logp_all = _log_softmax(z)
    pr = np.exp(logp_all)
    a_flat = act.reshape(N)
    logp = logp_all[np.arange(N), a_flat]
    log_rhos = logp.reshape(T, B) - mu_logp
    vs, pg_adv = ref_eq1(log_rhos, r, v, boot, term, trunc, final_v, p.gamma, p.lam, p.rho_bar, p.c_bar)
    ent_i = -(pr * logp_all).sum(1)
    policy_loss, g = _policy_loss(logp, log_rhos, vs, pg_adv, r, v, boot, term, trunc, final_v, p)
    dz = g[:, None] * (np.eye(A)[a_flat] - pr)  # d log pi(a) / d z = onehot(a) - pi
    dz += (p.entropy_coef / N) * pr * (logp_all + ent_i[:, None])  # - c_e * dH/dz
    dv = -2.0 * p.value_coef * (vs.reshape(N) - v.reshape(N)) / N
    stats = {"policy_loss": policy_loss, "value_loss": np.mean((vs.reshape(N) - v.reshape(N)) ** 2),
             "entropy": ent_i.mean(), "rho_mean": np.exp(log_rhos).mean(),
             "clip_fraction": np.mean(np.exp(log_rhos) > p.rho_bar) if p.clip_eps is None
             else np.mean(np.abs(np.exp(log_rhos) - 1) > p.clip_eps)}
    return _grads(w, x, h, dz, dv), stats


def _step_against(net, us, reference, p):
    """One SGD step of ``learner_step`` on ``us`` against ``reference(w, us, p)`` (gradients and
    statistics by hand): every parameter moved by -LR times its gradient, the statistics equal.
    Returns (the step's statistics, the reference's)."""
    w = _params(net)
    grads, ref = reference(w, us, p)
    stats = learner_step(net, torch.optim.SGD(net.parameters(), lr=LR), batch_unrolls(us), p)
    after = _params(net)
    assert set(after) == set(grads)
    for k in grads:
        np.testing.assert_allclose((w[k] - after[k]) / LR, grads[k].reshape(w[k].shape), rtol=2e-3, atol=2e-6, err_msg=k)
    for k, v in ref.items():
        assert stats[k] == pytest.approx(v, rel=1e-4, abs=1e-6), k
    return stats, ref


@pytest.mark.parametrize("p", [LossParams(gamma=0.9), LossParams(gamma=0.95, lam=0.8, rho_bar=1.2, c_bar=0.9, entropy_coef=0.05),
                               LossParams(gamma=0.9, clip_eps=0.2),
                               LossParams(gamma=0.9, clip_eps=0.1, normalize_advantages=True, value_coef=1.0)],
                         ids=["impala", "impala-lambda", "appo", "appo-normalized"])
def test_one_learner_step_matches_numpy(p):
    net = _net()
    stats, ref = _step_against(net, _unrolls(net), _np_step, p)
    assert stats["loss"] == pytest.approx(ref["policy_loss"] + p.value_coef * ref["value_loss"] - p.entropy_coef * ref["entropy"],
                                          rel=1e-4, abs=1e-6)
    assert 0.0 < stats["clip_fraction"] < 1.0  # the batch has clipped and unclipped samples


def test_forward_unrolls_places_final_values():
    net = _net()
    us = _unrolls(net)
    batch = batch_unrolls(us)
    logits, values, boot, final_values = forward_unrolls(net, batch)
    assert logits.shape == (T, B, A) and values.shape == (T, B) and boot.shape == (B,)
    assert values.requires_grad and not boot.requires_grad and not final_values.requires_grad
    w = _params(net)
    _, _, v2 = _np_forward(w, us[2].final_obs["obs"].astype(np.float64))
    np.testing.assert_allclose(final_values[[0, 2], 2].numpy(), v2, rtol=1e-5)
    _, _, v1 = _np_forward(w, us[1].final_obs["obs"].astype(np.float64))
    np.testing.assert_allclose(final_values[1, 1].numpy(), v1[0], rtol=1e-5)
    assert final_values[:, 0].abs().sum() == 0 and final_values[3, 1] == 0
    _, _, vb = _np_forward(w, np.stack([u.obs["obs"][T] for u in us]).astype(np.float64))
    np.testing.assert_allclose(boot.numpy(), vb, rtol=1e-5)


def test_impala_clip_fraction_counts_rhos_over_rho_bar():
    T_, B_ = 2, 2
    logits = torch.zeros(T_, B_, 2, requires_grad=True)  # pi = 1/2 everywhere
    behaviour = torch.log(torch.tensor([[0.25, 0.5], [0.75, 0.5]]))  # rhos 2, 1, 2/3, 1
    z = torch.zeros(T_, B_, dtype=torch.bool)
    _, stats = impala_loss(logits, torch.zeros(T_, B_, requires_grad=True), torch.zeros(B_), None,
                           torch.zeros(T_, B_, dtype=torch.int64), behaviour, torch.ones(T_, B_), z, z, LossParams())
    assert stats["clip_fraction"] == pytest.approx(0.25) and stats["rho_max"] == pytest.approx(2.0)
    assert stats["rho_mean"] == pytest.approx((2 + 1 + 2 / 3 + 1) / 4)


# --------------------------------------------------------------------------------------------
# Continuous actions: a Gaussian policy (mean tanh(policy head), state-independent log std)
# --------------------------------------------------------------------------------------------
DA = 2  # action dimensions
HALF_LOG_2PI = 0.5 * np.log(2 * np.pi)


def _gauss_net(log_std_init=-0.3):
    torch.manual_seed(0)
    cfg = NetworkConfig(hidden=[H], activation="tanh", orthogonal_init=False, shared_torso=True, dueling=False,
                        log_std_init=log_std_init)
    return ActorCritic({"obs": ArraySpec((D,), "float32")}, BoxActions(DA), cfg)


def _np_gauss_logp(mean, log_std, a):
    """Sum over dimensions of the normal log-density, element by element with math's functions."""
    out = np.zeros(mean.shape[0])
    for i in range(mean.shape[0]):
        for j in range(mean.shape[1]):
            sd = np.exp(log_std[j])
            out[i] += -0.5 * ((a[i, j] - mean[i, j]) / sd) ** 2 - np.log(sd) - 0.5 * np.log(2 * np.pi)
    return out


def _gaussian_draw(rng, w, obs):
    """float32[T, DA] actions around the net's own means (some outside [-1, 1], as an honest
    actor's samples are) and behaviour log-densities = the net's own plus noise."""
    _, u, _ = _np_forward(w, obs[:T].astype(np.float64))
    mean = np.tanh(u)
    act = (mean + np.exp(w["log_std"]) * rng.normal(size=(T, DA)) * 1.5).astype(np.float32)
    return act, _np_gauss_logp(mean, w["log_std"], act.astype(np.float64)) + rng.normal(scale=0.4, size=T)


def _np_gauss_step(w, us, p: LossParams):
    """Loss statistics and d loss / d parameter of the Gaussian policy, by hand:
    d logp / d mean = (a - mean) / sd^2, d logp / d log_std = z^2 - 1, dH / d log_std = 1 per
    dimension, d mean / d u = 1 - mean^2."""
    N = T * B
    x, h, u, v, boot, act, mu_logp, r, term, trunc, final_v = _batch(w, us, p)
    mean, act = np.tanh(u), act.reshape(N, DA).astype(np.float64)
    ls = w["log_std"]
    logp = _np_gauss_logp(mean, ls, act)
    log_rhos = logp.reshape(T, B) - mu_logp
    vs, pg_adv = ref_eq1(log_rhos, r, v, boot, term, trunc, final_v, p.gamma, p.lam, p.rho_bar, p.c_bar)
    policy_loss, g = _policy_loss(logp, log_rhos, vs, pg_adv, r, v, boot, term, trunc, final_v, p)
    zsc = (act - mean) / np.exp(ls)  # [N, DA]
    du = g[:, None] * zsc / np.exp(ls) * (1 - mean ** 2)
    dls = (g[:, None] * (zsc ** 2 - 1)).sum(0) - p.entropy_coef * np.ones(DA)
    dv = -2.0 * p.value_coef * (vs.reshape(N) - v.reshape(N)) / N
    stats = {"policy_loss": policy_loss, "value_loss": np.mean((vs.reshape(N) - v.reshape(N)) ** 2),
             "entropy": (ls + 0.5 + HALF_LOG_2PI).sum(), "rho_mean": np.exp(log_rhos).mean()}
    return _grads(w, x, h, du, dv, {"log_std": dls}), stats


@pytest.mark.parametrize("p", [LossParams(gamma=0.9, entropy_coef=0.05), LossParams(gamma=0.9, clip_eps=0.2),
                               LossParams(gamma=0.9, clip_eps=0.1, normalize_advantages=True, entropy_coef=0.01),
                               LossParams(gamma=0.9, clip_eps=0.2, reward_scale=0.1)],
                         ids=["impala", "appo", "appo-normalized", "appo-reward-scale"])
def test_one_learner_step_with_continuous_actions_matches_numpy(p):
    net = _gauss_net()
    assert net.continuous
    _step_against(net, _unrolls(net, _gaussian_draw, seed=2), _np_gauss_step, p)


def test_gaussian_log_std_is_clamped_where_used():
    """A log std below LOG_STD_MIN acts as LOG_STD_MIN (the entropy says so) and gets no gradient
    from the loss there."""
    net = _gauss_net(log_std_init=-5.0)
    with torch.no_grad():
        net.log_std.fill_(-9.0)
    assert torch.equal(net.clamped_log_std(), torch.full((DA,), LOG_STD_MIN))
    us = _unrolls(_gauss_net(), _gaussian_draw, seed=2)
    stats = learner_step(net, torch.optim.SGD(net.parameters(), lr=LR), batch_unrolls(us), LossParams(entropy_coef=0.1))
    assert stats["entropy"] == pytest.approx(DA * (LOG_STD_MIN + 0.5 + HALF_LOG_2PI), rel=1e-6)
    assert torch.equal(net.log_std.detach(), torch.full((DA,), -9.0))
