"""zenrl: distributed actor-learner reinforcement learning over Eclipse Zenoh."""

__version__ = "0.1.0"
