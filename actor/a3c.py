"""A3C worker (``zenrl actor`` with ``algo: a3c``): the actor worker (``actor/worker.py``)
composed of

* :class:`~zenrl.actor.policies.Sampling`: actions drawn from pi(.|s) with the newest params;
* :class:`~zenrl.actor.adders.RolloutGradients`: every t_max batched steps, one forward and
  backward pass over the rollout gives the gradients of the A3C loss
  (:mod:`zenrl.common.a3c_loss`), published on ``gradients/<id>`` with the version of the
  params they were taken at (BLOCK);
* the weights follower, polled every ``actor.weights_poll_steps`` batched steps (latest only,
  never blocking), and a gate that waits for the learner's first params.

No waiting for fresh params after a gradient: the worker keeps acting with what it has, as in
A3C. Its loss, entropy and value stats go to ``stats/actor/<id>`` and to the run's metrics
(source ``worker<slot>``).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from zenrl.actor.adders import RolloutGradients
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.env_guard import EnvLimits
from zenrl.actor.pacing import StepPacer
from zenrl.actor.policies import Sampling
from zenrl.actor.weights import WeightsFollower
from zenrl.actor.worker import ActorWorker, FirstWeights, match_opponents
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.networks import ActorCritic, action_size, obs_spec, set_compute_threads

log = logging.getLogger(__name__)


class A3CWorker(ActorWorker):
    """The A3C composition: E envs, local gradients out, newest params in. ``node`` is a
    :class:`~zenrl.common.transport.Node` (or a test fake with ``publisher``,
    ``subscribe_latest``, ``query``, ``token``). ``metrics``: a
    :class:`~zenrl.common.metrics.MetricsWriter` that also records each report's stats under
    source ``worker<slot>``."""

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, worker_id: str, slot: int, metrics: Any = None) -> None:
        self.cfg, self.node, self.metrics = cfg, node, metrics
        keys = P.Keys(run_id)
        set_compute_threads(cfg.actor.torch_threads)
        envs = EnvBatch(cfg.env, cfg.actor.envs_per_actor, seed=cfg.seed + 10_000 * (slot + 1), limits=EnvLimits.of(cfg))
        n_actions = action_size(envs.single_action_space, cfg.algo)
        spec = obs_spec(envs.single_observation_space)
        self.league = match_opponents(envs, cfg, node, run_id, worker_id, slot,
                                      lambda: ActorCritic(spec, n_actions, cfg.network))
        torch.manual_seed(cfg.seed)
        self.net = ActorCritic(spec, n_actions, cfg.network)
        weights = WeightsFollower(node, keys, self.net, cfg.transport.max_message_bytes)
        a = cfg.a3c
        self.adder: RolloutGradients = RolloutGradients(
            self.net, keys, worker_id, a.t_max, cfg.learner.gamma, a.value_coef, a.entropy_coef, a.gae_lambda,
            lambda: weights.version, cfg.transport.max_message_bytes)
        super().__init__(keys, worker_id, slot, envs,
                         Sampling(self.net, int(n_actions), np.random.default_rng(cfg.seed + 7919 * (slot + 1))),
                         self.adder, weights, FirstWeights(min(2.0, cfg.transport.query_timeout_s)),
                         poll_steps=cfg.actor.weights_poll_steps, report_s=cfg.actor.episode_report_s,
                         query_timeout_s=cfg.transport.query_timeout_s, episode_epsilon=0.0,
                         pacer=StepPacer(cfg.actor.max_steps_per_s, cfg.actor.envs_per_actor))
        self.max_rollouts: int | None = None

    def start(self, node: Any, sup: Any = None) -> None:
        super().start(node, sup)
        log.info("a3c worker %s slot %d: %d envs, t_max %d", self.id, self.slot, self.envs.num_envs, self.cfg.a3c.t_max)

    def done(self) -> bool:
        return self.max_rollouts is not None and self.adder.rollouts >= self.max_rollouts

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        vals, line = super().report(interval_s)
        if self.metrics is not None:
            self.metrics.write(f"worker{self.slot}", self.env_steps, vals)
        return vals, line

    def run(self, stop: threading.Event, max_rollouts: int | None = None) -> None:
        """Act, compute and publish gradients until ``stop`` (after ``max_rollouts``
        rollouts, idle until then)."""
        self.max_rollouts = max_rollouts
        self.run_loop(self.node, stop)


def run_a3c_worker(cfg: RunConfig, node: Any, run_id: str, worker_id: str, slot: int, num_slots: int | None,
                   stop: threading.Event) -> None:
    """The A3C half of ``zenrl actor`` (:data:`zenrl.algorithms.A3C`): a worker whose own
    loss and value stats also go to the run's metrics."""
    from zenrl.common.metrics import MetricsWriter

    metrics = MetricsWriter(Path(cfg.runs_dir) / run_id)
    try:
        A3CWorker(cfg, node, run_id, worker_id, slot, metrics).run(stop)
    finally:
        metrics.close()
