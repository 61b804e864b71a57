"""``zenrl plot``: learning curves from ``runs/<id>/metrics.jsonl`` (matplotlib, Agg)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from zenrl.common.errors import ZenrlError
from zenrl.common.metrics import read_metrics
from zenrl.tools.loading import need

def plot(run_dir: str | os.PathLike[str], out: str | os.PathLike[str], width: int = 1200, height: int = 800) -> dict[str, Any]:
    """Learning curves of a run as a ``width`` x ``height`` PNG: eval return mean +- std (and win
    rate if logged), learner loss, Q mean, updates/s, transitions trained/s and env steps/s if present,
    against wall-clock minutes since the run's first record. A resumed run's curves break where
    it was stopped (no line drawn across the pause). Returns which panels were drawn."""
    matplotlib = need("matplotlib", "zenrl plot")
    matplotlib.use("Agg")
    plt = need("matplotlib.pyplot", "zenrl plot")
    run = Path(run_dir)
    mpath = run / "metrics.jsonl" if run.is_dir() else run
    if not mpath.is_file():
        raise ZenrlError(f"no metrics file at {str(mpath)!r}")
    recs = read_metrics(mpath)
    if not recs:
        raise ZenrlError(f"{str(mpath)!r} holds no metrics yet")
    t0 = min(r.get("time", 0.0) for r in recs)
    breaks = _segment_starts(run if run.is_dir() else run.parent)

    def series(source: str | None, key: str) -> tuple[np.ndarray, np.ndarray]:
        pts = [(r["time"], r[key]) for r in recs
               if (source is None or r.get("source") == source) and isinstance(r.get(key), (int, float))]
        if not pts:
            return np.zeros(0), np.zeros(0)
        a = _break_gaps(np.asarray(pts, np.float64), breaks)
        return (a[:, 0] - t0) / 60.0, a[:, 1]

    panels: list[tuple[str, list[tuple[str, str | None, str]]]] = [
        ("eval return", [("return_mean", "eval", "mean")]),
        ("win rate", [("win_rate", None, "win rate")]),
        ("learner loss", [("loss", "learner", "loss")]),
        ("Q mean", [("q_mean", "learner", "q")]),
        ("updates/s", [("updates_per_s", None, "updates/s")]),
        ("transitions trained/s", [("transitions_per_s", "learner", "learner")]),
        ("env steps/s", [("env_steps_per_s", None, "env steps/s")]),
    ]
    drawn = [(title, curves) for title, curves in panels if any(series(s, k)[0].size for k, s, _ in curves)]
    if not drawn:
        raise ZenrlError(f"{str(mpath)!r} has none of the plotted metrics")
    dpi = 100
    ncol = 2 if len(drawn) > 1 else 1
    nrow = math.ceil(len(drawn) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(width / dpi, height / dpi), dpi=dpi, squeeze=False)
    for ax, (title, curves) in zip(axes.flat, drawn):
        for key, source, label in curves:
            x, y = series(source, key)
            if not x.size:
                continue
            ax.plot(x, y, label=label, lw=1.2)
            if key == "return_mean":
                _, sd = series(source, "return_std")
                if sd.size == y.size:
                    ax.fill_between(x, y - sd, y + sd, alpha=0.25, label="+- std")
        ax.set_title(title)
        ax.set_xlabel("minutes")
        ax.grid(alpha=0.3)
        if title == "learner loss":
            ax.set_yscale("log")
        ax.legend(loc="best", fontsize=8)
    for ax in list(axes.flat)[len(drawn):]:
        ax.axis("off")
    fig.suptitle(run.name if run.is_dir() else run.parent.name)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)  # no bbox_inches: the PNG is exactly width x height
    plt.close(fig)
    return {"out": str(out), "panels": [t for t, _ in drawn], "records": len(recs)}



#: a pause in a series longer than this many times its median interval (and over a minute) is
#: drawn as a gap: the run was stopped and resumed there
GAP_FACTOR = 10.0
MIN_GAP_S = 60.0


def _segment_starts(run_dir: Path) -> list[float]:
    """Wall-clock start times of a resumed run's later segments (``summary.json``), if known."""
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return []
    segs = summary.get("segments") if isinstance(summary, dict) else None
    if not isinstance(segs, list):
        return []
    return [float(s["started_at"]) for s in segs[1:] if isinstance(s, dict) and isinstance(s.get("started_at"), (int, float))]


def _break_gaps(pts: np.ndarray, breaks: list[float]) -> np.ndarray:
    """``pts`` float64[N, 2] of (time, value) sorted by time, with a (NaN, NaN) row inserted
    wherever a segment of the run starts or the series pauses far longer than usual, so that
    matplotlib leaves a gap there."""
    pts = pts[np.argsort(pts[:, 0], kind="stable")]
    if len(pts) < 2:
        return pts
    t = pts[:, 0]
    dt = np.diff(t)
    cut = dt > max(MIN_GAP_S, GAP_FACTOR * float(np.median(dt)))
    for b in breaks:
        cut |= (t[:-1] < b) & (t[1:] >= b)
    idx = np.flatnonzero(cut) + 1
    return np.insert(pts, idx, np.nan, axis=0)
