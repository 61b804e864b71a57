"""Steps per second of the Burger War envs on one core.

Both robots move: the agent takes uniformly random actions from the users' 5-action set, the
opponent is the scripted ``teriyaki`` (lidar-driven, 10 Hz); capture/judge is on. Each variant
runs ``--repeats`` timed blocks of ``--steps`` env steps (episodes auto-reset) after a warm-up;
the reported rate is the best block (the machine may be shared), all blocks are listed too.

Prints ONE JSON object as the last stdout line: vector_steps_per_s, image_steps_per_s,
speedup_vs_gazebo (= vector_steps_per_s / 0.75, the users' Gazebo rate of ~180 transitions per
4-minute match), plus details.

    python bench/match_env.py [--steps 3000] [--image-steps 1000] [--repeats 3] [--cpu 0]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

GAZEBO_STEPS_PER_S = 0.75


def _rate(env, steps: int, repeats: int, seed: int) -> list[float]:
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    for _ in range(200):  # warm-up (caches, first episode setup)
        _, _, term, trunc, _ = env.step(int(rng.integers(5)))
        if term or trunc:
            env.reset()
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            _, _, term, trunc, _ = env.step(int(rng.integers(5)))
            if term or trunc:
                env.reset()
        rates.append(steps / (time.perf_counter() - t0))
    return rates


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--image-steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cpu", type=int, default=None, help="pin to this core (default: first allowed)")
    ap.add_argument("--opponent", default="teriyaki")
    args = ap.parse_args()

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    cpu = None
    if hasattr(os, "sched_setaffinity"):
        cpu = args.cpu if args.cpu is not None else min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})

    from zenrl.games.burgerwar.env import BurgerWarEnv

    env = BurgerWarEnv(opponents=args.opponent)
    vec = _rate(env, args.steps, args.repeats, 0)
    env.close()
    env = BurgerWarEnv(opponents=args.opponent, image=True, image_size=64)
    img = _rate(env, args.image_steps, args.repeats, 1)
    env.close()

    result = {
        "vector_steps_per_s": round(max(vec), 1),
        "image_steps_per_s": round(max(img), 1),
        "speedup_vs_gazebo": round(max(vec) / GAZEBO_STEPS_PER_S, 1),
        "vector_blocks_steps_per_s": [round(r, 1) for r in vec],
        "image_blocks_steps_per_s": [round(r, 1) for r in img],
        "vector_ms_per_step": round(1000.0 / max(vec), 3),
        "image_ms_per_step": round(1000.0 / max(img), 3),
        "opponent": args.opponent,
        "agent": "uniform random, users' 5 actions",
        "control_hz": 10,
        "physics_hz": 60,
        "image_size": 64,
        "cpu_pinned": cpu,
        "load_avg_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
