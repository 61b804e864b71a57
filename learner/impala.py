"""IMPALA learner (``zenrl learner`` with ``algo: impala``; APPO with ``impala.clip_eps``).

Actors (:mod:`zenrl.actor.impala`) publish :class:`~zenrl.common.protocol.Unroll` s of T steps
on ``unrolls/<actor>``. The Zenoh callback (:meth:`ImpalaLearner.on_unroll`) handles one
message: a quarantined source's is dropped unread; the rest is decoded (form, sizes,
finiteness; the declared observation dtypes and shapes against the env's before anything is
decompressed; frame-mode stacks rebuilt from their frames), checked for meaning (:class:`~zenrl.common.unroll_checks.UnrollChecker`: the
env's observation spec and bounds, actions in range, T, reward and log-probability bounds) and
put in the :class:`~zenrl.learner.unroll_queue.UnrollQueue` (fair across actors, bounded in
count and bytes, unrolls more than ``impala.max_policy_lag`` versions behind dropped and
counted). A bad unroll is rejected alone, counted by reason (``rejected_<reason>``) and by
source (``rejected_from/<actor>``); an actor with ``impala.quarantine_rejections`` rejections
within ``impala.quarantine_window_s`` is quarantined (its unrolls dropped unread for
``impala.quarantine_s``; its queued ones forgotten).

Each :meth:`~ImpalaLearner.step` takes B = ``impala.batch_unrolls`` unrolls, stacks them
time-major (:func:`~zenrl.learner.unroll_queue.batch_unrolls`) and makes one optimizer step on
the V-trace loss (:func:`~zenrl.learner.impala_loss.learner_step`); every
``impala.broadcast_every`` updates the weights go out with a new version (low priority, on
``weights``; ``learner/weights`` queries get the latest). The guard
(:mod:`zenrl.learner.guard`) skips an update with a non-finite loss or gradient, rolls back to
the last checkpoint after ``learner.guard_max_bad_updates`` in a row, and never publishes or
saves non-finite parameters. The optimizer is ``learner.optimizer`` at ``learner.lr`` (RMSProp
with ``a3c.rmsprop_alpha`` / ``a3c.rmsprop_eps``, as the A3C learner's).

Why not a FIFO table in the replay service: the replay would add a hop (actor -> replay ->
learner, a sample request per batch) to data that is used exactly once, in arrival order; the
learner's own queue gets the unrolls in one hop, and the fairness, staleness and byte bounds
hold where the training happens.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch

from zenrl.common import protocol as P
from zenrl.common.checkpoints import ImpalaTrainingState
from zenrl.common.config import RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.errors import CheckpointError, ProtocolError
from zenrl.common.metrics import RateMeter, RejectCounter
from zenrl.common.networks import ActorCritic, arch_fingerprint, params_to_arrays
from zenrl.common.quarantine import Quarantine, SourceLedger
from zenrl.common.roles import Supervisor
from zenrl.common.unroll_checks import UnrollChecker
from zenrl.learner.a3c import make_optimizer
from zenrl.learner.base import LearnerBase
from zenrl.learner.guard import UpdateGuard, params_finite
from zenrl.learner.impala_loss import LossParams, learner_step
from zenrl.learner.sender import BackgroundSender
from zenrl.learner.unroll_queue import UnrollQueue, batch_unrolls

log = logging.getLogger(__name__)


def _finite(loss: float, norm: float) -> bool:
    return math.isfinite(loss) and math.isfinite(norm)

#: Sources listed by name in the stats' per-source rejection counts (the most rejected first).
TOP_SOURCES = 20
#: Sources whose rejections are counted by name (the totals count them all).
MAX_SOURCES = 10_000
#: The queue counters reported as stats (``queue_<name>``; ``stale_dropped`` also as itself).
QUEUE_COUNTERS = ("queued", "taken", "stale_dropped", "evicted", "too_large_dropped", "future_version")


def source_of(key: str) -> str:
    """The sender an ``unrolls/<actor>`` key names (its last segment)."""
    return key.rsplit("/", 1)[-1]


class ImpalaLearner(LearnerBase):
    """The IMPALA learner as a :class:`~zenrl.common.roles.Worker`; its checkpoint schema is
    :class:`~zenrl.common.checkpoints.ImpalaTrainingState`. ``node`` may be None for tests that
    call :meth:`on_unroll` and :meth:`step` directly (after :meth:`start_offline`)."""

    schema = ImpalaTrainingState

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, resume: str = "never", learner_id: str = "learner") -> None:
        super().__init__(cfg, node, run_id, learner_id)
        icfg = cfg.impala
        self.net = ActorCritic(self.spec, self.n_actions, cfg.network).to(self.device)
        self.arch = arch_fingerprint(self.net)
        self.opt = make_optimizer(self.net.parameters(), cfg.learner, cfg.a3c)
        self.loss_params = LossParams(gamma=cfg.learner.gamma, lam=icfg.lam, rho_bar=icfg.rho_bar, c_bar=icfg.c_bar,
                                      value_coef=icfg.value_coef, entropy_coef=icfg.entropy_coef,
                                      clip_eps=icfg.clip_eps, normalize_advantages=icfg.normalize_advantages,
                                      reward_scale=icfg.reward_scale)
        self.guard = UpdateGuard(cfg.learner.guard_max_bad_updates, cfg.learner.guard_log_interval_s)
        self.queue = UnrollQueue(icfg.queue_max_unrolls, icfg.queue_max_bytes, icfg.max_policy_lag)
        env = make_env(cfg.env)
        try:
            self.checker = UnrollChecker.from_spaces(env.observation_space, env.action_space, icfg.max_abs_reward,
                                                     unroll_length=icfg.unroll_length,
                                                     check_obs_bounds=icfg.check_obs_bounds)
        finally:
            env.close()
        #: field -> (dtype, item shape): what an unroll may declare, checked before decompressing
        self.wire_spec = {k: (r.dtype, tuple(r.shape)) for k, r in self.checker.rules.items()}
        self.limits = self.checker.decode_limits()
        self.quarantine = Quarantine(icfg.quarantine_rejections, icfg.quarantine_window_s, icfg.quarantine_s)
        self.rejects = RejectCounter(log, "unroll")
        #: rejections by source, internal errors by type, the quarantine they feed (its lock)
        self.ledger = SourceLedger(self.quarantine, MAX_SOURCES)
        self.dropped_quarantined = 0
        self.poisoned_unrolls = 0  #: unrolls left out of a step because their own step is non-finite
        self.updates = 0
        self.version = 0
        self.env_steps_trained = 0
        self._good = self._snapshot()
        self._latest_weights: bytes | None = None
        self._sender: BackgroundSender | None = None
        self._reset_interval()
        if self.wants_resume(resume):
            self.restore()

    # -- state -------------------------------------------------------------------------------
    def training_state(self) -> ImpalaTrainingState:
        return ImpalaTrainingState(**self.base_fields(self.version), model=self.net.state_dict(),
                                   optimizer=self.opt.state_dict(), updates=self.updates,
                                   env_steps_trained=self.env_steps_trained)

    def load_training_state(self, state: ImpalaTrainingState) -> None:  # type: ignore[override]
        self.net.load_state_dict(state.model)
        self.opt.load_state_dict(state.optimizer)
        self.updates = int(state.updates)
        self.env_steps_trained = int(state.env_steps_trained)
        # weights published after that checkpoint had higher versions: continue above them
        self.version = self.versions.resume_version(state.version)
        self.queue.set_version(self.version)
        self._good = self._snapshot()

    def current_version(self) -> int:
        return self.version

    def params_finite(self) -> bool:
        return params_finite(self.net.parameters())

    def save(self) -> Path | None:
        """Checkpoint, unless the parameters are non-finite (then roll back instead)."""
        if not self.params_finite():
            self.guard.unpublishable += 1
            log.error("parameters are non-finite: no checkpoint written")
            self.rollback()
            return None
        return self.write_checkpoint()

    def rollback(self) -> None:
        """Back to the newest readable checkpoint, else to the last parameters published; the
        optimizer state is reset in the latter case (it led here)."""
        try:
            state, path = self.read_latest()
        except CheckpointError as e:
            log.error("%d updates in a row skipped or parameters non-finite, and no checkpoint to roll back to (%s); "
                      "restoring the last published parameters and resetting the optimizer state", self.guard.in_a_row, e)
            with torch.no_grad():
                for p, g in zip(self.net.parameters(), self._good):
                    p.copy_(g)
            self.opt.state.clear()
        else:
            version = self.version
            self.load_training_state(state)
            self.version = max(self.version, version)  # versions only grow
            log.error("rolled back to %s (update %d) after %d skipped updates in a row", path, self.updates,
                      self.guard.in_a_row)
        self.guard.rolled_back()

    def _snapshot(self) -> list[torch.Tensor]:
        return [p.detach().clone() for p in self.net.parameters()]

    # -- weights -----------------------------------------------------------------------------
    def _publishable_weights(self) -> bytes | None:
        """Encoded weights of a new version, or None (and a rollback) if the parameters are
        non-finite: those are never broadcast."""
        if not self.params_finite():
            self.guard.unpublishable += 1
            log.error("parameters are non-finite: weights not published")
            self.rollback()
            return None
        self.version = self.versions.claim(self.version + 1)
        self.queue.set_version(self.version)
        self._good = self._snapshot()
        return P.Weights(version=self.version, learner_id=self.id, arch=self.arch, updates=self.updates,
                         params=params_to_arrays(self.net)).encode(self.cfg.transport.max_message_bytes)

    # -- unrolls in (Zenoh's thread) ---------------------------------------------------------
    def on_unroll(self, key: str, payload: bytes) -> str:
        """Zenoh's callback for ``unrolls/*``: one message to the queue, or rejected and counted.
        Returns the outcome: ``quarantined``, ``rejected`` or the queue's (``queued``,
        ``stale``, ``too_large``). Never raises."""
        src = source_of(key)
        if self.quarantine.active and self.quarantine.drop(src):
            self.dropped_quarantined += 1  # unread: a quarantined source costs a dict lookup
            return "quarantined"
        try:
            u = P.Unroll.decode(payload, self.cfg.transport.max_message_bytes, limits=self.limits, spec=self.wire_spec)
            if u.actor_id != src:
                raise ProtocolError("actor_id", f"{u.actor_id!r} differs from the key's {src!r}", "source")
            u = u.resolved()
            why = self.checker.check(u)
            if why is not None:
                self.reject(why.reason, why.detail, src)
                return "rejected"
            return self.queue.put(u, src)
        except ProtocolError as e:
            self.reject(e.reason, str(e), src)
        except Exception as e:  # noqa: BLE001 - one message's failure costs that message only
            t = type(e).__name__
            if self.ledger.internal_error(e):
                log.error("an unroll from %s raised %s; counted as rejected_internal, going on", src, t, exc_info=e)
            self.reject("internal", f"{t}: {e}", src)
        return "rejected"

    def reject(self, reason: str, detail: str, source: str) -> None:
        """Count a rejected unroll by reason and by source; a source that keeps sending bad
        unrolls is quarantined and its queued unrolls forgotten."""
        self.rejects.reject(reason, detail, source)
        if self.ledger.rejected(source, reason):
            dropped = self.queue.drop_source(source)
            log.warning("actor %s quarantined for %.0f s: %d rejected unrolls within %.0f s (last: %s); %d queued "
                        "unrolls of it dropped", source, self.quarantine.duration_s, self.quarantine.rejections,
                        self.quarantine.window_s, reason, dropped)

    # -- the role loop's Worker ---------------------------------------------------------------
    def start(self, node: Any, sup: Supervisor | None = None) -> None:
        """Publishers, the weights queryable, the first weights, the unrolls subscription; the
        sender's thread watched by ``sup``."""
        self._sender = BackgroundSender(sup=sup)
        self._w_pub = node.publisher(self.keys.weights, low_priority=True)
        node.queryable(self.keys.weights_query, lambda _req: self._latest_weights)
        self._latest_weights = self._publishable_weights()
        self._w_pub.put(self._latest_weights)
        node.subscribe(self.keys.unrolls_all, self.on_unroll)
        i = self.cfg.impala
        log.info("impala learner (%s): weights version %d, %d updates so far, batches of %d unrolls x %d steps, "
                 "optimizer %s lr %g", "APPO clip %g" % i.clip_eps if i.clip_eps is not None else "V-trace",
                 self.version, self.updates, i.batch_unrolls, i.unroll_length, self.cfg.learner.optimizer,
                 self.cfg.learner.lr)

    def start_offline(self) -> None:
        """Without a network (tests): the first weights version, no publisher."""
        self._latest_weights = self._publishable_weights()

    def step(self, timeout_s: float) -> bool:
        """One update on the next B unrolls, if they come within ``timeout_s``; broadcast every
        ``impala.broadcast_every`` updates."""
        icfg = self.cfg.impala
        unrolls = self.queue.take(icfg.batch_unrolls, timeout_s)
        if unrolls is None:
            return False
        refused: list[tuple[float, float]] = []
        batch = batch_unrolls(unrolls, self.device)
        stats = learner_step(self.net, self.opt, batch, self.loss_params, icfg.max_grad_norm,
                             lambda loss, norm: _finite(loss, norm) or bool(refused.append((loss, norm))))
        if stats is None:  # non-finite loss or gradient: step on the unrolls not to blame, if any
            batch, stats = self._without_poison(unrolls, refused[0])
            if stats is None:
                if self.guard.rollback_due:
                    self.rollback()
                return False
        else:
            self.guard.accept(stats["loss"], stats["grad_norm"])  # finite: resets the run of skips
        self.updates += 1
        T, B = batch.shape
        self.env_steps_trained += T * B
        self._upd_rate.add(1)
        self._step_rate.add(T * B)
        for k, v in stats.items():
            self._acc[k] = self._acc.get(k, 0.0) + v
        self._rho_max = max(self._rho_max, stats["rho_max"])
        self._lag_sum += self.version - float(batch.policy_version.float().mean())
        self._n_acc += 1
        if self.updates % icfg.broadcast_every == 0:
            w = self._publishable_weights()
            if w is not None:
                self._latest_weights = w
                if self._sender is not None:
                    self._sender.send(self._w_pub, w)
        return True

    def _without_poison(self, unrolls: list[Any], refused: tuple[float, float]) -> tuple[Any, dict[str, float] | None]:
        """After a refused step: the unrolls whose step alone is non-finite (found by bisection,
        no optimizer step) are charged to their senders (``poison``: an unroll inside every
        bound whose values the network cannot take) and the step is made on the others.
        Returns (batch, stats), stats None when the step was skipped (also when every unroll or
        none is to blame: the learner's problem, counted by the guard)."""
        bad = self._culprits(unrolls)
        if not bad or len(bad) == len(unrolls):
            self.guard.accept(*refused)
            return None, None
        for u in bad:
            self.poisoned_unrolls += 1
            self.reject("poison", "the unroll makes the learner's loss or gradient non-finite; left out of the step",
                        u.actor_id)
        keep = [u for u in unrolls if not any(u is b for b in bad)]
        batch = batch_unrolls(keep, self.device)
        return batch, learner_step(self.net, self.opt, batch, self.loss_params, self.cfg.impala.max_grad_norm,
                                   self.guard.accept)

    def _culprits(self, unrolls: list[Any]) -> list[Any]:
        """Within a set of unrolls whose step is non-finite, those whose step alone is."""
        if len(unrolls) == 1:
            return unrolls
        h = len(unrolls) // 2
        out: list[Any] = []
        for part in (unrolls[:h], unrolls[h:]):
            fin: list[bool] = []
            learner_step(self.net, self.opt, batch_unrolls(part, self.device), self.loss_params,
                         self.cfg.impala.max_grad_norm, lambda loss, norm: bool(fin.append(_finite(loss, norm))))
            if not fin[0]:
                out += self._culprits(part)
        return out

    def _reset_interval(self) -> None:
        self._upd_rate, self._step_rate = RateMeter(), RateMeter()
        self._acc: dict[str, float] = {}
        self._n_acc = 0
        self._lag_sum = 0.0
        self._rho_max = 0.0

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        n = max(self._n_acc, 1)
        vals: dict[str, Any] = {k: v / n for k, v in self._acc.items()}
        if self._n_acc:
            vals["rho_max"] = self._rho_max
        q = self.queue.counters
        vals.update({
            "updates": self.updates, "version": self.version, "updates_per_s": self._upd_rate.rate(),
            "env_steps_per_s": self._step_rate.rate(), "env_steps_trained": self.env_steps_trained,
            "policy_lag": self._lag_sum / n, "queue_len": len(self.queue), "queue_bytes": self.queue.nbytes,
            "stale_dropped": q["stale_dropped"], "dropped_quarantined": self.dropped_quarantined,
            "send_dropped": self._sender.dropped if self._sender is not None else 0,
                     "poisoned_unrolls": self.poisoned_unrolls, **self.guard.values()})
        vals.update({f"queue_{k}": q[k] for k in QUEUE_COUNTERS})
        vals.update(self.rejects.as_values())
        vals.update(self.ledger.values(TOP_SOURCES, expire=True))
        line = None
        if self._n_acc:
            line = (f"updates {self.updates} v{self.version} {vals['updates_per_s']:.1f} upd/s "
                    f"{vals['env_steps_per_s']:.0f} steps/s loss {vals['loss']:.3f} entropy {vals['entropy']:.3f} "
                    f"rho {vals['rho_mean']:.2f} lag {vals['policy_lag']:.1f} queue {len(self.queue)} "
                    f"stale {q['stale_dropped']} rejected {self.rejects.total}")
        # the rates' meters keep their own interval: only the sums restart
        self._acc, self._n_acc, self._lag_sum, self._rho_max = {}, 0, 0.0, 0.0
        return vals, line

    def close(self) -> None:
        if self._sender is not None:
            self._sender.close()
