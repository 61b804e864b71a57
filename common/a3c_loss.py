"""A3C's loss and the returns it is built on: pure functions of a rollout, no Zenoh.

A worker (:mod:`zenrl.actor.a3c`) collects a :class:`Rollout` of t_max steps on E envs and turns
it into gradients with :func:`rollout_gradients`: n-step returns bootstrapped with V
(:func:`nstep_returns`; no bootstrap after ``terminated``, the value of the episode's final
observation after ``truncated``) or, with ``a3c.gae_lambda`` < 1, generalized-advantage
lambda-returns (:func:`gae_returns`), then :func:`a3c_loss` and one backward pass. It lives in
``common/`` because the actor side computes it (the learner only applies what workers send).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from zenrl.common.networks import policy_logp_entropy, to_tensors


def nstep_returns(rewards: np.ndarray, terminated: np.ndarray, truncated: np.ndarray,
                  final_values: np.ndarray, bootstrap: np.ndarray, gamma: float) -> np.ndarray:
    """n-step returns of a rollout, bootstrapped with V, computed backwards.

    rewards float[T, E]; terminated, truncated bool[T, E] (the step at t ended the episode);
    final_values float[T, E]: V(final observation) of step t, read only where
    ``truncated & ~terminated``; bootstrap float[E]: V(observation after the last step).
    Returns float32[T, E] with, going backwards from ``R = bootstrap``::

        R_t = r_t                          if terminated[t]
        R_t = r_t + gamma * final_values_t if truncated[t]   (time limit: the state has a value)
        R_t = r_t + gamma * R_{t+1}        otherwise
    """
    T = rewards.shape[0]
    out = np.zeros(rewards.shape, np.float64)
    R = np.asarray(bootstrap, np.float64).copy()
    for t in range(T - 1, -1, -1):
        R = np.where(truncated[t], final_values[t], R)  # episode ended by the time limit
        R = rewards[t] + gamma * (1.0 - terminated[t].astype(np.float64)) * R
        out[t] = R
    return out.astype(np.float32)


def gae_returns(rewards: np.ndarray, terminated: np.ndarray, truncated: np.ndarray, values: np.ndarray,
                final_values: np.ndarray, bootstrap: np.ndarray, gamma: float, lam: float) -> np.ndarray:
    """Generalized-advantage (lambda-) return targets ``A_t + V(s_t)`` of a rollout.

    rewards float[T, E]; terminated, truncated bool[T, E]; values float[T, E]: V(s_t) of the
    observations acted on; final_values, bootstrap as in :func:`nstep_returns`. With
    ``v'_t`` the value of the state after step t (0 after ``terminated``, ``final_values_t``
    after ``truncated``, else ``V(s_{t+1})``, ``bootstrap`` after the last step)::

        delta_t = r_t + gamma * v'_t - V(s_t)
        A_t     = delta_t + gamma * lam * A_{t+1}   (A_{t+1} = 0 where the episode ended at t)

    ``lam = 1`` gives exactly :func:`nstep_returns`; ``lam = 0`` the one-step TD targets.
    Returns float32[T, E].
    """
    T = rewards.shape[0]
    v = np.asarray(values, np.float64)
    out = np.zeros(rewards.shape, np.float64)
    A = np.zeros(rewards.shape[1:], np.float64)
    for t in range(T - 1, -1, -1):
        nxt = np.asarray(bootstrap, np.float64) if t == T - 1 else v[t + 1]
        nxt = np.where(truncated[t], final_values[t], nxt)
        nxt = np.where(terminated[t], 0.0, nxt)
        ended = terminated[t] | truncated[t]
        delta = rewards[t] + gamma * nxt - v[t]
        A = delta + gamma * lam * np.where(ended, 0.0, A)
        out[t] = A + v[t]
    return out.astype(np.float32)


def a3c_loss(logits: torch.Tensor, values: torch.Tensor, actions: torch.Tensor, returns: torch.Tensor,
             value_coef: float, entropy_coef: float,
             log_std: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The A3C loss, averaged over N = T * E samples.

    logits float[N, A], values float[N] (V(s_t), with grad), actions int64[N], returns float[N]
    (targets, no grad). ``loss = policy_loss + value_coef * value_loss - entropy_coef * entropy``
    with ``policy_loss = -mean(log pi(a|s) * (R - V(s)).detach())``,
    ``value_loss = mean((R - V(s))^2)``, ``entropy = mean(H(pi(.|s)))``. Continuous actions:
    ``logits`` the Gaussian's means float[N, d], ``actions`` float[N, d], ``log_std`` float[d]
    (:func:`~zenrl.common.networks.policy_logp_entropy`). Returns (loss scalar, metrics).
    """
    logp, entropies = policy_logp_entropy(logits, actions, log_std)
    advantage = returns - values.detach()
    policy_loss = -(logp * advantage).mean()
    value_loss = F.mse_loss(values, returns)
    entropy = entropies.mean()
    loss = policy_loss + value_coef * value_loss - entropy_coef * entropy
    m = {"loss": loss, "policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
         "advantage_mean": advantage.mean()}
    return loss, {k: float(v.detach()) for k, v in m.items()}


