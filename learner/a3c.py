"""A3C learner (``zenrl learner`` with ``algo: a3c``): the parameter server of asynchronous
advantage actor-critic.

Workers (:mod:`zenrl.actor.a3c`) publish :class:`~zenrl.common.protocol.Gradients` on
``gradients/<worker>``. The Zenoh callback only enqueues the payload in a bounded queue that is
fair per source (:class:`~zenrl.learner.fair_queue.FairQueue`: one FIFO per worker key, served
round-robin; a full queue evicts the oldest message of the worker holding the most and counts it
in ``queue_dropped`` and ``queue_dropped_from/<worker>``, so the sender is never stalled and a
worker that floods pushes out only its own gradients; ``applied_from/<worker>`` and
``stale_from/<worker>`` in the stats show each worker's share, and
``queue_wait_turns_max_from/<worker>`` the most turns other workers took while one of its
gradients waited, per gradient of its own ahead of it and itself: at most the number of other
workers with gradients queued). The
main loop decodes, validates and
applies each gradient as it arrives with one shared optimizer (RMSProp by default for A3C, as in
the A3C paper's shared RMSProp), with gradient-norm clipping, and broadcasts the parameters every
``a3c.broadcast_every`` applications with a strictly increasing ``version`` (low priority, on the
``weights`` key; ``learner/weights`` queries get the latest).

Which gradients are applied (:class:`GradientApplier`, pure, unit-tested):

* names and shapes must match the model's parameters (else rejected, counted by reason);
* ``worker_id`` must be the worker named in the key (``source``), and ``steps`` (added to
  ``env_steps_trained``) at most what one rollout can hold, ``a3c.max_gradient_steps`` (default
  ``a3c.t_max * actor.envs_per_actor``) (``steps``): no message can inflate the learner's
  counters;
* NaN/Inf never get this far (rejected when decoded); a gradient whose norm overflows, or
  exceeds ``a3c.max_grad_norm`` (absurd for any honest worker), is rejected; if the parameters ever became non-finite after a step they are restored from the
  last broadcast and the optimizer state is reset;
* a gradient taken at params ``version`` v is dropped (``stale_dropped``) if the current version
  is more than ``a3c.max_staleness`` ahead of v, and dropped (``unknown_version_dropped``) if v is
  newer than the current version (a claim more than ``MAX_RESYNC_AHEAD`` above the version the
  learner started at, or within ``max_staleness + 1`` applied gradients of the last resync, is
  dropped without resync). The latter only happens after a learner restart from a
  checkpoint older than the params the workers hold; the learner then jumps its version past the
  claimed one (and past the staleness window) so that its next broadcast is taken by the workers
  again instead of being ignored as old.

The queue holds at most ``(max_staleness + 1) * broadcast_every + num_actors`` gradients: any
gradient further back would be stale by the time it is applied anyway.
"""

from __future__ import annotations

import collections
import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from zenrl.common import protocol as P
from zenrl.common.checkpoints import A3CTrainingState
from zenrl.common.config import A3CConfig, LearnerConfig, RunConfig
from zenrl.common.errors import ProtocolError
from zenrl.common.metrics import RateMeter, RejectCounter
from zenrl.common.networks import ActorCritic, arch_fingerprint, params_to_arrays
from zenrl.common.roles import Supervisor
from zenrl.common.transport import Node
from zenrl.learner.base import LearnerBase
from zenrl.learner.fair_queue import MAX_TRACKED, TOP_EVICTED, FairQueue
from zenrl.learner.sender import BackgroundSender

log = logging.getLogger(__name__)

#: Largest version a worker may claim before the learner resyncs to it (keeps versions far from
#: the uint64 limit of the wire format whatever a faulty worker sends).
MAX_RESYNC_VERSION = 1 << 53
#: Furthest a claimed version may lie above the version the learner started (or resumed) at
#: for it to resync: the run's version mark is reserved 1000 versions ahead, so workers are only
#: ahead of a resumed learner when the mark could not be written (a full disk) for a long time.
#: Bounds what messages claiming future versions can add to the version, over the learner's life.
MAX_RESYNC_AHEAD = 1 << 20

APPLIED = "applied"
STALE = "stale"
UNKNOWN_VERSION = "unknown_version"


def make_optimizer(params: Any, lcfg: LearnerConfig, acfg: A3CConfig) -> torch.optim.Optimizer:
    """``learner.optimizer``: rmsprop (non-centered, ``a3c.rmsprop_alpha``/``rmsprop_eps``, as in
    A3C) or adam (``learner.adam_eps``), both at ``learner.lr``."""
    if lcfg.optimizer == "rmsprop":
        return torch.optim.RMSprop(params, lr=lcfg.lr, alpha=acfg.rmsprop_alpha, eps=acfg.rmsprop_eps)
    return torch.optim.Adam(params, lr=lcfg.lr, eps=lcfg.adam_eps)


