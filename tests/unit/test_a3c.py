"""A3C without a network: n-step returns against hand-computed values, the worker's published
gradients against plain autograd on the same rollout, and the learner's gradient checks
(staleness, unknown versions, NaN/overflow, wrong names/shapes), checkpoint round trip."""

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from tests.unit.actor_fakes import FakeNode, run_until, step_until
from zenrl.actor.a3c import A3CWorker
from zenrl.common.a3c_loss import gae_returns, nstep_returns, rollout_gradients
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.errors import ProtocolError
from zenrl.common.networks import ActorCritic, arch_fingerprint, params_to_arrays
from zenrl.common.specs import ArraySpec
from zenrl.common.transport import LatestValue
from zenrl.learner.a3c import APPLIED, STALE, UNKNOWN_VERSION, A3CLearner, GradientApplier

G = 0.9


# --------------------------------------------------------------------------------------------
# n-step returns
# --------------------------------------------------------------------------------------------
def _episode_ends():
    """Rewards, terminated, truncated, final values and bootstrap of a 3-step, 4-env rollout:
    env 0: no episode end; env 1: terminated at t=1; env 2: truncated at t=0 (final value 7);
    env 3: terminated and truncated at t=2 (termination wins: its final value 1000 is ignored)."""
    r = np.array([[1.0, 1.0, 1.0, 1.0], [2.0, 2.0, 2.0, 2.0], [3.0, 3.0, 3.0, 3.0]], np.float32)
    term = np.zeros((3, 4), bool)
    trunc = np.zeros((3, 4), bool)
    term[1, 1] = True
    trunc[0, 2] = True
    term[2, 3] = trunc[2, 3] = True
    final = np.zeros((3, 4))
    final[0, 2] = 7.0
    final[2, 3] = 1000.0
    return r, term, trunc, final, np.array([10.0, 20.0, 30.0, 40.0])


def test_nstep_returns_hand_computed():
    r, term, trunc, final, boot = _episode_ends()
    R = nstep_returns(r, term, trunc, final, boot, G)
    assert R.dtype == np.float32 and R.shape == (3, 4)
    np.testing.assert_allclose(R[:, 0], [1 + G * 2 + G**2 * 3 + G**3 * 10, 2 + G * 3 + G**2 * 10, 3 + G * 10], rtol=1e-6)
    np.testing.assert_allclose(R[:, 1], [1 + G * 2, 2, 3 + G * 20], rtol=1e-6)
    np.testing.assert_allclose(R[:, 2], [1 + G * 7, 2 + G * 3 + G**2 * 30, 3 + G * 30], rtol=1e-6)
    np.testing.assert_allclose(R[:, 3], [1 + G * 2 + G**2 * 3, 2 + G * 3, 3], rtol=1e-6)


def test_nstep_returns_one_step():
    R = nstep_returns(np.array([[1.0]]), np.array([[False]]), np.array([[False]]), np.zeros((1, 1)), np.array([2.0]), 0.5)
    assert R[0, 0] == pytest.approx(2.0)


def test_gae_lambda_one_is_nstep_and_zero_is_td():
    r, term, trunc, final, boot = _episode_ends()
    v = np.random.default_rng(0).normal(size=(3, 4))
    np.testing.assert_allclose(gae_returns(r, term, trunc, v, final, boot, G, 1.0),
                               nstep_returns(r, term, trunc, final, boot, G), rtol=1e-5)
    # lambda = 0: one-step targets r_t + gamma * (value of the next state)
    td = gae_returns(r, term, trunc, v, final, boot, G, 0.0)
    np.testing.assert_allclose(td[:, 0], [1 + G * v[1, 0], 2 + G * v[2, 0], 3 + G * 10], rtol=1e-5)
    np.testing.assert_allclose(td[:, 1], [1 + G * v[1, 1], 2, 3 + G * 20], rtol=1e-5)
    np.testing.assert_allclose(td[:, 2], [1 + G * 7, 2 + G * v[2, 2], 3 + G * 30], rtol=1e-5)
    np.testing.assert_allclose(td[:, 3], [1 + G * v[1, 3], 2 + G * v[2, 3], 3], rtol=1e-5)


