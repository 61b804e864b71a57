"""Wall-clock time to solve CartPole-v1 (greedy eval mean >= 475 over 10 episodes): zenrl vs
Stable-Baselines3, on the same machine, in the same run, seeds interleaved (zenrl seed 0,
SB3 seed 0, zenrl seed 1, ...) so that machine noise hits both alike.

* zenrl: ``zenrl run --config configs/cartpole_<algo>.yaml --seed S`` as a subprocess with
  ``target_return=475``; the figures come from ``runs/<id>/summary.json``:
  ``solve_s_since_first_step`` (the launcher's clock starts at the first env step an actor
  reports; its evaluator runs in its own process, concurrently) and ``startup_s``. The actors
  report every ``--report-s`` seconds (``actor.episode_report_s``; their first report comes
  one interval after they start stepping, so the launcher's clock starts up to that late:
  at the configs' 1 s, up to a second of training went unclocked).
* SB3: in this process, the rl-baselines3-zoo CartPole-v1 hyper-parameters (below):
  apex is compared with SB3 DQN, a3c with SB3 A2C (8 envs). The clock starts at the first
  env step (first rollout) and is paused while evaluating: every ``--sb3-eval-every`` env steps
  a callback plays 10 greedy (``deterministic=True``) episodes on separate seeds (the same
  seed scheme as zenrl's evaluator: seed + 1,000,000 + 10 * round + i).

``--algo impala`` runs zenrl IMPALA, zenrl A3C and SB3 A2C in the same run (seeds
interleaved: impala 0, a3c 0, A2C 0, impala 1, ...), and then measures the env steps each zenrl
learner *consumes* per second (trains on: T * B per IMPALA update, the rollout's steps per A3C
gradient): one run of ``--throughput-s`` seconds per algorithm, no target, no evaluator; the
median of the learner's ``env_steps_per_s`` stats over its reports after its first update.

Reported (the last stdout line is one JSON object; progress goes to stderr):
  ``median_ratio_vs_sb3`` (apex) / ``median_ratio_vs_sb3_a2c`` (a3c): median zenrl solve time /
  median SB3 solve time (an unsolved seed counts as infinitely slow; null if a median is
  infinite). ``startup_s``: median zenrl start-up (launch -> first env step).
  ``throughput_ratio_vs_sb3_a2c`` (a3c): median env steps/s of zenrl A3C (2 workers, over the
  run up to its last eval) / median env steps/s of SB3 A2C (clock excluding evaluation).

    python bench/time_to_solve.py --algo a3c             # 3 seeds each (minutes)
    python bench/time_to_solve.py --algo apex --quick    # 1 seed each, capped time
    python bench/time_to_solve.py --algo impala          # IMPALA vs A3C vs SB3 A2C, + consumption
    python bench/time_to_solve.py --algo r2d2            # R2D2 vs Ape-X on StatelessCartPole, 600 s cap
    python bench/time_to_solve.py --algo pendulum        # APPO vs SB3 PPO on Pendulum-v1 (continuous)

``--algo r2d2`` (issue #34): see :func:`r2d2_main`. ``--algo pendulum`` (continuous actions):
zenrl APPO vs SB3 PPO on Pendulum-v1, :func:`pendulum_main`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent
TARGET = 475.0
EVAL_EPISODES = 10
EVAL_SEED_OFFSET = 1_000_000

# rl-baselines3-zoo, hyperparams/dqn.yml and a2c.yml, CartPole-v1 (values, not code).
ZOO_DQN = {"n_timesteps": 50_000, "policy": "MlpPolicy", "learning_rate": 2.3e-3, "batch_size": 64,
           "buffer_size": 100_000, "learning_starts": 1000, "gamma": 0.99, "target_update_interval": 10,
           "train_freq": 256, "gradient_steps": 128, "exploration_fraction": 0.16,
           "exploration_final_eps": 0.04, "policy_kwargs": {"net_arch": [256, 256]}}
ZOO_A2C = {"n_timesteps": 500_000, "policy": "MlpPolicy", "n_envs": 8, "ent_coef": 0.0}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def median_or_inf(xs: list[float | None]) -> float:
    return statistics.median([float("inf") if x is None else x for x in xs]) if xs else float("inf")


def finite(x: float) -> float | None:
    return None if x == float("inf") else round(x, 3)


# --------------------------------------------------------------------------------------------
def run_zenrl(algo: str, seed: int, cap_s: float, runs_dir: Path, sets: list[str] | None = None,
              report_s: float = 0.05, config: Path | None = None, target: float = TARGET) -> dict[str, Any]:
    """``config``: instead of ``configs/cartpole_<algo>.yaml``; ``target``: the greedy eval return
    that solves it."""
    run_id = f"tts-{algo}-s{seed}-{os.getpid()}"
    config = config or ROOT / "configs" / f"cartpole_{algo}.yaml"
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", str(config),
           "--seed", str(seed), "--run-id", run_id, "--no-progress", "--set", f"runs_dir={runs_dir}",
           "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]", "--set", f"target_return={target}",
           "--set", f"max_wall_s={cap_s}", "--set", f"actor.episode_report_s={report_s}"]
    for kv in sets or []:
        cmd += ["--set", kv]
    t0, started = time.monotonic(), time.time()
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=cap_s + 300)
    summary = runs_dir / run_id / "summary.json"
    # a summary older than this run is another run's (zenrl refuses a run folder in use)
    if not summary.is_file() or summary.stat().st_mtime < started:
        raise RuntimeError(f"zenrl run (seed {seed}) exited {p.returncode} without a summary of its own: {p.stderr[-2000:]}")
    s = json.loads(summary.read_text())
    evals = s.get("evals") or []
    last = next((e for e in reversed(evals) if e.get("since_first_step")), None)
    sps = last["env_steps"] / last["since_first_step"] if last and last["since_first_step"] > 0 else None
    at = next((e for e in evals if s["solved"] and e.get("since_first_step") == s["solve_s_since_first_step"]), {})
    out = {"seed": seed, "solved": bool(s["solved"]), "solve_s": s["solve_s_since_first_step"],
           "updates_at_solve": at.get("updates"), "env_steps_at_solve": at.get("env_steps"),
           "last_eval": evals[-1].get("mean") if evals else None,
           "startup_s": s["startup_s"], "env_steps": s["env_steps"], "env_steps_per_s": sps,
           "stop_reason": s["stop_reason"], "updates": (s.get("learner") or {}).get("updates"),  # at the end
           "env_steps_trained": (s.get("learner") or {}).get("env_steps_trained"),
           "returncode": p.returncode, "process_s": time.monotonic() - t0}
    log(f"zenrl {algo} seed {seed}: {json.dumps(out)}")
    return out


def learner_consumption(algo: str, seconds: float, runs_dir: Path, sets: list[str] | None = None) -> dict[str, Any]:
    """Env steps per second the zenrl learner trains on, over a run of ``seconds`` (no target,
    no evaluator): the median of its ``env_steps_per_s`` reports after the first update."""
    run_id = f"tput-{algo}-{os.getpid()}"
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", str(ROOT / "configs" / f"cartpole_{algo}.yaml"),
           "--run-id", run_id, "--no-progress", "--set", f"runs_dir={runs_dir}",
           "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]", "--set", "target_return=null",
           "--set", "evaluator.enabled=false", "--set", f"max_wall_s={seconds}"]
    for kv in sets or []:
        cmd += ["--set", kv]
    subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=seconds + 300)
    rates = []
    metrics = runs_dir / run_id / "metrics.jsonl"
    if metrics.is_file():
        for line in metrics.read_text().splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if row.get("source") == "learner" and row.get("step", 0) > 0 and row.get("env_steps_per_s"):
                rates.append(float(row["env_steps_per_s"]))
    rates = rates[1:]  # the first report's interval holds the start
    out = {"algo": algo, "seconds": seconds, "reports": len(rates),
           "median_env_steps_per_s": round(statistics.median(rates), 1) if rates else None}
    log(f"zenrl {algo} learner consumption: {json.dumps(out)}")
    return out


# --------------------------------------------------------------------------------------------
def sb3_solve_clock(env_id: str, seed: int, eval_every: int, cap_s: float, target: float,
                    prepare: Callable[[Any, Any], Any] = lambda model, obs: obs,
                    to_action: Callable[[Any], Any] = lambda a: a) -> Any:
    """An SB3 callback that clocks training from the first env step, pauses the clock while it
    plays ``EVAL_EPISODES`` greedy (``deterministic=True``) episodes of ``env_id`` every
    ``eval_every`` env steps (on zenrl's evaluation seeds: seed + 1,000,000 + 10 * round + i),
    and stops training once their mean reaches ``target`` (``solve_s``) or the clock ``cap_s``.
    ``prepare(model, obs)``: the observation the model acts on (e.g. normalised);
    ``to_action(a)``: the action the env takes."""
    import gymnasium as gym
    import numpy as np
    from stable_baselines3.common.callbacks import BaseCallback

    class SolveClock(BaseCallback):
        """Clock from the first env step, paused while evaluating; stops at the target."""

        def __init__(self) -> None:
            super().__init__()
            self.t_start: float | None = None
            self.paused = 0.0
            self.next_eval = eval_every
            self.rounds = 0
            self.solve_s: float | None = None
            self.evals: list[tuple[int, float, float]] = []
            self.eval_env = gym.make(env_id)

        def clock(self) -> float:
            return 0.0 if self.t_start is None else time.perf_counter() - self.t_start - self.paused

        def _on_rollout_start(self) -> None:
            if self.t_start is None:
                self.t_start = time.perf_counter()

        def _evaluate(self) -> float:
            rets = []
            for i in range(EVAL_EPISODES):
                obs, _ = self.eval_env.reset(seed=seed + EVAL_SEED_OFFSET + EVAL_EPISODES * self.rounds + i)
                done, ret = False, 0.0
                while not done:
                    a, _ = self.model.predict(prepare(self.model, obs), deterministic=True)
                    obs, r, term, trunc, _ = self.eval_env.step(to_action(a))
                    ret += float(r)
                    done = term or trunc
                rets.append(ret)
            self.rounds += 1
            return float(np.mean(rets))

        def _on_step(self) -> bool:
            if self.t_start is None:
                self.t_start = time.perf_counter()
            if self.num_timesteps >= self.next_eval:
                self.next_eval += eval_every
                t0 = time.perf_counter()
                m = self._evaluate()
                self.paused += time.perf_counter() - t0
                self.evals.append((self.num_timesteps, round(self.clock(), 2), m))
                if m >= target:
                    self.solve_s = self.clock()
                    return False
            return self.clock() < cap_s

    return SolveClock()


def run_sb3(algo: str, seed: int, cap_s: float, eval_every: int, threads: int) -> dict[str, Any]:
    import gymnasium as gym
    import torch
    from stable_baselines3 import A2C, DQN
    from stable_baselines3.common.env_util import make_vec_env

    torch.set_num_threads(threads)
    cb = sb3_solve_clock("CartPole-v1", seed, eval_every, cap_s, TARGET, to_action=int)
    if algo == "apex":  # the other algorithms compare with A2C
        hp = {k: v for k, v in ZOO_DQN.items() if k not in ("n_timesteps", "policy")}
        env = gym.make("CartPole-v1")
        model = DQN(ZOO_DQN["policy"], env, seed=seed, device="cpu", verbose=0, **hp)
        total = ZOO_DQN["n_timesteps"]
    else:
        env = make_vec_env("CartPole-v1", n_envs=ZOO_A2C["n_envs"], seed=seed)
        model = A2C(ZOO_A2C["policy"], env, seed=seed, device="cpu", verbose=0, ent_coef=ZOO_A2C["ent_coef"])
        total = ZOO_A2C["n_timesteps"]
    model.learn(total_timesteps=total, callback=cb)
    clock = cb.clock()
    out = {"seed": seed, "solved": cb.solve_s is not None, "solve_s": cb.solve_s, "env_steps": int(model.num_timesteps),
           "env_steps_per_s": model.num_timesteps / clock if clock > 0 else None, "train_s": clock,
           "eval_rounds": cb.rounds, "last_eval": cb.evals[-1][2] if cb.evals else None}
    log(f"sb3 {'DQN' if algo == 'apex' else 'A2C'} seed {seed}: {json.dumps(out)}")
    return out


# -- continuous actions: APPO on Pendulum-v1 vs SB3 PPO -------------------------------------
PENDULUM_CONFIG = ROOT / "configs" / "pendulum_appo.yaml"
PENDULUM_TARGET = -200.0
# rl-baselines3-zoo, hyperparams/ppo.yml, Pendulum-v1 (values, not code); ``normalize``:
# VecNormalize of observations and rewards, as the zoo trains it.
ZOO_PPO_PENDULUM = {"n_timesteps": 100_000, "policy": "MlpPolicy", "normalize": True, "n_envs": 4, "n_steps": 1024,
                    "gae_lambda": 0.95, "gamma": 0.9, "n_epochs": 10, "ent_coef": 0.0, "learning_rate": 1e-3,
                    "clip_range": 0.2, "use_sde": True, "sde_sample_freq": 4}


def run_sb3_ppo_pendulum(seed: int, cap_s: float, eval_every: int, threads: int) -> dict[str, Any]:
    """SB3 PPO with the zoo's Pendulum-v1 hyper-parameters (up to 4x its 100 k steps, or
    ``cap_s``), clocked by :func:`sb3_solve_clock` (greedy episodes on observations normalised
    with the training statistics)."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(threads)
    hp = ZOO_PPO_PENDULUM
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=hp["n_envs"], seed=seed), gamma=hp["gamma"])
    kw = {k: v for k, v in hp.items() if k not in ("n_timesteps", "policy", "normalize", "n_envs")}
    model = PPO(hp["policy"], env, seed=seed, device="cpu", verbose=0, **kw)
    cb = sb3_solve_clock("Pendulum-v1", seed, eval_every, cap_s, PENDULUM_TARGET,
                         prepare=lambda m, obs: m.get_env().normalize_obs(obs))
    model.learn(total_timesteps=4 * hp["n_timesteps"], callback=cb)
    clock = cb.clock()
    out = {"seed": seed, "solved": cb.solve_s is not None, "solve_s": cb.solve_s, "env_steps": int(model.num_timesteps),
           "env_steps_per_s": model.num_timesteps / clock if clock > 0 else None, "train_s": clock,
           "eval_rounds": cb.rounds, "last_eval": cb.evals[-1][2] if cb.evals else None,
           "env_steps_at_solve": cb.evals[-1][0] if cb.solve_s is not None else None}
    log(f"sb3 PPO Pendulum seed {seed}: {json.dumps(out)}")
    return out


