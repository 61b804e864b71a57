"""zenrl: distributed actor-learner reinforcement learning over Eclipse Zenoh."""

__version__ = "0.1.0"

#: exit status of a role process stopped by its configuration (sysexits' EX_CONFIG): ``zenrl run``
#: does not restart such a child, which would fail the same way
EXIT_CONFIG = 78
