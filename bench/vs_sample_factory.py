"""zenrl IMPALA next to Sample Factory's APPO (the field's throughput reference) on CartPole-v1,
on the same machine, in the same run, seeds interleaved (SF seed 0, zenrl seed 0, SF seed 1, ...).

* Sample Factory: its own CartPole example command (``sf_examples.train_gym_env``, the command
  line in that module's docstring) with 2 rollout workers on the CPU, run by the Python of a
  separate virtual environment (sample-factory 2.1.1 needs gymnasium < 1.0 and numpy < 2):
  ``--sf-python`` or ``$ZENRL_SF_PYTHON`` (default ``/work/sfvenv/bin/python``); absent or
  without sample-factory, the bench prints one line saying why and a JSON object with
  ``skipped``, and exits 0. Its clock starts at its first report of collected frames (after its
  start-up, as zenrl's starts at the first env step) and stops at the first report of a
  training mean (its ``Avg episode reward``, over the last ``--stats_avg`` episodes) >= 450.
  Its env steps per second: collected frames over that time (Sample Factory's APPO trains on
  every sampled step once, so these are also the steps its learner consumes).
* zenrl: ``zenrl run --config configs/cartpole_impala.yaml`` as ``bench/time_to_solve.py`` runs
  it: solved at a greedy evaluation mean >= 475 over 10 episodes (stricter than a training
  mean), seconds since the first env step; then one run of ``--throughput-s`` seconds without
  target or evaluator for the env steps its learner consumes per second (median of its reports),
  and, from the solve runs, the env steps its learner trained on per second while solving
  (updates at the solving eval x T x B / solve time).

Reported (the last stdout line is one JSON object; progress goes to stderr):
``time_ratio_vs_sf``: zenrl median solve time / SF median time to a training mean of 450 (< 1:
zenrl is ahead; an unsolved run counts as infinitely slow); ``consumption_ratio_vs_sf``: zenrl
learner's env steps/s / SF's; ``consumption_while_solving_ratio_vs_sf``: the same from the solve
runs. SF's times come from its own log stamps.

    python bench/vs_sample_factory.py                       # 3 seeds each (a few minutes)
    python bench/vs_sample_factory.py --seeds 1 --cap-s 120
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import time_to_solve as tts  # noqa: E402  (the zenrl half is time_to_solve's)
from _common import other_python_missing, print_skipped  # noqa: E402

SF_TARGET = 450.0
DEFAULT_SF_PYTHON = "/work/sfvenv/bin/python"
#: sf_examples/train_gym_env.py's own CartPole-v1 command line, plus 2 workers on the CPU
SF_EXAMPLE_ARGS = ["--algo=APPO", "--use_rnn=False", "--num_envs_per_worker=20", "--policy_workers_per_policy=2",
                   "--recurrence=1", "--with_vtrace=False", "--batch_size=512", "--reward_scale=0.1",
                   "--save_every_sec=10", "--experiment_summaries_interval=10", "--env=CartPole-v1"]
SF_MACHINE_ARGS = ["--num_workers=2", "--device=cpu"]
_STAMP = re.compile(r"\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3})\]")
_FRAMES = re.compile(r"Fps is \(10 sec: ([\d.na]+).*Total num frames: (\d+)")
_REWARD = re.compile(r"Avg episode reward: \[\(0, '(-?[\d.]+)'\)\]")


def run_sf(python: str, seed: int, cap_s: float, train_dir: Path) -> dict[str, Any]:
    """SF's CartPole example until a training mean >= SF_TARGET (or ``cap_s`` after its first frames)."""
    cmd = [python, "-m", "sf_examples.train_gym_env", *SF_EXAMPLE_ARGS, *SF_MACHINE_ARGS, f"--seed={seed}",
           f"--experiment=zenrl_bench_cartpole_s{seed}_{os.getpid()}", f"--train_dir={train_dir}",
           f"--train_for_seconds={int(cap_s + 120)}"]
    t_launch = time.time()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    first: tuple[float, int] | None = None     # (clock, frames) of the first report with frames
    last: tuple[float, int] | None = None
    fps10: list[float] = []
    solve: tuple[float, int, float] | None = None
    best = None
    tail: list[str] = []
    deadline = [time.monotonic() + cap_s + 300]

    def watchdog() -> None:
        while p.poll() is None:
            if time.monotonic() > deadline[0]:
                os.killpg(p.pid, signal.SIGKILL)
                return
            time.sleep(0.5)

    threading.Thread(target=watchdog, daemon=True).start()
    try:
        for line in p.stdout:  # type: ignore[union-attr]
            # SF's own log time (a pipe may deliver lines late, in bursts); arrival time without one
            st = _STAMP.search(line)
            now = (datetime.datetime.strptime(st.group(1), "%Y-%m-%d %H:%M:%S").timestamp() + int(st.group(2)) / 1000
                   if st else time.time())
            tail = (tail + [line.rstrip()])[-20:]
            m = _FRAMES.search(line)
            if m:
                frames = int(m.group(2))
                if frames > 0:
                    if first is None:
                        first = (now, frames)
                        deadline[0] = time.monotonic() + cap_s
                    last = (now, frames)
                    if m.group(1) != "nan" and float(m.group(1)) > 0:
                        fps10.append(float(m.group(1)))
                continue
            m = _REWARD.search(line)
            if m and first is not None:
                r = float(m.group(1))
                best = r if best is None else max(best, r)
                if r >= SF_TARGET:
                    solve = (now - first[0], last[1] if last else 0, r)
                    break
            if first is not None and now - first[0] > cap_s:
                break
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)  # SF saves and stops its workers on SIGINT
            try:
                p.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)
    if first is None:
        raise RuntimeError(f"Sample Factory (seed {seed}) reported no frames; last lines: {' | '.join(tail[-5:])}")
    span = (last[0] - first[0]) if last else 0.0
    sps = (last[1] - first[1]) / span if last and span > 0 else None
    out = {"seed": seed, "solved": solve is not None, "solve_s": None if solve is None else round(solve[0], 3),
           "frames_at_solve": None if solve is None else solve[1], "best_training_mean": best,
           "startup_s": round(first[0] - t_launch, 3), "env_steps_per_s": None if sps is None else round(sps, 1),
           "fps10_median": round(statistics.median(fps10), 1) if fps10 else None}
    tts.log(f"sample factory seed {seed}: {json.dumps(out)}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sf-python", default=os.environ.get("ZENRL_SF_PYTHON", DEFAULT_SF_PYTHON),
                    help="python of the virtual environment with sample-factory 2.1.1 (env ZENRL_SF_PYTHON)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--cap-s", type=float, default=300.0, help="wall-clock cap per run after its first step")
    ap.add_argument("--throughput-s", type=float, default=60.0,
                    help="seconds of zenrl's learner-consumption run (its start-up included: keep it well above that)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="zenrl config override")
    args = ap.parse_args()
    why = other_python_missing(args.sf_python, "sample_factory, sf_examples.train_gym_env", "Sample Factory",
                               "ZENRL_SF_PYTHON", "--sf-python")
    if why is not None:
        print_skipped("vs_sample_factory", why)
        return
    load_start = os.getloadavg()
    sf, zen = [], []
    with tempfile.TemporaryDirectory(prefix="zenrl-vs-sf-") as tmp:
        for s in range(args.seeds):
            sf.append(run_sf(args.sf_python, s, args.cap_s, Path(tmp) / "sf"))
            zen.append(tts.run_zenrl("impala", s, args.cap_s, Path(tmp), args.set))
        cons = tts.learner_consumption("impala", args.throughput_s, Path(tmp), args.set) if args.throughput_s > 0 else {}
    sf_med = tts.median_or_inf([r["solve_s"] for r in sf])
    z_med = tts.median_or_inf([r["solve_s"] for r in zen])
    sf_sps = [r["env_steps_per_s"] for r in sf if r["env_steps_per_s"]]
    sf_rate = statistics.median(sf_sps) if sf_sps else None
    z_rate = cons.get("median_env_steps_per_s")
    # the env steps zenrl's learner trained on per second while solving (T * B per update)
    from zenrl.common.config import load_config

    icfg = load_config(str(tts.ROOT / "configs" / "cartpole_impala.yaml"), args.set, environ={}).impala
    T, B = icfg.unroll_length, icfg.batch_unrolls
    for r in zen:
        r["trained_per_s_while_solving"] = (round(r["updates_at_solve"] * T * B / r["solve_s"], 1)
                                            if r.get("updates_at_solve") and r.get("solve_s") else None)
    z_solving = [r["trained_per_s_while_solving"] for r in zen if r["trained_per_s_while_solving"]]
    print(json.dumps({
        "bench": "vs_sample_factory", "env": "CartPole-v1", "seeds": args.seeds, "cap_s": args.cap_s,
        "load_average": {"start": load_start, "end": os.getloadavg()}, "cpus": os.cpu_count(),
        "sample_factory": {"command": ["-m", "sf_examples.train_gym_env", *SF_EXAMPLE_ARGS, *SF_MACHINE_ARGS],
                           "target": f"training mean >= {SF_TARGET}", "median_solve_s": tts.finite(sf_med),
                           "median_env_steps_per_s": sf_rate, "runs": sf},
        "zenrl_impala": {"config": "configs/cartpole_impala.yaml", "overrides": args.set,
                         "target": f"greedy eval mean >= {tts.TARGET}", "median_solve_s": tts.finite(z_med),
                         "learner_consumption": cons, "runs": zen},
        "time_ratio_vs_sf": (round(z_med / sf_med, 3) if z_med != float("inf") and sf_med not in (0.0, float("inf"))
                             else None),
        "consumption_ratio_vs_sf": round(z_rate / sf_rate, 3) if z_rate and sf_rate else None,
        "consumption_while_solving_ratio_vs_sf": (round(statistics.median(z_solving) / sf_rate, 3)
                                                  if z_solving and sf_rate else None),
    }, default=float))


if __name__ == "__main__":
    main()