def pendulum_main(args: argparse.Namespace) -> None:
    """zenrl APPO (``configs/pendulum_appo.yaml``) vs SB3 PPO (the zoo's Pendulum-v1 setting),
    seeds interleaved, time to a greedy eval mean >= -200 over 10 episodes; ratio = median zenrl
    solve time (from its first env step) / median SB3 solve time (evaluation excluded)."""
    load_start = os.getloadavg()
    seeds = 1 if args.quick else args.seeds
    cap = min(args.cap_s, 240.0) if args.quick else args.cap_s
    eval_every = args.sb3_eval_every or 4096  # one rollout of the zoo's 4 x 1024 steps
    zen, sb3 = [], []
    with tempfile.TemporaryDirectory(prefix="zenrl-tts-") as tmp:
        for s in range(seeds):
            zen.append(run_zenrl("impala", s, cap, Path(tmp), args.set, args.report_s, config=PENDULUM_CONFIG,
                                 target=PENDULUM_TARGET))
            if not args.skip_sb3:
                sb3.append(run_sb3_ppo_pendulum(s, cap, eval_every, args.sb3_threads))
    z_med = median_or_inf([r["solve_s"] for r in zen])
    s_med = median_or_inf([r["solve_s"] for r in sb3]) if sb3 else float("inf")
    ratio = z_med / s_med if z_med != float("inf") and s_med not in (0.0, float("inf")) else None
    print(json.dumps({
        "bench": "time_to_solve", "env": "Pendulum-v1", "algo": "pendulum", "target_return": PENDULUM_TARGET,
        "eval_episodes": EVAL_EPISODES, "seeds": seeds, "quick": args.quick, "cap_s": cap,
        "load_average": {"start": load_start, "end": os.getloadavg()},
        "zenrl": {"config": "configs/pendulum_appo.yaml", "overrides": args.set, "median_solve_s": finite(z_med), "runs": zen},
        "sb3": {"algo": "PPO", "zoo_hyperparameters": ZOO_PPO_PENDULUM, "eval_every_steps": eval_every,
                "torch_threads": args.sb3_threads, "median_solve_s": finite(s_med), "runs": sb3} if sb3 else None,
        "median_ratio_vs_sb3_ppo": None if ratio is None else round(ratio, 3),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
    }, default=float))


