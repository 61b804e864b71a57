"""``zenrl status``: the live processes of a run (liveliness tokens), each with a rate measured
over the seconds it listens (not a running total), its weights version and one detail."""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

from zenrl import strict_json
from zenrl.common import protocol as P

#: (stats field holding a running total, unit) per role: the rate is its change per second
TOTALS = {"actor": ("env_steps", "env steps/s"), "learner": ("updates", "updates/s"),
          "replay": ("inserted_total", "inserts/s"), "league": ("results_total", "results/s")}
#: the rate a process reports itself, used when it was heard only once
OWN_RATE = {"learner": "updates_per_s", "replay": "inserts_per_s"}


def _rate(samples: list[tuple[float, float]]) -> float | None:
    """Change per second between the first and last (time, total) heard; None with fewer than 2."""
    if len(samples) < 2 or samples[-1][0] <= samples[0][0]:
        return None
    (t0, v0), (t1, v1) = samples[0], samples[-1]
    return (v1 - v0) / (t1 - t0)


def last_logged_eval(run_dir: Path | None) -> dict[str, Any] | None:
    """The newest ``eval`` record of ``metrics.jsonl`` (for an evaluator that evaluates less often
    than ``zenrl status`` listens)."""
    if run_dir is None:
        return None
    path = run_dir / "metrics.jsonl"
    try:
        with open(path, "rb") as f:
            f.seek(max(0, path.stat().st_size - 262144))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        if '"eval"' not in line:
            continue
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("source") == "eval" and isinstance(rec.get("return_mean"), (int, float)):
            return rec
    return None


def collect(node: Any, run_id: str, wait_s: float) -> list[dict[str, Any]]:
    """Rows of the live processes of ``run_id``: listen up to ``wait_s`` seconds (less once every
    process was heard twice) to their stats and the evaluator's results."""
    k = P.Keys(run_id)
    lock = threading.Lock()
    stats: dict[str, list[tuple[float, dict[str, Any]]]] = {}
    evals: list[tuple[float, Any]] = []

    def on_stats(key: str, payload: bytes) -> None:
        try:
            m = P.Stats.decode(payload)
        except P.ProtocolError:
            return
        with lock:
            stats.setdefault(f"{m.role}/{m.id}", []).append((float(m.time), dict(m.values)))

    def on_eval(key: str, payload: bytes) -> None:
        try:
            m = P.EvalResult.decode(payload)
        except P.ProtocolError:
            return
        with lock:
            evals.append((time.time(), m))

    node.subscribe(k.stats_all, on_stats)
    node.subscribe(k.eval, on_eval)
    alive = sorted(k.parse_alive(x) for x in node.alive_now(k.alive_all))
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        with lock:
            heard = all(len(stats.get(f"{r}/{i}", [])) >= 2 for r, i in alive if r in TOTALS)
        if alive and heard:
            break
        time.sleep(0.1)
    rows = []
    with lock:
        for role, pid in alive:
            seen = stats.get(f"{role}/{pid}", [])
            row: dict[str, Any] = {"role": role, "id": pid, **(seen[-1][1] if seen else {})}
            if role in TOTALS:
                field, unit = TOTALS[role]
                pts = [(t, float(v[field])) for t, v in seen if isinstance(v.get(field), (int, float))]
                row["rate"], row["rate_unit"] = _rate(pts), unit
                if row["rate"] is None and isinstance(row.get(OWN_RATE.get(role, "")), (int, float)):
                    row["rate"] = float(row[OWN_RATE[role]])
            elif role == "evaluator":
                row["rate"] = _rate([(t, float(i)) for i, (t, _) in enumerate(evals)])
                row["rate_unit"] = "evals/s"
                if evals:
                    m = evals[-1][1]
                    row.update({"version": m.version, "eval_return": float(m.returns.mean()),
                                "eval_episodes": int(m.returns.size)})
                    if m.outcomes is not None:
                        row["eval_win_rate"] = float((m.outcomes == 1).mean())
            rows.append(row)
    return rows


def _fmt_rate(r: dict[str, Any]) -> str:
    v = r.get("rate")
    if v is None:
        return "-"
    return f"{v:,.1f} {r.get('rate_unit', '/s')}" if v < 100 else f"{v:,.0f} {r.get('rate_unit', '/s')}"


