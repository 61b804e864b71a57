"""R2D2 actor process (``zenrl actor`` with ``algo: r2d2``): the actor worker
(``actor/worker.py``) composed of

* :class:`~zenrl.actor.policies.RecurrentEpsilonGreedyQ`: one batched step of the recurrent Q
  network per env step (numpy for MLP encoders), a state (h, c) per env zeroed where an episode
  begins, per-env epsilon from the Ape-X ladder (``common/exploration.py``);
* :class:`SequencesToReplay`: fixed-length sequences with their start state and initial
  priorities (:class:`~zenrl.actor.sequences.SequenceBuilder`), sent to the replay in chunks
  whose items are sequences (docs/protocol.md, "R2D2 sequences"), wrapped in
  :class:`~zenrl.actor.policies.EpisodeStartsToPolicy`, which tells the policy where episodes
  begin;
* the weights follower, polled every ``actor.weights_poll_steps`` batched steps (never blocking);
  a new version is taken mid-episode and the state carried on (the learner's burn-in is there
  for such stale states).

Priorities reuse the Q values computed for acting, as the Ape-X actor's do; only sequences
closed by a truncated episode need one extra step of the network on the final observation.
Image envs (a uint8 observation of 2+ dims) with ``actor.frames`` (the default) send frame ids:
each frame once, whatever the overlap of sequences and stacks (``actor.frame_stack``), as
Ape-X's actor does; ``actor.compress: lz4`` compresses the frames (docs/protocol.md).
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import numpy as np
import torch

from zenrl.actor.batch_env import EnvBatch, StepResult
from zenrl.actor.env_guard import EnvLimits
from zenrl.actor.pacing import StepPacer
from zenrl.actor.policies import EpisodeStartsToPolicy, Obs, RecurrentEpsilonGreedyQ, RecurrentExtras
from zenrl.actor.sequences import SequenceBlock, SequenceBuilder
from zenrl.actor.weights import WeightsFollower
from zenrl.actor.worker import ActorWorker, AtOnce, match_opponents
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.exploration import elastic_env_epsilons, env_epsilons
from zenrl.common.networks import num_actions, obs_spec, set_compute_threads
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.replay_client import ZenohReplayClient

log = logging.getLogger(__name__)


def sequences_per_chunk(chunk_size: int, length: int) -> int:
    """Sequences per replay message: ``actor.chunk_size`` counts steps, a sequence holds ``length``."""
    return max(1, -(-chunk_size // length))


class SequencesToReplay:
    """An adder: each batched step goes to a :class:`SequenceBuilder`; the sequences it closes
    leave every ``block_steps`` steps in chunks of at most ``per_chunk`` sequences (the block's
    last chunk may be shorter), with their initial priorities, stamped with ``version()``.
    Extras: the policy's :class:`RecurrentExtras`; ``q_after(next_obs, idx)`` is the Q values of
    the final observations of envs ``idx`` (truncated episodes) from the state their step left.
    Open sequences are dropped at the end (a shutdown flushes only closed ones)."""

    def __init__(self, replay: ZenohReplayClient, builder: SequenceBuilder, per_chunk: int,
                 q_after: Callable[[Obs, np.ndarray], np.ndarray], version: Callable[[], int]) -> None:
        self.replay, self.builder, self.per_chunk = replay, builder, per_chunk
        self.q_after, self.version = q_after, version
        self.sent_sequences = 0
        self.sent_steps = 0  # valid (unpadded) steps in the sequences sent

    def start(self, node: Any) -> None:
        pass  # the replay client declares its publisher with the first chunk

    def add(self, obs: Obs, actions: np.ndarray, extras: RecurrentExtras, res: StepResult) -> bool:
        block = self.builder.add(obs, extras.q, (extras.h, extras.c), actions, res.rewards, res.next_obs,
                                 res.terminated, res.truncated, lambda idx: self.q_after(res.next_obs, idx))
        self._send(block)
        return False

    def _send(self, block: SequenceBlock | None) -> None:
        if block is None or len(block) == 0:
            return
        k = self.per_chunk
        frames, base = block.frames, block.frame_base
        for i in range(0, len(block), k):
            self.replay.insert({name: v[i:i + k] for name, v in block.data.items()}, block.priorities[i:i + k],
                               self.version(), frames, None if frames is None else base)
            if frames is not None:  # the block's frames go with its first chunk
                base += len(next(iter(frames.values())))
                frames = {name: v[:0] for name, v in frames.items()}
        self.sent_sequences += len(block)
        self.sent_steps += int(block.length.sum())

    def flush(self) -> None:
        self._send(self.builder.flush())
        left = self.replay.flush_backlog()
        if left:
            self.replay.undelivered_chunks += left
            log.warning("actor %s stops with %d chunks no replay could take", self.replay.actor_id, left)

    def values(self) -> dict[str, Any]:
        """``sent_sequences``; ``sent_transitions``: the valid steps they hold (Ape-X's name, for
        the displays); the replay client's chunk counters."""
        r = self.replay
        return {"sent_sequences": self.sent_sequences, "sent_transitions": self.sent_steps,
                "sent_chunks": r.sent_chunks, "failed_chunks": r.failed_chunks,
                "undelivered_chunks": r.undelivered_chunks, "backlog_chunks": r.backlog,
                "split_chunks": r.split_chunks, "oversized_chunks": r.oversized_chunks}


