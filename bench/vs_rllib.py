"""zenrl next to RLlib on CartPole-v1, on the same machine, in the same run, seeds interleaved.

Each RLlib algorithm with its own tuned CartPole settings, against zenrl's of the same family
(RLlib no longer ships Ape-X; its DQN keeps Ape-X's prioritized replay, double and dueling Q and
n-step returns):

* ``dqn``: RLlib DQN against zenrl Ape-X (``configs/cartpole_apex.yaml``);
* ``appo`` and ``impala``: RLlib APPO and RLlib IMPALA against zenrl IMPALA
  (``configs/cartpole_impala.yaml``, which runs APPO's clipped objective on V-trace).

RLlib runs ``bench/rllib_cartpole.py`` (see there) with the Python of a separate virtual
environment holding ``ray[rllib]`` (``--rllib-python`` or ``$ZENRL_RLLIB_PYTHON``, default
``/work/rlvenv/bin/python``); absent, the bench prints one line saying why and a JSON object
with ``skipped``, and exits 0. Set one up with::

    python3 -m venv /work/rlvenv && /work/rlvenv/bin/pip install torch==2.13.0 "ray[rllib]==2.60.0"

Clocks and targets (each framework's clock starts after its own start-up):

* RLlib: seconds since its first ``train()`` call, to the first iteration whose training mean
  (its last 100 episodes) is >= 450, the stop criterion of its tuned examples. The mean crosses
  the target somewhere inside that iteration (iterations last >= 1 s; DQN's ~5 s): the time
  counted is the iteration's *start*, the earliest it can have happened, in RLlib's favour.
* zenrl: as ``bench/time_to_solve.py``: a greedy evaluation mean >= 475 over 10 episodes
  (stricter than a training mean), seconds since the first env step.

Reported (the last stdout line is one JSON object; progress goes to stderr), per RLlib algorithm
X: ``time_ratio_vs_rllib_X`` = zenrl's median solve time / RLlib's (< 1: zenrl is ahead; an
unsolved run counts as infinitely slow, so where RLlib solves in no seed there is no ratio and
``rllib_X.solved`` says 0), and ``env_steps_ratio_vs_rllib_X``: env steps per second sampled
over each run (median of the seeds), zenrl's / RLlib's.

    python bench/vs_rllib.py                            # dqn, appo, impala; 3 seeds (30-60 minutes)
    python bench/vs_rllib.py --rllib dqn --seeds 1 --cap-s 120
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import time_to_solve as tts  # noqa: E402  (the zenrl half is time_to_solve's)
from _common import other_python_missing, print_skipped  # noqa: E402

RLLIB_TARGET = 450.0
DEFAULT_RLLIB_PYTHON = "/work/rlvenv/bin/python"
DRIVER = Path(__file__).resolve().parent / "rllib_cartpole.py"
#: RLlib algorithm -> the zenrl algorithm measured against it
PAIRS = {"dqn": "apex", "appo": "impala", "impala": "impala"}


def rllib_version(python: str) -> str:
    p = subprocess.run([python, "-c", "import ray; print(ray.__version__)"], capture_output=True, text=True, timeout=120)
    return p.stdout.strip() or "?"


def run_rllib(python: str, algo: str, seed: int, cap_s: float) -> dict[str, Any]:
    """One RLlib run until its training mean >= RLLIB_TARGET (or ``cap_s`` after its first
    ``train()``); its iterations read from the driver's JSON lines."""
    cmd = [python, str(DRIVER), "--algo", algo, "--seed", str(seed), "--cap-s", str(cap_s),
           "--target", str(RLLIB_TARGET)]
    t_launch = time.monotonic()
    env = {**os.environ, "RAY_DEDUP_LOGS": "0", "PYTHONWARNINGS": "ignore"}
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         env=env)
    try:
        out, err = p.communicate(timeout=cap_s + 300)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
    iters = []
    for line in out.splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and "iter" in row:
            iters.append(row)
    if not iters:
        raise RuntimeError(f"RLlib {algo} (seed {seed}) exited {p.returncode} with no iteration; "
                           f"stderr: {' | '.join(err.strip().splitlines()[-5:])}")
    solve = None
    for prev, row in zip([None, *iters], iters):
        if row["return_mean"] is not None and row["return_mean"] >= RLLIB_TARGET:
            solve = (0.0 if prev is None else prev["t"], row)
            break
    last = iters[-1]
    rets = [r["return_mean"] for r in iters if r["return_mean"] is not None]
    res = {"algo": algo, "seed": seed, "solved": solve is not None,
           "solve_s": None if solve is None else solve[0],
           "solve_iteration_end_s": None if solve is None else solve[1]["t"],
           "env_steps_at_solve": None if solve is None else solve[1]["env_steps"],
           "best_training_mean": max(rets) if rets else None, "iterations": len(iters),
           "env_steps": last["env_steps"], "train_s": last["t"],
           "env_steps_per_s": round(last["env_steps"] / last["t"], 1) if last["env_steps"] and last["t"] > 0 else None,
           "process_s": round(time.monotonic() - t_launch, 1), "returncode": p.returncode}
    tts.log(f"rllib {algo} seed {seed}: {json.dumps(res)}")
    return res