class GradientApplier:
    """The shared model and optimizer; applies workers' gradients (no I/O).

    ``version`` is the version of the params last broadcast (0 before the first
    :meth:`next_version`); ``updates`` counts applied gradients.
    """

    def __init__(self, net: torch.nn.Module, lcfg: LearnerConfig, acfg: A3CConfig) -> None:
        self.net = net
        self.lcfg, self.acfg = lcfg, acfg
        self.params = dict(net.named_parameters())
        self.opt = make_optimizer(self.params.values(), lcfg, acfg)
        self.version = 0
        self.updates = 0
        self.restored = 0
        self._good = [p.detach().clone() for p in self.params.values()]
        self._start_version = 0
        self._last_resync: int | None = None  # ``updates`` at the last resync

    def check(self, msg: P.Gradients) -> None:
        """Raise :class:`ProtocolError` if ``msg.grads`` does not match the parameters."""
        got, want = set(msg.grads), set(self.params)
        if got != want:
            raise ProtocolError("grads", f"parameter names differ: missing {sorted(want - got)[:3]}, "
                                         f"unexpected {sorted(got - want)[:3]}", "names")
        for k, p in self.params.items():
            if tuple(msg.grads[k].shape) != tuple(p.shape):
                raise ProtocolError(f"grads.{k}", f"shape {list(msg.grads[k].shape)}, expected {list(p.shape)}", "shape")

    def apply(self, msg: P.Gradients) -> tuple[str, float]:
        """Validate and apply one gradient. Returns (outcome, gradient norm before clipping):
        outcome :data:`APPLIED`, :data:`STALE` or :data:`UNKNOWN_VERSION`; a malformed gradient
        raises :class:`ProtocolError` (reason ``names``, ``shape`` or ``nonfinite``)."""
        self.check(msg)
        if msg.version > self.version:
            return UNKNOWN_VERSION, 0.0
        if self.version - msg.version > self.acfg.max_staleness:
            return STALE, 0.0
        dev = next(iter(self.params.values())).device
        for k, p in self.params.items():
            g = msg.grads[k]
            p.grad = torch.from_numpy(np.array(g, np.float32)).to(dev)
        norm = float(torch.nn.utils.clip_grad_norm_(list(self.params.values()), self.lcfg.grad_clip))
        if not np.isfinite(norm):
            self.opt.zero_grad(set_to_none=True)
            raise ProtocolError("grads", f"gradient norm is {norm} (overflow)", "nonfinite")
        if norm > self.acfg.max_grad_norm:
            # clipping would still take a full-size step in the direction a faulty worker chose
            self.opt.zero_grad(set_to_none=True)
            raise ProtocolError("grads", f"gradient norm {norm:.3g} exceeds a3c.max_grad_norm {self.acfg.max_grad_norm:.3g}",
                                "grad_norm")
        lr = self.current_lr()
        for group in self.opt.param_groups:
            group["lr"] = lr
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        self.updates += 1
        if not self.params_finite():
            self._restore_good()
        return APPLIED, norm

    def current_lr(self) -> float:
        """``learner.lr``, or with ``a3c.lr_anneal_updates`` = N the linear anneal from it to
        ``lr * a3c.lr_final_fraction`` over the first N applied gradients (held after)."""
        n = self.acfg.lr_anneal_updates
        if n is None:
            return self.lcfg.lr
        frac = min(1.0, self.updates / n)
        return self.lcfg.lr * (1.0 - frac * (1.0 - self.acfg.lr_final_fraction))

    def params_finite(self) -> bool:
        return all(bool(torch.isfinite(p).all()) for p in self.params.values())

    def _restore_good(self) -> None:
        log.error("parameters became non-finite after update %d; restoring the params of version %d "
                  "and resetting the optimizer state", self.updates, self.version)
        with torch.no_grad():
            for p, g in zip(self.params.values(), self._good):
                p.copy_(g)
        self.opt.state.clear()
        self.restored += 1

    def next_version(self) -> int:
        """Mark the current params as a new version (to be broadcast); returns it."""
        self.version += 1
        self._good = [p.detach().clone() for p in self.params.values()]
        return self.version

    def resync(self, claimed: int) -> bool:
        """A worker holds params of version ``claimed`` > ours (we restarted from an older
        checkpoint): jump past it and its staleness window. Returns whether the version moved.
        Bounded whatever workers claim: never above :data:`MAX_RESYNC_AHEAD` past the version
        this learner started at, and at most once per ``a3c.max_staleness + 1`` applied
        gradients (each jump makes every gradient in flight stale, so a worker claiming future
        versions over and over would otherwise starve the others)."""
        if claimed <= self.version or claimed > min(MAX_RESYNC_VERSION, self._start_version + MAX_RESYNC_AHEAD):
            return False
        if self._last_resync is not None and self.updates - self._last_resync <= self.acfg.max_staleness:
            return False
        self.version = claimed + self.acfg.max_staleness
        self._last_resync = self.updates
        return True

    def load(self, model: Mapping[str, Any], optimizer: Mapping[str, Any], version: int, updates: int) -> None:
        """Take back saved parameters, optimizer state and counters (a checkpoint's)."""
        self.net.load_state_dict(model)
        self.opt.load_state_dict(optimizer)
        self.version, self.updates = int(version), int(updates)
        self._start_version, self._last_resync = self.version, None
        self._good = [p.detach().clone() for p in self.params.values()]


