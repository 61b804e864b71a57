"""Cost of monitoring a run: the learner's updates/s with `zenrl exporter` on (and scraped
every second, as Prometheus would) vs off, same config, same machine, rounds interleaved
(off, on, on, off, ...) so that a drift in the machine's load hits both alike.

Each round is one ``zenrl run --config configs/cartpole_apex.yaml`` (no target: it runs for
``--round-s`` seconds); its updates/s come from the learner's records in
``runs/<id>/metrics.jsonl`` after ``--warmup-s`` seconds (start-up and the replay filling up
excluded): (last updates - first updates) / (last time - first time).

Reported (the last stdout line is one JSON object; progress goes to stderr):
``ratio_on_off``: median updates/s with the exporter / median without (the issue's bar:
>= 0.98); ``updates_per_s_on``/``_off`` (medians) and every round; ``scrapes``: successful
scrapes of the exporter over the "on" rounds.

    python bench/exporter_cost.py                    # 3 rounds each (~5 minutes)
    python bench/exporter_cost.py --quick            # 1 round each, short
    python bench/exporter_cost.py --dry-run          # print the plan, start nothing
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
import uuid
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, Procs, emit, log, machine_info, record_error, stop_on_sigterm  # noqa: E402

TARGET_RATIO = 0.98


def free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_argv(run_id: str, runs_dir: Path, round_s: float, exporter_port: int | None) -> list[str]:
    argv = ["-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml", "--run-id", run_id, "--no-progress",
            "--set", f"runs_dir={runs_dir}", "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]",
            "--set", "target_return=null", "--set", f"max_wall_s={round_s}", "--set", "learner.log_interval_s=1"]
    if exporter_port is not None:
        argv += ["--exporter-port", str(exporter_port)]
    return argv


def updates_rate(metrics: Path, warmup_s: float) -> dict[str, Any]:
    """Updates/s from the learner's metrics.jsonl records after ``warmup_s`` (from the first)."""
    pts: list[tuple[float, float]] = []
    for line in metrics.read_text().splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("source") == "learner" and isinstance(rec.get("updates"), (int, float)):
            pts.append((float(rec["time"]), float(rec["updates"])))
    if not pts:
        raise RuntimeError(f"no learner records in {metrics}")
    t0 = pts[0][0] + warmup_s
    window = [p for p in pts if p[0] >= t0]
    if len(window) < 2 or window[-1][0] <= window[0][0]:
        raise RuntimeError(f"fewer than 2 learner records after the {warmup_s} s warm-up in {metrics}")
    (ta, ua), (tb, ub) = window[0], window[-1]
    return {"updates_per_s": (ub - ua) / (tb - ta), "window_s": tb - ta, "updates": ub}


def one_round(tmp: Path, on: bool, round_s: float, warmup_s: float, scrape_s: float) -> dict[str, Any]:
    run_id = f"bench-exp-{'on' if on else 'off'}-{uuid.uuid4().hex[:6]}"
    port = free_port() if on else None
    procs = Procs(tmp)
    stop = threading.Event()
    scrapes = [0, 0]  # ok, failed

    def scrape() -> None:  # what Prometheus does to the exporter, once a scrape_s
        while not stop.wait(scrape_s):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
                    r.read()
                scrapes[0] += 1
            except OSError:
                scrapes[1] += 1

    t = threading.Thread(target=scrape, daemon=True) if on else None
    try:
        p = procs.start(run_id, run_argv(run_id, tmp, round_s, port))
        if t is not None:
            t.start()
        p.wait(timeout=round_s + 120)
        if p.returncode != 0:
            raise RuntimeError(f"zenrl run exited {p.returncode}: {procs.log_text(run_id)[-2000:]}")
    finally:
        stop.set()
        procs.stop_all()
    out = {"exporter": on, "run_id": run_id, **updates_rate(tmp / run_id / "metrics.jsonl", warmup_s)}
    if on:
        out.update(scrapes=scrapes[0], failed_scrapes=scrapes[1])
    log(f"round exporter={'on' if on else 'off'}: {out['updates_per_s']:.1f} updates/s")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="rounds with and rounds without the exporter")
    ap.add_argument("--round-s", type=float, default=50.0, help="wall-clock seconds of each zenrl run")
    ap.add_argument("--warmup-s", type=float, default=15.0, help="seconds of each run not measured")
    ap.add_argument("--scrape-s", type=float, default=1.0, help="how often the exporter is scraped")
    ap.add_argument("--quick", action="store_true", help="1 round each, 30 s runs")
    ap.add_argument("--dry-run", action="store_true", help="print the plan (the JSON shape), start nothing")
    args = ap.parse_args(argv)
    if args.quick:
        args.rounds, args.round_s, args.warmup_s = 1, 30.0, 10.0
    stop_on_sigterm()
    t_start = time.perf_counter()
    order = [(r % 2 == 1) ^ (i == 1) for r in range(args.rounds) for i in range(2)]  # off,on / on,off / ...
    out: dict[str, Any] = {"bench": "exporter_cost", "target_ratio": TARGET_RATIO, "rounds_each": args.rounds,
                           "round_s": args.round_s, "warmup_s": args.warmup_s, "scrape_s": args.scrape_s,
                           "order": ["on" if o else "off" for o in order]}
    if args.dry_run:
        out["dry_run"] = True
        out["argv_example"] = run_argv("RUN_ID", Path("TMP"), args.round_s, 9464)
        out.update(machine_info(t_start))
        return emit(out)
    rounds: list[dict[str, Any]] = []
    try:
        with tempfile.TemporaryDirectory(prefix="zenrl-exporter-cost-") as d:
            for on in order:
                rounds.append(one_round(Path(d), on, args.round_s, args.warmup_s, args.scrape_s))
        on_r = [r["updates_per_s"] for r in rounds if r["exporter"]]
        off_r = [r["updates_per_s"] for r in rounds if not r["exporter"]]
        out.update(updates_per_s_on=statistics.median(on_r), updates_per_s_off=statistics.median(off_r),
                   ratio_on_off=statistics.median(on_r) / statistics.median(off_r),
                   scrapes=sum(r.get("scrapes", 0) for r in rounds))
        out["meets_target"] = out["ratio_on_off"] >= TARGET_RATIO
    except (Exception, KeyboardInterrupt) as e:  # a failed run still prints its JSON line
        record_error(out, e)
    out["rounds"] = rounds
    out.update(machine_info(t_start))
    return emit(out)


if __name__ == "__main__":
    sys.exit(main())
