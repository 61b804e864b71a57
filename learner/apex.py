"""Ape-X learner (``zenrl learner`` with ``algo: apex``): samples from the replay service through a prefetcher
(several requests in flight), trains (:mod:`zenrl.learner.dqn`), sends priorities back from a
watched background thread, broadcasts weights every ``publish_every_updates`` updates at low Zenoh
priority (and answers ``learner/weights`` queries with the latest). Stats, metrics, checkpoints
and the stop are the role loop's, the checkpoint files the base's
(:class:`~zenrl.learner.base.LearnerBase`); its checkpoint schema is
:class:`~zenrl.common.checkpoints.ApexTrainingState`. A3C's learner is :mod:`zenrl.learner.a3c`;
the process entry point that picks one is :mod:`zenrl.processes`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.checkpoints import ApexTrainingState
from zenrl.common.config import RunConfig
from zenrl.common.errors import CheckpointError
from zenrl.common.metrics import RateMeter
from zenrl.common.networks import arch_fingerprint, params_to_arrays
from zenrl.common.policy_io import initial_q_weights
from zenrl.common.replay_client import SamplePrefetcher, ShardedReplayClient, replay_client_for
from zenrl.common.roles import Supervisor
from zenrl.common.transport import Node
from zenrl.learner.base import LearnerBase
from zenrl.learner.dqn import DQNLearner
from zenrl.learner.sender import CLOSE_BUDGET_S, BackgroundSender

log = logging.getLogger(__name__)


class ApexLearner(LearnerBase):
    """The Ape-X DQN learner as a :class:`~zenrl.common.roles.Worker`."""

    schema = ApexTrainingState

    def __init__(self, cfg: RunConfig, node: Node, run_id: str, resume: str = "never", learner_id: str = "learner") -> None:
        super().__init__(cfg, node, run_id, learner_id)
        self.dqn = self.make_core()
        self.arch = arch_fingerprint(self.dqn.online)
        self.version = 0
        self.transitions_consumed = 0
        self._latest_weights: bytes | None = None
        if self.wants_resume(resume):
            self.restore()
        elif cfg.learner.init_from:
            # a fresh learner from given weights (a league's main agent from an earlier policy):
            # the first broadcast hands them to the actors
            self.dqn.load_initial(initial_q_weights(cfg.learner.init_from, cfg.learner.init_exported),
                                  cfg.learner.init_from)
            log.info("initial weights from %s", cfg.learner.init_from)
        # replay.shards > 1: batches drawn across the shards by their priority mass (common/replay_client.py)
        self.client = replay_client_for(node, run_id, cfg.replay.shards, self.id, cfg.transport.query_timeout_s,
                                        cfg.transport.max_message_bytes, seed=cfg.seed)

    def make_core(self) -> DQNLearner:
        """The learning step this learner drives (R2D2 gives its recurrent one)."""
        return DQNLearner(self.spec, self.n_actions, self.cfg.network, self.cfg.learner, self.device,
                          max_priority=self.cfg.replay.max_priority, guard=self.guard_rule)

    @property
    def updates(self) -> int:
        return self.dqn.updates

    # -- state -------------------------------------------------------------------------------
    def training_state(self) -> ApexTrainingState:
        return ApexTrainingState(**self.base_fields(self.version), learner=self.dqn.state_dict(),
                                 transitions_consumed=self.transitions_consumed)

    def load_training_state(self, state: ApexTrainingState) -> None:  # type: ignore[override]
        self.dqn.load_state_dict(state.learner)
        # versions published after that checkpoint are above it: continue above the high-water mark
        self.version = self.versions.resume_version(state.version)
        self.transitions_consumed = int(state.transitions_consumed)

    def current_version(self) -> int:
        return self.version

    def save(self) -> Path | None:
        """Checkpoint, unless the parameters are non-finite (then roll back instead)."""
        if not self.dqn.params_finite():
            self.dqn.guard.unpublishable += 1
            log.error("parameters are non-finite: no checkpoint written")
            self.rollback()
            return None
        return self.write_checkpoint()

    def rollback(self) -> None:
        """Back to the newest readable checkpoint (never one of non-finite parameters: none is
        written); without one, the optimizer state is reset and training goes on."""
        try:
            state, path = self.read_latest()
        except CheckpointError as e:
            log.error("%d updates in a row skipped or parameters non-finite, and no checkpoint to roll back to "
                      "(%s); resetting the optimizer state", self.dqn.guard.in_a_row, e)
            self.dqn.opt.state.clear()
        else:
            self.dqn.load_state_dict(state.learner)
            log.error("rolled back to %s (update %d) after %d skipped updates in a row", path, self.dqn.updates,
                      self.dqn.guard.in_a_row)
        self.dqn.guard.rolled_back()

    # -- weights -----------------------------------------------------------------------------
    def _publishable_weights(self) -> bytes | None:
        """Encoded weights of a new version, or ``None`` (and a rollback) if the parameters are
        non-finite: those are never broadcast."""
        if not self.dqn.params_finite():
            self.dqn.guard.unpublishable += 1
            log.error("parameters are non-finite: weights not published")
            self.rollback()
            return None
        return self._encode_weights()

    def _encode_weights(self) -> bytes:
        self.version = self.versions.claim(self.version + 1)
        return P.Weights(version=self.version, learner_id=self.id, arch=self.arch, updates=self.dqn.updates,
                         params=params_to_arrays(self.dqn.online)).encode(self.cfg.transport.max_message_bytes)

    # -- the role loop's Worker ---------------------------------------------------------------
    def start(self, node: Node, sup: Supervisor | None = None) -> None:
        """Publishers, the weights queryable, the first weights; the sender's and the
        prefetcher's threads watched by ``sup``."""
        cfg = self.cfg.learner
        self._sender = BackgroundSender(linger_s=cfg.send_linger_s, sup=sup)
        self._w_pub = node.publisher(self.keys.weights, low_priority=True)
        node.queryable(self.keys.weights_query, lambda _req: self._latest_weights)
        self._latest_weights = self._encode_weights()
        self._w_pub.put(self._latest_weights)
        self._pf = SamplePrefetcher(self.client, cfg.batch_size, self.dqn.beta, cfg.requests_in_flight,
                                    prepare=lambda s: self.dqn.batch_to_tensors(s.data, s.weights),
                                    batches_per_request=cfg.batches_per_request, seed=self.cfg.seed).start(sup)
        self._upd_rate, self._tr_rate = RateMeter(), RateMeter()
        self._acc: dict[str, float] = {}
        self._n_acc = 0
        self._lag_sum = self._wait_s = 0.0

    def step(self, timeout_s: float) -> bool:
        """One update on the next prefetched batch, if one comes within ``timeout_s``."""
        t0 = time.monotonic()
        s = self._pf.get(timeout_s=timeout_s)
        self._wait_s += time.monotonic() - t0
        if s is None:
            return False
        m, prios = self.dqn.update(s.prepared)
        bad = self.dqn.poisoned
        if prios is None:  # skipped by the guard (non-finite loss or gradient)
            if bad.size:
                self._sender.send_priorities(self.client.update_priorities, s.keys[:0], np.zeros(0, np.float32), s.keys[bad])
            if self.dqn.guard.rollback_due:
                self.rollback()
            return False
        if bad.size:  # left out of the step: the replay removes them and charges their sender
            keep = np.ones(len(prios), bool)
            keep[bad] = False
            self._sender.send_priorities(self.client.update_priorities, s.keys[keep], prios[keep], s.keys[bad])
            prios = prios[keep]
        else:
            self._sender.send_priorities(self.client.update_priorities, s.keys, prios)
        self.transitions_consumed += len(prios)
        self._upd_rate.add(1)
        self._tr_rate.add(len(prios))
        for k, v in m.items():
            self._acc[k] = self._acc.get(k, 0.0) + v
        self._n_acc += 1
        pv = s.data.get("meta/policy_version")
        if pv is not None:
            self._lag_sum += float(self.version - pv.mean())
        if self.dqn.updates % self.cfg.learner.publish_every_updates == 0:
            w = self._publishable_weights()
            if w is not None:
                self._latest_weights = w
                self._sender.send(self._w_pub, w)
        return True

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        n = max(self._n_acc, 1)
        vals: dict[str, Any] = {k: v / n for k, v in self._acc.items()}
        pf, sender = self._pf, self._sender
        vals.update({"updates": self.dqn.updates, "version": self.version, "updates_per_s": self._upd_rate.rate(),
                     "transitions_per_s": self._tr_rate.rate(), "policy_lag": self._lag_sum / n,
                     "beta": self.dqn.beta(), "wait_fraction": self._wait_s / max(interval_s, 1e-9),
                     "transitions_consumed": self.transitions_consumed, "not_ready": pf.not_ready,
                     "sample_timeouts": pf.timeouts, "sample_errors": pf.errors,
                     "send_dropped": sender.dropped, "send_failed": sender.failed, **self.dqn.values()})
        if isinstance(self.client, ShardedReplayClient):
            vals.update(self.client.values())
        line = None
        if self._n_acc:
            line = (f"updates {self.dqn.updates} v{self.version} loss {vals.get('loss', 0.0):.4f} q {vals.get('q_mean', 0.0):.3f} "
                    f"{vals['updates_per_s']:.1f} upd/s lag {vals['policy_lag']:.1f}")
        elif pf.last_not_ready_reason:
            line = f"waiting for replay: {pf.last_not_ready_reason}"
        self._acc, self._n_acc, self._lag_sum, self._wait_s = {}, 0, 0.0, 0.0
        return vals, line

    def close(self) -> None:
        # one budget for both joins, inside the launcher's 5 s grace after SIGTERM (the final
        # checkpoint is already written): what is unsent then is lost with the process
        deadline = time.monotonic() + CLOSE_BUDGET_S
        if getattr(self, "_pf", None) is not None:  # a start that failed before it (its error is the one to see)
            self._pf.stop(timeout=1.0)
        if getattr(self, "_sender", None) is not None:
            self._sender.close(timeout=deadline - time.monotonic())

