"""The files ``zenrl run`` keeps in ``runs/<run-id>/`` besides the processes' own:
``launcher.json`` (where a running launcher's router listens, for ``zenrl status runs/<id>``)
and ``summary.json`` (how the run went, over every segment of a resumed run)."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

LAUNCHER_FILE = "launcher.json"
SUMMARY_FILE = "summary.json"

_ERROR_LINE = re.compile(r"^(zenrl: error: |[A-Za-z_][\w.]*(Error|Exception|Exit)\b)|\s(ERROR|CRITICAL)\s")


def write_json_atomic(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=float))
    os.replace(tmp, path)


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
