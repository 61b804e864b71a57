"""R2D2 learner (``zenrl learner`` with ``algo: r2d2``): Ape-X's learner loop on sequences.

:class:`R2D2Core` is the learning step with no I/O, :class:`~zenrl.learner.dqn.DQNLearner`'s
counterpart: online and target :class:`~zenrl.common.recurrent.RecurrentQNetwork`, optimizer,
the R2D2 loss (:mod:`zenrl.learner.r2d2_loss`: burn-in from the stored state without gradient,
n-step double-Q on value-rescaled Q, the mixed sequence priority), gradient clipping, the update
guard and the target network copy. The regression is a squared error on the rescaled values, as
in the paper (the rescaling keeps its scale small); ``learner.huber_delta`` is Ape-X's.

:class:`R2D2Learner` is :class:`~zenrl.learner.apex.ApexLearner` with that core: the same
prefetcher (replay items are sequences here), priorities back from the watched sender, weights
broadcast and queryable, guard and rollback, checkpoints (schema
:class:`~zenrl.common.checkpoints.R2D2TrainingState`) and resume. Its stats name sequences
where Ape-X's name transitions (``sequences_per_s``, ``sequences_consumed``) and add the steps
trained (``trained_steps_per_s``).

Batch layout (item-major, B sequences of m steps; see :mod:`zenrl.learner.r2d2_loss`)::

    obs/*  [B, m+1, ...]   action int64[B, m]   reward float32[B, m]   terminated bool[B, m]
    mask   bool[B, m]      first  bool[B]       h, c float32[B, H]     weights float32[B]
"""

from __future__ import annotations

import logging
import math
from typing import Any, Mapping

import numpy as np
import torch

from zenrl.common.checkpoints import R2D2TrainingState
from zenrl.common.config import LearnerConfig, NetworkConfig, R2D2Config, RunConfig
from zenrl.common.networks import to_tensors
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.specs import ArraySpec
from zenrl.learner.apex import ApexLearner
from zenrl.learner.dqn import DQNLearner, LossTerms
from zenrl.learner.r2d2_loss import r2d2_loss

log = logging.getLogger(__name__)

#: the sampled fields the loss reads besides the observations
BATCH_FIELDS = ("action", "reward", "terminated", "mask", "first", "h", "c")


class R2D2Core(DQNLearner):
    """Online and target recurrent Q networks plus optimizer; :meth:`update` is one step on a
    batch of sequences. Beta's schedule, the parameter check, ``state_dict`` and
    ``load_state_dict`` are :class:`DQNLearner`'s (the same attributes: ``online``, ``target``,
    ``opt``, ``updates``, ``guard``)."""

    def __init__(self, spec: Mapping[str, ArraySpec], n_actions: int, net_cfg: NetworkConfig, cfg: LearnerConfig,
                 rcfg: R2D2Config, device: torch.device, max_priority: float = math.inf) -> None:
        super().__init__(spec, n_actions, net_cfg, cfg, device,
                         network=lambda obs, n, nc: RecurrentQNetwork(obs, n, nc, rcfg.lstm_size),
                         max_priority=max_priority)
        self.rcfg = rcfg

    def batch_to_tensors(self, data: Mapping[str, np.ndarray], weights: np.ndarray) -> dict[str, Any]:
        """Tensors for :meth:`update` (:meth:`check_actions` first, then :meth:`screen`)."""
        self.check_actions(data["action"])
        data, weights, book = self.screen(data, weights, list(self.obs_spec))
        t = to_tensors({k: data[k] for k in (*self.obs_spec, *BATCH_FIELDS)}, self.device)
        t["weights"] = torch.from_numpy(np.array(weights, np.float32)).to(self.device)
        t.update(book)
        return t

    def loss_terms(self, b: Mapping[str, Any]) -> LossTerms:
        """The R2D2 loss (:func:`~zenrl.learner.r2d2_loss.r2d2_loss`) of a batch from
        :meth:`batch_to_tensors`; priorities float[B] are the mixed sequence priorities. A
        sequence is blamed for a refused step when its TD errors (over every step: a non-finite
        value anywhere in its unroll reaches them through the recurrent state) are non-finite or
        above ``max_priority``."""
        r = self.rcfg
        res = r2d2_loss(self.online, self.target, b, burn_in=r.burn_in, n_step=r.n_step, gamma=self.cfg.gamma,
                        eps=r.value_rescale_eps, eta=r.eta, train_episode_starts=r.train_episode_starts)

        def metrics() -> dict[str, float]:
            return {"q_mean": res.q_mean, "trained_steps": float(res.trained.sum().item())}

        def bad() -> torch.Tensor:
            return ~(res.td.abs() <= self.max_priority).all(1) | ~torch.isfinite(res.priorities)

        return LossTerms(res.loss, res.priorities.detach(), metrics, bad, self._over(res.td.abs()))

class R2D2Learner(ApexLearner):
    """The R2D2 learner as a :class:`~zenrl.common.roles.Worker` (see the module docstring)."""

    schema = R2D2TrainingState

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, resume: str = "never", learner_id: str = "learner") -> None:
        self._steps_acc = 0.0
        super().__init__(cfg, node, run_id, resume, learner_id)  # transitions_consumed counts sequences here

    def make_core(self) -> R2D2Core:
        return R2D2Core(self.spec, self.n_actions, self.cfg.network, self.cfg.learner, self.cfg.r2d2, self.device,
                        self.cfg.replay.max_priority)

    def training_state(self) -> R2D2TrainingState:
        return R2D2TrainingState(**self.base_fields(self.version), learner=self.dqn.state_dict(),
                                 sequences_consumed=self.transitions_consumed)

    def load_training_state(self, state: R2D2TrainingState) -> None:  # type: ignore[override]
        self.dqn.load_state_dict(state.learner)
        self.version = self.versions.resume_version(state.version)
        self.transitions_consumed = int(state.sequences_consumed)

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        n = max(self._n_acc, 1)
        steps = self._acc.get("trained_steps", 0.0)
        vals, line = super().report(interval_s)
        vals.pop("trained_steps", None)
        vals["sequences_per_s"] = vals.pop("transitions_per_s")
        vals["sequences_consumed"] = vals.pop("transitions_consumed")
        vals["trained_steps_per_s"] = steps / max(interval_s, 1e-9)
        vals["trained_steps_per_sequence"] = steps / n / max(self.cfg.learner.batch_size, 1)
        return vals, line
