"""Durable file writes shared by every role that keeps state on disk (the learner's checkpoints
and version mark, the replay's priority snapshot and log segments, the league's state).

A write goes to a temp file beside its target (``.<name>.tmp-<pid>``), is fsynced, moved over the
target with ``os.replace`` and the folder is fsynced, so a power cut leaves either the old file or
the new one, never a name pointing at nothing; a failed write (a full disk) leaves no temp file,
and :func:`remove_stale_temp_files` removes those of writes that were killed before their rename.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO, Callable


def fsync_dir(directory: str | os.PathLike[str]) -> None:
    """fsync a directory, so that a file created, renamed or removed in it survives a power cut."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomically(path: str | os.PathLike[str], write: Callable[[IO[bytes]], object]) -> None:
    """``write(f)`` into a temp file beside ``path``, fsync it, rename it over ``path``, fsync the
    folder (created if missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # a failed write (a full disk) leaves no partial temp file
    fsync_dir(path.parent)


def write_bytes_atomically(path: str | os.PathLike[str], data: bytes) -> None:
    """:func:`write_atomically` of ``data``."""
    write_atomically(path, lambda f: f.write(data))


def remove_stale_temp_files(directory: str | os.PathLike[str]) -> list[Path]:
    """Delete the ``.<name>.tmp-<pid>`` files of writes that were killed before their rename
    (they are never read, and a crash loop would otherwise fill the disk with them). Returns them."""
    d = Path(directory)
    if not d.is_dir():
        return []
    stale = [p for p in d.iterdir() if p.name.startswith(".") and ".tmp-" in p.name and p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale
