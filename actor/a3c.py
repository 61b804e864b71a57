"""A3C worker (``zenrl actor`` with ``algo: a3c``) and the pure pieces it is built from.

The calling loop of one worker::

    params <- newest broadcast (WeightsFollower, never blocks)
    repeat:
        roll out t_max steps on E envs, acting by sampling pi(.|s) with the newest params
        (new params are taken between steps as soon as they arrive, latest only)
        one forward + backward over the rollout -> gradients of the A3C loss
        publish Gradients(version of the params the gradients were taken at)  -- BLOCK
        (no waiting for fresh params: the worker keeps acting with what it has, as in A3C)

Returns are n-step returns bootstrapped with V (no bootstrap after ``terminated``; after
``truncated`` the value of the episode's final observation is used), or with
``a3c.gae_lambda`` < 1 generalized-advantage lambda-returns over the same rollout. Everything above the
``A3CWorker`` class is pure (no Zenoh) and unit-tested.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from torch.nn import functional as F

from zenrl.actor.batch_env import EnvBatch
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.networks import ActorCritic, num_actions, obs_spec, sample_categorical, set_compute_threads, to_tensors

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Pure functions
# --------------------------------------------------------------------------------------------
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
             value_coef: float, entropy_coef: float) -> tuple[torch.Tensor, dict[str, float]]:
    """The A3C loss, averaged over N = T * E samples.

    logits float[N, A], values float[N] (V(s_t), with grad), actions int64[N], returns float[N]
    (targets, no grad). ``loss = policy_loss + value_coef * value_loss - entropy_coef * entropy``
    with ``policy_loss = -mean(log pi(a|s) * (R - V(s)).detach())``,
    ``value_loss = mean((R - V(s))^2)``, ``entropy = mean(H(pi(.|s)))``.
    Returns (loss scalar, metrics).
    """
    logp = F.log_softmax(logits, dim=1)
    advantage = returns - values.detach()
    policy_loss = -(logp.gather(1, actions.long().unsqueeze(1)).squeeze(1) * advantage).mean()
    value_loss = F.mse_loss(values, returns)
    entropy = -(logp.exp() * logp).sum(dim=1).mean()
    loss = policy_loss + value_coef * value_loss - entropy_coef * entropy
    m = {"loss": loss, "policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
         "advantage_mean": advantage.mean()}
    return loss, {k: float(v.detach()) for k, v in m.items()}


@dataclass
class Rollout:
    """t_max steps of E envs. obs: ``{name: array[T, E, ...]}`` (the observations acted on);
    actions int64[T, E]; rewards float32[T, E]; terminated, truncated bool[T, E];
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
        return int(self.actions.size)