# -- R2D2 on StatelessCartPole (issue #34) ----------------------------------------------------
R2D2_CONFIG = ROOT / "configs" / "stateless_cartpole_r2d2.yaml"
STATELESS = "zenrl/StatelessCartPole-v1"


def r2d2_main(args: argparse.Namespace) -> None:
    """``--algo r2d2``: ``zenrl run`` R2D2 (``configs/stateless_cartpole_r2d2.yaml``) and, as the
    contrast, Ape-X (``configs/cartpole_apex.yaml`` with ``env.id`` set to StatelessCartPole), on
    the same seeds and wall cap (default 600 s), seeds interleaved (r2d2 0, apex 0, r2d2 1, ...).
    ``wall_to_solve_s`` is the run's clock from ``zenrl run``'s start to the first greedy eval
    >= 475 over 10 episodes: ``startup_s`` + ``solve_s`` (since the first env step). No SB3.
    ``--set`` applies to the R2D2 runs only; ``--skip-contrast``: no Ape-X runs."""
    seeds = 1 if args.quick else args.seeds
    cap = args.cap_s if args.cap_s != 900.0 else 600.0  # the budget: 10 minutes
    load = [os.getloadavg()[0]]
    runs: dict[str, list[dict[str, Any]]] = {"r2d2": [], "apex": []}
    with tempfile.TemporaryDirectory(prefix="zenrl-tts-r2d2-") as tmp:
        for s in range(args.first_seed, args.first_seed + seeds):
            runs["r2d2"].append(run_zenrl("r2d2", s, cap, Path(tmp), args.set, config=R2D2_CONFIG))
            load.append(os.getloadavg()[0])
            if not args.skip_contrast:
                runs["apex"].append(run_zenrl("apex", s, cap, Path(tmp), [f"env.id={STATELESS}"]))
                load.append(os.getloadavg()[0])
    summary: dict[str, Any] = {}
    for algo, rs in runs.items():
        for r in rs:
            r["wall_to_solve_s"] = (round(r["startup_s"] + r["solve_s"], 2)
                                    if r["solved"] and r["startup_s"] is not None else None)
        med = median_or_inf([r["wall_to_solve_s"] for r in rs]) if rs else float("inf")
        summary[algo] = {"solved": sum(r["solved"] for r in rs), "of": len(rs), "median_wall_to_solve_s": finite(med),
                         "runs": rs}
    summary["r2d2"]["config"], summary["r2d2"]["overrides"] = "configs/stateless_cartpole_r2d2.yaml", args.set
    summary["apex"]["config"], summary["apex"]["overrides"] = "configs/cartpole_apex.yaml", [f"env.id={STATELESS}"]
    r_med, a_med = (median_or_inf([r["wall_to_solve_s"] for r in runs[k]]) for k in ("r2d2", "apex"))
    result = {"bench": "time_to_solve", "env": STATELESS, "algo": "r2d2", "target_return": TARGET,
              "eval_episodes": EVAL_EPISODES, "seeds": seeds, "first_seed": args.first_seed, "cap_s": cap,
              "target_median_wall_to_solve_s": 600.0,
              "r2d2_meets_target": len(runs["r2d2"]) >= 3 and summary["r2d2"]["solved"] == len(runs["r2d2"])
              and r_med <= 600.0,
              "ratio_r2d2_vs_apex": (round(r_med / a_med, 3) if r_med != float("inf") and a_med not in (0.0, float("inf"))
                                     else None),
              **summary, "load_avg_1m": [round(x, 2) for x in load],
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}}
    print(json.dumps(result, default=float))


