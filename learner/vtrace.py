"""V-trace off-policy targets (Espeholt et al., 2018, "IMPALA", section 4), time-major.

The actors act with a behaviour policy mu (the parameters they held, some versions behind); the
learner evaluates the unrolls with its current policy pi and value V. V-trace (eq. 1)::

    v_s = V(x_s) + sum_{t=s}^{s+n-1} gamma^{t-s} (prod_{i=s}^{t-1} c_i) delta_t
    delta_t = rho_t (r_t + gamma V(x_{t+1}) - V(x_t))
    rho_t = min(rho_bar, pi(a_t|x_t) / mu(a_t|x_t)),   c_i = lambda * min(c_bar, pi(a_i|x_i) / mu(a_i|x_i))

computed backwards with the recursive form ``v_s - V(x_s) = delta_s + gamma c_s (v_{s+1} - V(x_{s+1}))``.
The policy-gradient advantage is ``rho_pg_s (r_s + gamma v_{s+1} - V(x_s))`` with
``rho_pg = min(rho_pg_bar, pi/mu)`` (``rho_pg_bar`` defaults to ``rho_bar``). ``lambda`` scales
the traces as in rlax (``lambda = 1`` is the paper's V-trace); on-policy (pi = mu, clipping
inactive) the targets are TD(lambda) / n-step returns.

Episode ends inside an unroll (each step ``s`` leads from ``x_s`` to the next observation):

* ``terminated[s]``: the episode really ended; nothing is bootstrapped (discount 0) and the
  trace stops.
* ``truncated[s]`` (and not terminated): the episode was cut off (time limit). The value of the
  true final observation, ``truncated_values[s]``, stands in for ``V(x_{s+1})`` and for
  ``v_{s+1}``, and the trace stops: ``x_{s+1}`` in the unroll is already the next episode's
  first observation, whose value must not leak into this episode's targets.

Everything here is computed without gradient (the targets are constants of the loss).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class VTraceReturns:
    """Outputs, all [T, B] in the dtype of ``values``, detached.

    ``vs``: V-trace value targets v_s. ``pg_advantages``: ``rho_pg_s (q_s - V(x_s))``, the
    IMPALA policy-gradient advantages. ``q_estimates``: ``q_s = r_s + gamma_s v_{s+1}`` (the
    one-step target of the action taken; APPO uses ``q_s - V(x_s)``, its ratio already
    importance-weights). ``rhos``: the unclipped ratios pi/mu (for statistics)."""

    vs: torch.Tensor
    pg_advantages: torch.Tensor
    q_estimates: torch.Tensor
    rhos: torch.Tensor


@torch.no_grad()
def vtrace(log_rhos: torch.Tensor, rewards: torch.Tensor, values: torch.Tensor, bootstrap_value: torch.Tensor,
           terminated: torch.Tensor, truncated: torch.Tensor, truncated_values: torch.Tensor | None,
           gamma: float, lam: float = 1.0, rho_bar: float = 1.0, c_bar: float = 1.0,
           rho_pg_bar: float | None = None) -> VTraceReturns:
    """V-trace targets and policy-gradient advantages of B unrolls of T steps.

    log_rhos float[T, B]: ``log pi(a_s|x_s) - log mu(a_s|x_s)``. rewards float[T, B].
    values float[T, B]: V(x_s) under the learner's parameters. bootstrap_value float[B]:
    V(x_T), the observation after the last step. terminated, truncated bool[T, B].
    truncated_values float[T, B] or None: V(final observation of step s) where ``truncated &
    ~terminated`` (other entries are ignored; None when nothing is truncated). ``gamma``
    discount, ``lam`` trace coefficient, ``rho_bar``/``c_bar``/``rho_pg_bar`` clipping levels
    (``math.inf`` disables one)."""
    if log_rhos.ndim != 2 or rewards.shape != log_rhos.shape or values.shape != log_rhos.shape:
        raise ValueError(f"log_rhos, rewards, values must be [T, B], got {list(log_rhos.shape)}, "
                         f"{list(rewards.shape)}, {list(values.shape)}")
    if bootstrap_value.shape != log_rhos.shape[1:]:
        raise ValueError(f"bootstrap_value must be [B] = {list(log_rhos.shape[1:])}, got {list(bootstrap_value.shape)}")
    T = log_rhos.shape[0]
    dtype = values.dtype
    rhos = torch.exp(log_rhos.to(dtype))
    clipped_rhos = rhos.clamp(max=rho_bar) if math.isfinite(rho_bar) else rhos
    pg_bar = rho_bar if rho_pg_bar is None else rho_pg_bar
    pg_rhos = rhos.clamp(max=pg_bar) if math.isfinite(pg_bar) else rhos
    cs = lam * (rhos.clamp(max=c_bar) if math.isfinite(c_bar) else rhos)

    terminated = terminated.bool()
    cut = truncated.bool() & ~terminated  # bootstrap from the final observation, not x_{s+1}
    if truncated_values is None and bool(cut.any()):
        raise ValueError("truncated steps need truncated_values (else the next episode's value would leak in)")
    discounts = gamma * (~terminated).to(dtype)
    # the trace from s+1 reaches s only inside one episode
    traces = discounts * cs * (~(terminated | cut)).to(dtype)

    def next_of(x: torch.Tensor) -> torch.Tensor:
        """x_{s+1} for s in 0..T-1: the next row, the bootstrap after the last step, the
        final observation's value at truncations (terminations: ``discounts`` is 0)."""
        nxt = torch.cat([x[1:], bootstrap_value.to(dtype).unsqueeze(0)], dim=0)
        if truncated_values is not None:
            nxt = torch.where(cut, truncated_values.to(dtype), nxt)
        return nxt

    deltas = clipped_rhos * (rewards.to(dtype) + discounts * next_of(values) - values)
    acc = torch.zeros_like(bootstrap_value, dtype=dtype)
    vs_minus_v = torch.empty_like(values)
    for t in range(T - 1, -1, -1):
        acc = deltas[t] + traces[t] * acc
        vs_minus_v[t] = acc
    vs = values + vs_minus_v
    q = rewards.to(dtype) + discounts * next_of(vs)
    return VTraceReturns(vs=vs, pg_advantages=pg_rhos * (q - values), q_estimates=q, rhos=rhos)
