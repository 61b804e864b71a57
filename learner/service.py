"""Learner process (``zenrl learner``). Ape-X mode: samples from the replay service through a
prefetcher (several requests in flight), trains, sends priorities back from a background thread,
broadcasts weights every ``publish_every_updates`` updates at low Zenoh priority (and answers
``learner/weights`` queries with the latest), checkpoints every ``checkpoint_interval_s`` and on
stop. A3C mode lives in :mod:`zenrl.learner.a3c`.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

import torch

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig, config_from_dict
from zenrl.common.env_factory import make_env
from zenrl.common.errors import CheckpointError
from zenrl.common.metrics import MetricsWriter, RateMeter
from zenrl.common.networks import arch_fingerprint, num_actions, obs_spec, params_to_arrays, resolve_device
from zenrl.common.replay_client import SamplePrefetcher, ZenohReplayClient
from zenrl.common.transport import Node
from zenrl.learner.checkpoint import VersionReservation, checkpoint_dir, list_checkpoints, load_latest, save_checkpoint
from zenrl.learner.dqn import DQNLearner

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = 1


class BackgroundSender:
    """Puts payloads from a thread of its own so the training step never waits on the network.

    ``send`` queues bytes; ``send_priorities`` queues one batch's new priorities, and the
    priorities queued since the last wake-up go out as one :class:`PriorityUpdate` (concatenated
    in order, so for a key sampled twice the later value wins, as the replay applies them). With
    ``linger_s`` > 0 the thread waits that long after the first item before it sends, so it
    wakes once per few training steps instead of once per step (each wake-up of another thread
    costs the training thread a GIL hand-off). Over ``max_items`` queued, items are dropped and
    counted in ``dropped``; a failed put or encoding is logged and counted in ``failed``.
    """

    def __init__(self, max_items: int = 256, linger_s: float = 0.0, max_message_bytes: int = P.DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self.max_items = max_items
        self.linger_s = linger_s
        self.max_bytes = max_message_bytes
        self._items: collections.deque[tuple[Any, Any]] = collections.deque()
        self._wake = threading.Event()
        self._closed = False
        self.dropped = 0
        self.failed = 0
        self.sent = 0
        self._t = threading.Thread(target=self._loop, name="sender", daemon=True)
        self._t.start()

    def _queue(self, publisher: Any, item: Any) -> None:
        if len(self._items) >= self.max_items:
            self.dropped += 1
            return
        self._items.append((publisher, item))
        if not self._wake.is_set():
            self._wake.set()

    def send(self, publisher: Any, payload: bytes) -> None:
        self._queue(publisher, payload)

    def send_priorities(self, publisher: Any, keys: np.ndarray, priorities: np.ndarray) -> None:
        """keys int64[B], priorities float32[B] (held by reference: do not modify them)."""
        self._queue(publisher, (keys, priorities))

    def _loop(self) -> None:
        while True:
            self._wake.wait()
            if not self._closed and self.linger_s > 0:
                time.sleep(self.linger_s)
            self._wake.clear()
            items = []
            while self._items:
                items.append(self._items.popleft())
            self._flush(items)
            if self._closed and not self._items:
                return

    def _flush(self, items: list[tuple[Any, Any]]) -> None:
        # priorities for one publisher become one message, sent where their first part was queued
        merged: dict[int, tuple[list, list]] = {}
        out: list[tuple[Any, Any]] = []
        for pub, item in items:
            if isinstance(item, bytes):
                out.append((pub, item))
                continue
            parts = merged.get(id(pub))
            if parts is None:
                parts = merged[id(pub)] = ([], [])
                out.append((pub, parts))
            parts[0].append(item[0])
            parts[1].append(item[1])
        for pub, item in out:
            try:
                if not isinstance(item, bytes):
                    item = P.PriorityUpdate(keys=np.concatenate(item[0]),
                                            priorities=np.concatenate(item[1])).encode(self.max_bytes)
                pub.put(item)
                self.sent += 1
            except Exception as e:  # zenoh.ZError if the session closed, an encoding error: keep going
                self.failed += 1
                log.warning("background put failed: %s", e)

    def close(self) -> None:
        """Send what is queued, then stop the thread."""
        self._closed = True
        self._wake.set()
        self._t.join(timeout=5)


def env_shapes(cfg: RunConfig) -> tuple[dict, int]:
    env = make_env(cfg.env)
    try:
        return obs_spec(env.observation_space), num_actions(env.action_space)
    finally:
        env.close()


def check_resume_compatible(saved_cfg: dict[str, Any], cfg: RunConfig, saved_arch: str, arch: str) -> None:
    """A change that cannot be honoured on resume is an error naming it; others are accepted."""
    old = config_from_dict(saved_cfg)
    if old.algo != cfg.algo:
        raise CheckpointError(f"cannot resume: checkpoint is algo={old.algo}, config says algo={cfg.algo}")
    if old.env.id != cfg.env.id:
        raise CheckpointError(f"cannot resume: checkpoint trained env.id={old.env.id}, config says {cfg.env.id}")
    if saved_arch != arch:
        raise CheckpointError(f"cannot resume: the network differs (checkpoint {saved_arch}, config {arch}); "
                              f"network={old.network.model_dump()} was saved, config gives {cfg.network.model_dump()}")


class LearnerBase:
    """What every learner service shares: identity and keys, run and checkpoint paths, device,
    the env's observation spec and action count, and the seed set before the network is built
    (so actors that build theirs from the same seed start from the same weights)."""

    def __init__(self, cfg: RunConfig, node: Node, run_id: str, learner_id: str) -> None:
        self.cfg = cfg
        self.node = node
        self.keys = P.Keys(run_id)
        self.id = learner_id
        self.run_dir = Path(cfg.runs_dir) / run_id
        self.ckpt_dir = checkpoint_dir(cfg.runs_dir, run_id)
        self.versions = VersionReservation(self.run_dir)
        torch.set_num_threads(cfg.learner.torch_threads)
        self.device = resolve_device(cfg.learner.device)
        self.spec, self.n_actions = env_shapes(cfg)
        torch.manual_seed(cfg.seed)

    def wants_resume(self, resume: str) -> bool:
        """``resume``: "never", "require" (an error without a checkpoint) or "auto"."""
        return resume == "require" or (resume == "auto" and bool(list_checkpoints(self.ckpt_dir)))


class ApexLearnerService(LearnerBase):
    def __init__(self, cfg: RunConfig, node: Node, run_id: str, resume: str = "never", learner_id: str = "learner") -> None:
        super().__init__(cfg, node, run_id, learner_id)
        self.dqn = DQNLearner(self.spec, self.n_actions, cfg.network, cfg.learner, self.device)
        self.arch = arch_fingerprint(self.dqn.online)
        self.version = 0
        self.transitions_consumed = 0
        self._latest_weights: bytes | None = None
        if self.wants_resume(resume):
            self._restore()
        self.client = ZenohReplayClient(node, self.keys, self.id, cfg.transport.query_timeout_s, cfg.transport.max_message_bytes)

    # -- state -------------------------------------------------------------------------------
    def training_state(self) -> dict[str, Any]:
        return {"format": CHECKPOINT_FORMAT, "algo": "apex", "arch": self.arch, "version": self.version,
                "transitions_consumed": self.transitions_consumed, "learner": self.dqn.state_dict(),
                "torch_rng": torch.get_rng_state(), "config": self.cfg.model_dump(mode="json"),
                "saved_at": time.time()}

    def _restore(self) -> None:
        state, path = load_latest(self.ckpt_dir)
        check_resume_compatible(state["config"], self.cfg, state["arch"], self.arch)
        self.dqn.load_state_dict(state["learner"])
        # versions published after that checkpoint are above it: continue above the high-water mark
        self.version = self.versions.resume_version(int(state["version"]))
        self.transitions_consumed = int(state["transitions_consumed"])
        torch.set_rng_state(state["torch_rng"])
        log.info("resumed from %s: %d updates, weights version %d", path, self.dqn.updates, self.version)

    def save(self) -> Path | None:
        """Checkpoint, unless the parameters are non-finite (then roll back instead)."""
        if not self.dqn.params_finite():
            self.dqn.guard.unpublishable += 1
            log.error("parameters are non-finite: no checkpoint written")
            self.rollback()
            return None
        p = save_checkpoint(self.ckpt_dir, self.training_state(), self.dqn.updates, self.cfg.learner.keep_checkpoints)
        log.info("checkpoint %s", p)
        return p

    def rollback(self) -> None:
        """Back to the newest readable checkpoint (never one of non-finite parameters: none is
        written); without one, the optimizer state is reset and training goes on."""
        try:
            state, path = load_latest(self.ckpt_dir)
            check_resume_compatible(state["config"], self.cfg, state["arch"], self.arch)
        except CheckpointError as e:
            log.error("%d updates in a row skipped or parameters non-finite, and no checkpoint to roll back to "
                      "(%s); resetting the optimizer state", self.dqn.guard.in_a_row, e)
            self.dqn.opt.state.clear()
        else:
            self.dqn.load_state_dict(state["learner"])
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

    # -- main loop ---------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        cfg = self.cfg.learner
        metrics = MetricsWriter(self.run_dir)
        sender = BackgroundSender(linger_s=cfg.send_linger_s, max_message_bytes=self.cfg.transport.max_message_bytes)
        w_pub = self.node.publisher(self.keys.weights, low_priority=True)
        stats_pub = self.node.publisher(self.keys.stats("learner", self.id))
        prio_pub = self.node.publisher(self.keys.priorities)
        self.node.queryable(self.keys.weights_query, lambda _req: self._latest_weights)
        self.node.token(self.keys.alive("learner", self.id))
        self._latest_weights = self._encode_weights()
        w_pub.put(self._latest_weights)
        pf = SamplePrefetcher(self.client, cfg.batch_size, self.dqn.beta, cfg.requests_in_flight,
                              prepare=lambda s: self.dqn.batch_to_tensors(s.data, s.weights),
                              batches_per_request=cfg.batches_per_request, seed=self.cfg.seed).start()
        upd_rate, smp_rate = RateMeter(), RateMeter()
        last_log = last_ckpt = time.monotonic()
        acc: dict[str, float] = {}
        n_acc = 0
        lag_sum = 0.0
        wait_s = 0.0
        try:
            while not stop.is_set():
                budget_done = self.cfg.max_updates is not None and self.dqn.updates >= self.cfg.max_updates
                t0 = time.monotonic()
                s = None if budget_done else pf.get(timeout_s=0.5)
                if budget_done:
                    stop.wait(0.5)  # the launcher stops the run once it sees the final count
                wait_s += time.monotonic() - t0
                if s is not None:
                    m, prios = self.dqn.update(s.prepared)
                    if prios is None:  # skipped by the guard (non-finite loss or gradient)
                        if self.dqn.guard.rollback_due:
                            self.rollback()
                        s = None
                if s is not None:
                    sender.send_priorities(prio_pub, s.keys, prios)
                    self.transitions_consumed += len(prios)
                    upd_rate.add(1)
                    smp_rate.add(len(prios))
                    for k, v in m.items():
                        acc[k] = acc.get(k, 0.0) + v
                    n_acc += 1
                    pv = s.data.get("meta/policy_version")
                    if pv is not None:
                        lag_sum += float(self.version - pv.mean())
                    if self.dqn.updates % cfg.publish_every_updates == 0:
                        w = self._publishable_weights()
                        if w is not None:
                            self._latest_weights = w
                            sender.send(w_pub, w)
                now = time.monotonic()
                if now - last_log >= cfg.log_interval_s:
                    vals = {k: v / max(n_acc, 1) for k, v in acc.items()}
                    vals.update({"updates": self.dqn.updates, "version": self.version, "updates_per_s": upd_rate.rate(),
                                 "samples_per_s": smp_rate.rate(), "policy_lag": lag_sum / max(n_acc, 1),
                                 "beta": self.dqn.beta(), "wait_fraction": wait_s / max(now - last_log, 1e-9),
                                 "transitions_consumed": self.transitions_consumed, "not_ready": pf.not_ready,
                                 "sample_timeouts": pf.timeouts, "sample_errors": pf.errors,
                                 "send_dropped": sender.dropped, "send_failed": sender.failed,
                                 **self.dqn.guard.values()})
                    stats_pub.put(P.Stats(role="learner", id=self.id, time=time.time(), values=vals).encode())
                    metrics.write("learner", self.dqn.updates, vals)
                    if n_acc:
                        log.info("updates %d v%d loss %.4f q %.3f %.1f upd/s lag %.1f", self.dqn.updates, self.version,
                                 vals.get("loss", 0.0), vals.get("q_mean", 0.0), vals["updates_per_s"], vals["policy_lag"])
                    elif pf.last_not_ready_reason:
                        log.info("waiting for replay: %s", pf.last_not_ready_reason)
                    acc, n_acc, lag_sum, wait_s, last_log = {}, 0, 0.0, 0.0, now
                if now - last_ckpt >= cfg.checkpoint_interval_s:
                    self.save()
                    last_ckpt = now
        finally:
            pf.stop()
            self.save()
            sender.close()
            metrics.close()


def main(cfg: RunConfig, run_id: str, stop: threading.Event, resume: str = "never") -> None:
    """Entry point of ``zenrl learner``. ``resume``: "never", "require" (newest valid checkpoint,
    an error if none) or "auto" (resume if a checkpoint exists)."""
    with Node.from_config(cfg.transport) as node:
        if cfg.algo == "a3c":
            from zenrl.learner.a3c import A3CLearnerService

            A3CLearnerService(cfg, node, run_id, resume).run(stop)
        else:
            ApexLearnerService(cfg, node, run_id, resume).run(stop)
