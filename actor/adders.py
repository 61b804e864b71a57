"""Where what an actor experiences goes: an adder takes each batched step (the observations
acted on, the actions, the policy's extras, the :class:`~zenrl.actor.batch_env.StepResult`) and
sends what its algorithm learns from.

* :class:`NStepToReplay` (Ape-X): n-step transitions and initial priorities
  (:mod:`zenrl.actor.nstep`) in chunks to the replay (``transitions/<id>``).
* :class:`RolloutGradients` (A3C): t_max-step rollouts turned into gradients of the A3C loss
  (:mod:`zenrl.common.a3c_loss`) on ``gradients/<id>``.
* :class:`UnrollsToLearner` (IMPALA): every T batched steps, one
  :class:`~zenrl.common.protocol.Unroll` per env on ``unrolls/<id>``.
* :class:`EvalEpisodes` (evaluation): one episode per env per round, its returns (and match
  outcomes) as an :class:`~zenrl.common.protocol.EvalResult` on ``eval`` and in the metrics.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Mapping, Protocol

import numpy as np
import torch

from zenrl.actor.batch_env import StepResult
from zenrl.actor.nstep import Block, NStepBlocks, ValueFn
from zenrl.common import protocol as P
from zenrl.common.a3c_loss import Rollout, rollout_gradients
from zenrl.common.replay_client import ZenohReplayClient

log = logging.getLogger(__name__)

Obs = Mapping[str, np.ndarray]

#: fewest batched steps per n-step block (actor/nstep.py)
MIN_BLOCK_STEPS = 16


class Adder(Protocol):
    """What :class:`~zenrl.actor.worker.ActorWorker` asks of an adder."""

    def start(self, node: Any) -> None:
        """Declare the publishers it sends on."""

    def add(self, obs: Obs, actions: np.ndarray, extras: Any, res: StepResult) -> bool:
        """Record one batched step; True when it ended a round (the envs are reset before the
        next step; only evaluation has rounds)."""

    def flush(self) -> None:
        """Send what is pending (the worker stops)."""

    def values(self) -> dict[str, Any]:
        """Its stats values since the last call."""


class NStepToReplay:
    """n-step transitions with initial priorities, sent to the replay in chunks of
    ``ceil(chunk_size / E) * E`` transitions (whole batched steps), built in blocks of whole
    chunks and at least :data:`MIN_BLOCK_STEPS` steps (the per-block arithmetic is then spread
    over more steps). Extras: the float32[E, A] Q values the policy acted on, which the
    priorities reuse; ``value_fn`` bootstraps truncated episodes; ``version()`` is the policy
    version the chunks are stamped with. ``frame_stack`` not None: image observations leave as
    frame ids (docs/protocol.md)."""

    def __init__(self, replay: ZenohReplayClient, num_envs: int, n_step: int, gamma: float, chunk_size: int,
                 value_fn: ValueFn, version: Callable[[], int], frame_stack: int | None = None,
                 cut_non_greedy: bool = False) -> None:
        chunk_steps = -(-chunk_size // num_envs)
        self.chunk_len = chunk_steps * num_envs
        self.builder = NStepBlocks(num_envs, n_step, gamma, block_steps=chunk_steps * -(-MIN_BLOCK_STEPS // chunk_steps),
                                   frame_stack=frame_stack, cut_non_greedy=cut_non_greedy)
        self.replay, self.value_fn, self.version = replay, value_fn, version
        self.sent_transitions = 0

    def start(self, node: Any) -> None:
        pass  # the replay client declares its publisher with the first chunk

    def add(self, obs: Obs, actions: np.ndarray, extras: np.ndarray, res: StepResult) -> bool:
        self._send(self.builder.add(obs, extras, actions, res.rewards, res.next_obs, res.terminated, res.truncated,
                                    self.value_fn))
        return False

    def _send(self, block: Block | None) -> None:
        """A block in chunks (the last chunk of a shutdown flush may be shorter)."""
        if block is None or len(block) == 0:
            return
        cs = self.chunk_len
        frames, base = block.frames, block.frame_base
        for i in range(0, len(block), cs):
            self.replay.insert({k: v[i:i + cs] for k, v in block.data.items()}, block.priorities[i:i + cs],
                               self.version(), frames, None if frames is None else base)
            if frames is not None:  # the block's frames go with its first chunk
                base += len(next(iter(frames.values())))
                frames = {k: v[:0] for k, v in frames.items()}
        self.sent_transitions += len(block)

    def flush(self) -> None:
        self._send(self.builder.flush(self.value_fn))
        left = self.replay.flush_backlog()
        if left:
            self.replay.undelivered_chunks += left
            log.warning("actor %s stops with %d chunks no replay could take", self.replay.actor_id, left)

    def values(self) -> dict[str, Any]:
        r = self.replay
        return {"sent_transitions": self.sent_transitions, "sent_chunks": r.sent_chunks,
                "failed_chunks": r.failed_chunks, "undelivered_chunks": r.undelivered_chunks,
                "backlog_chunks": r.backlog, "split_chunks": r.split_chunks, "oversized_chunks": r.oversized_chunks}


class RolloutGradients:
    """Every ``t_max`` batched steps, the rollout's gradients of the A3C loss at the current
    parameters of ``net`` (:func:`~zenrl.common.a3c_loss.rollout_gradients`), published as
    :class:`~zenrl.common.protocol.Gradients` with ``version()``, the parameters' version.
    Its stats: the mean loss terms over the rollouts since the last report."""

    def __init__(self, net: torch.nn.Module, keys: P.Keys, worker_id: str, t_max: int, gamma: float,
                 value_coef: float, entropy_coef: float, gae_lambda: float, version: Callable[[], int],
                 max_bytes: int) -> None:
        self.net, self.keys, self.id, self.t_max = net, keys, worker_id, t_max
        self.gamma, self.value_coef, self.entropy_coef, self.gae_lambda = gamma, value_coef, entropy_coef, gae_lambda
        self.version, self.max_bytes = version, max_bytes
        self.sent_gradients = self.rollouts = 0
        self._steps: list[tuple[Obs, np.ndarray, StepResult]] = []
        self._acc: dict[str, float] = {}
        self._n_acc = 0
        self._pub: Any = None

    def start(self, node: Any) -> None:
        self._pub = node.publisher(self.keys.gradients(self.id))

    def add(self, obs: Obs, actions: np.ndarray, extras: Any, res: StepResult) -> bool:
        self._steps.append((obs, actions, res))
        if len(self._steps) == self.t_max:
            ro, self._steps = self.rollout(self._steps), []
            self._pub.put(self.gradients_message(ro).encode(self.max_bytes))
            self.sent_gradients += 1
            self.rollouts += 1
        return False

    @staticmethod
    def rollout(steps: list[tuple[Obs, np.ndarray, StepResult]]) -> Rollout:
        """The :class:`Rollout` of T recorded steps (final observations of the truncated
        episodes in row-major (t, e) order)."""
        finals = []
        for _, _, res in steps:
            tr = np.flatnonzero(res.truncated & ~res.terminated)
            if tr.size:
                finals.append({k: v[tr] for k, v in res.next_obs.items()})
        last = steps[-1][2].obs
        final_obs = ({k: np.concatenate([f[k] for f in finals]) for k in finals[0]} if finals
                     else {k: v[:0] for k, v in last.items()})
        obs = {k: np.stack([o[k] for o, _, _ in steps]) for k in steps[0][0]}
        return Rollout(obs, np.stack([a for _, a, _ in steps]), np.stack([r.rewards for _, _, r in steps]),
                       np.stack([r.terminated for _, _, r in steps]), np.stack([r.truncated for _, _, r in steps]),
                       final_obs, dict(last))

    def gradients_message(self, ro: Rollout) -> P.Gradients:
        """The gradients of the loss on ``ro`` at the current parameters, as a wire message."""
        grads, m = rollout_gradients(self.net, ro, self.gamma, self.value_coef, self.entropy_coef, self.gae_lambda)
        for k, v in m.items():
            self._acc[k] = self._acc.get(k, 0.0) + v
        self._n_acc += 1
        return P.Gradients(worker_id=self.id, version=max(self.version(), 0), steps=ro.steps, grads=grads)

    def flush(self) -> None:
        pass  # a partial rollout is dropped, as its gradients would be of an unfinished t_max

    def values(self) -> dict[str, Any]:
        vals: dict[str, Any] = {k: v / self._n_acc for k, v in self._acc.items()} if self._n_acc else {}
        self._acc, self._n_acc = {}, 0
        vals["sent_gradients"] = self.sent_gradients
        return vals


class UnrollsToLearner:
    """IMPALA: keeps the last T batched steps and, every T steps, publishes one
    :class:`~zenrl.common.protocol.Unroll` per env on ``unrolls/<id>`` (E messages, env order):
    the T + 1 observations (the T acted on, then the one after the last step, which the next
    unroll starts from), the actions, the behaviour log-probabilities (the policy's extras,
    float32[E] per step), rewards, terminations, truncations, the true final observations of
    the truncated (not terminated) steps, and ``version()`` when the unroll's first step was
    taken (the oldest policy in it: the learner's lag check errs on the stale side). ``codec``
    "lz4" compresses uint8 observation arrays. A partial unroll is dropped on stop (the learner
    takes unrolls of exactly T steps)."""

    def __init__(self, keys: P.Keys, actor_id: str, unroll_length: int, version: Callable[[], int],
                 max_bytes: int, codec: str | None = None) -> None:
        self.keys, self.id, self.T = keys, actor_id, unroll_length
        self.version, self.max_bytes, self.codec = version, max_bytes, codec
        self.sent_unrolls = self.sent_bytes = self.seq = 0
        self._steps: list[tuple[Obs, np.ndarray, np.ndarray, StepResult]] = []
        self._first_version = -1
        self._pub: Any = None

    def start(self, node: Any) -> None:
        self._pub = node.publisher(self.keys.unrolls(self.id))

    def add(self, obs: Obs, actions: np.ndarray, extras: np.ndarray, res: StepResult) -> bool:
        if not self._steps:
            self._first_version = self.version()
        self._steps.append((obs, actions, extras, res))
        if len(self._steps) == self.T:
            steps, self._steps = self._steps, []
            for u in self.unrolls(steps):
                payload = u.encode(self.max_bytes, self.codec)
                self._pub.put(payload)
                self.sent_unrolls += 1
                self.sent_bytes += len(payload)
        return False

    def unrolls(self, steps: list[tuple[Obs, np.ndarray, np.ndarray, StepResult]]) -> list[P.Unroll]:
        """The E unrolls of T recorded batched steps ``(obs, actions, logp, result)``."""
        E = len(steps[0][1])
        obs = {k: np.stack([o[k] for o, _, _, _ in steps] + [steps[-1][3].obs[k]]) for k in steps[0][0]}  # [T+1, E, ...]
        act = np.stack([a for _, a, _, _ in steps])  # int64[T, E], or float32[T, E, d] for continuous actions
        act = act.astype(np.float32 if act.dtype.kind == "f" else np.int64, copy=False)
        logp = np.stack([np.asarray(lp, np.float32) for _, _, lp, _ in steps])
        rew = np.stack([np.asarray(r.rewards, np.float32) for _, _, _, r in steps])
        term = np.stack([r.terminated for _, _, _, r in steps])
        trunc = np.stack([r.truncated for _, _, _, r in steps])
        cut = trunc & ~term
        out = []
        for e in range(E):
            ts = np.flatnonzero(cut[:, e])
            final = {k: np.stack([steps[t][3].next_obs[k][e] for t in ts]) for k in obs} if ts.size else None
            out.append(P.Unroll(actor_id=self.id, policy_version=int(self._first_version), seq=self.seq,
                                obs={k: np.ascontiguousarray(v[:, e]) for k, v in obs.items()},
                                action=np.ascontiguousarray(act[:, e]), behaviour_logp=np.ascontiguousarray(logp[:, e]),
                                reward=np.ascontiguousarray(rew[:, e]), terminated=np.ascontiguousarray(term[:, e]),
                                truncated=np.ascontiguousarray(trunc[:, e]), final_obs=final))
            self.seq += 1
        return out

    def flush(self) -> None:
        self._steps = []  # a partial unroll is not one the learner takes

    def values(self) -> dict[str, Any]:
        return {"sent_unrolls": self.sent_unrolls, "sent_bytes": self.sent_bytes}


class EvalEpisodes:
    """One episode per env per round; when every env has finished its first episode, the
    round's float32[E] returns and (match envs) int8[E] outcomes (+1 win, 0 draw, -1 loss) go
    out as an :class:`~zenrl.common.protocol.EvalResult` stamped with ``version()`` and
    ``updates()`` of the weights played, to the metrics (source ``eval``) and the log."""

    def __init__(self, keys: P.Keys, num_envs: int, version: Callable[[], int], updates: Callable[[], int],
                 metrics: Any = None) -> None:
        self.keys, self.E, self.version, self.updates, self.metrics = keys, num_envs, version, updates, metrics
        self.rounds = 0
        self.last: dict[str, Any] = {}
        self._pub: Any = None
        self._new_round()

    def _new_round(self) -> None:
        self.returns = np.zeros(self.E, np.float64)
        self.outcomes: list[int | None] = [None] * self.E
        self.finished = np.zeros(self.E, bool)

    def start(self, node: Any) -> None:
        self._pub = node.publisher(self.keys.eval)

    def add(self, obs: Obs, actions: np.ndarray, extras: Any, res: StepResult) -> bool:
        self.returns += np.where(self.finished, 0.0, res.rewards)
        ended = (res.terminated | res.truncated) & ~self.finished
        # EnvBatch lists finished episodes in env order
        for i, out in zip(np.flatnonzero(res.terminated | res.truncated), res.ep_outcomes):
            if ended[i]:
                self.outcomes[i] = out
        self.finished |= ended
        if not self.finished.all():
            return False
        known = None if any(o is None for o in self.outcomes) else np.array(self.outcomes, np.int8)
        self._publish(self.returns.astype(np.float32), known)
        self._new_round()
        return True

    def _publish(self, rets: np.ndarray, outcomes: np.ndarray | None) -> None:
        version, updates = self.version(), self.updates()
        self._pub.put(P.EvalResult(version=version, updates=updates, returns=rets, outcomes=outcomes).encode())
        values = {"return_mean": float(rets.mean()), "return_std": float(rets.std()),
                  "return_min": float(rets.min()), "return_max": float(rets.max()), "version": version}
        won = ""
        if outcomes is not None:
            values.update(win_rate=float((outcomes == 1).mean()), draw_rate=float((outcomes == 0).mean()))
            won = f", won {int((outcomes == 1).sum())}/{outcomes.size}"
        if self.metrics is not None:
            self.metrics.write("eval", updates, values)
        self.rounds += 1
        self.last = values
        log.info("eval v%d (%d updates): return %.1f +- %.1f%s", version, updates, rets.mean(), rets.std(), won)

    def flush(self) -> None:
        pass  # an unfinished round is not a result

    def values(self) -> dict[str, Any]:
        return {"eval_rounds": self.rounds, **self.last}