def ratio(a: float, b: float) -> float | None:
    return round(a / b, 4) if a != float("inf") and b not in (0.0, float("inf")) else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rllib-python", default=os.environ.get("ZENRL_RLLIB_PYTHON", DEFAULT_RLLIB_PYTHON),
                    help="python of the virtual environment with ray[rllib] (env ZENRL_RLLIB_PYTHON)")
    ap.add_argument("--rllib", default="dqn,appo,impala",
                    help="comma-separated RLlib algorithms: dqn (vs zenrl Ape-X), appo, impala (vs zenrl IMPALA)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--cap-s", type=float, default=300.0, help="wall-clock cap per run after its start-up")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="zenrl config override")
    args = ap.parse_args()
    pairs = [p.strip() for p in args.rllib.split(",") if p.strip()]
    if not pairs or any(p not in PAIRS for p in pairs):
        ap.error(f"--rllib takes {', '.join(PAIRS)}; got {args.rllib!r}")
    why = other_python_missing(args.rllib_python, "ray.rllib, torch", "RLlib", "ZENRL_RLLIB_PYTHON", "--rllib-python")
    if why is not None:
        print_skipped("vs_rllib", why)
        return
    load_start = os.getloadavg()
    result: dict[str, Any] = {"bench": "vs_rllib", "env": "CartPole-v1", "seeds": args.seeds, "cap_s": args.cap_s,
                              "rllib_version": rllib_version(args.rllib_python), "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="zenrl-vs-rllib-") as tmp:
        for ralgo in pairs:
            zalgo = PAIRS[ralgo]
            rl, zen = [], []
            for s in range(args.seeds):
                rl.append(run_rllib(args.rllib_python, ralgo, s, args.cap_s))
                # a folder per pair: zenrl IMPALA runs against two RLlib algorithms, and a run id
                # met again would resume that run
                zen.append(tts.run_zenrl(zalgo, s, args.cap_s, Path(tmp) / ralgo, args.set))
            r_med = tts.median_or_inf([r["solve_s"] for r in rl])
            z_med = tts.median_or_inf([r["solve_s"] for r in zen])
            r_sps = [r["env_steps_per_s"] for r in rl if r["env_steps_per_s"]]
            z_sps = [r["env_steps_per_s"] for r in zen if r["env_steps_per_s"]]
            result[f"rllib_{ralgo}"] = {"driver": "bench/rllib_cartpole.py", "target": f"training mean >= {RLLIB_TARGET}",
                                        "median_solve_s": tts.finite(r_med), "solved": sum(r["solved"] for r in rl),
                                        "runs": rl}
            result[f"zenrl_{zalgo}_vs_{ralgo}"] = {"config": f"configs/cartpole_{zalgo}.yaml", "overrides": args.set,
                                        "target": f"greedy eval mean >= {tts.TARGET}", "median_solve_s": tts.finite(z_med),
                                        "solved": sum(r["solved"] for r in zen), "runs": zen}
            result[f"time_ratio_vs_rllib_{ralgo}"] = ratio(z_med, r_med)
            result[f"env_steps_ratio_vs_rllib_{ralgo}"] = (round(statistics.median(z_sps) / statistics.median(r_sps), 3)
                                                           if z_sps and r_sps else None)
    result["load_average"] = {"start": load_start, "end": os.getloadavg()}
    print(json.dumps(result, default=float))


if __name__ == "__main__":
    main()
