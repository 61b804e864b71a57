"""R2D2 loss against a hand-written loop reference: burn-in, n-step double-Q with value
rescaling, padding, a terminal and a truncation mid-sequence, IS weights, mixed priorities; and
no gradient into the burn-in steps."""

import numpy as np
import pytest
import torch

from zenrl.common.config import NetworkConfig
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.specs import ArraySpec
from zenrl.learner.r2d2_loss import r2d2_loss

EPS, GAMMA, N, K, M, A, H = 1e-3, 0.9, 3, 3, 8, 3, 8


def h_ref(x):  # the paper's formulas, literally
    return np.sign(x) * (np.sqrt(abs(x) + 1) - 1) + EPS * x


def h_inv_ref(x):
    return np.sign(x) * (((np.sqrt(1 + 4 * EPS * (abs(x) + 1 + EPS)) - 1) / (2 * EPS)) ** 2 - 1)


def _nets():
    torch.manual_seed(0)
    spec = {"obs": ArraySpec((2,), "float32")}
    cfg = NetworkConfig(hidden=[16])
    online = RecurrentQNetwork(spec, A, cfg, lstm_size=H)
    target = RecurrentQNetwork(spec, A, cfg, lstm_size=H)  # different weights: double Q matters
    return online, target


#: (len, first, terminated at len-1, truncated at len-1) per sequence
CASES = [(8, False, False, False),   # full, mid-episode
         (5, False, True, False),    # terminal in the middle, padding after
         (6, True, False, True),     # episode start, truncated: bootstraps from the final obs
         (2, False, True, False),    # ends inside the burn-in: nothing to train
         (8, True, False, False),    # episode start, full
         (4, False, False, True)]    # truncated after the burn-in


def _batch(seed=1):
    rng = np.random.default_rng(seed)
    B = len(CASES)
    mask = np.zeros((B, M), bool)
    term = np.zeros((B, M), bool)
    trunc = np.zeros((B, M), bool)
    for b, (L, _, te, tr) in enumerate(CASES):
        mask[b, :L] = True
        term[b, L - 1], trunc[b, L - 1] = te, tr
    obs = rng.normal(size=(B, M + 1, 2)).astype(np.float32)
    first = np.array([c[1] for c in CASES])
    h = rng.normal(size=(B, H)).astype(np.float32)
    h[first] = 0.0
    c = rng.normal(size=(B, H)).astype(np.float32)
    c[first] = 0.0
    for b, (L, *_rest) in enumerate(CASES):
        obs[b, L + 1:] = 0.0
    return {"obs": torch.from_numpy(obs), "action": torch.from_numpy(rng.integers(0, A, (B, M))),
            "reward": torch.from_numpy((rng.normal(size=(B, M)) * 5 * mask).astype(np.float32)),
            "terminated": torch.from_numpy(term), "truncated": torch.from_numpy(trunc), "mask": torch.from_numpy(mask),
            "first": torch.from_numpy(first), "h": torch.from_numpy(h), "c": torch.from_numpy(c),
            "weights": torch.from_numpy(rng.uniform(0.3, 1.0, B).astype(np.float32))}


def _reference(online, target, batch, train_starts=True):
    """Loops over sequences and steps; Q values from plain unrolls over the whole sequence."""
    B = batch["mask"].shape[0]
    with torch.no_grad():
        reset = torch.zeros(M + 1, B, dtype=torch.bool)
        reset[0] = batch["first"]
        st = (batch["h"], batch["c"])
        q_on = online({"obs": batch["obs"].transpose(0, 1)}, st, reset)[0].double().numpy()
        q_tg = target({"obs": batch["obs"].transpose(0, 1)}, st, reset)[0].double().numpy()
    r, a, w = batch["reward"].numpy().astype(np.float64), batch["action"].numpy(), batch["weights"].numpy()
    total, count, prios = 0.0, 0, []
    for b, (L, first, terminated, _) in enumerate(CASES):
        deltas = []
        for t in range(M):
            if t >= L or (t < K and not (first and train_starts)):
                continue
            j = min(N, L - t)
            ret = sum(GAMMA ** i * r[b, t + i] for i in range(j))
            if t + j == L and terminated:
                boot = 0.0
            else:
                a_star = int(np.argmax(q_on[t + j, b]))
                boot = h_inv_ref(q_tg[t + j, b, a_star])
            delta = q_on[t, b, a[b, t]] - h_ref(ret + GAMMA ** j * boot)
            deltas.append(abs(delta))
            total += w[b] * 0.5 * delta ** 2
            count += 1
        prios.append(0.9 * max(deltas) + 0.1 * np.mean(deltas) if deltas else 0.0)
    return total / count, np.array(prios)


