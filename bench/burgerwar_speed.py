"""Wall-clock time for a Burger War config to reach a target win rate against named opponents.

Trains ``--config`` with ``zenrl run`` in a subprocess (its own Zenoh port and runs directory)
and, while it trains, evaluates the newest checkpoint each time a new one appears: greedy (or,
with ``--policy sample``, an actor-critic's sampled) matches against each opponent not yet beaten
(``--episodes`` per opponent, half as red, half as blue, seeds from ``--eval-seed``, never used in
training). An opponent's time is the moment (seconds since ``zenrl run`` was launched, start-up
included) at which the first checkpoint that wins at least ``--target`` of its matches was
written; the checkpoint's write time counts, not the end of its evaluation, so a slow evaluation
does not inflate the figure. The run stops when every opponent is beaten, at ``--max-wall`` or
when the training ends.

The evaluation shares the machine with the training: it runs in this process at ``--eval-nice``
(lower priority than the training) and evaluates only the newest checkpoint, skipping those
written while it was busy. ``--every-checkpoint`` evaluates each checkpoint in turn instead (the
learner keeps them all, and the evaluation goes on after the training ends until the last one is
done): the first to reach the target is then never skipped, at the cost of a longer bench. For a
figure on a 2-core machine, run it alone on an unloaded one.

Reported (the last stdout line is one JSON object; progress goes to stderr):
``time_to_target_s`` {opponent: seconds or null}, ``reached`` {opponent: the checkpoint,
its updates, wins / matches and Wilson 95% interval}, ``evals`` (the learning curve: every
evaluated checkpoint with its time and per-opponent win rate), ``startup_s`` (launch -> first
env step, from the run's summary), the run's stop reason, env steps and updates.

    python bench/burgerwar_speed.py                                  # apex config, 20-min cap
    python bench/burgerwar_speed.py --config configs/burgerwar_a3c.yaml --max-wall 1200
    python bench/burgerwar_speed.py --max-wall 60 --episodes 2       # smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, Procs, emit, log, machine_info, record_error, stop_on_sigterm  # noqa: E402


def free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def next_checkpoint(ckpt_dir: Path, after: int, oldest: bool = False) -> tuple[int, Path, float] | None:
    """(updates, path, mtime) of the newest checkpoint in ``ckpt_dir`` (with ``oldest``: the
    oldest) of more than ``after`` updates, or None."""
    from zenrl.common.checkpoints import checkpoint_step, list_checkpoints

    found = [p for p in list_checkpoints(ckpt_dir) if (checkpoint_step(p) or 0) > after]
    for p in (found if oldest else reversed(found)):
        try:
            return checkpoint_step(p), p, p.stat().st_mtime
        except FileNotFoundError:  # pruned by the learner meanwhile
            continue
    return None


def evaluate_checkpoint(path: Path, opponents: list[str], episodes: int, seed: int,
                        workers: int, policy: str = "greedy") -> dict[str, Any] | None:
    """Per-opponent results of ``path``, or None when the learner pruned it before it loaded."""
    from zenrl.tools import evaluate

    try:
        out = evaluate(str(path), opponents=opponents, episodes=episodes, workers=workers, seed=seed,
                       progress=False, policy=policy)
    except FileNotFoundError:
        return None
    except Exception as e:  # a checkpoint pruned while loading shows up as a load error
        if not path.exists():
            return None
        raise RuntimeError(f"evaluating {path.name} failed: {e}") from e
    return {r["opponent"]: {"wins": r["wins"], "episodes": r["episodes"], "win_rate": r["win_rate"],
                            "win_rate_ci95": r["win_rate_ci95"], "score_diff_mean": r["score_diff_mean"]}
            for r in out["rows"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/burgerwar_apex.yaml", help="zenrl run config")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="config override for the run (repeatable)")
    ap.add_argument("--opponents", default="cheese,teriyaki,clubhouse", help="comma-separated")
    ap.add_argument("--target", type=float, default=0.9, help="win rate to reach")
    ap.add_argument("--episodes", type=int, default=20, help="matches per opponent per evaluation (even)")
    ap.add_argument("--eval-seed", type=int, default=1_000_000, help="first evaluation match seed")
    ap.add_argument("--policy", choices=("greedy", "sample"), default="greedy",
                    help="how the evaluation plays: greedy (argmax) or sample (draw from an a3c/impala "
                         "policy's action distribution, as the policy the learner trains acts)")
    ap.add_argument("--eval-workers", type=int, default=1, help="evaluation processes")
    ap.add_argument("--eval-nice", type=int, default=5, help="niceness of the evaluation (this process)")
    ap.add_argument("--max-wall", type=float, default=1200.0, help="training budget, seconds since launch")
    ap.add_argument("--checkpoint-every", type=float, default=60.0,
                    help="learner.checkpoint_interval_s for the run (the time resolution)")
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--every-checkpoint", action="store_true",
                    help="evaluate every checkpoint in order (the learner prunes none), not only the newest")
    ap.add_argument("--runs-dir", default=None, help="keep the run here (default: a temporary directory)")
    args = ap.parse_args()
    opponents = [o.strip() for o in args.opponents.split(",") if o.strip()]
    if not opponents:
        ap.error("--opponents names no opponent")
    if args.episodes < 2 or args.episodes % 2:
        ap.error(f"--episodes must be even and >= 2 (half red, half blue), got {args.episodes}")
    if not 0 < args.target <= 1:
        ap.error(f"--target must be in (0, 1], got {args.target}")
    stop_on_sigterm()

    t_bench = time.perf_counter()
    out: dict[str, Any] = {"bench": "burgerwar_speed", "config": args.config, "overrides": args.set,
                           "opponents": opponents, "target": args.target, "episodes_per_eval": args.episodes,
                           "policy": args.policy, "max_wall_s": args.max_wall, "seed": args.seed,
                           "every_checkpoint": args.every_checkpoint}
    time_to: dict[str, float | None] = {o: None for o in opponents}
    reached: dict[str, Any] = {}
    evals: list[dict[str, Any]] = []
    tmp_ctx = tempfile.TemporaryDirectory(prefix="zenrl-bwspeed-")
    tmp = Path(tmp_ctx.name)
    runs_dir = Path(args.runs_dir).resolve() if args.runs_dir else tmp / "runs"
    run_id = f"bwspeed-s{args.seed}-{os.getpid()}"
    procs = Procs(tmp)
    try:
        cmd = ["-m", "zenrl.cli", "run", "--config", str(ROOT / args.config), "--seed", str(args.seed),
               "--run-id", run_id, "--no-progress", "--set", f"runs_dir={runs_dir}",
               "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]",
               "--set", f"max_wall_s={args.max_wall}",
               "--set", f"learner.checkpoint_interval_s={args.checkpoint_every}"]
        if args.every_checkpoint:
            cmd += ["--set", "learner.keep_checkpoints=1000000"]
        for kv in args.set:
            cmd += ["--set", kv]
        t0 = time.time()
        run = procs.start("zenrl-run", cmd)
        log(f"zenrl run {run_id} started (pid {run.pid}); logs in {tmp}")
        os.nice(args.eval_nice)  # after the launch: the training keeps its priority
        ckpt_dir = runs_dir / run_id / "checkpoints"
        last_updates = -1
        while True:
            finished = run.poll() is not None
            newest = next_checkpoint(ckpt_dir, last_updates, oldest=args.every_checkpoint)
            if newest is not None:
                updates, path, mtime = newest
                todo = [o for o in opponents if time_to[o] is None]
                res = evaluate_checkpoint(path, todo, args.episodes, args.eval_seed, args.eval_workers, args.policy)
                if res is not None:
                    last_updates = updates
                    t_ckpt = round(mtime - t0, 1)
                    evals.append({"checkpoint": path.name, "updates": updates, "t_s": t_ckpt,
                                  "evaluated_at_s": round(time.time() - t0, 1),
                                  "win_rate": {o: r["win_rate"] for o, r in res.items()}})
                    log(f"t={t_ckpt:7.1f} s  {path.name}: " + "  ".join(
                        f"{o} {r['wins']}/{r['episodes']}" for o, r in res.items()))
                    for o, r in res.items():
                        if r["win_rate"] >= args.target and time_to[o] is None:
                            time_to[o] = t_ckpt
                            reached[o] = {"checkpoint": path.name, "updates": updates, **r}
                    if all(v is not None for v in time_to.values()):
                        log("every opponent beaten: stopping the training")
                        break
                continue  # a newer checkpoint may have appeared while evaluating
            if finished:
                break
            time.sleep(1.0)
        procs.stop(run, grace_s=60.0)
        summary_path = runs_dir / run_id / "summary.json"
        if summary_path.is_file():
            s = json.loads(summary_path.read_text())
            out.update({"startup_s": s.get("startup_s"), "stop_reason": s.get("stop_reason"),
                        "env_steps": s.get("env_steps"), "updates": (s.get("learner") or {}).get("updates")})
        else:
            out["run_log_tail"] = procs.log_text("zenrl-run")[-2000:]
        out["run_returncode"] = run.returncode
        if run.returncode not in (0, None) and not evals:
            raise RuntimeError(f"zenrl run exited {run.returncode}: {procs.log_text('zenrl-run')[-1500:]}")
    except BaseException as e:  # KeyboardInterrupt/SIGTERM too: report what was measured
        record_error(out, e)
    finally:
        procs.stop_all(grace_s=60.0)
        out.update({"time_to_target_s": time_to, "reached": reached, "evals": evals,
                    "runs_dir": str(runs_dir) if args.runs_dir else None, **machine_info(t_bench)})
        tmp_ctx.cleanup()
    return emit(out)


if __name__ == "__main__":
    sys.exit(main())
