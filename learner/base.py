"""What the Ape-X and A3C learners share: the env's shapes, the resume check, and
:class:`LearnerBase`, which runs either one in the common role loop."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import torch

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig, config_from_dict
from zenrl.common.env_factory import make_env
from zenrl.common.errors import CheckpointError
from zenrl.common.metrics import MetricsWriter
from zenrl.common.networks import num_actions, obs_spec, resolve_device
from zenrl.common.roles import Cadence, RoleLoop
from zenrl.learner.checkpoint import VersionReservation, checkpoint_dir, list_checkpoints


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
    """What every learner shares: identity and keys, run and checkpoint paths, device, the env's
    observation spec and action count, the seed set before the network is built (so actors that
    build theirs from the same seed start from the same weights), and the role loop.

    A learner is a :class:`~zenrl.common.roles.Worker`: subclasses give ``updates``,
    ``start``, ``step``, ``report``, ``save`` and ``close``; :meth:`run` hands them to the one
    :class:`~zenrl.common.roles.RoleLoop` (stats, metrics, log and checkpoint cadence, the
    ``max_updates`` budget, the final checkpoint on stop)."""

    #: updates applied so far (the step metrics and checkpoints are recorded against)
    updates: int

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, learner_id: str) -> None:
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

    def done(self) -> bool:
        return self.cfg.max_updates is not None and self.updates >= self.cfg.max_updates

    def progress(self) -> int:
        return self.updates

    def run(self, stop: threading.Event) -> None:
        cadence = Cadence(self.cfg.learner.log_interval_s, self.cfg.learner.checkpoint_interval_s)
        RoleLoop(self.node, self.keys, "learner", self.id, cadence, MetricsWriter(self.run_dir)).run(self, stop)
