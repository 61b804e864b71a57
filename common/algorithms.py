"""The algorithm families, each one object the roles ask instead of branching on ``algo``.

Parts are named as "module:attribute" and resolved when asked for, so that ``common/`` imports
no role package (``actor/``, ``learner/`` and ``replay/`` stay independent of each other) and
the launcher need not import torch to plan a run.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable



@dataclass(frozen=True)
class Algorithm:
    """What the processes of a run need to know about its algorithm family."""

    name: str
    #: "module:class" of the network actors act with and checkpoints hold the policy of
    policy_net: str
    #: where a checkpoint keeps the policy network's state dict (keys into the training state)
    policy_state: tuple[str, ...]
    #: whether the run has a replay service (Ape-X) or workers push gradients (A3C)
    uses_replay: bool
    #: whether ``zenrl run`` may give the learner a CPU of its own (cpu_placement: auto)
    places_learner: bool
    #: "module:attribute" of the learner (a LearnerBase subclass) and of the actor's main loop
    learner: str
    actor: str

    def policy_network(self, spec: Any, n_actions: int, net_cfg: Any) -> Any:
        """A new policy network (``torch.nn.Module``) for observations ``spec`` and ``n_actions``."""
        return _resolve(self.policy_net)(spec, n_actions, net_cfg)

    def learner_class(self) -> Any:
        return _resolve(self.learner)

    def actor_main(self) -> Callable[..., None]:
        return _resolve(self.actor)


def _resolve(path: str) -> Any:
    module, attr = path.split(":")
    return getattr(importlib.import_module(module), attr)


APEX = Algorithm("apex", "zenrl.common.networks:QNetwork", ("learner", "online"), uses_replay=True, places_learner=True,
                 learner="zenrl.learner.service:ApexLearnerService", actor="zenrl.actor.service:run_apex_actor")
A3C = Algorithm("a3c", "zenrl.common.networks:ActorCritic", ("model",), uses_replay=False, places_learner=False,
                learner="zenrl.learner.a3c:A3CLearnerService", actor="zenrl.actor.a3c:run_a3c_worker")
ALGORITHMS = {a.name: a for a in (APEX, A3C)}


def algorithm(name: str) -> Algorithm:
    """The family called ``name`` (``RunConfig.algo`` is validated to be one of them)."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; one of {sorted(ALGORITHMS)}") from None