@pytest.mark.parametrize("train_starts", [True, False])
def test_loss_and_priorities_match_the_loop_reference(train_starts):
    online, target = _nets()
    batch = _batch()
    out = r2d2_loss(online, target, batch, burn_in=K, n_step=N, gamma=GAMMA, eps=EPS, train_episode_starts=train_starts)
    want_loss, want_prio = _reference(online, target, batch, train_starts)
    assert float(out.loss.detach()) == pytest.approx(want_loss, rel=1e-5)
    np.testing.assert_allclose(out.priorities.numpy(), want_prio, rtol=1e-5, atol=1e-7)
    assert out.priorities[3] == 0.0 and not out.trained[3].any()
    assert out.td.shape == out.trained.shape == (len(CASES), M)
    assert not out.td[~out.trained].any()


def test_no_gradient_flows_into_the_burn_in():
    online, target = _nets()
    batch = _batch()
    batch["obs"].requires_grad_(True)
    r2d2_loss(online, target, batch, burn_in=K, n_step=N, gamma=GAMMA, eps=EPS).loss.backward()
    g = batch["obs"].grad.abs().sum(-1)          # [B, m+1]
    for b, (L, first, *_rest) in enumerate(CASES):
        if first:
            assert g[b, 0] > 0                   # an episode start is trained from step 0
        else:
            assert not g[b, :K].any(), f"sequence {b} has gradient in its burn-in"
            if L > K:
                assert g[b, K] > 0
    for p in online.parameters():
        assert p.grad is not None
    assert all(p.grad is None for p in target.parameters())


def test_burn_in_and_stored_state_shape_the_trained_steps():
    """The burn-in is unrolled (not skipped): the stored state and the burn-in observations
    change the loss of a mid-episode sequence, and nothing of an episode start's stored state."""
    online, target = _nets()

    def prio(mutate):
        batch = _batch()
        mutate(batch)
        return r2d2_loss(online, target, batch, burn_in=K, n_step=N, gamma=GAMMA, eps=EPS).priorities

    base = prio(lambda b: None)
    p_obs = prio(lambda b: b["obs"][0, 0].add_(1.0))
    p_state = prio(lambda b: b["h"][0].add_(1.0))
    assert p_obs[0] != base[0] and p_state[0] != base[0]
    torch.testing.assert_close(p_obs[1:], base[1:])
    p_first = prio(lambda b: b["h"][4].add_(1.0))      # a first sequence's state is reset to zero
    torch.testing.assert_close(p_first, base)


def test_padding_contributes_nothing():
    online, target = _nets()
    base = r2d2_loss(online, target, _batch(), burn_in=K, n_step=N, gamma=GAMMA, eps=EPS)
    batch = _batch()
    g = torch.Generator().manual_seed(5)
    for b, (L, _, terminated, _) in enumerate(CASES):
        start = L if terminated else L + 1      # a truncated sequence's s_len is its final observation
        batch["obs"][b, start:] = torch.randn(M + 1 - start, 2, generator=g) * 10
        batch["reward"][b, L:] = 100.0
        batch["action"][b, L:] = 2
    out = r2d2_loss(online, target, batch, burn_in=K, n_step=N, gamma=GAMMA, eps=EPS)
    torch.testing.assert_close(out.loss, base.loss)
    torch.testing.assert_close(out.priorities, base.priorities)


def test_burn_in_must_leave_steps_to_train():
    online, target = _nets()
    with pytest.raises(ValueError, match="burn_in"):
        r2d2_loss(online, target, _batch(), burn_in=M, n_step=N, gamma=GAMMA)
