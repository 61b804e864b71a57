"""The registry of algorithms: each one a set of explicit parts, one entry in :data:`ALGORITHMS`.

An algorithm is its network class (``common/networks.py``), its learner (a
:class:`~zenrl.learner.base.LearnerBase` in ``learner/``), its actor's entry function (in
``actor/``), its checkpoint schema (a :class:`~zenrl.common.checkpoints.TrainingState`
subclass in ``common/checkpoints.py``) and two facts the launcher plans with. Adding one means
its own modules plus one entry here (and its schema in
:data:`~zenrl.common.checkpoints.TRAINING_STATES`, which ``common/`` reads by name).

This module may import every role package (the roles import only ``common/``): the process
entry points (:mod:`zenrl.processes`), the launcher and the tools ask it instead of branching on
``algo``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from zenrl.actor.a3c import run_a3c_worker
from zenrl.actor.impala import run_impala_actor
from zenrl.actor.r2d2 import run_r2d2_actor
from zenrl.actor.service import run_apex_actor
from zenrl.common.checkpoints import (A3CTrainingState, ApexTrainingState, ImpalaTrainingState, R2D2TrainingState,
                                      TrainingState)
from zenrl.common.config import RunConfig
from zenrl.common.networks import ActorCritic, QNetwork
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.learner.a3c import A3CLearner
from zenrl.learner.apex import ApexLearner
from zenrl.learner.base import LearnerBase
from zenrl.learner.impala import ImpalaLearner
from zenrl.learner.r2d2 import R2D2Learner


class ActorMain(Protocol):
    """An actor process's loop: ``(cfg, node, run_id, actor_id, slot, num_slots, stop)``;
    ``num_slots`` None when the slot was claimed from the running system (elastic)."""

    def __call__(self, cfg: RunConfig, node: Any, run_id: str, actor_id: str, slot: int, num_slots: int | None,
                 stop: threading.Event) -> None: ...


@dataclass(frozen=True)
class Algorithm:
    """The parts of one algorithm family."""

    name: str
    #: the policy network: ``network(spec, n_actions, NetworkConfig)``
    network: type[torch.nn.Module]
    #: the learner process's worker: ``learner(cfg, node, run_id, resume)``
    learner: type[LearnerBase]
    #: the actor process's loop
    actor: ActorMain
    #: what its checkpoints hold
    checkpoint: type[TrainingState]
    #: whether the run has a replay service (Ape-X), or actors send to the learner (A3C, IMPALA)
    uses_replay: bool
    #: whether ``zenrl run`` may give the learner a CPU of its own (``cpu_placement: auto``)
    places_learner: bool


APEX = Algorithm("apex", network=QNetwork, learner=ApexLearner, actor=run_apex_actor, checkpoint=ApexTrainingState,
                 uses_replay=True, places_learner=True)
A3C = Algorithm("a3c", network=ActorCritic, learner=A3CLearner, actor=run_a3c_worker, checkpoint=A3CTrainingState,
                uses_replay=False, places_learner=False)
IMPALA = Algorithm("impala", network=ActorCritic, learner=ImpalaLearner, actor=run_impala_actor,
                   checkpoint=ImpalaTrainingState, uses_replay=False, places_learner=True)
R2D2 = Algorithm("r2d2", network=RecurrentQNetwork, learner=R2D2Learner, actor=run_r2d2_actor,
                 checkpoint=R2D2TrainingState, uses_replay=True, places_learner=True)

#: every algorithm, by ``RunConfig.algo``
ALGORITHMS: dict[str, Algorithm] = {a.name: a for a in (APEX, A3C, IMPALA, R2D2)}


def algorithm(name: str) -> Algorithm:
    """The algorithm called ``name`` (``RunConfig.algo`` is validated to be one of them)."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; one of {sorted(ALGORITHMS)}") from None
