"""Discrete observations (FrozenLake, Taxi, CliffWalking, a Dict holding a Discrete) reach the
networks one-hot encoded: their index names a state, it is not a quantity."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from zenrl.common.config import NetworkConfig
from zenrl.common.networks import ActorCritic, NumpyQ, OneHotEncoder, QNetwork, obs_spec
from zenrl.common.recurrent import NumpyRecurrentQ, RecurrentQNetwork
from zenrl.common.specs import MAX_CATEGORIES, ArraySpec


def test_a_discrete_space_gives_an_int64_index_that_names_its_categories():
    assert obs_spec(gym.spaces.Discrete(16)) == {"obs": ArraySpec((), "int64")}
    assert obs_spec(gym.spaces.Discrete(16))["obs"].categories == (0, 16)
    assert obs_spec(gym.spaces.Discrete(5, start=-2))["obs"].categories == (-2, 5)
    d = obs_spec(gym.spaces.Dict({"cell": gym.spaces.Discrete(3), "x": gym.spaces.Box(-1, 1, (2,))}))
    assert d["obs/cell"].categories == (0, 3) and d["obs/x"].categories is None
    # too many to one-hot: the index, a number, as before
    assert obs_spec(gym.spaces.Discrete(MAX_CATEGORIES + 1))["obs"].categories is None
    assert obs_spec(gym.spaces.Discrete(MAX_CATEGORIES))["obs"].categories == (0, MAX_CATEGORIES)


def test_one_hot_encoder_by_hand():
    enc = OneHotEncoder(start=-2, n=4)
    out = enc(torch.tensor([-2, 1, 0, 7, -9]))  # the last two outside the space: clamped
    expected = torch.tensor([[1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]], dtype=torch.float32)
    torch.testing.assert_close(out, expected)
    assert enc.out_dim == 4


def test_q_of_a_one_hot_state_is_the_first_layer_column_of_that_state():
    """With an identity hidden layer, Q(s) = W[:, s] + b: each state has its own values (a number
    input would make the first layer's output linear in the index, one slope for every state)."""
    net = QNetwork(obs_spec(gym.spaces.Discrete(5)), 3, NetworkConfig(hidden=[5], dueling=False)).eval()
    w = torch.arange(15, dtype=torch.float32).reshape(3, 5) ** 2  # not linear in the state
    b = torch.tensor([0.5, -1.0, 2.0])
    with torch.no_grad():
        net.trunk[0].weight.copy_(torch.eye(5))
        net.trunk[0].bias.zero_()
        net.q.weight.copy_(w)
        net.q.bias.copy_(b)
        q = net({"obs": torch.tensor([0, 3, 4])})
    torch.testing.assert_close(q, torch.stack([w[:, 0] + b, w[:, 3] + b, w[:, 4] + b]))


@pytest.mark.parametrize("make", [
    lambda spec: QNetwork(spec, 4, NetworkConfig(hidden=[16, 8], dueling=True)),
    lambda spec: QNetwork(spec, 4, NetworkConfig(hidden=[16], activation="tanh", dueling=False)),
    lambda spec: ActorCritic(spec, 4, NetworkConfig(hidden=[16])),
])
def test_numpy_copy_one_hot_encodes_as_the_network_does(make):
    space = gym.spaces.Dict({"cell": gym.spaces.Discrete(7, start=1), "x": gym.spaces.Box(-1, 1, (3,))})
    spec = obs_spec(space)
    torch.manual_seed(0)
    net = make(spec).eval()
    if isinstance(net, ActorCritic):
        with torch.no_grad():
            net.policy.weight.mul_(100.0)
    first = next(m for m in net.trunk if isinstance(m, torch.nn.Linear))
    assert first.in_features == 7 + 3
    fast = NumpyQ.of(net)
    assert fast is not None
    rng = np.random.default_rng(0)
    obs = {"obs/cell": rng.integers(1, 8, size=11).astype(np.int64),
           "obs/x": rng.uniform(-1, 1, size=(11, 3)).astype(np.float32)}
    with torch.no_grad():
        ref = net({k: torch.from_numpy(v) for k, v in obs.items()})
    ref = (ref[0] if isinstance(ref, tuple) else ref).numpy()
    np.testing.assert_allclose(fast(obs), ref, rtol=1e-5, atol=1e-5)
    # two states the network tells apart: their one-hot rows differ
    assert not np.allclose(fast({"obs/cell": np.array([1]), "obs/x": obs["obs/x"][:1]}),
                           fast({"obs/cell": np.array([7]), "obs/x": obs["obs/x"][:1]}))


def test_recurrent_network_and_its_numpy_step_one_hot_encode_too():
    spec = obs_spec(gym.spaces.Dict({"cell": gym.spaces.Discrete(9), "x": gym.spaces.Box(-1, 1, (2,))}))
    torch.manual_seed(3)
    net = RecurrentQNetwork(spec, 3, NetworkConfig(hidden=[8]), 16).eval()
    assert net.encoder.out_dim == 9 + 2
    fast = NumpyRecurrentQ.of(net)
    assert fast is not None
    rng = np.random.default_rng(2)
    state = (torch.zeros(6, 16), torch.zeros(6, 16))
    np_state = (np.zeros((6, 16), np.float32), np.zeros((6, 16), np.float32))
    for _ in range(3):
        obs = {"obs/cell": rng.integers(0, 9, size=6), "obs/x": rng.uniform(-1, 1, (6, 2)).astype(np.float32)}
        with torch.no_grad():
            q, state = net.step({k: torch.from_numpy(v) for k, v in obs.items()}, state)
        q_np, np_state = fast(obs, np_state)
        np.testing.assert_allclose(q_np, q.numpy(), atol=1e-5, rtol=1e-5)
    # sequences [T, B] of indices, as the learner unrolls them
    seq = {"obs/cell": torch.randint(0, 9, (4, 6)), "obs/x": torch.rand(4, 6, 2)}
    with torch.no_grad():
        q_seq, _ = net(seq, (torch.zeros(6, 16), torch.zeros(6, 16)))
    assert q_seq.shape == (4, 6, 3) and torch.isfinite(q_seq).all()
