"""Writing checkpoints: one :class:`~zenrl.common.checkpoints.TrainingState` per file, written
atomically and durably (temp file, fsync, ``os.replace``, fsync of the folder, so a power cut
leaves either the old set or the new file, never a name pointing at nothing), the newest K kept;
temp files a killed write left behind are removed when a learner starts
(:func:`remove_stale_temp_files`); and the weights-version high-water mark, written the same way. The schema and reading (the newest readable one, a corrupt newest file skipped) are
:mod:`zenrl.common.checkpoints`."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import torch

from zenrl.common.atomic_files import fsync_dir, remove_stale_temp_files, write_atomically
from zenrl.common.checkpoints import TrainingState, checkpoint_name, list_checkpoints, load_latest, read_checkpoint

__all__ = ["TrainingState", "checkpoint_dir", "list_checkpoints", "load_latest", "read_checkpoint", "save_checkpoint",
           "VersionReservation", "read_version_mark", "remove_stale_temp_files", "write_version_mark"]

log = logging.getLogger(__name__)


def checkpoint_dir(runs_dir: str | os.PathLike[str], run_id: str) -> Path:
    return Path(runs_dir) / run_id / "checkpoints"


def save_checkpoint(directory: str | os.PathLike[str], state: TrainingState, keep: int) -> Path:
    """Write ``state`` as ``ckpt-<state.updates>.pt`` atomically and prune to the newest ``keep``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    path = d / checkpoint_name(state.updates)
    write_atomically(path, lambda f: torch.save(state.to_dict(), f))
    old = list_checkpoints(d)[:-keep]
    for p in old:
        p.unlink(missing_ok=True)
    if old:
        fsync_dir(d)
    return path


VERSION_MARK = "weights_version"
#: seconds between tries to write a version mark that failed (a full disk)
MARK_RETRY_S = 5.0


def write_version_mark(run_dir: str | os.PathLike[str], version: int) -> None:
    """Record the highest weights version published (before publishing it), so a learner
    resumed from an older checkpoint continues above every version actors have seen."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    write_atomically(d / VERSION_MARK, lambda f: f.write(str(int(version)).encode()))


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
        self.mark_errors = 0
        self._retry_at = 0.0

    def resume_version(self, checkpoint_version: int) -> int:
        """The version to continue from after restoring a checkpoint saved at ``checkpoint_version``."""
        return max(int(checkpoint_version), self.reserved)

    def claim(self, version: int) -> int:
        """Call before publishing ``version``; returns it. A mark that cannot be written (a full
        disk) does not stop publishing: the error is logged and counted (``mark_errors``) and the
        write retried at the next claim at most every :data:`MARK_RETRY_S`; until it succeeds a
        learner resumed from an older checkpoint may start below versions already published."""
        if version > self.reserved and time.monotonic() >= self._retry_at:
            want = int(version) + self.block
            try:
                write_version_mark(self.run_dir, want)
            except OSError as e:
                self.mark_errors += 1
                self._retry_at = time.monotonic() + MARK_RETRY_S
                log.error("cannot record weights version %d in %s (%s); publishing anyway, retrying in %g s",
                          want, self.run_dir / VERSION_MARK, e, MARK_RETRY_S)
                return version
            self.reserved = want
        return version