def _rejections(r: dict[str, Any], top: int = 3) -> str:
    """``; rejected N (top: a 8, b 3); quarantined K: ...`` from a service's stats, or ``""``."""
    n = r.get("rejected_total") or 0
    if not n:
        return ""
    srcs = sorted(((k.split("/", 1)[1], v) for k, v in r.items() if k.startswith("rejected_from/") and isinstance(v, int)),
                  key=lambda kv: -kv[1])[:top]
    out = f"; rejected {n:,}" + (f" (top: {', '.join(f'{s} {c:,}' for s, c in srcs)})" if srcs else "")
    if r.get("quarantined"):
        out += f"; quarantined {r['quarantined']}: {str(r.get('quarantined_sources', ''))[:120]}"
    return out


def _detail(r: dict[str, Any], learner_version: int | None) -> str:
    role = r["role"]
    if role == "replay" and "size" in r:
        size = f"size {r['size']:,} / {r.get('capacity', 0):,}"
        if isinstance(r.get("priority_mass"), (int, float)):
            size += f", priority mass {r['priority_mass']:.4g}"
        if r.get("durable_degraded"):  # ingest goes on in memory; a restart would not restore it all
            size += (f", DURABLE LOG DEGRADED ({r.get('durable_error') or 'disk error'}; "
                     f"{r.get('durable_backlog_items', 0):,} items in memory only)")
        return size + _rejections(r)
    if role == "actor" and learner_version is not None and r.get("policy_version") is not None:
        return f"lag {learner_version - int(r['policy_version'])} versions"
    if role == "league" and "players" in r:
        return f"{r['players']} players, {r.get('snapshots', 0)} snapshots (zenrl league status)"
    if role == "learner" and r.get("policy_lag") is not None:
        shards = sorted(int(k[6:-6]) for k in r if k.startswith("replay") and k.endswith("_items") and k[6:-6].isdigit())
        if not shards:
            return f"policy lag {float(r['policy_lag']):.1f}"
        # a sharded replay: which shards the learner draws from, and how its items split
        items = ", ".join(f"{k}: {int(r.get(f'replay{k}_items') or 0):,}" for k in shards)
        return (f"policy lag {float(r['policy_lag']):.1f}; replay shards up {r.get('replay_shards_up', 0)}/{len(shards)}, "
                f"items drawn {items}")
    if role == "evaluator" and r.get("eval_return") is not None:
        win = f", win rate {r['eval_win_rate']:.0%}" if r.get("eval_win_rate") is not None else ""
        return f"return {r['eval_return']:.1f}{win}" + (" (from metrics.jsonl)" if r.get("eval_from_log") else "")
    return ""


def status(endpoint: str, run_id: str, connect_timeout_s: float = 5.0, client_config: str | None = None,
           run_dir: Path | None = None, as_json: bool = False, wait_s: float = 3.0,
           sub_runs: list[str] | None = None) -> int:
    """Print the live processes of ``run_id`` (table or ``--json``); 1 when none is alive.
    ``sub_runs``: run ids whose processes belong to this run too (a league run's agents,
    ``<run>.<agent>``): their rows carry ``run`` and their ids are prefixed with the agent."""
    from zenrl.common.transport import Node

    with Node(endpoint, connect_timeout_s, config_file=client_config) as node:
        rows = collect(node, run_id, wait_s)
        for sub in sub_runs or []:
            for r in collect(node, sub, wait_s):
                r["run"], r["id"] = sub, f"{sub[len(run_id) + 1:]}:{r['id']}"
                rows.append(r)
    for r in rows:
        if r["role"] == "evaluator" and r.get("eval_return") is None:
            rec = last_logged_eval(run_dir)
            if rec is not None:
                r.update({"eval_return": float(rec["return_mean"]), "eval_from_log": True,
                          **({"eval_win_rate": rec["win_rate"]} if isinstance(rec.get("win_rate"), (int, float)) else {})})
    out = {"run_id": run_id, "router": endpoint, "processes": rows}
    if as_json:
        sys.stdout.write(strict_json.dumps(out, default=float) + "\n")
    elif not rows:
        sys.stderr.write(f"zenrl status: no live process of run {run_id!r} at {endpoint}\n")
    else:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"zenrl run {run_id} ({endpoint})")
        for col in ("role", "id", "rate", "weights", "detail"):
            t.add_column(col, justify="right" if col == "rate" else "left")
        lv = {r.get("run"): r.get("version") for r in rows if r["role"] == "learner"}
        for r in rows:
            weights = r.get("version", r.get("policy_version"))
            t.add_row(r["role"], r["id"], _fmt_rate(r), "-" if weights is None else str(weights),
                      _detail(r, lv.get(r.get("run"))))
        Console().print(t)
    return 0 if rows else 1
