"""Learner process (``zenrl learner``). Ape-X mode: samples from the replay service through a
prefetcher (several requests in flight), trains, sends priorities back from a background thread,
broadcasts weights every ``publish_every_updates`` updates at low Zenoh priority (and answers
``learner/weights`` queries with the latest), checkpoints every ``checkpoint_interval_s`` and on
stop. A3C mode lives in :mod:`zenrl.learner.a3c`.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any

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
    """Puts payloads from a queue so the training step never waits on the network."""

    def __init__(self, maxsize: int = 64) -> None:
        self._q: queue.Queue[tuple[Any, bytes] | None] = queue.Queue(maxsize=maxsize)
        self.dropped = 0
        self._t = threading.Thread(target=self._loop, name="sender", daemon=True)
        self._t.start()

    def send(self, publisher: Any, payload: bytes) -> None:
        try:
            self._q.put_nowait((publisher, payload))
        except queue.Full:
            self.dropped += 1

    def _loop(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            pub, payload = item
            try:
                pub.put(payload)
            except Exception as e:  # zenoh.ZError if the session closed; keep the thread alive
                log.warning("background put failed: %s", e)

    def close(self) -> None:
        self._q.put(None)
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

    def save(self) -> Path:
        p = save_checkpoint(self.ckpt_dir, self.training_state(), self.dqn.updates, self.cfg.learner.keep_checkpoints)
        log.info("checkpoint %s", p)
        return p

    # -- weights -----------------------------------------------------------------------------
    def _encode_weights(self) -> bytes:
        self.version = self.versions.claim(self.version + 1)
        return P.Weights(version=self.version, learner_id=self.id, arch=self.arch, updates=self.dqn.updates,
                         params=params_to_arrays(self.dqn.online)).encode(self.cfg.transport.max_message_bytes)

    # -- main loop ---------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        cfg = self.cfg.learner
        metrics = MetricsWriter(self.run_dir)
        sender = BackgroundSender()
        w_pub = self.node.publisher(self.keys.weights, low_priority=True)
        stats_pub = self.node.publisher(self.keys.stats("learner", self.id))
        prio_pub = self.node.publisher(self.keys.priorities)
        self.node.queryable(self.keys.weights_query, lambda _req: self._latest_weights)
        self.node.token(self.keys.alive("learner", self.id))
        self._latest_weights = self._encode_weights()
        w_pub.put(self._latest_weights)
        pf = SamplePrefetcher(self.client, cfg.batch_size, self.dqn.beta, cfg.requests_in_flight).start()
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
                    b = self.dqn.batch_to_tensors(s.data, s.weights)
                    m, prios = self.dqn.update(b)
                    sender.send(prio_pub, P.PriorityUpdate(keys=s.keys, priorities=prios).encode())
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
                        self._latest_weights = self._encode_weights()
                        sender.send(w_pub, self._latest_weights)
                now = time.monotonic()
                if now - last_log >= cfg.log_interval_s:
                    vals = {k: v / max(n_acc, 1) for k, v in acc.items()}
                    vals.update({"updates": self.dqn.updates, "version": self.version, "updates_per_s": upd_rate.rate(),
                                 "samples_per_s": smp_rate.rate(), "policy_lag": lag_sum / max(n_acc, 1),
                                 "beta": self.dqn.beta(), "wait_fraction": wait_s / max(now - last_log, 1e-9),
                                 "transitions_consumed": self.transitions_consumed, "not_ready": pf.not_ready,
                                 "sample_timeouts": pf.timeouts, "send_dropped": sender.dropped})
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
