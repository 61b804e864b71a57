"""Ape-X actor process (``zenrl actor``): E envs stepped as a batch, one batched forward per
step, per-env epsilon from the Ape-X ladder, n-step transitions with initial priorities, chunks
published to the replay, the newest weights taken between steps (never blocking).

Transitions and their initial priorities are built in blocks of at least 16 steps
(actor/nstep.py) and sent in chunks of ``ceil(chunk_size / E) * E`` transitions. Priorities
reuse the Q values computed for acting: a transition is bootstrapped from the forward pass made
when the actor acted on its ``next_obs`` (``max_a Q(s', a)``, the actor has no target network);
only transitions that end in a truncated episode need an extra forward pass on their final
observation.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import threading
import time
from typing import Any

import numpy as np
import torch

from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.nstep import Block, NStepBlocks
from zenrl.actor.pacing import StepPacer
from zenrl.actor.slots import claim_slot
from zenrl.actor.weights import WeightsFollower
from zenrl.common import protocol as P
from zenrl.common.algorithms import algorithm
from zenrl.common.config import RunConfig
from zenrl.common.exploration import EpsilonGreedy, elastic_env_epsilons, env_epsilons
from zenrl.common.networks import NumpyQ, QNetwork, num_actions, obs_spec, set_compute_threads, to_tensors
from zenrl.common.policy_io import wrap_selfplay
from zenrl.common.replay_client import ZenohReplayClient
from zenrl.common.transport import Node

log = logging.getLogger(__name__)

#: fewest batched steps per n-step block (actor/nstep.py)
MIN_BLOCK_STEPS = 16



class ApexActor:
    def __init__(self, cfg: RunConfig, node: Node, run_id: str, actor_id: str, slot: int, num_slots: int | None) -> None:
        """``num_slots`` None: the slot came from the running system (elastic ladder)."""
        self.cfg = cfg
        acfg = cfg.actor
        self.node = node
        self.keys = P.Keys(run_id)
        self.id = actor_id
        self.slot = slot
        set_compute_threads(acfg.torch_threads)
        self.envs = EnvBatch(cfg.env, acfg.envs_per_actor, seed=cfg.seed + 10_000 * (slot + 1))
        if cfg.selfplay.enabled:  # frozen learner snapshots join the opponents (common/policy_io.py)
            self.envs.envs = wrap_selfplay(self.envs.envs, cfg, run_id, seed=cfg.seed + 31 * (slot + 1))
        self.spec = obs_spec(self.envs.single_observation_space)
        self.n_actions = num_actions(self.envs.single_action_space)
        torch.manual_seed(cfg.seed)  # same initial weights as the learner's before the first broadcast
        self.net = QNetwork(self.spec, self.n_actions, cfg.network).eval()
        self._fast = NumpyQ.of(self.net)  # numpy forward for MLP nets (None: torch)
        self._fast_version = -1
        if num_slots is None:
            self.eps = elastic_env_epsilons(slot, acfg.envs_per_actor, acfg.eps_base, acfg.eps_alpha)
        else:
            self.eps = env_epsilons(slot, num_slots, acfg.envs_per_actor, acfg.eps_base, acfg.eps_alpha)
        self.rng = np.random.default_rng(cfg.seed + 7919 * (slot + 1))
        self._epsilon_greedy = EpsilonGreedy(self.eps, self.n_actions, self.rng)
        # a chunk is chunk_size rounded up to whole batched steps; a block is whole chunks and at
        # least MIN_BLOCK_STEPS steps (the per-block arithmetic is then spread over more steps)
        chunk_steps = -(-acfg.chunk_size // acfg.envs_per_actor)
        self._chunk_len = chunk_steps * acfg.envs_per_actor
        image = any(s.dtype == "uint8" and len(s.shape) >= 2 for s in self.spec.values())
        self.builder = NStepBlocks(acfg.envs_per_actor, acfg.n_step, cfg.learner.gamma,
                                   block_steps=chunk_steps * -(-MIN_BLOCK_STEPS // chunk_steps),
                                   frame_stack=acfg.frame_stack if acfg.frames and image else None)
        self.replay = ZenohReplayClient(node, self.keys, actor_id, cfg.transport.query_timeout_s,
                                        cfg.transport.max_message_bytes, acfg.backlog_chunks,
                                        None if acfg.compress == "none" else acfg.compress)
        self.weights = WeightsFollower(node, self.keys, self.net, cfg.transport.max_message_bytes)
        self.env_steps = 0
        self._ep_returns: list[float] = []
        self._ep_lengths: list[int] = []
        self.sent_transitions = 0

    def _forward(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """float32[B, A] Q values of the acting network for flat observations."""
        if self._fast is not None:
            if self._fast_version != self.weights.version:
                self._fast.load(self.net)
                self._fast_version = self.weights.version
            return self._fast(obs)
        with torch.no_grad():
            return self.net(to_tensors(obs)).numpy()

    def _values(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self._forward(obs).max(1)

    def _send(self, block: Block | None) -> None:
        """A block in chunks of chunk_size rounded up to whole batched steps (the last chunk of
        a shutdown flush may be shorter)."""
        if block is None or len(block) == 0:
            return
        cs = self._chunk_len
        frames, base = block.frames, block.frame_base
        for i in range(0, len(block), cs):
            self.replay.insert({k: v[i:i + cs] for k, v in block.data.items()}, block.priorities[i:i + cs],
                               self.weights.version, frames, None if frames is None else base)
            if frames is not None:  # the block's frames go with its first chunk
                base += len(next(iter(frames.values())))
                frames = {k: v[:0] for k, v in frames.items()}
        self.sent_transitions += len(block)

    # -- main loop ----------------------------------------------------------------------------
    def run(self, stop: threading.Event, max_steps: int | None = None) -> None:
        eps_pub = self.node.publisher(self.keys.episodes(self.id))
        stats_pub = self.node.publisher(self.keys.stats("actor", self.id))
        self.node.token(self.keys.alive("actor", self.id))
        if self.weights.fetch_initial(min(2.0, self.cfg.transport.query_timeout_s)):
            log.info("actor %s starts with weights version %d", self.id, self.weights.version)
        log.info("actor %s slot %d, %d envs, epsilon %.4g..%.4g", self.id, self.slot, len(self.eps), self.eps.min(), self.eps.max())
        obs = self.envs.reset()
        E = self.envs.num_envs
        last_report = time.monotonic()
        steps = 0
        poll = self.cfg.actor.weights_poll_steps
        pacer = StepPacer(self.cfg.actor.max_steps_per_s, E)
        try:
            while not stop.is_set() and (max_steps is None or steps < max_steps):
                delay = pacer.delay()
                if delay:
                    stop.wait(delay)
                if steps % poll == 0:
                    self.weights.maybe_load()
                q = self._forward(obs)
                actions = self._epsilon_greedy(q)
                res = self.envs.step(actions)
                self._send(self.builder.add(obs, q, actions, res.rewards, res.next_obs, res.terminated,
                                            res.truncated, self._values))
                obs = res.obs
                steps += 1
                self.env_steps += E
                self._ep_returns += res.ep_returns
                self._ep_lengths += res.ep_lengths
                now = time.monotonic()
                if now - last_report >= self.cfg.actor.episode_report_s:
                    self._report(eps_pub, stats_pub, now - last_report)
                    last_report = now
        finally:
            self._send(self.builder.flush(self._values))
            left = self.replay.flush_backlog()
            if left:
                self.replay.undelivered_chunks += left
                log.warning("actor %s stops with %d chunks no replay could take", self.id, left)
            self._report(eps_pub, stats_pub, max(time.monotonic() - last_report, 1e-6))
            self.envs.close()

    def _report(self, eps_pub: Any, stats_pub: Any, dt: float) -> None:
        if self._ep_returns:
            eps_pub.put(P.EpisodeStats(actor_id=self.id, slot=self.slot, epsilon=float(self.eps.mean()),
                                       policy_version=self.weights.version, env_steps=self.env_steps,
                                       returns=np.array(self._ep_returns, np.float32),
                                       lengths=np.array(self._ep_lengths, np.int64)).encode())
            self._ep_returns, self._ep_lengths = [], []
        stats_pub.put(P.Stats(role="actor", id=self.id, time=time.time(), values={
            "env_steps": self.env_steps, "slot": self.slot, "policy_version": self.weights.version,
            "sent_transitions": self.sent_transitions, "sent_chunks": self.replay.sent_chunks,
            "failed_chunks": self.replay.failed_chunks, "undelivered_chunks": self.replay.undelivered_chunks,
            "backlog_chunks": self.replay.backlog, "weights_rejected": self.weights.rejected}).encode())


def main(cfg: RunConfig, run_id: str, stop: threading.Event, actor_id: str | None = None, slot: int | None = None) -> None:
    """Entry point of ``zenrl actor``."""
    actor_id = actor_id or re.sub(r"[^A-Za-z0-9_.-]", "-", f"actor-{socket.gethostname()}-{os.getpid()}")[:64]
    num_slots: int | None = cfg.actor.ladder_size or cfg.actor.num_actors
    if slot is None:
        slot = cfg.actor.slot
    with Node.from_config(cfg.transport) as node:
        if slot is None:  # elastic: the slot comes from the running system
            slot, _ = claim_slot(node, P.Keys(run_id), actor_id)
            num_slots = None
        algorithm(cfg.algo).actor_main()(cfg, node, run_id, actor_id, slot, num_slots, stop)


def run_apex_actor(cfg: RunConfig, node: Node, run_id: str, actor_id: str, slot: int, num_slots: int | None,
                   stop: threading.Event) -> None:
    """The Ape-X half of ``zenrl actor`` (:data:`zenrl.common.algorithms.APEX`)."""
    ApexActor(cfg, node, run_id, actor_id, slot, num_slots).run(stop)
