"""The exception hierarchy of zenrl, in one place."""


class ZenrlError(Exception):
    """Base class of every error zenrl raises on purpose."""


class ConfigError(ZenrlError, ValueError):
    """A configuration value is invalid; the message names the option and the value."""


class RunningConfigError(ConfigError):
    """A configuration error found while a role runs (not at its start) that every later unit
    of work would meet again: the role stops on it as on a configuration error found at start
    (exit code 2, not restarted), and the message names what to change."""


class EnvOutputError(RunningConfigError):
    """An env gave what every later step would give again and the run cannot use (a reward that
    is not one number, a reward beyond the run's bound)."""


class MemoryTooSmall(RunningConfigError):
    """The replay's storage, sized once its first chunk shows the item size, needs more memory
    than the process may have (the machine's, or its container's limit)."""


class ProtocolError(ZenrlError, ValueError):
    """A wire message is malformed. ``field`` names what was wrong, ``reason`` is a short
    machine-readable tag used to count rejections (e.g. ``"version"``, ``"dtype"``)."""

    def __init__(self, field: str, message: str, reason: str = "invalid") -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.reason = reason


class SpecMismatch(ZenrlError, ValueError):
    """A batch does not match the spec of the storage or network it is meant for."""


class TransportError(ZenrlError):
    """Zenoh could not be reached or a remote call failed."""


class RemoteTimeout(TransportError):
    """A remote call got no answer before its timeout."""


class NotReady(ZenrlError):
    """The replay service is not ready to serve samples (too few items, or rate limited).
    ``mass`` and ``size``: the replay's priority mass and size its not-ready reply reported
    (None when unknown)."""

    def __init__(self, *args: object, mass: float | None = None, size: int | None = None) -> None:
        super().__init__(*args)
        self.mass = mass
        self.size = size


class CheckpointError(ZenrlError):
    """A checkpoint is missing, corrupt, or incompatible with the current configuration."""
