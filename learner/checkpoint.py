"""Checkpoints: one training state per file, written atomically (temp file + ``os.replace``),
the newest K kept, loaded with ``torch.load(..., weights_only=True)``; a corrupt or truncated
newest file is reported and skipped for the one before it."""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Any

import torch

from zenrl.common.errors import CheckpointError

log = logging.getLogger(__name__)

_NAME = re.compile(r"^ckpt-(\d{12})\.pt$")


def checkpoint_dir(runs_dir: str | os.PathLike[str], run_id: str) -> Path:
    return Path(runs_dir) / run_id / "checkpoints"


def list_checkpoints(directory: str | os.PathLike[str]) -> list[Path]:
    """Checkpoint files, oldest first."""
    d = Path(directory)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if _NAME.match(p.name))


def save_checkpoint(directory: str | os.PathLike[str], state: dict[str, Any], step: int, keep: int) -> Path:
    """Write ``state`` as ``ckpt-<step>.pt`` atomically and prune to the newest ``keep``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"ckpt-{int(step):012d}.pt"
    tmp = d / f".{path.name}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    for old in list_checkpoints(d)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist") from None
    except Exception as e:  # torch raises many types for truncated/corrupt archives
        raise CheckpointError(f"checkpoint {str(path)!r} is unreadable: {type(e).__name__}: {e}") from None
    if not isinstance(state, dict) or "format" not in state:
        raise CheckpointError(f"checkpoint {str(path)!r} is not a zenrl training state")
    return state


def load_latest(directory: str | os.PathLike[str]) -> tuple[dict[str, Any], Path]:
    """The newest readable checkpoint in ``directory``; raise :class:`CheckpointError` if none."""
    files = list_checkpoints(directory)
    if not files:
        raise CheckpointError(f"no checkpoint in {str(directory)!r}")
    for p in reversed(files):
        try:
            return load_checkpoint(p), p
        except CheckpointError as e:
            log.error("%s; trying the previous one", e)
    raise CheckpointError(f"no readable checkpoint in {str(directory)!r} ({len(files)} corrupt)")


VERSION_MARK = "weights_version"


def write_version_mark(run_dir: str | os.PathLike[str], version: int) -> None:
    """Record the highest weights version published (before publishing it), so a learner
    resumed from an older checkpoint continues above every version actors have seen."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f".{VERSION_MARK}.tmp-{os.getpid()}"
    tmp.write_text(str(int(version)))
    os.replace(tmp, d / VERSION_MARK)


def read_version_mark(run_dir: str | os.PathLike[str]) -> int:
    p = Path(run_dir) / VERSION_MARK
    try:
        return int(p.read_text().strip())
    except (FileNotFoundError, ValueError):
        return 0


class VersionReservation:
    """Versions handed out in blocks recorded in the run's high-water mark file: before a
    version above the reserved one is published, the mark moves to ``version + block`` (one
    small file write per ``block`` versions, not per broadcast). A learner resumed from any
    checkpoint starts at ``max(checkpoint version, mark)``, above every version it published."""

    def __init__(self, run_dir: str | os.PathLike[str], block: int = 1000) -> None:
        if block < 1:
            raise ValueError(f"block must be >= 1, got {block}")
        self.run_dir = Path(run_dir)
        self.block = block
        self.reserved = read_version_mark(self.run_dir)

    def resume_version(self, checkpoint_version: int) -> int:
        """The version to continue from after restoring a checkpoint saved at ``checkpoint_version``."""
        return max(int(checkpoint_version), self.reserved)

    def claim(self, version: int) -> int:
        """Call before publishing ``version``; returns it."""
        if version > self.reserved:
            self.reserved = int(version) + self.block
            write_version_mark(self.run_dir, self.reserved)
        return version