def test_gae_hand_computed():
    # one env, no episode end: A_1 = d_1, A_0 = d_0 + gamma * lam * d_1
    lam = 0.5
    r = np.array([[1.0], [2.0]])
    v = np.array([[0.5], [1.5]])
    no = np.zeros((2, 1), bool)
    d1 = 2 + G * 4.0 - 1.5
    d0 = 1 + G * 1.5 - 0.5
    out = gae_returns(r, no, no, v, np.zeros((2, 1)), np.array([4.0]), G, lam)
    np.testing.assert_allclose(out[:, 0], [d0 + G * lam * d1 + 0.5, d1 + 1.5], rtol=1e-6)


# --------------------------------------------------------------------------------------------
# Worker: published gradients == autograd of the same loss on the same rollout
# --------------------------------------------------------------------------------------------
def _cfg(tmp_path, **kw):
    sets = [f"runs_dir={tmp_path}", "algo=a3c", "network.hidden=[16]", "actor.envs_per_actor=4",
            "a3c.t_max=20", "a3c.entropy_coef=0.05", "a3c.value_coef=0.5", "learner.gamma=0.9",
            "env.max_episode_steps=15", "actor.episode_report_s=0.01"] + [f"{k}={v}" for k, v in kw.items()]
    return load_config(None, sets, environ={})


def _weights(cfg, version, seed=123):
    torch.manual_seed(seed)
    net = ActorCritic({"obs": ArraySpec((4,), "float32")}, 2, cfg.network)
    return net, P.Weights(version=version, learner_id="learner", arch=arch_fingerprint(net), updates=5,
                          params=params_to_arrays(net)).encode()


def _reference_grads(net, ro, gamma, vc, ec, lam=1.0):
    """The A3C loss written out element by element, then plain autograd (``lam`` < 1:
    generalized-advantage targets, written out per env as well)."""
    T, E = ro.actions.shape
    with torch.no_grad():
        boot = net({"obs": torch.as_tensor(ro.last_obs["obs"])})[1]
        fin = net({"obs": torch.as_tensor(ro.final_obs["obs"])})[1] if len(ro.final_obs["obs"]) else None
    R = np.zeros((T, E))
    k_of = {}
    for i, flat in enumerate(np.flatnonzero((ro.truncated & ~ro.terminated).reshape(-1))):
        k_of[divmod(int(flat), E)] = i
    for e in range(E):
        ret = float(boot[e])
        for t in reversed(range(T)):
            if ro.terminated[t, e]:
                ret = float(ro.rewards[t, e])
            elif ro.truncated[t, e]:
                ret = float(ro.rewards[t, e]) + gamma * float(fin[k_of[(t, e)]])
            else:
                ret = float(ro.rewards[t, e]) + gamma * ret
            R[t, e] = ret
    if lam != 1.0:
        with torch.no_grad():
            V = np.stack([net({"obs": torch.as_tensor(ro.obs["obs"][t])})[1].numpy() for t in range(T)])
        for e in range(E):
            adv = 0.0
            for t in reversed(range(T)):
                if ro.terminated[t, e]:
                    nxt, adv = 0.0, 0.0
                elif ro.truncated[t, e]:
                    nxt, adv = float(fin[k_of[(t, e)]]), 0.0
                else:
                    nxt = float(boot[e]) if t == T - 1 else float(V[t + 1, e])
                adv = float(ro.rewards[t, e]) + gamma * nxt - float(V[t, e]) + gamma * lam * adv
                R[t, e] = adv + float(V[t, e])
    net.zero_grad()
    total = 0.0
    for t in range(T):
        logits, v = net({"obs": torch.as_tensor(ro.obs["obs"][t])})
        for e in range(E):
            logp = F.log_softmax(logits[e], dim=0)
            adv = R[t, e] - float(v[e].detach())
            ent = -(logp.exp() * logp).sum()
            total = total - logp[ro.actions[t, e]] * adv + vc * (R[t, e] - v[e]) ** 2 - ec * ent
    (total / (T * E)).backward()
    return {k: p.grad.numpy().copy() for k, p in net.named_parameters()}


def _record_rollouts(w):
    """The rollouts ``w`` turns into gradients, in order."""
    rollouts = []
    message = w.adder.gradients_message
    w.adder.gradients_message = lambda ro: rollouts.append(ro) or message(ro)
    return rollouts


