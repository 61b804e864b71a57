"""Ape-X learner math on hand-made batches, networks, and weight versioning."""

import copy

import numpy as np
import pytest
import torch

from zenrl.actor.weights import WeightsFollower
from zenrl.common import protocol as P
from zenrl.common.config import LearnerConfig, NetworkConfig
from zenrl.common.networks import (ActorCritic, NumpyQ, QNetwork, arch_fingerprint, arrays_to_params, obs_spec,
                                   params_to_arrays)
from zenrl.common.specs import ArraySpec
from zenrl.learner.dqn import DQNLearner, double_dqn_target, dqn_loss


def test_double_dqn_target_by_hand():
    q_next_online = torch.tensor([[1.0, 5.0], [3.0, 2.0], [0.0, 1.0]])
    q_next_target = torch.tensor([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]])
    reward = torch.tensor([1.0, 2.0, 3.0])
    n = torch.tensor([3, 1, 2], dtype=torch.uint8)
    terminated = torch.tensor([False, False, True])
    y = double_dqn_target(q_next_online, q_next_target, reward, n, terminated, gamma=0.5)
    # online argmax picks action 1, 0, 1; target evaluates it; terminated stops bootstrapping
    torch.testing.assert_close(y, torch.tensor([1.0 + 0.125 * 20.0, 2.0 + 0.5 * 30.0, 3.0]))


def test_weighted_huber_loss_by_hand():
    q = torch.tensor([[0.0, 1.0], [2.0, 0.0]], requires_grad=True)
    action = torch.tensor([1, 0])
    target = torch.tensor([1.5, 5.0])       # td 0.5 (quadratic), 3.0 (linear)
    weights = torch.tensor([1.0, 0.5])
    loss, td, q_sa = dqn_loss(q, action, target, weights, huber_delta=1.0)
    expected = (1.0 * 0.5 * 0.5 ** 2 + 0.5 * (3.0 - 0.5)) / 2
    assert loss.item() == pytest.approx(expected)
    torch.testing.assert_close(td, torch.tensor([0.5, 3.0]))
    loss.backward()
    torch.testing.assert_close(q.grad, torch.tensor([[0.0, -0.25], [-0.25, 0.0]]))


def test_learner_update_matches_a_step_computed_by_hand():
    """One DQNLearner.update against numpy: a 3-2-2 ReLU net (online and target set by hand and
    different), double-DQN n-step targets, IS-weighted Huber loss, backprop, gradient clipping
    and Adam's first step. Swapping online and target, dropping a weight, the discount or the
    clip each changes the result."""
    W1 = np.array([[0.5, -0.2, 0.1], [0.3, 0.4, -0.1]])
    b1 = np.array([0.1, 0.2])
    W2 = np.array([[1.0, -0.5], [0.2, 0.8]])
    b2 = np.array([0.05, -0.05])
    T1, t1, T2, t2 = W1 * 0.5, b1 + 0.3, W2[::-1] * 2.0, b2 * -3.0  # the target net
    obs = np.array([[1.0, 0.5, 0.2], [0.4, 1.0, 0.3], [0.9, 0.1, 1.2]])
    nxt = np.array([[0.8, 0.9, 0.1], [1.1, 0.2, 0.4], [0.3, 0.7, 0.9]])
    action = np.array([0, 1, 1])
    reward = np.array([1.0, -0.5, 2.0])
    n = np.array([3, 1, 2])
    terminated = np.array([False, False, True])
    isw = np.array([1.0, 0.5, 0.25])
    gamma, delta, clip, lr, eps = 0.9, 1.0, 0.5, 0.01, 1e-3

    def forward(x, A1, a1, A2, a2):
        pre = x @ A1.T + a1
        h = np.maximum(pre, 0.0)
        return pre, h, h @ A2.T + a2

    _, _, q_next_on = forward(nxt, W1, b1, W2, b2)
    _, _, q_next_tg = forward(nxt, T1, t1, T2, t2)
    a_star = q_next_on.argmax(1)
    y = reward + gamma ** n * (1 - terminated) * q_next_tg[np.arange(3), a_star]
    pre, h, q = forward(obs, W1, b1, W2, b2)
    q_sa = q[np.arange(3), action]
    err = q_sa - y
    huber = np.where(np.abs(err) <= delta, 0.5 * err ** 2, delta * (np.abs(err) - 0.5 * delta))
    loss = np.mean(isw * huber)
    dq = np.zeros_like(q)
    dq[np.arange(3), action] = isw * np.clip(err, -delta, delta) / 3
    gW2, gb2 = dq.T @ h, dq.sum(0)
    dpre = (dq @ W2) * (pre > 0)
    gW1, gb1 = dpre.T @ obs, dpre.sum(0)
    grads = [gW1, gb1, gW2, gb2]
    norm = np.sqrt(sum((g ** 2).sum() for g in grads))
    grads = [g * min(1.0, clip / (norm + 1e-6)) for g in grads]
    # Adam's first step: m_hat = g, v_hat = g^2
    expected = [p - lr * g / (np.abs(g) + eps) for p, g in zip((W1, b1, W2, b2), grads)]

    spec = {"obs": ArraySpec((3,), "float32")}
    learner = DQNLearner(spec, 2, NetworkConfig(hidden=[2], dueling=False),
                         LearnerConfig(lr=lr, adam_eps=eps, gamma=gamma, huber_delta=delta, grad_clip=clip,
                                       target_update_period=1000, optimizer="adam"), torch.device("cpu"))
    f32 = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        for net, (A1, a1, A2, a2) in ((learner.online, (W1, b1, W2, b2)), (learner.target, (T1, t1, T2, t2))):
            lin1, lin2 = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
            lin1.weight.copy_(f32(A1)), lin1.bias.copy_(f32(a1)), lin2.weight.copy_(f32(A2)), lin2.bias.copy_(f32(a2))
    data = {"obs": obs.astype(np.float32), "next_obs": nxt.astype(np.float32), "action": action.astype(np.int64),
            "reward": reward.astype(np.float32), "n": n.astype(np.uint8), "terminated": terminated}
    metrics, priorities = learner.update(learner.batch_to_tensors(data, isw.astype(np.float32)))

    assert norm > clip, "the example must exercise the clip"
    assert metrics["loss"] == pytest.approx(loss, rel=1e-5)
    assert metrics["grad_norm"] == pytest.approx(norm, rel=1e-5)
    np.testing.assert_allclose(priorities, np.abs(err), rtol=1e-5)
    lin1, lin2 = [m for m in learner.online.modules() if isinstance(m, torch.nn.Linear)]
    got = [lin1.weight, lin1.bias, lin2.weight, lin2.bias]
    for name, g, e in zip(("W1", "b1", "W2", "b2"), got, expected):
        np.testing.assert_allclose(g.detach().numpy(), e, rtol=1e-5, atol=1e-7, err_msg=name)
    # the target network is untouched until its period
    np.testing.assert_allclose([m for m in learner.target.modules() if isinstance(m, torch.nn.Linear)][0].weight.numpy(),
                               T1, rtol=1e-6)