class A3CLearner(LearnerBase):
    """The A3C parameter server as a :class:`~zenrl.common.roles.Worker`; its checkpoint schema
    is :class:`~zenrl.common.checkpoints.A3CTrainingState`."""

    schema = A3CTrainingState
    version_noun = "params"

    def __init__(self, cfg: RunConfig, node: Node, run_id: str, resume: str = "never", learner_id: str = "learner") -> None:
        super().__init__(cfg, node, run_id, learner_id)
        self.net = ActorCritic(self.spec, self.n_actions, cfg.network).to(self.device)
        self.arch = arch_fingerprint(self.net)
        self.applier = GradientApplier(self.net, cfg.learner, cfg.a3c)
        self.env_steps_trained = 0
        a = cfg.a3c
        self._q: FairQueue[bytes] = FairQueue((a.max_staleness + 1) * a.broadcast_every + cfg.actor.num_actors)
        self._applied_by: collections.Counter[str] = collections.Counter()
        self._stale_by: collections.Counter[str] = collections.Counter()
        #: most env steps one gradient message may claim
        self.max_steps = a.max_gradient_steps or a.t_max * cfg.actor.envs_per_actor
        self.queue_dropped = 0
        self.stale_dropped = 0
        self.unknown_version_dropped = 0
        self.rejects = RejectCounter(log, "gradients")
        self._norm_sum = self._lag_sum = 0.0  # since the last stats message
        self._n_applied = 0
        self._resync_pending = False
        self._latest_weights: bytes | None = None
        if self.wants_resume(resume):
            self.restore()

    # -- state -------------------------------------------------------------------------------
    def training_state(self) -> A3CTrainingState:
        a = self.applier
        return A3CTrainingState(**self.base_fields(a.version), model=self.net.state_dict(), optimizer=a.opt.state_dict(),
                                updates=a.updates, env_steps_trained=self.env_steps_trained)

    def load_training_state(self, state: A3CTrainingState) -> None:  # type: ignore[override]
        # parameters published after that checkpoint had higher versions: continue above them
        self.applier.load(state.model, state.optimizer, self.versions.resume_version(state.version), state.updates)
        self.env_steps_trained = int(state.env_steps_trained)

    def current_version(self) -> int:
        return self.applier.version

    def save(self) -> Path:
        if not self.applier.params_finite():  # cannot persist after apply(); kept as a last guard
            self.applier._restore_good()
        return self.write_checkpoint()

    # -- network -----------------------------------------------------------------------------
    def _on_gradients(self, key: str, payload: bytes) -> None:
        """Zenoh callback: enqueue only (in the worker's FIFO); never blocks the sender."""
        if self._q.put(key.rsplit("/", 1)[-1], payload):
            self.queue_dropped += 1

    def _encode_weights(self) -> bytes:
        if not self.applier.params_finite():  # never broadcast non-finite parameters
            self.applier._restore_good()
        version = self.versions.claim(self.applier.next_version())
        return P.Weights(version=version, learner_id=self.id, arch=self.arch, updates=self.applier.updates,
                         params=params_to_arrays(self.net)).encode(self.cfg.transport.max_message_bytes)

    # -- gradients ---------------------------------------------------------------------------
    def handle(self, key: str, payload: bytes) -> str | None:
        """Decode and apply one gradient message from ``key`` (``gradients/<worker>``, or the
        worker's name alone); returns the outcome (None if rejected)."""
        source = key.rsplit("/", 1)[-1]
        try:
            msg = P.Gradients.decode(payload, self.cfg.transport.max_message_bytes)
            self.check_claims(msg, source)
            outcome, norm = self.applier.apply(msg)
        except ProtocolError as e:
            self.rejects.reject(e.reason, str(e), source)
            return None
        if outcome == STALE:
            self.stale_dropped += 1
            if source in self._stale_by or len(self._stale_by) < MAX_TRACKED:
                self._stale_by[source] += 1
        elif outcome == UNKNOWN_VERSION:
            self.unknown_version_dropped += 1
            if self.applier.resync(msg.version):
                log.warning("%s sent gradients of params version %d, newer than ours; resyncing the version "
                            "(learner restarted from an older checkpoint?)", msg.worker_id, msg.version)
                self._resync_pending = True
        else:
            if source in self._applied_by or len(self._applied_by) < MAX_TRACKED:
                self._applied_by[source] += 1
            self.env_steps_trained += msg.steps
            self._norm_sum += norm
            self._lag_sum += self.applier.version - msg.version
            self._n_applied += 1
        return outcome

    def check_claims(self, msg: P.Gradients, source: str) -> None:
        """Raise :class:`ProtocolError` if ``msg`` claims another sender than its key's
        (``source``) or more env steps than one rollout holds (``self.max_steps``)."""
        if msg.worker_id != source:
            raise ProtocolError("worker_id", f"{msg.worker_id!r} sent on the key of {source!r}", "source")
        if msg.steps > self.max_steps:
            raise ProtocolError("steps", f"{msg.steps} env steps in one gradient, more than a3c.max_gradient_steps "
                                         f"{self.max_steps}", "steps")

    # -- the role loop's Worker ---------------------------------------------------------------
    @property
    def updates(self) -> int:
        return self.applier.updates

    def start(self, node: Node, sup: Supervisor | None = None) -> None:
        """Publishers, the weights queryable, the gradients subscription, the first weights; the
        sender's thread watched by ``sup``."""
        self._sender = BackgroundSender(sup=sup)
        self._w_pub = node.publisher(self.keys.weights, low_priority=True)
        node.queryable(self.keys.weights_query, lambda _req: self._latest_weights)
        node.subscribe(self.keys.gradients_all, self._on_gradients)
        self._latest_weights = self._encode_weights()
        self._w_pub.put(self._latest_weights)
        log.info("a3c learner: params version %d, %d updates so far, optimizer %s lr %g",
                 self.applier.version, self.applier.updates, self.cfg.learner.optimizer, self.cfg.learner.lr)
        self._upd_rate, self._step_rate = RateMeter(), RateMeter()

    def step(self, timeout_s: float) -> bool:
        """Apply the next queued gradient, if one comes within ``timeout_s``; broadcast every
        ``a3c.broadcast_every`` applications (and after a version resync)."""
        item = self._q.get(timeout_s)
        if item is None:
            return False
        before = self.env_steps_trained
        if self.handle(*item) == APPLIED:
            self._upd_rate.add(1)
            self._step_rate.add(self.env_steps_trained - before)
            if self.applier.updates % self.cfg.a3c.broadcast_every == 0:
                self._broadcast()
            return True
        if self._resync_pending:
            self._resync_pending = False
            self._broadcast()
        return False

    def _broadcast(self) -> None:
        self._latest_weights = self._encode_weights()
        self._sender.send(self._w_pub, self._latest_weights)

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        n = max(self._n_applied, 1)
        vals: dict[str, Any] = {
            "updates": self.applier.updates, "version": self.applier.version,
            "updates_per_s": self._upd_rate.rate(), "env_steps_per_s": self._step_rate.rate(),
            "env_steps_trained": self.env_steps_trained, "grad_norm": self._norm_sum / n,
            "policy_lag": self._lag_sum / n, "stale_dropped": self.stale_dropped,
            "unknown_version_dropped": self.unknown_version_dropped,
            "queue_dropped": self.queue_dropped, "queue_len": len(self._q),
            "params_restored": self.applier.restored, "send_dropped": self._sender.dropped,
            "lr": self.applier.current_lr()}
        vals.update(self.rejects.as_values())
        vals.update(self._q.evicted_values())
        vals.update(self._q.wait_values())
        vals.update({f"applied_from/{s}": n for s, n in self._applied_by.most_common(TOP_EVICTED)})
        vals.update({f"stale_from/{s}": n for s, n in self._stale_by.most_common(TOP_EVICTED)})
        line = None
        if self._n_applied:
            line = (f"updates {self.applier.updates} v{self.applier.version} {vals['updates_per_s']:.1f} upd/s "
                    f"{vals['env_steps_per_s']:.0f} steps/s lag {vals['policy_lag']:.2f} |g| {vals['grad_norm']:.3f} "
                    f"stale {self.stale_dropped} rejected {self.rejects.total}")
        self._norm_sum = self._lag_sum = 0.0
        self._n_applied = 0
        return vals, line

    def close(self) -> None:
        self._sender.close()
