"""IMPALA actor (``zenrl actor`` with ``algo: impala``): the actor worker (``actor/worker.py``)
composed of

* :class:`~zenrl.actor.policies.Sampling` with the behaviour log-probabilities as extras
  (numpy forward for MLP networks): actions drawn from pi(.|s) with the newest weights;
* :class:`~zenrl.actor.adders.UnrollsToLearner`: every ``impala.unroll_length`` batched steps,
  one :class:`~zenrl.common.protocol.Unroll` per env on ``unrolls/<id>`` (BLOCK, lz4 with
  ``actor.compress``), stamped with the policy version it was acted with; for frame-stacked
  image envs (``actor.frames`` and ``actor.frame_stack`` >= 2) :class:`FramedUnrolls`, each
  distinct frame of an unroll once (the stacks as frame ids, docs/protocol.md);
* the weights follower, polled every ``actor.weights_poll_steps`` batched steps (latest only,
  never blocking), and a gate that waits for the learner's first weights (an unroll's version
  must be one the learner published, or its lag could not be measured).

The actor never waits for the learner after an unroll: V-trace corrects for the policy lag
(``impala.max_policy_lag`` bounds it on the learner).
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Mapping

import numpy as np
import torch

from zenrl.actor.adders import UnrollsToLearner
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.env_guard import EnvLimits
from zenrl.actor.pacing import StepPacer
from zenrl.actor.policies import Sampling
from zenrl.actor.weights import WeightsFollower
from zenrl.actor.worker import ActorWorker, FirstWeights, match_opponents
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.networks import ActorCritic, action_size, obs_spec, set_compute_threads
from zenrl.common.specs import ArraySpec

log = logging.getLogger(__name__)


def frame_fields(spec: Mapping[str, ArraySpec], frame_stack: int) -> list[str]:
    """The observation fields sent in frame mode: uint8 stacks ``[k, H, W(, C)]`` of
    ``frame_stack`` >= 2 frames (unstacked observations already travel once per unroll row)."""
    if frame_stack < 2:
        return []
    return [k for k, s in spec.items() if s.dtype == "uint8" and len(s.shape) >= 3 and s.shape[0] == frame_stack]


class FramedUnrolls(UnrollsToLearner):
    """:class:`~zenrl.actor.adders.UnrollsToLearner` whose unrolls carry the ``fields``' stacks
    as frames and ids (:meth:`~zenrl.common.protocol.Unroll.framed`): a k-frame stack shares
    k - 1 frames with its neighbour, so an unroll of T steps sends ~T + k frames, not (T + 1) * k."""

    def __init__(self, *args: Any, fields: list[str], **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.fields = fields

    def unrolls(self, steps: list[Any]) -> list[P.Unroll]:
        return [u.framed(self.fields) for u in super().unrolls(steps)]


class ImpalaActor(ActorWorker):
    """The IMPALA composition: E envs, unrolls out, newest weights in. ``node`` is a
    :class:`~zenrl.common.transport.Node` (or a test fake with ``publisher``,
    ``subscribe_latest``, ``query``, ``token``)."""

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, actor_id: str, slot: int) -> None:
        self.cfg, self.node = cfg, node
        keys = P.Keys(run_id)
        set_compute_threads(cfg.actor.torch_threads)
        envs = EnvBatch(cfg.env, cfg.actor.envs_per_actor, seed=cfg.seed + 10_000 * (slot + 1), limits=EnvLimits.of(cfg))
        n_actions = action_size(envs.single_action_space, cfg.algo)
        spec = obs_spec(envs.single_observation_space)
        self.league = match_opponents(envs, cfg, node, run_id, actor_id, slot,
                                      lambda: ActorCritic(spec, n_actions, cfg.network))
        torch.manual_seed(cfg.seed)
        self.net = ActorCritic(spec, n_actions, cfg.network)
        weights = WeightsFollower(node, keys, self.net, cfg.transport.max_message_bytes)
        adder_args = (keys, actor_id, cfg.impala.unroll_length, lambda: weights.version,
                      cfg.transport.max_message_bytes, None if cfg.actor.compress == "none" else cfg.actor.compress)
        stacked = frame_fields(spec, cfg.actor.frame_stack) if cfg.actor.frames else []
        self.adder: UnrollsToLearner = FramedUnrolls(*adder_args, fields=stacked) if stacked else UnrollsToLearner(*adder_args)
        policy = Sampling(self.net, int(n_actions), np.random.default_rng(cfg.seed + 7919 * (slot + 1)),
                          use_numpy=True, with_logp=True)
        super().__init__(keys, actor_id, slot, envs, policy, self.adder, weights,
                         FirstWeights(min(2.0, cfg.transport.query_timeout_s)),
                         poll_steps=cfg.actor.weights_poll_steps, report_s=cfg.actor.episode_report_s,
                         query_timeout_s=cfg.transport.query_timeout_s, episode_epsilon=0.0,
                         pacer=StepPacer(cfg.actor.max_steps_per_s, cfg.actor.envs_per_actor))
        self.max_unrolls: int | None = None

    def start(self, node: Any, sup: Any = None) -> None:
        super().start(node, sup)
        log.info("impala actor %s slot %d: %d envs, unrolls of %d steps", self.id, self.slot, self.envs.num_envs,
                 self.cfg.impala.unroll_length)

    def done(self) -> bool:
        return self.max_unrolls is not None and self.adder.sent_unrolls >= self.max_unrolls

    def run(self, stop: threading.Event, max_unrolls: int | None = None) -> None:
        """Act and publish unrolls until ``stop`` (after ``max_unrolls`` unrolls, idle until then)."""
        self.max_unrolls = max_unrolls
        self.run_loop(self.node, stop)


def run_impala_actor(cfg: RunConfig, node: Any, run_id: str, actor_id: str, slot: int, num_slots: int | None,
                     stop: threading.Event) -> None:
    """The IMPALA half of ``zenrl actor`` (:data:`zenrl.algorithms.IMPALA`)."""
    ImpalaActor(cfg, node, run_id, actor_id, slot).run(stop)