def test_published_gradients_equal_autograd(tmp_path):
    cfg = _cfg(tmp_path)
    ref_net, payload = _weights(cfg, version=7)
    node = FakeNode(payload)
    w = A3CWorker(cfg, node, "t", "w0", 0)
    rollouts = _record_rollouts(w)
    stats_key = P.Keys("t").stats("actor", "w0")
    # the worker idles once its budget is spent; its stats keep coming on their cadence
    run_until(lambda stop: w.run(stop, max_rollouts=2),
              lambda: w.done() and any(P.Stats.decode(p).values["env_steps"] == 2 * 20 * 4 for p in node.sent(stats_key)),
              what="2 rollouts and their stats")
    sent = node.pubs[P.Keys("t").gradients("w0")].sent
    assert len(sent) == 2 and len(rollouts) == 2
    assert any(ro.terminated.any() for ro in rollouts), "the rollouts should hold terminations"
    assert any((ro.truncated & ~ro.terminated).any() for ro in rollouts), "... and truncations"
    for ro, payload in zip(rollouts, sent):
        msg = P.Gradients.decode(payload)
        assert msg.worker_id == "w0" and msg.version == 7 and msg.steps == 20 * 4
        ref = _reference_grads(ref_net, ro, 0.9, 0.5, 0.05)
        assert set(msg.grads) == set(ref)
        for k in ref:
            np.testing.assert_allclose(msg.grads[k], ref[k], rtol=1e-4, atol=1e-6, err_msg=k)
        assert any(np.abs(g).sum() > 0 for g in ref.values())
    stats = P.Stats.decode(node.sent(stats_key)[-1])
    assert stats.values["env_steps"] == 2 * 20 * 4 and stats.values["sent_gradients"] == 2
    # the loss stats come with the reports of intervals that had rollouts
    assert any({"loss", "policy_loss", "value_loss", "entropy", "slot", "policy_version"} <= set(P.Stats.decode(p).values)
               for p in node.sent(stats_key))
    assert node.tokens == [P.Keys("t").alive("actor", "w0")]
    episodes = [P.EpisodeStats.decode(p) for p in node.sent(P.Keys("t").episodes("w0"))]
    assert episodes and all(e.epsilon == 0.0 and e.actor_id == "w0" for e in episodes)
    assert sum(int(e.lengths.sum()) for e in episodes) <= 2 * 20 * 4 and all((e.lengths <= 15).all() for e in episodes)


def test_gae_gradients_equal_autograd(tmp_path):
    cfg = _cfg(tmp_path)
    net, payload = _weights(cfg, version=3)
    node = FakeNode(payload)
    w = A3CWorker(cfg, node, "t", "w0", 0)
    rollouts = _record_rollouts(w)
    w.start(node)
    step_until(w, lambda: rollouts)
    ro = rollouts[0]
    assert ro.terminated.any() and (ro.truncated & ~ro.terminated).any()
    grads, _ = rollout_gradients(w.net, ro, 0.9, 0.5, 0.05, gae_lambda=0.8)
    ref = _reference_grads(net, ro, 0.9, 0.5, 0.05, lam=0.8)
    plain = _reference_grads(net, ro, 0.9, 0.5, 0.05)
    for k in ref:
        np.testing.assert_allclose(grads[k], ref[k], rtol=1e-4, atol=1e-6, err_msg=k)
    assert any(not np.allclose(ref[k], plain[k], rtol=1e-3, atol=1e-5) for k in ref), "lambda must change the gradient"


def test_lr_anneals_linearly_then_holds(tmp_path):
    cfg = _cfg(tmp_path, **{"learner.lr": 0.01, "a3c.lr_anneal_updates": 4, "a3c.lr_final_fraction": 0.2})
    net, _ = _weights(cfg, version=1)
    ap = GradientApplier(net, cfg.learner, cfg.a3c)
    grads = {k: np.ones(p.shape, np.float32) for k, p in net.named_parameters()}
    seen = []
    for _ in range(6):
        seen.append(ap.current_lr())
        assert ap.apply(P.Gradients(worker_id="w", version=0, steps=1, grads=grads))[0] == APPLIED
        assert ap.opt.param_groups[0]["lr"] == pytest.approx(seen[-1])
    np.testing.assert_allclose(seen, [0.01, 0.008, 0.006, 0.004, 0.002, 0.002], rtol=1e-9)
    assert GradientApplier(net, _cfg(tmp_path).learner, _cfg(tmp_path).a3c).current_lr() == _cfg(tmp_path).learner.lr