class R2D2Actor(ActorWorker):
    """The R2D2 composition. ``num_slots`` None: the slot came from the running system (elastic
    ladder). ``node``: a :class:`~zenrl.common.transport.Node` (or a test fake)."""

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, actor_id: str, slot: int, num_slots: int | None) -> None:
        acfg, rcfg = cfg.actor, cfg.r2d2
        self.cfg, self.node = cfg, node
        keys = P.Keys(run_id)
        set_compute_threads(acfg.torch_threads)
        envs = EnvBatch(cfg.env, acfg.envs_per_actor, seed=cfg.seed + 10_000 * (slot + 1), limits=EnvLimits.of(cfg))
        spec = obs_spec(envs.single_observation_space)
        n_actions = num_actions(envs.single_action_space, cfg.algo)
        self.league = match_opponents(envs, cfg, node, run_id, actor_id, slot,
                                      lambda: RecurrentQNetwork(spec, n_actions, cfg.network, rcfg.lstm_size))
        torch.manual_seed(cfg.seed)  # same initial weights as the learner's before the first broadcast
        net = RecurrentQNetwork(spec, n_actions, cfg.network, rcfg.lstm_size).eval()
        if num_slots is None:
            eps = elastic_env_epsilons(slot, acfg.envs_per_actor, acfg.eps_base, acfg.eps_alpha)
        else:
            eps = env_epsilons(slot, num_slots, acfg.envs_per_actor, acfg.eps_base, acfg.eps_alpha)
        policy = RecurrentEpsilonGreedyQ(net, eps, n_actions, np.random.default_rng(cfg.seed + 7919 * (slot + 1)))
        weights = WeightsFollower(node, keys, net, cfg.transport.max_message_bytes)
        # a sharded replay: this actor's chunks go to shard slot % replay.shards, for its life
        self.replay = ZenohReplayClient(node, P.Keys(run_id, P.actor_shard(slot, cfg.replay.shards)), actor_id,
                                        cfg.transport.query_timeout_s,
                                        # the replay drops chunks over its cap: split them here instead
                                        min(cfg.transport.max_message_bytes, cfg.replay.max_chunk_bytes), acfg.backlog_chunks,
                                        None if acfg.compress == "none" else acfg.compress)
        image = any(s.dtype == "uint8" and len(s.shape) >= 2 for s in spec.values())
        builder = SequenceBuilder(acfg.envs_per_actor, rcfg.sequence_length, rcfg.n_step, cfg.learner.gamma,
                                  burn_in=rcfg.burn_in, eta=rcfg.eta, eps=rcfg.value_rescale_eps,
                                  block_steps=rcfg.block_steps,
                                  frame_stack=acfg.frame_stack if acfg.frames and image else None)
        self.sequences = SequencesToReplay(self.replay, builder, sequences_per_chunk(acfg.chunk_size, rcfg.sequence_length),
                                           policy.q_after, lambda: weights.version)
        super().__init__(keys, actor_id, slot, envs, policy, EpisodeStartsToPolicy(self.sequences, policy), weights,
                         AtOnce(), poll_steps=acfg.weights_poll_steps, report_s=acfg.episode_report_s,
                         query_timeout_s=cfg.transport.query_timeout_s,
                         pacer=StepPacer(acfg.max_steps_per_s, acfg.envs_per_actor),
                         episode_epsilon=float(eps.mean()))
        self.eps, self.net = eps, net

    def start(self, node: Any, sup: Any = None) -> None:
        super().start(node, sup)
        log.info("r2d2 actor %s slot %d, %d envs, epsilon %.4g..%.4g, sequences of %d steps", self.id, self.slot,
                 len(self.eps), self.eps.min(), self.eps.max(), self.cfg.r2d2.sequence_length)

    def run(self, stop: threading.Event, max_steps: int | None = None) -> None:
        """Act until ``stop`` (after ``max_steps`` batched steps, idle until then)."""
        self.max_steps = max_steps
        self.run_loop(self.node, stop)


def run_r2d2_actor(cfg: RunConfig, node: Any, run_id: str, actor_id: str, slot: int, num_slots: int | None,
                   stop: threading.Event) -> None:
    """The R2D2 half of ``zenrl actor`` (:data:`zenrl.algorithms.R2D2`)."""
    R2D2Actor(cfg, node, run_id, actor_id, slot, num_slots).run(stop)
