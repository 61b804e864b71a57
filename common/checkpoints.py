"""The learner's checkpoint files: their one schema, and reading them.

A checkpoint (``runs/<id>/checkpoints/ckpt-<updates>.pt``) holds one :class:`TrainingState`,
stored as a plain dict of tensors, numbers and strings (read with torch's ``weights_only=True``
loader, so that a file from elsewhere cannot run code). Its layout::

    {"format": 1, "algo": "apex" | "a3c" | "impala", # which schema reads the rest
     "arch": str, "version": int, "config": dict,    # every algorithm (TrainingState)
     "torch_rng": uint8 tensor, "saved_at": float,
     ...the algorithm's own fields}                  # ApexTrainingState, A3CTrainingState,
                                                     # ImpalaTrainingState

:class:`TrainingState` holds the fields every learner writes; each algorithm extends it with a
subclass that names its own fields, its policy network class and where in the file the policy's
state dict lives (:attr:`TrainingState.policy_path`). The learners write it
(:meth:`~zenrl.learner.base.LearnerBase.training_state`), and everything that reads a checkpoint
(resume, rollback, ``zenrl evaluate/play/export``, self-play snapshots, tests and benchmarks)
reads it through :func:`read_checkpoint`; nothing builds the dict by hand. The schemas live in
``common/`` because the actors' self-play reader (:mod:`zenrl.common.policy_io`) may not import
``learner/``. Writing files is :mod:`zenrl.learner.checkpoint`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from pathlib import Path
from typing import Any, ClassVar, Mapping

import torch

from zenrl.common.config import NetworkConfig, RunConfig, config_from_dict
from zenrl.common.errors import CheckpointError, ConfigError
from zenrl.common.networks import ActorCritic, QNetwork
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.specs import ArraySpec

log = logging.getLogger(__name__)

_NAME = re.compile(r"^ckpt-(\d{12})\.pt$")

#: the layout version written in ``"format"``; a file of a newer one is refused by name
FORMAT = 1
#: the algorithm of a file that names none (written before ``"algo"`` was recorded)
DEFAULT_ALGO = "apex"


# --------------------------------------------------------------------------------------------
# The schema
# --------------------------------------------------------------------------------------------
#: the checkpoint schema of each algorithm, by ``algo``: every :class:`TrainingState` subclass
#: with an ``algo`` enters it when defined (the registry of whole algorithms,
#: :data:`zenrl.algorithms.ALGORITHMS`, names the same classes; a unit test holds them equal)
TRAINING_STATES: dict[str, type["TrainingState"]] = {}


@dataclasses.dataclass(kw_only=True)
class TrainingState:
    """What every learner's checkpoint holds. Subclasses (one per algorithm) add their fields and
    set the class attributes :attr:`algo`, :attr:`network` and :attr:`policy_path`."""

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        if cls.algo:
            TRAINING_STATES[cls.algo] = cls


    #: the ``"algo"`` the file records (``RunConfig.algo``); a subclass that sets it is
    #: registered in :data:`TRAINING_STATES` by being defined
    algo: ClassVar[str] = ""
    #: the policy network class: what actors act with and tools load the policy into
    network: ClassVar[type[torch.nn.Module]]
    #: the keys leading to the policy's state dict in the file (e.g. ``("learner", "online")``)
    policy_path: ClassVar[tuple[str, ...]] = ()

    #: :func:`~zenrl.common.networks.arch_fingerprint` of the network (resume refuses another)
    arch: str
    #: the weights version last published (a resumed learner continues above it)
    version: int
    #: the resolved run configuration, ``RunConfig.model_dump(mode="json")``
    config: dict[str, Any]
    #: ``torch.get_rng_state()`` when saved (None in files that did not record it)
    torch_rng: torch.Tensor | None = None
    #: ``time.time()`` when saved
    saved_at: float = 0.0

    @property
    def updates(self) -> int:
        """Updates applied when saved (the step in the file name)."""
        raise NotImplementedError

    def run_config(self) -> RunConfig:
        """The run configuration the state was trained with."""
        return config_from_dict(self.config)

    def policy_state(self) -> Mapping[str, torch.Tensor]:
        """The policy network's state dict (at :attr:`policy_path`)."""
        weights: Any = self.to_dict()
        for key in self.policy_path:
            weights = weights.get(key) if isinstance(weights, Mapping) else None
        if not isinstance(weights, Mapping):
            raise CheckpointError(f"{self.algo} checkpoint has no {'.'.join(self.policy_path)} state dict")
        return weights

    @classmethod
    def policy_network(cls, spec: Mapping[str, ArraySpec], n_actions: int, net_cfg: NetworkConfig) -> torch.nn.Module:
        """A new policy network (:attr:`network`) for observations ``spec`` and ``n_actions``."""
        return cls.network(spec, n_actions, net_cfg)

    @classmethod
    def run_policy_network(cls, spec: Mapping[str, ArraySpec], n_actions: int, cfg: RunConfig) -> torch.nn.Module:
        """The policy network of a run configured by ``cfg`` (what the evaluator and the tools
        build): :meth:`policy_network` with ``cfg.network``. An algorithm whose network takes
        options from its own section too (R2D2's LSTM size) overrides this."""
        return cls.policy_network(spec, n_actions, cfg.network)

    # -- the file's dict ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The dict ``torch.save`` writes: ``format``, ``algo`` and every field by name."""
        d: dict[str, Any] = {"format": FORMAT, "algo": self.algo}
        d.update({f.name: getattr(self, f.name) for f in dataclasses.fields(self)})
        return d

    @staticmethod
    def from_dict(d: Any, where: str = "checkpoint") -> "TrainingState":
        """The schema of ``d["algo"]`` filled from ``d``; :class:`CheckpointError` naming what is
        missing or unknown. Keys the schema does not name are ignored (so an older reader takes a
        newer file's extra fields)."""
        if not isinstance(d, Mapping) or "format" not in d or "config" not in d:
            raise CheckpointError(f"{where} is not a zenrl training state")
        if not isinstance(d["format"], int) or d["format"] > FORMAT:
            raise CheckpointError(f"{where} has format {d['format']!r}; this zenrl reads format {FORMAT} and older")
        schema = training_state_class(d.get("algo", DEFAULT_ALGO), where)
        names = {f.name: f for f in dataclasses.fields(schema)}
        missing = [n for n, f in names.items() if n not in d and f.default is dataclasses.MISSING
                   and f.default_factory is dataclasses.MISSING]
        if missing:
            raise CheckpointError(f"{where} ({schema.algo}) lacks {', '.join(missing)}")
        return schema(**{n: d[n] for n in names if n in d})


