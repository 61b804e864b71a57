"""What ``common/`` and the actors know of an algorithm by its name (``RunConfig.algo``): its
checkpoint schema, which names its policy network (:data:`~zenrl.common.checkpoints.TRAINING_STATES`).

The registry of whole algorithms (network, learner, actor, checkpoint schema, whether the run
has a replay) is :data:`zenrl.algorithms.ALGORITHMS`: it imports every role package, which
``common/`` and the roles may not.
"""

from __future__ import annotations

from zenrl.common.checkpoints import TRAINING_STATES, TrainingState

__all__ = ["TRAINING_STATES", "algorithm"]


def algorithm(name: str) -> type[TrainingState]:
    """The checkpoint schema of algorithm ``name``; its ``policy_network(spec, n_actions,
    net_cfg)`` builds the network the algorithm acts with. :class:`ValueError` for an unknown name."""
    try:
        return TRAINING_STATES[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; one of {sorted(TRAINING_STATES)}") from None