@dataclass
class Rollout:
    """t_max steps of E envs. obs: ``{name: array[T, E, ...]}`` (the observations acted on);
    actions int64[T, E] (float32[T, E, d]: continuous); rewards float32[T, E]; terminated, truncated bool[T, E];
    final_obs: ``{name: array[K, ...]}``, the final observations of the K steps with
    ``truncated & ~terminated``, in row-major (t, e) order; last_obs: ``{name: array[E, ...]}``,
    the observations after the last step (reset observations where an episode just ended)."""

    obs: dict[str, np.ndarray]
    actions: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    final_obs: dict[str, np.ndarray]
    last_obs: dict[str, np.ndarray]

    @property
    def steps(self) -> int:
        """T * E, the env steps of the rollout."""
        return int(self.actions.shape[0] * self.actions.shape[1])


def rollout_gradients(net: torch.nn.Module, ro: Rollout, gamma: float, value_coef: float,
                      entropy_coef: float, gae_lambda: float = 1.0) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Gradients of :func:`a3c_loss` on one rollout w.r.t. ``net``'s parameters.

    One forward pass over the T*E rollout observations, the E bootstrap observations and the K
    final observations of truncated episodes; the values of the last two groups are detached and
    only feed the targets: :func:`nstep_returns` (``gae_lambda`` = 1, A3C) or
    :func:`gae_returns`. Returns (``{parameter name: float32 array}``, metrics).
    """
    T, E = ro.actions.shape[:2]
    N = T * E
    trunc_idx = np.flatnonzero((ro.truncated & ~ro.terminated).reshape(-1))
    K = trunc_idx.size
    names = list(ro.obs)
    batch = {}
    for k in names:
        parts = [ro.obs[k].reshape(N, *ro.obs[k].shape[2:]), ro.last_obs[k]]
        if K:
            parts.append(ro.final_obs[k])
        batch[k] = np.concatenate(parts)
    logits, values = net(to_tensors(batch))
    extra = values[N:].detach().numpy().astype(np.float64)
    final_values = np.zeros(N, np.float64)
    final_values[trunc_idx] = extra[E:]
    if gae_lambda == 1.0:
        returns = nstep_returns(ro.rewards, ro.terminated, ro.truncated, final_values.reshape(T, E), extra[:E], gamma)
    else:
        returns = gae_returns(ro.rewards, ro.terminated, ro.truncated, values[:N].detach().numpy().reshape(T, E),
                              final_values.reshape(T, E), extra[:E], gamma, gae_lambda)
    log_std = net.clamped_log_std() if getattr(net, "continuous", False) else None
    loss, m = a3c_loss(logits[:N], values[:N], torch.from_numpy(ro.actions.reshape(N, *ro.actions.shape[2:])),
                       torch.from_numpy(returns.reshape(N)), value_coef, entropy_coef, log_std)
    net.zero_grad(set_to_none=True)
    loss.backward()
    grads = {}
    for name, p in net.named_parameters():
        g = p.grad if p.grad is not None else torch.zeros_like(p)
        grads[name] = g.detach().to("cpu").numpy().astype(np.float32, copy=True)
    m["value_mean"] = float(values[:N].detach().mean())
    return grads, m