def rollout_gradients(net: torch.nn.Module, ro: Rollout, gamma: float, value_coef: float,
                      entropy_coef: float, gae_lambda: float = 1.0) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Gradients of :func:`a3c_loss` on one rollout w.r.t. ``net``'s parameters.

    One forward pass over the T*E rollout observations, the E bootstrap observations and the K
    final observations of truncated episodes; the values of the last two groups are detached and
    only feed the targets: :func:`nstep_returns` (``gae_lambda`` = 1, A3C) or
    :func:`gae_returns`. Returns (``{parameter name: float32 array}``, metrics).
    """
    T, E = ro.actions.shape
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
    loss, m = a3c_loss(logits[:N], values[:N], torch.from_numpy(ro.actions.reshape(N)),
                       torch.from_numpy(returns.reshape(N)), value_coef, entropy_coef)
    net.zero_grad(set_to_none=True)
    loss.backward()
    grads = {}
    for name, p in net.named_parameters():
        g = p.grad if p.grad is not None else torch.zeros_like(p)
        grads[name] = g.detach().to("cpu").numpy().astype(np.float32, copy=True)
    m["value_mean"] = float(values[:N].detach().mean())
    return grads, m


def _stack(steps: list[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([s[k] for s in steps]) for k in steps[0]}


# --------------------------------------------------------------------------------------------
# The worker process
# --------------------------------------------------------------------------------------------
class A3CWorker:
    """One A3C worker: E envs, local gradients, :class:`~zenrl.common.protocol.Gradients` out,
    newest params in. ``node`` is a :class:`~zenrl.common.transport.Node` (or a test fake with
    ``publisher``, ``subscribe_latest``, ``query``, ``token``)."""

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, worker_id: str, slot: int) -> None:
        from zenrl.actor.weights import WeightsFollower  # network-facing; imported late so the pure part needs no Zenoh

        self.cfg = cfg
        self.node = node
        self.keys = P.Keys(run_id)
        self.id = worker_id
        self.slot = slot
        set_compute_threads(cfg.actor.torch_threads)
        self.envs = EnvBatch(cfg.env, cfg.actor.envs_per_actor, seed=cfg.seed + 10_000 * (slot + 1))
        self.spec = obs_spec(self.envs.single_observation_space)
        self.n_actions = num_actions(self.envs.single_action_space)
        torch.manual_seed(cfg.seed)
        self.net = ActorCritic(self.spec, self.n_actions, cfg.network)
        self.rng = np.random.default_rng(cfg.seed + 7919 * (slot + 1))
        self.weights = WeightsFollower(node, self.keys, self.net, cfg.transport.max_message_bytes)
        self.env_steps = 0
        self.sent_gradients = 0
        self.rollouts = 0
        self._obs: dict[str, np.ndarray] | None = None
        self._ep_returns: list[float] = []
        self._ep_lengths: list[int] = []
        self._acc: dict[str, float] = {}
        self._n_acc = 0
        self._metrics: Any = None

    # -- acting ---------------------------------------------------------------------------
    def collect(self) -> Rollout:
        """Play t_max batched steps with the newest params (checked before every step)."""
        if self._obs is None:
            self._obs = self.envs.reset()
        T = self.cfg.a3c.t_max
        poll = self.cfg.actor.weights_poll_steps
        obs_l, act_l, rew_l, term_l, trunc_l, finals = [], [], [], [], [], []
        for t in range(T):
            if t % poll == 0:
                self.weights.maybe_load()
            with torch.no_grad():
                logits, _ = self.net(to_tensors(self._obs))
            a = sample_categorical(logits.numpy(), self.rng)
            res = self.envs.step(a)
            obs_l.append(self._obs)
            act_l.append(a)
            rew_l.append(res.rewards)
            term_l.append(res.terminated)
            trunc_l.append(res.truncated)
            tr = np.flatnonzero(res.truncated & ~res.terminated)
            if tr.size:
                finals.append({k: v[tr] for k, v in res.next_obs.items()})
            self._ep_returns += res.ep_returns
            self._ep_lengths += res.ep_lengths
            self._obs = res.obs
            self.env_steps += self.envs.num_envs
        final_obs = ({k: np.concatenate([f[k] for f in finals]) for k in finals[0]} if finals
                     else {k: v[:0] for k, v in self._obs.items()})
        return Rollout(_stack(obs_l), np.stack(act_l), np.stack(rew_l), np.stack(term_l), np.stack(trunc_l),
                       final_obs, dict(self._obs))

    def gradients_message(self, ro: Rollout) -> P.Gradients:
        """The gradients of the loss on ``ro`` at the current params, as a wire message."""
        a = self.cfg.a3c
        grads, m = rollout_gradients(self.net, ro, self.cfg.learner.gamma, a.value_coef, a.entropy_coef, a.gae_lambda)
        for k, v in m.items():
            self._acc[k] = self._acc.get(k, 0.0) + v
        self._n_acc += 1
        return P.Gradients(worker_id=self.id, version=max(self.weights.version, 0), steps=ro.steps, grads=grads)

    # -- main loop ------------------------------------------------------------------------
    def _wait_for_weights(self, stop: threading.Event) -> bool:
        timeout = min(2.0, self.cfg.transport.query_timeout_s)
        while not stop.is_set():
            if self.weights.maybe_load() or self.weights.fetch_initial(timeout):
                return True
            stop.wait(0.1)
        return False

    def run(self, stop: threading.Event, max_rollouts: int | None = None, metrics: Any = None) -> None:
        """Act, compute and publish gradients until ``stop`` (or ``max_rollouts``). Every
        ``actor.episode_report_s`` the worker publishes its episodes and stats (mean loss,
        policy loss, value loss, entropy, advantage and value over the rollouts since) and, with
        a ``metrics`` writer (:class:`~zenrl.common.metrics.MetricsWriter`), also records those
        stats under source ``worker<slot>``."""
        self._metrics = metrics
        grads_pub = self.node.publisher(self.keys.gradients(self.id))
        eps_pub = self.node.publisher(self.keys.episodes(self.id))
        stats_pub = self.node.publisher(self.keys.stats("actor", self.id))
        self.node.token(self.keys.alive("actor", self.id))
        log.info("a3c worker %s slot %d: %d envs, t_max %d; waiting for params", self.id, self.slot,
                 self.envs.num_envs, self.cfg.a3c.t_max)
        last_report = time.monotonic()
        try:
            if not self._wait_for_weights(stop):
                return
            log.info("a3c worker %s starts with params version %d", self.id, self.weights.version)
            while not stop.is_set() and (max_rollouts is None or self.rollouts < max_rollouts):
                ro = self.collect()
                grads_pub.put(self.gradients_message(ro).encode(self.cfg.transport.max_message_bytes))
                self.sent_gradients += 1
                self.rollouts += 1
                now = time.monotonic()
                if now - last_report >= self.cfg.actor.episode_report_s:
                    self._report(eps_pub, stats_pub)
                    last_report = now
        finally:
            self._report(eps_pub, stats_pub)
            self.envs.close()

    def _report(self, eps_pub: Any, stats_pub: Any) -> None:
        if self._ep_returns:
            eps_pub.put(P.EpisodeStats(actor_id=self.id, slot=self.slot, epsilon=0.0,
                                       policy_version=self.weights.version, env_steps=self.env_steps,
                                       returns=np.array(self._ep_returns, np.float32),
                                       lengths=np.array(self._ep_lengths, np.int64)).encode())
            self._ep_returns, self._ep_lengths = [], []
        vals: dict[str, Any] = {k: v / self._n_acc for k, v in self._acc.items()} if self._n_acc else {}
        vals.update({"env_steps": self.env_steps, "slot": self.slot, "policy_version": self.weights.version,
                     "sent_gradients": self.sent_gradients, "weights_rejected": self.weights.rejected})
        self._acc, self._n_acc = {}, 0
        if self._metrics is not None:
            self._metrics.write(f"worker{self.slot}", self.env_steps, vals)
        stats_pub.put(P.Stats(role="actor", id=self.id, time=time.time(), values=vals).encode())


def run_a3c_worker(cfg: RunConfig, node: Any, run_id: str, worker_id: str, slot: int, num_slots: int | None,
                   stop: threading.Event) -> None:
    """The A3C half of ``zenrl actor`` (:data:`zenrl.common.algorithms.A3C`): a worker whose own
    loss and value stats also go to the run's metrics."""
    from zenrl.common.metrics import MetricsWriter

    metrics = MetricsWriter(Path(cfg.runs_dir) / run_id)
    try:
        A3CWorker(cfg, node, run_id, worker_id, slot).run(stop, metrics=metrics)
    finally:
        metrics.close()
