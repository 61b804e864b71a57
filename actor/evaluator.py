"""Evaluator process (``zenrl evaluator``): the actor worker (``actor/worker.py``) composed of

* :class:`~zenrl.actor.policies.Greedy` (or, with ``evaluator.policy: sample``,
  :class:`~zenrl.actor.policies.Sampling`; for a recurrent network (R2D2)
  :class:`~zenrl.actor.policies.RecurrentGreedy`, which carries each env's state through its
  episode), with ``evaluator.epsilon`` random actions;
* :class:`~zenrl.actor.adders.EvalEpisodes`: one episode per env per round, published as an
  :class:`~zenrl.common.protocol.EvalResult` and written to the run's metrics (source
  ``eval``: mean and spread of the return, match win and draw rates);
* the weights follower, read only between rounds (a round plays one version), and a gate that
  starts a round every ``evaluator.interval_s`` once newer weights are loaded.

Round k plays on seeds ``seed + evaluator.seed_offset + k * episodes + i``, separate from
training; its policy draws restart from the round's first seed.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from zenrl.actor.adders import EvalEpisodes
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.env_guard import EnvLimits
from zenrl.actor.policies import EpisodeStartsToPolicy, Greedy, RecurrentGreedy, Sampling
from zenrl.actor.weights import WeightsFollower
from zenrl.actor.worker import ActorWorker, EvalInterval
from zenrl.common import protocol as P
from zenrl.common.checkpoints import training_state_class
from zenrl.common.config import RunConfig
from zenrl.common.metrics import MetricsWriter
from zenrl.common.networks import action_size, obs_spec, set_compute_threads
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.transport import Node

log = logging.getLogger(__name__)


def build_policy_net(cfg: RunConfig, envs: EnvBatch) -> torch.nn.Module:
    """The run's policy network (Q network or actor-critic) for ``envs``, in eval mode."""
    spec = obs_spec(envs.single_observation_space)
    n = action_size(envs.single_action_space, cfg.algo)
    return training_state_class(cfg.algo).run_policy_network(spec, n, cfg).eval()


class Evaluator(ActorWorker):
    """The evaluation composition (role ``evaluator``, id ``evaluator``). ``use_numpy``: greedy
    MLP networks act in numpy, cheaper than torch for the small MLPs evaluated, which lets a
    config evaluate every second at a small cost."""

    role = "evaluator"

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, metrics: Any = None, use_numpy: bool = True) -> None:
        ecfg = cfg.evaluator
        self.node = node
        keys = P.Keys(run_id)
        set_compute_threads(1)
        envs = EnvBatch(cfg.env, ecfg.episodes, seed=cfg.seed + ecfg.seed_offset, limits=EnvLimits.of(cfg))
        self.net = build_policy_net(cfg, envs)
        n_actions = int(action_size(envs.single_action_space, cfg.algo))
        first = cfg.seed + ecfg.seed_offset
        policy: Any
        if ecfg.policy == "sample":
            policy = Sampling(self.net, n_actions, np.random.default_rng(first), ecfg.epsilon)
        elif isinstance(self.net, RecurrentQNetwork):
            policy = RecurrentGreedy(self.net, n_actions, ecfg.epsilon, first, use_numpy)
        else:
            policy = Greedy(self.net, n_actions, ecfg.epsilon, first, use_numpy)
        weights = WeightsFollower(node, keys, self.net, cfg.transport.max_message_bytes)
        self.adder: EvalEpisodes = EvalEpisodes(keys, ecfg.episodes, lambda: weights.version, lambda: weights.updates,
                                                metrics)
        adder: Any = self.adder
        if isinstance(policy, RecurrentGreedy):  # its state is zeroed where an episode begins
            adder = EpisodeStartsToPolicy(adder, policy)
        super().__init__(keys, "evaluator", None, envs, policy, adder, weights, EvalInterval(ecfg.interval_s),
                         poll_steps=None, report_s=ecfg.interval_s, query_timeout_s=cfg.transport.query_timeout_s,
                         round_seed=lambda k: first + k * ecfg.episodes)

    def run(self, stop: threading.Event) -> None:
        self.run_loop(self.node, stop)


def main(cfg: RunConfig, run_id: str, stop: threading.Event) -> None:
    """Entry point of ``zenrl evaluator``."""
    metrics = MetricsWriter(Path(cfg.runs_dir) / run_id)
    try:
        with Node.from_config(cfg.transport) as node:
            Evaluator(cfg, node, run_id, metrics).run(stop)
    finally:
        metrics.close()