def test_networks_on_dict_and_image_observations():
    import gymnasium as gym

    space = gym.spaces.Dict({"lidar": gym.spaces.Box(0, 4, (360,), np.float32),
                             "image": gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)})
    spec = obs_spec(space)
    assert spec == {"obs/lidar": ArraySpec((360,), "float32"), "obs/image": ArraySpec((64, 64, 3), "uint8")}
    net = QNetwork(spec, 5, NetworkConfig(hidden=[32]))
    obs = {"obs/lidar": torch.rand(7, 360), "obs/image": torch.randint(0, 255, (7, 64, 64, 3), dtype=torch.uint8)}
    q = net(obs)
    assert q.shape == (7, 5)
    assert any(isinstance(m, torch.nn.Conv2d) for m in net.modules())
    # dueling: the advantages are centred, so V is the mean of Q over actions
    h = net.trunk(net.encoder(obs))
    torch.testing.assert_close(q.mean(1), net.value(h).squeeze(1))


class _FakeNode:
    def __init__(self):
        self.latest = None

    def subscribe_latest(self, key):
        outer = self

        class LV:
            def take(self):
                v, outer.latest = outer.latest, None
                return v

        return LV()


def _weights(net, version, arch=None):
    return P.Weights(version=version, learner_id="l", arch=arch or arch_fingerprint(net), updates=version * 10,
                     params=params_to_arrays(net)).encode()


def test_weights_follower_takes_only_newer_matching_weights():
    spec = {"obs": ArraySpec((4,), "float32")}
    torch.manual_seed(0)
    learner_net = QNetwork(spec, 2, NetworkConfig(hidden=[16]))
    actor_net = QNetwork(spec, 2, NetworkConfig(hidden=[16]))
    node = _FakeNode()
    f = WeightsFollower(node, P.Keys("r"), actor_net, P.DEFAULT_MAX_MESSAGE_BYTES)
    node.latest = _weights(learner_net, 3)
    assert f.maybe_load() and f.version == 3 and f.updates == 30
    for a, b in zip(actor_net.state_dict().values(), learner_net.state_dict().values()):
        assert torch.equal(a, b)
    node.latest = _weights(learner_net, 3)
    assert not f.maybe_load()                       # same version: ignored
    node.latest = _weights(learner_net, 2)
    assert not f.maybe_load() and f.version == 3    # older: ignored
    other = QNetwork(spec, 2, NetworkConfig(hidden=[8]))
    node.latest = _weights(other, 9)
    assert not f.maybe_load() and f.rejected == 1   # another architecture: refused
    assert not f.maybe_load()                       # nothing new