@dataclasses.dataclass(kw_only=True)
class ApexTrainingState(TrainingState):
    """Ape-X DQN: the learner's state (online and target Q networks, optimizer, updates) and the
    transitions trained on."""

    algo: ClassVar[str] = "apex"
    network: ClassVar[type[torch.nn.Module]] = QNetwork
    policy_path: ClassVar[tuple[str, ...]] = ("learner", "online")

    #: ``DQNLearner.state_dict()``: ``online``, ``target``, ``optimizer``, ``updates``
    learner: dict[str, Any]
    transitions_consumed: int = 0

    @property
    def updates(self) -> int:
        return int(self.learner.get("updates", 0))


@dataclasses.dataclass(kw_only=True)
class A3CTrainingState(TrainingState):
    """A3C: the shared actor-critic, its optimizer, the gradients applied and the env steps they
    came from."""

    algo: ClassVar[str] = "a3c"
    network: ClassVar[type[torch.nn.Module]] = ActorCritic
    policy_path: ClassVar[tuple[str, ...]] = ("model",)

    model: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    #: gradients applied (a field of its own here, not inside a learner dict)
    updates: int = 0  # type: ignore[assignment]  # a stored field where the base has a property
    env_steps_trained: int = 0


@dataclasses.dataclass(kw_only=True)
class R2D2TrainingState(TrainingState):
    """R2D2: the learner's state (online and target recurrent Q networks, optimizer, updates) and
    the sequences trained on. Its policy is a :class:`~zenrl.common.recurrent.RecurrentQNetwork`
    whose LSTM size is the run's ``r2d2.lstm_size``."""

    algo: ClassVar[str] = "r2d2"
    network: ClassVar[type[torch.nn.Module]] = RecurrentQNetwork
    policy_path: ClassVar[tuple[str, ...]] = ("learner", "online")

    #: ``R2D2Core.state_dict()`` (learner/r2d2.py): ``online``, ``target``, ``optimizer``, ``updates``
    learner: dict[str, Any]
    sequences_consumed: int = 0

    @property
    def updates(self) -> int:
        return int(self.learner.get("updates", 0))

    @classmethod
    def policy_network(cls, spec: Mapping[str, ArraySpec], n_actions: int, net_cfg: NetworkConfig,
                       lstm_size: int | None = None) -> torch.nn.Module:
        """``lstm_size`` None: the network's default size; a run's network is
        :meth:`run_policy_network`'s (``r2d2.lstm_size``)."""
        if lstm_size is None:
            return RecurrentQNetwork(spec, n_actions, net_cfg)
        return RecurrentQNetwork(spec, n_actions, net_cfg, lstm_size)

    @classmethod
    def run_policy_network(cls, spec: Mapping[str, ArraySpec], n_actions: int, cfg: RunConfig) -> torch.nn.Module:
        return cls.policy_network(spec, n_actions, cfg.network, cfg.r2d2.lstm_size)


