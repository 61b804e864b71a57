"""R2D2's loss on a batch of stored sequences (Kapturowski et al., ICLR 2019).

A batch holds B sequences of m steps as cut by :mod:`zenrl.actor.sequences`, item-major as the
replay serves them (flat field names as everywhere in zenrl)::

    obs / obs/<key>  [B, m+1, ...]  s_0..s_m; s_len is the observation after the last valid step
                                    (the final one where the episode ended), zeros after it
    action           int64[B, m]    reward float[B, m]    terminated bool[B, m]
    mask             bool[B, m]     valid steps: a prefix of length len <= m (padding after)
    first            bool[B]        the sequence starts its episode (its stored state is zero)
    h, c             float[B, H]    the actor's recurrent state before s_0
    weights          float[B]       importance-sampling weights

The online network unrolls the first ``burn_in`` = k steps from the stored state without
gradient (the stored state is stale: it came from older weights), then the rest with gradient.
A sequence that starts its episode needs no burn-in (its true start state is exactly zero), so
with ``train_episode_starts`` it is trained from step 0; otherwise the first k steps of every
episode would never be learnt from. The target network unrolls the whole sequence.

Targets, for a trained step t with j = min(n, len - t) (n-step, shortened at the sequence's
end)::

    y_t = h( sum_{i<j} gamma^i r_{t+i} + gamma^j (1 - terminal) h_inv(Q_tgt(s_{t+j}, a*)) )
    a*  = argmax_a Q_online(s_{t+j}, a)          (double Q)

``terminal`` only where t+j = len and the episode terminated at step len-1; a truncated episode
bootstraps from its final observation. delta_t = Q_online(s_t, a_t) - y_t; loss = IS-weighted
mean over trained steps of 0.5 delta^2 (Huber with ``huber_delta``); the sequence's new priority
is ``eta max|delta| + (1 - eta) mean|delta|`` over its trained steps (0 if it has none).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import torch
import torch.nn.functional as F

from zenrl.common.recurrent import RecurrentQNetwork, inverse_value_rescale, mixed_priority, value_rescale

__all__ = ["R2D2Loss", "r2d2_loss", "value_rescale", "inverse_value_rescale"]


@dataclass
class R2D2Loss:
    """loss: scalar (differentiable); priorities float[B]; td float[B, m] (delta, 0 where not
    trained); trained bool[B, m] the steps in the loss; q_mean: mean Q(s_t, a_t) over them."""

    loss: torch.Tensor
    priorities: torch.Tensor
    td: torch.Tensor
    trained: torch.Tensor
    q_mean: float


def _online_q(net: RecurrentQNetwork, obs: dict[str, torch.Tensor], state, reset: torch.Tensor,
              k: int) -> torch.Tensor:
    """[T, B, A]: steps < k without gradient (burn-in), the rest with."""
    if k == 0:
        return net(obs, state, reset)[0]
    with torch.no_grad():
        q_burn, state = net({n: v[:k] for n, v in obs.items()}, state, reset[:k])
    q_rest, _ = net({n: v[k:] for n, v in obs.items()}, state, reset[k:])
    return torch.cat([q_burn, q_rest], dim=0)


def r2d2_loss(online: RecurrentQNetwork, target: RecurrentQNetwork, batch: Mapping[str, torch.Tensor], *,
              burn_in: int, n_step: int, gamma: float, eps: float = 1e-3, eta: float = 0.9,
              huber_delta: float | None = None, train_episode_starts: bool = True) -> R2D2Loss:
    """The loss and priorities for one batch (fields and formulas: see the module docstring)."""
    mask = batch["mask"].T                                      # [m, B]; time-major from here on
    m, B = mask.shape
    if not 0 <= burn_in < m:
        raise ValueError(f"burn_in must be in [0, {m}), got {burn_in}")
    obs = {k: v.transpose(0, 1) for k, v in batch.items() if k == "obs" or k.startswith("obs/")}
    first = batch["first"].bool()
    reset = torch.zeros(m + 1, B, dtype=torch.bool, device=mask.device)
    reset[0] = first
    state = (batch["h"], batch["c"])

    with torch.no_grad():
        q_tgt, _ = target(obs, state, reset)                    # [m+1, B, A]
    starts = first if train_episode_starts and burn_in > 0 else torch.zeros_like(first)
    if starts.all():
        q_on = _online_q(online, obs, state, reset, 0)
    elif not starts.any():
        q_on = _online_q(online, obs, state, reset, burn_in)
    else:  # episode starts unroll with gradient from step 0, the others after their burn-in
        i_s, i_b = starts.nonzero().flatten(), (~starts).nonzero().flatten()
        part = [_online_q(online, {k: v[:, i] for k, v in obs.items()}, (state[0][i], state[1][i]), reset[:, i], k)
                for i, k in ((i_s, 0), (i_b, burn_in))]
        q_on = torch.cat(part, dim=1)[:, torch.argsort(torch.cat([i_s, i_b]))]

    # n-step returns, shortened at the sequence's end (len); rewards past it are padding
    t = torch.arange(m, device=mask.device).unsqueeze(1)        # [m, 1]
    length = mask.sum(0)                                        # [B]
    j = torch.clamp(length.unsqueeze(0) - t, min=0).clamp(max=n_step)   # [m, B]
    reward = torch.where(mask, batch["reward"].T.double(), 0.0)
    padded = torch.cat([reward, reward.new_zeros(n_step, B)], dim=0)
    ret = sum(gamma ** i * padded[i:i + m] for i in range(n_step))  # zeros past len end the sum at j
    term_end = (batch["terminated"].T & mask).any(0)            # the episode terminated at len-1
    boot_at = t + j                                             # [m, B], <= len
    discount = gamma ** j.double() * ~(term_end.unsqueeze(0) & (boot_at == length.unsqueeze(0)))
    with torch.no_grad():
        a_star = q_on.argmax(-1, keepdim=True)                  # [m+1, B, 1]
        v_next = q_tgt.gather(-1, a_star).squeeze(-1)           # [m+1, B]
        v_boot = v_next.gather(0, boot_at).double()
        y = value_rescale(ret + discount * inverse_value_rescale(v_boot, eps), eps).float()

    q_sa = q_on[:m].gather(-1, batch["action"].T.unsqueeze(-1)).squeeze(-1)   # [m, B]
    trained = mask & ((t >= burn_in) | starts.unsqueeze(0))
    delta = q_sa - y
    per_step = F.huber_loss(q_sa, y, reduction="none", delta=huber_delta) if huber_delta else 0.5 * delta ** 2
    w = batch["weights"].float().unsqueeze(0)
    loss = (w * per_step * trained).sum() / trained.sum().clamp(min=1)
    td = (delta * trained).detach()
    prio = mixed_priority(td.abs().T, trained.T, eta)
    q_mean = float((q_sa.detach() * trained).sum() / trained.sum().clamp(min=1))
    return R2D2Loss(loss, prio, td.T, trained.T, q_mean)
