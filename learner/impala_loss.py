"""The IMPALA loss (Espeholt et al., 2018) and its APPO variant, on a batch of unrolls.

With N = T * B samples, pi/V the learner's actor-critic, mu the behaviour policy, and the
V-trace targets ``vs`` and advantages of :func:`zenrl.learner.vtrace.vtrace` (constants)::

    loss = policy_loss + value_coef * value_loss - entropy_coef * entropy
    value_loss = mean((vs - V(x))^2)            entropy = mean(H(pi(.|x)))
    IMPALA: policy_loss = -mean(rho_pg * (q - V(x)) * log pi(a|x))         (q = r + gamma v_{s+1})
    APPO:   policy_loss = -mean(min(ratio * A, clip(ratio, 1 - eps, 1 + eps) * A)),
            ratio = pi(a|x) / mu(a|x),  A = q - V(x) (the ratio already importance-weights;
            optionally normalized over the batch)

The same coefficients' meaning as zenrl's A3C loss (``actor/a3c.py``), so configs carry over.
:func:`forward_unrolls` evaluates the network once on all the batch's observations;
:func:`learner_step` is one optimizer step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch.nn import functional as F

from zenrl.common.networks import policy_logp_entropy
from zenrl.learner.unroll_queue import UnrollBatch
from zenrl.learner.vtrace import vtrace

#: log(pi/mu) is capped here before exp: a ratio of e^20 is already absurd, and the cap keeps
#: the statistics finite when a behaviour log-probability is extreme.
MAX_LOG_RHO = 20.0


@dataclass(frozen=True)
class LossParams:
    """``clip_eps`` None: IMPALA's policy gradient; a number: APPO's clipped surrogate.
    ``reward_scale``: the rewards are multiplied by it before anything else (the value function
    learns scaled returns; with the gradient clipped as a whole, rewards of large magnitude
    would otherwise let the value loss's gradient crowd out the policy's)."""

    gamma: float = 0.99
    lam: float = 1.0
    rho_bar: float = 1.0
    c_bar: float = 1.0
    value_coef: float = 0.5
    entropy_coef: float = 0.01
    clip_eps: float | None = None
    normalize_advantages: bool = False
    reward_scale: float = 1.0


def impala_loss(logits: torch.Tensor, values: torch.Tensor, bootstrap_value: torch.Tensor,
                truncated_values: torch.Tensor | None, action: torch.Tensor, behaviour_logp: torch.Tensor,
                reward: torch.Tensor, terminated: torch.Tensor, truncated: torch.Tensor,
                p: LossParams, log_std: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """logits float[T, B, A] and values float[T, B] (with grad); bootstrap_value float[B] and
    truncated_values float[T, B] or None (V of the observation after the last step and of the
    truncated steps' final observations: detached, they only feed the targets); action
    int64[T, B]; behaviour_logp, reward float[T, B]; terminated, truncated bool[T, B].
    Continuous actions: ``log_std`` float[d] (with grad), ``logits`` the means float[T, B, d],
    ``action`` float[T, B, d] (:func:`~zenrl.common.networks.policy_logp_entropy`).
    Returns (loss scalar, stats: loss, policy_loss, value_loss, entropy, rho_mean, rho_max,
    clip_fraction (APPO: |ratio - 1| > eps; IMPALA: rho > rho_bar), advantage_mean, vs_mean)."""
    logp, entropies = policy_logp_entropy(logits, action, log_std)
    if p.reward_scale != 1.0:
        reward = reward * p.reward_scale
    log_rhos = (logp.detach() - behaviour_logp).clamp(max=MAX_LOG_RHO)
    vt = vtrace(log_rhos, reward, values.detach(), bootstrap_value.detach(), terminated, truncated,
                None if truncated_values is None else truncated_values.detach(),
                p.gamma, p.lam, p.rho_bar, p.c_bar)
    if p.clip_eps is None:
        adv = vt.pg_advantages
        policy_loss = -(logp * adv).mean()
        clipped = (vt.rhos > p.rho_bar).float().mean() if math.isfinite(p.rho_bar) else torch.zeros(())
    else:
        adv = vt.q_estimates - values.detach()
        if p.normalize_advantages and adv.numel() > 1:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        ratio = torch.exp((logp - behaviour_logp).clamp(max=MAX_LOG_RHO))
        surrogate = torch.min(ratio * adv, ratio.clamp(1.0 - p.clip_eps, 1.0 + p.clip_eps) * adv)
        policy_loss = -surrogate.mean()
        clipped = ((ratio.detach() - 1.0).abs() > p.clip_eps).float().mean()
    value_loss = F.mse_loss(values, vt.vs)
    entropy = entropies.mean()
    loss = policy_loss + p.value_coef * value_loss - p.entropy_coef * entropy
    stats = {"loss": loss, "policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
             "rho_mean": vt.rhos.mean(), "rho_max": vt.rhos.max(), "clip_fraction": clipped,
             "advantage_mean": adv.mean(), "vs_mean": vt.vs.mean()}
    return loss, {k: float(v.detach()) for k, v in stats.items()}


def forward_unrolls(net: torch.nn.Module, batch: UnrollBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """One forward pass of an actor-critic (``{name: [N, ...]}`` -> (logits [N, A], values
    [N])) over the (T+1)*B unroll observations and the K final observations. Returns logits
    [T, B, A] and values [T, B] of the acted-on observations (with grad), the bootstrap values
    [B] and the truncated steps' final values [T, B] (0 elsewhere; None when K = 0), detached."""
    T, B = batch.shape
    K = int(batch.final_index.numel())
    flat = {}
    for k, o in batch.obs.items():
        x = o.reshape((T + 1) * B, *o.shape[2:])
        flat[k] = torch.cat([x, batch.final_obs[k]]) if K else x
    logits, values = net(flat)
    n = (T + 1) * B
    final_values = None
    if K:
        final_values = torch.zeros(T * B, dtype=values.dtype, device=values.device)
        final_values[batch.final_index] = values[n:].detach()
        final_values = final_values.view(T, B)
    return (logits[:T * B].view(T, B, -1), values[:T * B].view(T, B), values[T * B:n].detach(), final_values)


def learner_step(net: torch.nn.Module, optimizer: torch.optim.Optimizer, batch: UnrollBatch, p: LossParams,
                 max_grad_norm: float | None = None,
                 accept: Callable[[float, float], bool] | None = None) -> dict[str, float] | None:
    """Forward, loss, backward, gradient-norm clipping (``max_grad_norm``), one optimizer step.
    Returns the loss statistics plus ``grad_norm`` (before clipping). ``accept(loss,
    grad_norm)`` (the learner's guard) is asked before the step: False skips it (the gradients
    are cleared, the optimizer never sees them) and None is returned."""
    logits, values, boot, final_values = forward_unrolls(net, batch)
    log_std = net.clamped_log_std() if getattr(net, "continuous", False) else None
    loss, stats = impala_loss(logits, values, boot, final_values, batch.action, batch.behaviour_logp, batch.reward,
                              batch.terminated, batch.truncated, p, log_std)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    params = [q for q in net.parameters() if q.grad is not None]
    norm = torch.nn.utils.clip_grad_norm_(params, max_grad_norm if max_grad_norm is not None else math.inf)
    stats["grad_norm"] = float(norm)
    if accept is not None and not accept(stats["loss"], stats["grad_norm"]):
        optimizer.zero_grad(set_to_none=True)
        return None
    optimizer.step()
    return stats