# --------------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algo", choices=["apex", "a3c", "impala", "r2d2", "pendulum"], default="apex",
                    help="pendulum: zenrl APPO vs SB3 PPO on Pendulum-v1 (continuous actions)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per system (>= 3 for a real comparison)")
    ap.add_argument("--quick", action="store_true", help="1 seed each and --cap-s 240")
    ap.add_argument("--cap-s", type=float, default=900.0, help="wall-clock cap per run (unsolved after it)")
    ap.add_argument("--sb3-eval-every", type=int, default=None,
                    help="SB3 env steps between evaluations (default: 1000 for DQN; 2500 for A2C, about the env "
                         "steps between two of zenrl A3C's evaluations: 0.5 s at ~5,000 steps/s)")
    ap.add_argument("--sb3-threads", type=int, default=1, help="torch threads for SB3 (zenrl uses 1 per process)")
    ap.add_argument("--skip-sb3", action="store_true", help="only zenrl")
    ap.add_argument("--skip-a3c", action="store_true", help="--algo impala: no zenrl A3C runs")
    ap.add_argument("--throughput-s", type=float, default=30.0,
                    help="--algo impala: seconds of each learner-consumption run (0: none)")
    ap.add_argument("--report-s", type=float, default=0.05,
                    help="actor.episode_report_s of the zenrl solve runs: the launcher's clock starts at the first "
                         "actor report, up to this long after the first env step")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for the zenrl runs (repeatable), e.g. --set evaluator.interval_s=1")
    ap.add_argument("--skip-contrast", action="store_true", help="--algo r2d2: no Ape-X runs")
    ap.add_argument("--first-seed", type=int, default=0, help="--algo r2d2: the first seed")
    args = ap.parse_args()
    if args.algo == "r2d2":
        r2d2_main(args)
        return
    if args.algo == "pendulum":
        pendulum_main(args)
        return
    load_start = os.getloadavg()
    seeds = 1 if args.quick else args.seeds
    cap = min(args.cap_s, 240.0) if args.quick else args.cap_s
    eval_every = args.sb3_eval_every or (1000 if args.algo == "apex" else 2500)
    zen, sb3, a3c = [], [], []
    consumption: dict[str, Any] = {}
    with_a3c = args.algo == "impala" and not args.skip_a3c
    with tempfile.TemporaryDirectory(prefix="zenrl-tts-") as tmp:
        for s in range(seeds):
            zen.append(run_zenrl(args.algo, s, cap, Path(tmp), args.set, args.report_s))
            if with_a3c:
                a3c.append(run_zenrl("a3c", s, cap, Path(tmp), report_s=args.report_s))
            if not args.skip_sb3:
                try:
                    sb3.append(run_sb3(args.algo, s, cap, eval_every, args.sb3_threads))
                except ImportError as e:
                    log(f"stable-baselines3 is not installed ({e}); pip install stable-baselines3")
                    args.skip_sb3 = True
        if args.algo == "impala" and args.throughput_s > 0:
            for algo in ["impala"] + (["a3c"] if with_a3c else []):
                consumption[algo] = learner_consumption(algo, args.throughput_s, Path(tmp), args.set if algo == "impala" else None)
    z_med = median_or_inf([r["solve_s"] for r in zen])
    s_med = median_or_inf([r["solve_s"] for r in sb3]) if sb3 else float("inf")
    ratio = z_med / s_med if z_med != float("inf") and s_med not in (0.0, float("inf")) else None
    startups = [r["startup_s"] for r in zen if r["startup_s"] is not None]
    result: dict[str, Any] = {
        "bench": "time_to_solve", "env": "CartPole-v1", "algo": args.algo, "target_return": TARGET,
        "eval_episodes": EVAL_EPISODES, "seeds": seeds, "quick": args.quick, "cap_s": cap,
        "report_s": args.report_s, "load_average": {"start": load_start, "end": os.getloadavg()},
        "zenrl": {"config": f"configs/cartpole_{args.algo}.yaml", "overrides": args.set, "median_solve_s": finite(z_med), "runs": zen},
        "sb3": {"algo": "DQN" if args.algo == "apex" else "A2C",  # a3c and impala: A2C
                "zoo_hyperparameters": ZOO_DQN if args.algo == "apex" else ZOO_A2C,
                "eval_every_steps": eval_every, "torch_threads": args.sb3_threads,
                "median_solve_s": finite(s_med), "runs": sb3} if sb3 else None,
        "startup_s": round(statistics.median(startups), 3) if startups else None,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
    }
    if args.algo == "apex":
        result["median_ratio_vs_sb3"] = None if ratio is None else round(ratio, 3)
    else:
        if args.algo == "impala":
            a_med = median_or_inf([r["solve_s"] for r in a3c]) if a3c else float("inf")
            result["zenrl_a3c"] = {"config": "configs/cartpole_a3c.yaml", "median_solve_s": finite(a_med),
                                   "runs": a3c} if a3c else None
            result["median_ratio_vs_a3c"] = (round(z_med / a_med, 3) if z_med != float("inf")
                                             and a_med not in (0.0, float("inf")) else None)
            ci, ca = (consumption.get(k, {}).get("median_env_steps_per_s") for k in ("impala", "a3c"))
            result["learner_consumption"] = {**consumption,
                                             "ratio_impala_vs_a3c": round(ci / ca, 3) if ci and ca else None}
        result["median_ratio_vs_sb3_a2c"] = None if ratio is None else round(ratio, 3)
        z_sps = [r["env_steps_per_s"] for r in zen if r["env_steps_per_s"]]
        s_sps = [r["env_steps_per_s"] for r in sb3 if r["env_steps_per_s"]]
        result["zenrl"]["median_env_steps_per_s"] = round(statistics.median(z_sps), 1) if z_sps else None
        if result["sb3"] is not None:
            result["sb3"]["median_env_steps_per_s"] = round(statistics.median(s_sps), 1) if s_sps else None
        result["throughput_ratio_vs_sb3_a2c"] = (round(statistics.median(z_sps) / statistics.median(s_sps), 3)
                                                 if z_sps and s_sps else None)
    print(json.dumps(result, default=float))


if __name__ == "__main__":
    main()