@dataclasses.dataclass(kw_only=True)
class ImpalaTrainingState(TrainingState):
    """IMPALA / APPO: the learner's actor-critic, its optimizer, the updates made and the env
    steps (T * B per update) they trained on."""

    algo: ClassVar[str] = "impala"
    network: ClassVar[type[torch.nn.Module]] = ActorCritic
    policy_path: ClassVar[tuple[str, ...]] = ("model",)

    model: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    updates: int = 0  # type: ignore[assignment]  # a stored field where the base has a property
    env_steps_trained: int = 0




def training_state_class(algo: str, where: str = "checkpoint") -> type[TrainingState]:
    """The schema of ``algo``; :class:`CheckpointError` for one this zenrl does not know."""
    try:
        return TRAINING_STATES[algo]
    except (KeyError, TypeError):
        raise CheckpointError(f"{where} is of unknown algorithm {algo!r}; one of {sorted(TRAINING_STATES)}") from None


def weights_cap(cfg: RunConfig) -> int:
    """The largest weights message the run can carry: ``transport.max_message_bytes`` (a learner's
    broadcast and every reply to a weights query), and with a league ``league.max_weights_bytes``
    (the snapshots it serves)."""
    cap = cfg.transport.max_message_bytes
    return min(cap, cfg.league.max_weights_bytes) if cfg.league.enabled else cap


def check_weights_fit(cfg: RunConfig, spec: Mapping[str, ArraySpec], n_actions: int) -> None:
    """:class:`ConfigError` when the run's policy network (``spec``, ``n_actions``) has more
    parameter bytes than one weights message may carry (:func:`weights_cap`). The network is
    built on torch's meta device: its size is known without allocating it (a network too large for
    the machine is refused here, not by the allocator). Without the check, the learner failed on
    its first broadcast and was restarted until the run gave up, and actors never got weights."""
    try:
        with torch.device("meta"):
            net = training_state_class(cfg.algo).run_policy_network(spec, n_actions, cfg)
    except Exception:  # noqa: BLE001 - a network that cannot be built is the learner's to report
        return
    n = sum(p.numel() for p in net.parameters())
    nbytes = sum(p.numel() * p.element_size() for p in net.parameters())
    cap = weights_cap(cfg)
    if nbytes > cap:
        which = "transport.max_message_bytes" + (" / league.max_weights_bytes" if cfg.league.enabled else "")
        raise ConfigError(f"network.hidden = {list(cfg.network.hidden)}: the {cfg.algo} network has {n:,} parameters "
                          f"({nbytes / 2**20:,.1f} MiB), more than one weights message may carry ({which} = "
                          f"{cap / 2**20:,.1f} MiB): lower network.hidden, or raise {which.split(' ')[0]}")


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------
def checkpoint_name(step: int) -> str:
    """The file name of the checkpoint written at ``step`` updates (sorts by step)."""
    return f"ckpt-{int(step):012d}.pt"


def checkpoint_step(path: str | os.PathLike[str]) -> int | None:
    """The updates a checkpoint file's name records (``ckpt-<updates>.pt``), None for another name."""
    m = _NAME.match(Path(path).name)
    return int(m.group(1)) if m else None


def list_checkpoints(directory: str | os.PathLike[str]) -> list[Path]:
    """``ckpt-<updates>.pt`` files in ``directory``, oldest first (empty if none or no folder)."""
    d = Path(directory)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if _NAME.match(p.name))


def read_checkpoint(path: str | os.PathLike[str]) -> TrainingState:
    """The training state in ``path`` (tensors on the CPU); :class:`CheckpointError` if it is
    missing, unreadable or not a zenrl training state."""
    try:
        d = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist") from None
    except Exception as e:  # torch raises many types for truncated/corrupt archives
        if not _is_zip(path):  # torch's own error for these says nothing useful ("list index out of range")
            raise CheckpointError(f"checkpoint {str(path)!r} is not a PyTorch checkpoint "
                                  "(torch.save writes a zip archive; this file is not one)") from None
        raise CheckpointError(f"checkpoint {str(path)!r} is unreadable: {type(e).__name__}: {e}") from None
    return TrainingState.from_dict(d, f"checkpoint {str(path)!r}")


def _is_zip(path: str | os.PathLike[str]) -> bool:
    """The file starts as a zip archive does (a truncated one too: only its end is missing)."""
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"PK\x03\x04"
    except OSError:
        return False


def load_latest(directory: str | os.PathLike[str]) -> tuple[TrainingState, Path]:
    """The newest readable checkpoint in ``directory`` and its path; a corrupt newer file is
    reported and skipped. :class:`CheckpointError` if there is none."""
    files = list_checkpoints(directory)
    if not files:
        raise CheckpointError(f"no checkpoint in {str(directory)!r}")
    for p in reversed(files):
        try:
            return read_checkpoint(p), p
        except CheckpointError as e:
            log.error("%s; trying the previous one", e)
    raise CheckpointError(f"no readable checkpoint in {str(directory)!r} ({len(files)} corrupt)")
