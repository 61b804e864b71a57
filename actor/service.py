"""Ape-X actor process (``zenrl actor``): the actor worker (``actor/worker.py``) composed of

* :class:`~zenrl.actor.policies.EpsilonGreedyQ`: one batched forward per step (numpy for MLP
  networks), per-env epsilon from the Ape-X ladder;
* :class:`~zenrl.actor.adders.NStepToReplay`: n-step transitions with initial priorities
  (actor/nstep.py), built in blocks of at least 16 steps and published in chunks of
  ``ceil(chunk_size / E) * E`` transitions to the replay;
* the weights follower, polled every ``actor.weights_poll_steps`` batched steps (never blocking).

Priorities reuse the Q values computed for acting: a transition is bootstrapped from the forward
pass made when the actor acted on its ``next_obs`` (``max_a Q(s', a)``, the actor has no target
network); only transitions that end in a truncated episode need an extra forward pass on their
final observation.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import numpy as np
import torch

from zenrl.actor.adders import NStepToReplay
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.env_guard import EnvLimits
from zenrl.actor.pacing import StepPacer
from zenrl.actor.policies import Demonstrated, EpsilonGreedyQ, Obs
from zenrl.actor.weights import WeightsFollower
from zenrl.actor.worker import ActorWorker, AtOnce, match_opponents
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.errors import ConfigError
from zenrl.common.exploration import elastic_env_epsilons, env_epsilons
from zenrl.common.networks import QNetwork, num_actions, obs_spec, set_compute_threads
from zenrl.common.replay_client import ZenohReplayClient
from zenrl.common.transport import Node

log = logging.getLogger(__name__)


class ApexActor(ActorWorker):
    """The Ape-X composition. ``num_slots`` None: the slot came from the running system
    (elastic ladder)."""

    def __init__(self, cfg: RunConfig, node: Node, run_id: str, actor_id: str, slot: int, num_slots: int | None) -> None:
        acfg = cfg.actor
        self.cfg, self.node = cfg, node
        keys = P.Keys(run_id)
        set_compute_threads(acfg.torch_threads)
        envs = EnvBatch(cfg.env, acfg.envs_per_actor, seed=cfg.seed + 10_000 * (slot + 1), limits=EnvLimits.of(cfg))
        spec = obs_spec(envs.single_observation_space)
        n_actions = num_actions(envs.single_action_space, cfg.algo)
        self.league = match_opponents(envs, cfg, node, run_id, actor_id, slot, lambda: QNetwork(spec, n_actions, cfg.network))
        torch.manual_seed(cfg.seed)  # same initial weights as the learner's before the first broadcast
        net = QNetwork(spec, n_actions, cfg.network).eval()
        if num_slots is None:
            eps = elastic_env_epsilons(slot, acfg.envs_per_actor, acfg.eps_base, acfg.eps_alpha)
        else:
            eps = env_epsilons(slot, num_slots, acfg.envs_per_actor, acfg.eps_base, acfg.eps_alpha)
        policy: EpsilonGreedyQ | Demonstrated = EpsilonGreedyQ(net, eps, n_actions,
                                                               np.random.default_rng(cfg.seed + 7919 * (slot + 1)))
        if acfg.guard_share > 0:
            policy = Demonstrated(policy, guard_rule(envs), acfg.guard_share,
                                  np.random.default_rng([cfg.seed, slot, 1]))
        weights = WeightsFollower(node, keys, net, cfg.transport.max_message_bytes)
        # a sharded replay: this actor's chunks go to shard slot % replay.shards, for its life
        self.replay = ZenohReplayClient(node, P.Keys(run_id, P.actor_shard(slot, cfg.replay.shards)), actor_id,
                                        cfg.transport.query_timeout_s,
                                        # the replay drops chunks over its cap: split them here instead
                                        min(cfg.transport.max_message_bytes, cfg.replay.max_chunk_bytes), acfg.backlog_chunks,
                                        None if acfg.compress == "none" else acfg.compress)
        image = any(s.dtype == "uint8" and len(s.shape) >= 2 for s in spec.values())
        adder = NStepToReplay(self.replay, acfg.envs_per_actor, acfg.n_step, cfg.learner.gamma, acfg.chunk_size,
                              policy.values, lambda: weights.version,
                              frame_stack=acfg.frame_stack if acfg.frames and image else None,
                              cut_non_greedy=acfg.cut_non_greedy)
        super().__init__(keys, actor_id, slot, envs, policy, adder, weights, AtOnce(),
                         poll_steps=acfg.weights_poll_steps, report_s=acfg.episode_report_s,
                         query_timeout_s=cfg.transport.query_timeout_s,
                         pacer=StepPacer(acfg.max_steps_per_s, acfg.envs_per_actor),
                         episode_epsilon=float(eps.mean()))
        self.eps, self.net = eps, net
        self.adder: NStepToReplay = adder

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        vals, line = super().report(interval_s)
        if isinstance(self.policy, Demonstrated):
            vals["guard_actions"] = self.policy.taken
        return vals, line

    @property
    def sent_transitions(self) -> int:
        return self.adder.sent_transitions

    def start(self, node: Any, sup: Any = None) -> None:
        super().start(node, sup)
        log.info("actor %s slot %d, %d envs, epsilon %.4g..%.4g", self.id, self.slot, len(self.eps), self.eps.min(),
                 self.eps.max())

    def run(self, stop: threading.Event, max_steps: int | None = None) -> None:
        """Act until ``stop`` (after ``max_steps`` batched steps, idle until then)."""
        self.max_steps = max_steps
        self.run_loop(self.node, stop)


def guard_rule(envs: EnvBatch) -> Callable[[Obs], np.ndarray]:
    """``actor.guard_share``'s demonstrator over ``envs``: batched obs (``obs/enemy_seen`` float32[E, 3]) ->
    int64[E], the env's guard rule on each reading (-1 where the guard does not act; the envs of
    one batch share their config, so the first env's rule is every env's). ConfigError where the
    envs have no guard (not a match env, no enemy detector, continuous actions)."""
    rule = getattr(envs.envs[0].unwrapped, "guard_rule", None)
    space = envs.single_observation_space
    if rule is None or "enemy_seen" not in getattr(space, "spaces", {}):
        raise ConfigError("actor.guard_share needs a match env (zenrl/BurgerWar-v0) with enemy_detector: true "
                          "and dict observations (flatten_obs: false)")
    try:
        g = rule()
    except ValueError as e:
        raise ConfigError(f"actor.guard_share: {e}") from None
    return lambda obs: g.actions(obs["obs/enemy_seen"])


def run_apex_actor(cfg: RunConfig, node: Node, run_id: str, actor_id: str, slot: int, num_slots: int | None,
                   stop: threading.Event) -> None:
    """The Ape-X half of ``zenrl actor`` (:data:`zenrl.algorithms.APEX`)."""
    ApexActor(cfg, node, run_id, actor_id, slot, num_slots).run(stop)