def test_worker_takes_newest_params_between_steps(tmp_path):
    cfg = _cfg(tmp_path)
    _, p7 = _weights(cfg, version=7)
    _, p9 = _weights(cfg, version=9, seed=5)
    node = FakeNode(p7)
    w = A3CWorker(cfg, node, "t", "w0", 0)
    w.start(node)
    assert w.weights.version == 7
    node.latest.set("k", p9)
    step_until(w, lambda: w.adder.rollouts == 1)
    assert w.weights.version == 9
    assert P.Gradients.decode(node.sent(P.Keys("t").gradients("w0"))[0]).version == 9


def test_worker_waits_for_the_learners_first_params(tmp_path):
    """No learner yet: the worker takes no step (its gradients need a version), and starts
    once the broadcast brings params."""
    cfg = _cfg(tmp_path)
    _, p4 = _weights(cfg, version=4)
    node = FakeNode(None)
    w = A3CWorker(cfg, node, "t", "w0", 0)
    w.start(node)
    assert not w.step(0.05) and w.env_steps == 0
    node.latest.set("k", p4)
    assert w.step(0.05) and w.env_steps == 4 and w.weights.version == 4


# --------------------------------------------------------------------------------------------
# Learner: which gradients are applied
# --------------------------------------------------------------------------------------------
def _applier(tmp_path, **kw):
    cfg = _cfg(tmp_path, **kw)
    net, _ = _weights(cfg, 0)
    return GradientApplier(net, cfg.learner, cfg.a3c), net


def _grad_msg(net, version, scale=1.0, worker="w0"):
    g = {k: np.full(p.shape, scale, np.float32) for k, p in net.named_parameters()}
    return P.Gradients(worker_id=worker, version=version, steps=10, grads=g)


def _snapshot(net):
    return {k: v.clone() for k, v in net.state_dict().items()}


def _same(net, snap):
    return all(torch.equal(v, snap[k]) for k, v in net.state_dict().items())


def test_staleness_and_unknown_version(tmp_path):
    ap, net = _applier(tmp_path, **{"a3c.max_staleness": 3})
    for _ in range(5):
        ap.next_version()
    assert ap.version == 5
    snap = _snapshot(net)
    assert ap.apply(_grad_msg(net, 1))[0] == STALE          # 5 - 1 = 4 > 3
    assert ap.apply(_grad_msg(net, 6))[0] == UNKNOWN_VERSION
    assert _same(net, snap) and ap.updates == 0
    assert ap.apply(_grad_msg(net, 2))[0] == APPLIED        # 5 - 2 = 3, still accepted
    assert not _same(net, snap) and ap.updates == 1 and ap.params_finite()


def test_resync_after_restart(tmp_path):
    ap, net = _applier(tmp_path, **{"a3c.max_staleness": 3})
    ap.next_version()
    assert ap.resync(40) and ap.version == 43
    assert ap.next_version() == 44
    assert ap.apply(_grad_msg(net, 40))[0] == STALE         # params of the dead incarnation
    assert not ap.resync(10) and not ap.resync(1 << 60)


def test_nan_gradient_rejected_params_finite(tmp_path):
    ap, net = _applier(tmp_path)
    ap.next_version()
    bad = _grad_msg(net, 1)
    k0 = next(iter(bad.grads))
    bad.grads[k0][0] = np.nan
    with pytest.raises(ProtocolError) as e:
        P.Gradients.decode(bad.encode())
    assert e.value.reason == "nonfinite"
    snap = _snapshot(net)
    huge = _grad_msg(net, 1, scale=3e38)                      # finite, but the norm overflows
    with pytest.raises(ProtocolError) as e:
        ap.apply(P.Gradients.decode(huge.encode()))
    assert e.value.reason == "nonfinite"
    assert _same(net, snap) and ap.params_finite() and ap.updates == 0


