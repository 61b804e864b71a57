"""The registry of algorithms (zenrl/algorithms.py): each entry's parts fit together, and what
common/ reads by an algorithm's name (its checkpoint schema and policy network) is the entry's."""

import pytest

from zenrl.algorithms import ALGORITHMS, algorithm
from zenrl.common.checkpoints import TRAINING_STATES, training_state_class
from zenrl.common.errors import CheckpointError
from zenrl.common.config import RunConfig
from zenrl.learner.base import LearnerBase


def test_every_configurable_algorithm_has_an_entry():
    names = set(RunConfig.model_fields["algo"].annotation.__args__)
    assert set(ALGORITHMS) == names == set(TRAINING_STATES)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_an_entrys_parts_agree_with_what_common_reads(name):
    a = algorithm(name)
    assert a.name == name and a.checkpoint.algo == name
    assert TRAINING_STATES[name] is a.checkpoint and training_state_class(name) is a.checkpoint
    assert a.checkpoint.network is a.network  # tools and self-play build the network the learner trains
    assert issubclass(a.learner, LearnerBase) and a.learner.schema is a.checkpoint
    assert callable(a.actor)


def test_unknown_algorithm_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown algorithm 'ppo'"):
        algorithm("ppo")
    with pytest.raises(CheckpointError, match="unknown algorithm 'ppo'"):
        training_state_class("ppo")
