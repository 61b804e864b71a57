"""The checkpoint files of a run, read by the learner (to resume) and by every tool (evaluate,
play, export, self-play snapshots): one training-state dict per ``ckpt-<updates>.pt``, loaded
with ``torch.load(..., weights_only=True)`` so that a file from elsewhere cannot run code.
Writing them is the learner's (:mod:`zenrl.learner.checkpoint`)."""

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


def checkpoint_name(step: int) -> str:
    """The file name of the checkpoint written at ``step`` updates (sorts by step)."""
    return f"ckpt-{int(step):012d}.pt"


def list_checkpoints(directory: str | os.PathLike[str]) -> list[Path]:
    """``ckpt-<updates>.pt`` files in ``directory``, oldest first (empty if none or no folder)."""
    d = Path(directory)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if _NAME.match(p.name))


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The training-state dict of ``path`` (tensors on the CPU); :class:`CheckpointError` if
    it is missing, unreadable or not a zenrl training state."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist") from None
    except Exception as e:  # torch raises many types for truncated/corrupt archives
        raise CheckpointError(f"checkpoint {str(path)!r} is unreadable: {type(e).__name__}: {e}") from None
    if not isinstance(state, dict) or "format" not in state or "config" not in state:
        raise CheckpointError(f"checkpoint {str(path)!r} is not a zenrl training state")
    return state


def load_latest(directory: str | os.PathLike[str]) -> tuple[dict[str, Any], Path]:
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
