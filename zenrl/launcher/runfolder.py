"""The files ``zenrl run`` keeps in ``runs/<run-id>/`` besides the processes' own:
``launcher.json`` (where a running launcher's router listens, for ``zenrl status runs/<id>``),
``summary.json`` (how the run went, over every segment of a resumed run) and ``.lock`` (held by
the running launcher, so that no second one writes the same folder)."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

from zenrl.common.atomic_files import write_bytes_atomically
from zenrl.common.errors import ConfigError

try:
    import fcntl
except ImportError:  # not POSIX: no run-folder lock
    fcntl = None  # type: ignore[assignment]

LAUNCHER_FILE = "launcher.json"
SUMMARY_FILE = "summary.json"
LOCK_FILE = ".lock"

_ERROR_LINE = re.compile(r"^(zenrl: error: |[A-Za-z_][\w.]*(Error|Exception|Exit)\b)|\s(ERROR|CRITICAL)\s")


def write_json_atomic(path: Path, obj: Any) -> None:
    """``obj`` as JSON through :func:`~zenrl.common.atomic_files.write_bytes_atomically`: a
    reader sees the old file or the new one whole; a failed write (a full disk) leaves no temp."""
    write_bytes_atomically(path, json.dumps(obj, indent=2, default=float).encode())


def write_launcher_info(run_dir: Path, run_id: str, router: str) -> None:
    import time

    write_json_atomic(run_dir / LAUNCHER_FILE, {"run_id": run_id, "router": router, "pid": os.getpid(),
                                                "started_at": time.time()})


def read_launcher_info(run_dir: Path) -> dict[str, Any] | None:
    """``launcher.json`` of a running ``zenrl run`` (None if absent or unreadable)."""
    try:
        info = json.loads((run_dir / LAUNCHER_FILE).read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and isinstance(info.get("router"), str) else None


def remove_launcher_info(run_dir: Path) -> None:
    try:
        (run_dir / LAUNCHER_FILE).unlink()
    except FileNotFoundError:
        pass


def lock_run_folder(run_dir: Path) -> int | None:
    """Take ``run_dir``'s lock for this launch (created if need be): an ``flock`` on its
    ``.lock``, which the OS lets go however the process ends (no stale lock after a crash or
    SIGKILL). Returns the descriptor to close when the launch is over (None where there is no
    ``flock``). Raises ConfigError when another process holds it: a second ``zenrl run`` on the
    same folder (``--resume`` of a run that is still running, or the same ``--run-id``) would
    write the same checkpoints, logs and summary as the first; and when the folder cannot be
    made or written."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        if fcntl is None:
            return None
        fd = os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:  # runs_dir under a file, read-only, not ours, ...
        raise ConfigError(f"cannot use the run folder {run_dir} (runs_dir {str(run_dir.parent)!r}): "
                          f"{e.strerror or e}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        info = read_launcher_info(run_dir) or {}
        who = f" (launcher pid {info['pid']})" if isinstance(info.get("pid"), int) else ""
        raise ConfigError(f"run folder {run_dir} is in use by another zenrl run{who}: stop that one first "
                          f"(zenrl status {run_dir} shows it)") from None
    return fd


def unlock_run_folder(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)


def holds_a_run(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a run already (its launcher wrote ``config.yaml`` there)."""
    return (run_dir / "config.yaml").is_file()


def read_summary(run_dir: Path) -> dict[str, Any] | None:
    try:
        s = json.loads((run_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    return s if isinstance(s, dict) else None


def earlier_segments(summary: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The segments an earlier ``summary.json`` describes (a summary written before segments were
    recorded counts as one)."""
    if not summary:
        return []
    segs = summary.get("segments")
    if isinstance(segs, list):
        return [s for s in segs if isinstance(s, dict)]
    return [{"wall_s": float(summary.get("wall_s") or 0.0), "env_steps": int(summary.get("env_steps") or 0),
             "stop_reason": summary.get("stop_reason", ""), "startup_s": summary.get("startup_s")}]


def last_error_line(log_path: Path | None, tail_bytes: int = 65536) -> str | None:
    """The last line of a process log that reads as an error (an exception, ``zenrl: error:``, an
    ERROR record), else its last non-empty line; None without a log."""
    if log_path is None:
        return None
    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, os.path.getsize(log_path) - tail_bytes))
            lines = [x.strip() for x in f.read().decode(errors="replace").splitlines() if x.strip()]
    except OSError:
        return None
    if not lines:
        return None
    line = next((x for x in reversed(lines) if _ERROR_LINE.search(x)), lines[-1])
    line = line.removeprefix("zenrl: error: ")
    return line if len(line) <= 400 else line[:397] + "..."