def test_arrays_to_params_names_the_bad_parameter():
    spec = {"obs": ArraySpec((4,), "float32")}
    net = QNetwork(spec, 2, NetworkConfig(hidden=[16]))
    arrays = params_to_arrays(net)
    name = next(iter(arrays))
    arrays[name] = np.zeros((3, 3), np.float32)
    with pytest.raises(ValueError, match=name):
        arrays_to_params(net, arrays)


@pytest.mark.parametrize("activation,dueling", [("relu", True), ("tanh", False), ("relu", False)])
def test_numpy_q_equals_torch_forward(activation, dueling):
    spec = {"obs/lidar": ArraySpec((6,), "float32"), "obs/pose": ArraySpec((3,), "float32"),
            "obs/grid": ArraySpec((2, 2), "float32")}
    torch.manual_seed(0)
    net = QNetwork(spec, 5, NetworkConfig(hidden=[32, 16], activation=activation, dueling=dueling)).eval()
    fast = NumpyQ.of(net)
    assert fast is not None
    rng = np.random.default_rng(0)
    obs = {k: rng.normal(size=(7, *v.shape)).astype(np.float32) for k, v in spec.items()}
    with torch.no_grad():
        ref = net({k: torch.from_numpy(v) for k, v in obs.items()}).numpy()
    got = fast(obs)
    assert got.dtype == np.float32 and got.shape == (7, 5)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    # new weights: stale until load() is called
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1)
        ref2 = net({k: torch.from_numpy(v) for k, v in obs.items()}).numpy()
    assert not np.allclose(fast(obs), ref2, atol=1e-3)
    fast.load(net)
    np.testing.assert_allclose(fast(obs), ref2, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("activation,shared", [("tanh", False), ("relu", True)])
def test_numpy_copy_of_an_actor_critic_gives_its_policy_logits(activation, shared):
    spec = {"obs/lidar": ArraySpec((6,), "float32"), "obs/pose": ArraySpec((3,), "float32")}
    torch.manual_seed(0)
    net = ActorCritic(spec, 4, NetworkConfig(hidden=[32, 16], activation=activation, shared_torso=shared)).eval()
    with torch.no_grad():  # orthogonal init gives the policy head tiny weights: make them count
        net.policy.weight.mul_(100.0)
        net.policy.bias.normal_()
    fast = NumpyQ.of(net)
    assert fast is not None
    obs = {k: np.random.default_rng(1).normal(size=(9, *v.shape)).astype(np.float32) for k, v in spec.items()}
    with torch.no_grad():
        logits, _ = net({k: torch.from_numpy(v) for k, v in obs.items()})
    got = fast(obs)
    assert got.shape == (9, 4)
    np.testing.assert_allclose(got, logits.numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(got.argmax(1), logits.numpy().argmax(1))


def test_numpy_q_declines_conv_networks():
    net = QNetwork({"obs": ArraySpec((36, 36, 3), "uint8")}, 3, NetworkConfig(hidden=[16]))
    assert NumpyQ.of(net) is None
    assert NumpyQ.of(QNetwork({"obs": ArraySpec((36, 36, 3), "uint8")}, 3, NetworkConfig(hidden=[16], conv=False))) is not None


def _learner_and_batch(B=32):
    """A small DQNLearner (seeded) and one batch of B random transitions as tensors."""
    from zenrl.common.config import LearnerConfig
    from zenrl.learner.dqn import DQNLearner

    torch.manual_seed(3)
    spec = {"obs": ArraySpec((4,), "float32")}
    dqn = DQNLearner(spec, 2, NetworkConfig(hidden=[16, 16], dueling=True), LearnerConfig(lr=1e-2), torch.device("cpu"))
    rng = np.random.default_rng(0)
    data = {"obs": rng.normal(size=(B, 4)).astype(np.float32), "next_obs": rng.normal(size=(B, 4)).astype(np.float32),
            "action": rng.integers(0, 2, B), "reward": rng.normal(size=B).astype(np.float32),
            "n": np.full(B, 3, np.uint8), "terminated": rng.random(B) < 0.2}
    return dqn, dqn.batch_to_tensors(data, rng.random(B).astype(np.float32))


def test_fused_adam_takes_the_same_steps_and_old_optimizer_state():
    """The learner's fused Adam gives the parameters a plain (unfused) Adam would, and takes the
    optimizer state of a checkpoint written with an unfused one."""
    fused, b = _learner_and_batch()
    plain, _ = _learner_and_batch()
    assert fused.opt.defaults["fused"]
    plain.opt = torch.optim.Adam(plain.online.parameters(), lr=1e-2, eps=plain.cfg.adam_eps, foreach=False)
    for _ in range(5):
        fused.update(b)
        plain.update(b)
    for p, q in zip(fused.online.parameters(), plain.online.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
    resumed, _ = _learner_and_batch()
    resumed.load_state_dict(copy.deepcopy(plain.state_dict()))  # as from a file: no shared tensors
    assert resumed.opt.param_groups[0]["fused"]  # still the fused kernel after the unfused state
    resumed.update(b)
    plain.update(b)
    for p, q in zip(resumed.online.parameters(), plain.online.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
