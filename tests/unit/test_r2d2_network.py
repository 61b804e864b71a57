"""RecurrentQNetwork: an unroll equals its single steps, resets equal fresh starts; the value
rescaling h and its inverse against hand values and each other; the mixed priority."""

import numpy as np
import pytest
import torch

from zenrl.common.config import NetworkConfig
from zenrl.common.recurrent import NumpyRecurrentQ, RecurrentQNetwork, inverse_value_rescale, mixed_priority, value_rescale
from zenrl.common.specs import ArraySpec

VEC = {"obs": ArraySpec((2,), "float32")}
DICT = {"obs/pos": ArraySpec((3,), "float32"), "obs/img": ArraySpec((12, 12, 3), "uint8")}


def _obs(spec, T, B, gen):
    out = {}
    for k, s in spec.items():
        if s.dtype == "uint8":
            out[k] = torch.randint(0, 256, (T, B, *s.shape), generator=gen, dtype=torch.uint8)
        else:
            out[k] = torch.randn(T, B, *s.shape, generator=gen)
    return out


def _net(spec, dueling=True, seed=0):
    torch.manual_seed(seed)
    return RecurrentQNetwork(spec, 3, NetworkConfig(hidden=[16], dueling=dueling), lstm_size=8)


def _random_state(B, H, gen):
    return torch.randn(B, H, generator=gen), torch.randn(B, H, generator=gen)


