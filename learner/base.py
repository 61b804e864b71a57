"""What the Ape-X and A3C learners share: the env's shapes, the resume check, and
:class:`LearnerBase`, which owns the checkpoint (its :class:`TrainingState` fields, writing,
resuming) and runs either learner in the common role loop."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, ClassVar

import torch

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig, config_from_dict
from zenrl.common.checkpoints import TrainingState, check_weights_fit
from zenrl.common.env_factory import make_env
from zenrl.common.errors import CheckpointError, ConfigError
from zenrl.common.guard_rule import GuardRule
from zenrl.common.league_reset import GenerationWatch
from zenrl.common.metrics import MetricsWriter
from zenrl.common.networks import action_size, obs_spec, resolve_device
from zenrl.common.roles import Cadence, RoleLoop
from zenrl.learner.checkpoint import (VersionReservation, checkpoint_dir, list_checkpoints, load_latest,
                                     remove_stale_temp_files, save_checkpoint)

log = logging.getLogger(__name__)


def env_facts(cfg: RunConfig) -> tuple[dict, int, GuardRule | None]:
    """``cfg.env``'s observation spec, policy head size (:func:`~zenrl.common.networks.action_size`) and, with ``learner.guard_imitation``,
    its guard rule (else None), from one env made and closed here. ConfigError naming what is
    missing where the env has no guard rule (not a match env)."""
    env = make_env(cfg.env)
    try:
        spec, n = obs_spec(env.observation_space), action_size(env.action_space, cfg.algo)
        if not cfg.learner.guard_imitation:
            return spec, n, None
        rule = getattr(env.unwrapped, "guard_rule", None)
        if rule is None:
            raise ConfigError(f"learner.guard_imitation needs a match env (zenrl/BurgerWar-v0), not {cfg.env.id}")
        return spec, n, rule()  # a match env: a discrete action set
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
        if old.network.model_dump() == cfg.network.model_dump():
            raise CheckpointError(f"cannot resume: the network differs (checkpoint {saved_arch}, config {arch}) with the "
                                  "same network settings: the env's spaces give another network (env.kwargs changed, or "
                                  "the checkpoint is from a zenrl that built it otherwise, e.g. before Discrete "
                                  "observations were one-hot encoded); start a new run")
        raise CheckpointError(f"cannot resume: the network differs (checkpoint {saved_arch}, config {arch}); "
                              f"network={old.network.model_dump()} was saved, config gives {cfg.network.model_dump()}")


class LearnerBase:
    """What every learner shares: identity and keys, run and checkpoint paths, device, the env's
    observation spec and action count, the seed set before the network is built (so actors that
    build theirs from the same seed start from the same weights), and the role loop.

    A learner is a :class:`~zenrl.common.roles.Worker`: subclasses give ``updates``,
    ``start``, ``step``, ``report``, ``save`` and ``close``; :meth:`run` hands them to the one
    :class:`~zenrl.common.roles.RoleLoop` (stats, metrics, log and checkpoint cadence, the
    ``max_updates`` budget, the final checkpoint on stop).

    Checkpoints: the base owns the fields every learner saves (:meth:`base_fields`) and the
    files (:meth:`write_checkpoint`, :meth:`read_latest`, :meth:`restore`); a subclass names
    its schema (:attr:`schema`, a :class:`~zenrl.common.checkpoints.TrainingState` subclass),
    builds it (:meth:`training_state`) and takes its own fields back (:meth:`load_training_state`)."""

    #: the algorithm's checkpoint schema
    schema: ClassVar[type[TrainingState]]
    #: updates applied so far (the step metrics and checkpoints are recorded against)
    updates: int
    #: :func:`~zenrl.common.networks.arch_fingerprint` of the trained network (set by the subclass)
    arch: str
    #: what the log calls the published versions ("weights", "params")
    version_noun: ClassVar[str] = "weights"

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, learner_id: str) -> None:
        self.cfg = cfg
        self.node = node
        self.keys = P.Keys(run_id)
        self.id = learner_id
        self.run_dir = Path(cfg.runs_dir) / run_id
        self.ckpt_dir = checkpoint_dir(cfg.runs_dir, run_id)
        for stale in remove_stale_temp_files(self.ckpt_dir) + remove_stale_temp_files(self.run_dir):
            log.warning("removed %s, left by a write that was killed before it finished", stale)
        self.versions = VersionReservation(self.run_dir)
        torch.set_num_threads(cfg.learner.torch_threads)
        self.device = resolve_device(cfg.learner.device)
        #: the env's guard rule, for learner.guard_imitation (None when off)
        self.spec, self.n_actions, self.guard_rule = env_facts(cfg)
        check_weights_fit(cfg, self.spec, self.n_actions)  # before the network is built: ConfigError, exit 2
        torch.manual_seed(cfg.seed)

    def wants_resume(self, resume: str) -> bool:
        """``resume``: "never", "require" (an error without a checkpoint) or "auto"."""
        return resume == "require" or (resume == "auto" and bool(list_checkpoints(self.ckpt_dir)))

    # -- checkpoints -------------------------------------------------------------------------
    def base_fields(self, version: int) -> dict[str, Any]:
        """The :class:`TrainingState` fields every learner saves, for weights ``version``."""
        return {"arch": self.arch, "version": int(version), "config": self.cfg.model_dump(mode="json"),
                "torch_rng": torch.get_rng_state(), "saved_at": time.time()}

    def training_state(self) -> TrainingState:
        """The state to save now: ``self.schema(**self.base_fields(version), <own fields>)``."""
        raise NotImplementedError

    def load_training_state(self, state: TrainingState) -> None:
        """Take back the algorithm's own fields of ``state`` (one of :attr:`schema`) and continue
        its weights versions above ``self.versions.resume_version(state.version)``."""
        raise NotImplementedError

    def write_checkpoint(self) -> Path:
        """Save :meth:`training_state` as the run's newest checkpoint (the oldest beyond
        ``learner.keep_checkpoints`` pruned)."""
        p = save_checkpoint(self.ckpt_dir, self.training_state(), self.cfg.learner.keep_checkpoints)
        log.info("checkpoint %s", p)
        return p

    def read_latest(self) -> tuple[TrainingState, Path]:
        """The run's newest readable checkpoint, checked to be one this learner can continue
        (:func:`check_resume_compatible`); :class:`CheckpointError` otherwise."""
        state, path = load_latest(self.ckpt_dir)
        if not isinstance(state, self.schema):
            raise CheckpointError(f"cannot resume: {path} is a {state.algo} checkpoint, this learner is {self.schema.algo}")
        check_resume_compatible(state.config, self.cfg, state.arch, self.arch)
        return state, path

    def restore(self) -> None:
        """Continue from the run's newest checkpoint: the algorithm's state, the weights
        version and the random state."""
        state, path = self.read_latest()
        self.load_training_state(state)
        if state.torch_rng is not None:
            torch.set_rng_state(state.torch_rng)
        log.info("resumed from %s: %d updates, %s version %d", path, self.updates, self.version_noun, self.current_version())

    def current_version(self) -> int:
        """The weights version last published (or restored)."""
        raise NotImplementedError

    def done(self) -> bool:
        return self.cfg.max_updates is not None and self.updates >= self.cfg.max_updates

    def progress(self) -> int:
        return self.updates

    def run(self, stop: threading.Event) -> None:
        cadence = Cadence(self.cfg.learner.log_interval_s, self.cfg.learner.checkpoint_interval_s)
        watch = GenerationWatch.for_config(self.cfg, self.node, self.keys.run_id, "learner", stop)  # league.self_reset
        RoleLoop(self.node, self.keys, "learner", self.id, cadence, MetricsWriter(self.run_dir)).run(self, stop)
        if watch is not None:
            watch.finish([self.ckpt_dir])  # a new generation: its learner starts without them