def test_wrong_names_and_shapes_rejected(tmp_path):
    ap, net = _applier(tmp_path)
    ap.next_version()
    snap = _snapshot(net)
    m = _grad_msg(net, 1)
    k0 = next(iter(m.grads))
    wrong_shape = dict(m.grads, **{k0: np.zeros((3, 3), np.float32)})
    missing = {k: v for k, v in m.grads.items() if k != k0}
    extra = dict(m.grads, **{"bogus.weight": np.zeros(2, np.float32)})
    for grads, reason in ((wrong_shape, "shape"), (missing, "names"), (extra, "names")):
        with pytest.raises(ProtocolError) as e:
            ap.apply(P.Gradients("w0", 1, 10, grads))
        assert e.value.reason == reason
    assert _same(net, snap) and ap.updates == 0


def test_service_counts_rejections_and_checkpoint_round_trip(tmp_path):
    cfg = _cfg(tmp_path, **{"network.hidden": "[8]"})
    svc = A3CLearner(cfg, node=None, run_id="ck")
    svc.applier.next_version()
    net = svc.net
    bad = P.Gradients("w1", 1, 10, {k: np.zeros((1,), np.float32) for k, _ in net.named_parameters()}).encode()
    assert svc.handle("zenrl/ck/gradients/w1", bad) is None
    assert svc.handle("zenrl/ck/gradients/w1", b"\x00garbage") is None
    assert svc.rejects.counts["shape"] == 1 and svc.rejects.counts["malformed"] == 1
    assert svc.handle("zenrl/ck/gradients/w0", _grad_msg(net, 1, 0.1).encode()) == APPLIED
    assert svc.env_steps_trained == 10
    svc.save()
    again = A3CLearner(cfg, node=None, run_id="ck", resume="require")
    assert again.applier.version == 1 and again.applier.updates == 1
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), again.net.state_dict().values()))
    # the same next gradient gives the same params (optimizer state restored too)
    for s in (svc, again):
        assert s.handle("k/w0", _grad_msg(s.net, 1, -0.2).encode()) == APPLIED
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), again.net.state_dict().values()))


def test_orthogonal_init_starts_near_uniform(tmp_path):
    cfg = _cfg(tmp_path)
    net = ActorCritic({"obs": ArraySpec((4,), "float32")}, 3, cfg.network).requires_grad_(False)
    w = net.trunk[0].weight
    # orthogonal rows (16 x 4 layer: the columns are orthonormal, scaled by sqrt(2))
    np.testing.assert_allclose((w.T @ w).numpy(), 2.0 * np.eye(4), atol=1e-5)
    assert float(net.policy.weight.abs().max()) < 0.05 and float(net.trunk[0].bias.abs().max()) == 0.0
    x = torch.randn(64, 4) * 3
    logits, _ = net({"obs": x})
    probs = torch.softmax(logits, 1)
    assert float((probs - 1 / 3).abs().max()) < 0.05
    plain = ActorCritic({"obs": ArraySpec((4,), "float32")}, 3, _cfg(tmp_path, **{"network.orthogonal_init": False}).network)
    plain.requires_grad_(False)
    assert float(plain.trunk[0].bias.abs().max()) > 0.0


def test_absurd_gradient_norm_rejected_not_clipped(tmp_path):
    ap, net = _applier(tmp_path, **{"a3c.max_grad_norm": 1e3})
    ap.next_version()
    snap = _snapshot(net)
    n_params = sum(p.numel() for p in net.parameters())
    # finite, below the overflow, but a norm of 1e4 * sqrt(n) no honest worker sends
    with pytest.raises(ProtocolError, match="exceeds a3c.max_grad_norm") as e:
        ap.apply(P.Gradients.decode(_grad_msg(net, 1, scale=1e4).encode()))
    assert e.value.reason == "grad_norm" and n_params > 1
    assert _same(net, snap) and ap.updates == 0 and all(p.grad is None for p in net.parameters())
    # an ordinary one still applies
    assert ap.apply(_grad_msg(net, 1, scale=1e-3))[0] == APPLIED and not _same(net, snap)


def test_worker_keeps_actor_max_steps_per_s(tmp_path):
    """actor.max_steps_per_s paces an A3C worker (it once applied to Ape-X and R2D2 actors only)."""
    cfg = _cfg(tmp_path, **{"actor.max_steps_per_s": 40})
    _, payload = _weights(cfg, version=1)
    w = A3CWorker(cfg, FakeNode(payload), "t", "w0", 0)
    assert w.pacer is not None and w.pacer.period_s == pytest.approx(4 / 40)