@pytest.mark.parametrize("spec,dueling", [(VEC, True), (VEC, False), (DICT, True)])
def test_unroll_equals_single_steps(spec, dueling):
    gen = torch.Generator().manual_seed(1)
    net = _net(spec, dueling)
    T, B = 7, 4
    obs = _obs(spec, T, B, gen)
    state = _random_state(B, 8, gen)
    reset = torch.zeros(T, B, dtype=torch.bool)
    reset[0, 1] = reset[4, 2] = reset[4, 3] = reset[6, 0] = True
    with torch.no_grad():
        q, (h, c) = net(obs, state, reset)
        s = state
        for t in range(T):
            q_t, s = net.step({k: v[t] for k, v in obs.items()}, s, reset[t])
            torch.testing.assert_close(q[t], q_t, atol=1e-5, rtol=1e-5)
    assert q.shape == (T, B, 3)
    torch.testing.assert_close(h, s[0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(c, s[1], atol=1e-5, rtol=1e-5)


def test_reset_in_the_middle_equals_a_fresh_start():
    gen = torch.Generator().manual_seed(2)
    net = _net(VEC)
    T, B, r = 9, 3, 4
    obs = _obs(VEC, T, B, gen)
    state = _random_state(B, 8, gen)
    reset = torch.zeros(T, B, dtype=torch.bool)
    reset[r, 0] = True
    with torch.no_grad():
        q, _ = net(obs, state, reset)
        fresh, _ = net({k: v[r:] for k, v in obs.items()}, net.initial_state(B), None)
        plain, _ = net(obs, state, None)
    torch.testing.assert_close(q[r:, 0], fresh[:, 0], atol=1e-5, rtol=1e-5)
    # the envs without a reset carry their state through, and the stored state matters
    torch.testing.assert_close(q[:, 1:], plain[:, 1:], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(q[:r, 0], plain[:r, 0], atol=1e-5, rtol=1e-5)
    assert not torch.allclose(plain[r:, 0], fresh[:, 0], atol=1e-3)


def test_reset_at_t0_ignores_the_given_state_and_step_reset_zeroes_it():
    gen = torch.Generator().manual_seed(3)
    net = _net(VEC)
    obs = _obs(VEC, 5, 2, gen)
    with torch.no_grad():
        q, _ = net(obs, _random_state(2, 8, gen), torch.ones(5, 2, dtype=torch.bool) & (torch.arange(5) == 0)[:, None])
        fresh, _ = net(obs, net.initial_state(2))
        torch.testing.assert_close(q, fresh, atol=1e-6, rtol=1e-6)
        q1, _ = net.step({"obs": obs["obs"][0]}, _random_state(2, 8, gen), torch.tensor([True, True]))
        q0, _ = net.step({"obs": obs["obs"][0]}, net.initial_state(2))
        torch.testing.assert_close(q1, q0)
    h, c = net.initial_state(4)
    assert h.shape == c.shape == (4, 8) and not h.any() and not c.any()


def test_gradient_reaches_every_parameter():
    gen = torch.Generator().manual_seed(4)
    net = _net(DICT)
    q, _ = net(_obs(DICT, 4, 2, gen), net.initial_state(2))
    (q * torch.randn(q.shape, generator=gen)).sum().backward()  # q.sum() cancels the advantage
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


@pytest.mark.parametrize("dueling,activation", [(True, "relu"), (False, "tanh")])
def test_numpy_step_equals_the_torch_step(dueling, activation):
    torch.manual_seed(6)
    spec = {"obs/a": ArraySpec((2,), "float32"), "obs/b": ArraySpec((3,), "float32")}
    net = RecurrentQNetwork(spec, 4, NetworkConfig(hidden=[16, 8], dueling=dueling, activation=activation), lstm_size=8)
    fast = NumpyRecurrentQ.of(net)
    gen = torch.Generator().manual_seed(7)
    state = _random_state(5, 8, gen)
    np_state = tuple(x.numpy().copy() for x in state)
    for t in range(4):
        obs = {k: torch.randn(5, *s.shape, generator=gen) for k, s in spec.items()}
        reset = torch.tensor([t == 2, False, t == 1, False, False])
        with torch.no_grad():
            q, state = net.step(obs, state, reset)
        q_np, np_state = fast({k: v.numpy() for k, v in obs.items()}, np_state, reset.numpy())
        np.testing.assert_allclose(q_np, q.numpy(), atol=1e-5, rtol=1e-5)
        np.testing.assert_allclose(np_state[0], state[0].numpy(), atol=1e-5, rtol=1e-5)
        np.testing.assert_allclose(np_state[1], state[1].numpy(), atol=1e-5, rtol=1e-5)
        assert q_np.dtype == np_state[0].dtype == np_state[1].dtype == np.float32
    assert NumpyRecurrentQ.of(_net(DICT)) is None  # conv encoders stay in torch


# --- value rescaling ----------------------------------------------------------------------------
def test_value_rescale_hand_values():
    eps = 1e-3
    for x, hx in [(0.0, 0.0), (3.0, 1.0 + 3 * eps), (-8.0, -2.0 - 8 * eps), (99.0, 9.0 + 99 * eps),
                  (-0.44, -0.2 - 0.44 * eps)]:
        assert value_rescale(np.float64(x)) == pytest.approx(hx, rel=1e-12, abs=1e-15)
        assert inverse_value_rescale(np.float64(hx)) == pytest.approx(x, rel=1e-12, abs=1e-15)
    assert value_rescale(np.float64(3.0), eps=0.0) == 1.0


def test_inverse_is_exact_over_a_wide_range():
    x = np.concatenate([-np.logspace(-9, 8, 3001), [0.0], np.logspace(-9, 8, 3001)])
    np.testing.assert_allclose(inverse_value_rescale(value_rescale(x)), x, rtol=1e-12, atol=0)
    y = value_rescale(x)
    np.testing.assert_allclose(value_rescale(inverse_value_rescale(y)), y, rtol=1e-12, atol=0)
    x32 = x.astype(np.float32)
    np.testing.assert_allclose(inverse_value_rescale(value_rescale(x32)), x32, rtol=2e-6, atol=0)
    t = torch.from_numpy(x32)
    torch.testing.assert_close(inverse_value_rescale(value_rescale(t)), t, rtol=2e-6, atol=0)
    assert np.all(np.diff(value_rescale(np.sort(x))) > 0)  # strictly increasing


def test_mixed_priority_numpy_and_torch():
    td = np.array([[1.0, -3.0, 2.0, 100.0], [0.5, 0.0, 0.0, 0.0], [7.0, 7.0, 7.0, 7.0]])
    mask = np.array([[True, True, True, False], [True, False, False, False], [False] * 4])
    want = [0.9 * 3 + 0.1 * 2.0, 0.5, 0.0]
    np.testing.assert_allclose(mixed_priority(np.abs(td), mask), want)
    np.testing.assert_allclose(mixed_priority(torch.tensor(td).abs(), torch.tensor(mask)).numpy(), want)
    np.testing.assert_allclose(mixed_priority(np.abs(td), mask, eta=0.0), [2.0, 0.5, 0.0])
