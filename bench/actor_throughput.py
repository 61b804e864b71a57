"""Actor throughput (issue 7): env steps/s of one Ape-X actor vs its bare environments.

Measures, in one run and one process, CartPole-v1 with 64 envs (``actor.envs_per_actor=64``,
network and n-step from ``configs/cartpole_apex.yaml``):

  * ``actor``    - env steps/s of an :class:`ApexActor` doing everything it does in a run:
                   batched Q forward, epsilon ladder, n-step transitions, initial priorities,
                   chunks published over Zenoh (BLOCK) to a running ``zenrl replay`` process;
  * ``baseline`` - env steps/s of the same :class:`EnvBatch` (64 envs, same-step auto-reset)
                   stepped with random actions, nothing computed or published.

Rounds alternate (baseline, actor, baseline, actor, ...) and the medians are compared:
``actor_efficiency`` = median actor rate / median baseline rate (target >= 0.8). The actor's rate
is read from its ``env_steps`` counter between two instants after a warm-up, so start-up (envs,
network, the initial weights query) is not counted. The replay's stats confirm that what was
published arrived.

When the efficiency (wall or CPU) is below target (or with ``--profile``), one more actor run is profiled with
cProfile and the report says where the time goes (``profile``).

Progress goes to stderr; the last stdout line is one JSON object.

    python bench/actor_throughput.py            # full run (~1.5 min)
    python bench/actor_throughput.py --quick    # one short round (~30 s)
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from _common import ROOT, Procs, emit, log, machine_info, record_error, shut_down, stop_on_sigterm, wait_until  # noqa: E402  (bench/ is on sys.path when run as a script)

CONFIG = ROOT / "configs" / "cartpole_apex.yaml"
ENVS = 64
TARGET = 0.8


class ReplayStats:
    def __init__(self, node: Any, keys: Any) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self.latest: dict[str, Any] = {}
        node.subscribe(keys.stats("replay", "replay"), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        self.latest = dict(self._P.Stats.decode(payload).values)


def baseline_rate(cfg: Any, warmup_s: float, duration_s: float, seed: int) -> dict[str, Any]:
    """Env steps/s of a bare EnvBatch with random actions."""
    from zenrl.actor.batch_env import EnvBatch
    from zenrl.common.networks import num_actions

    envs = EnvBatch(cfg.env, ENVS, seed=seed)
    n_act = num_actions(envs.single_action_space)
    rng = np.random.default_rng(seed)
    envs.reset()
    try:
        t_end = time.perf_counter() + warmup_s
        while time.perf_counter() < t_end:
            envs.step(rng.integers(0, n_act, ENVS))
        steps = 0
        t0, c0 = time.perf_counter(), time.thread_time()
        t_end = t0 + duration_s
        while True:
            for _ in range(10):
                envs.step(rng.integers(0, n_act, ENVS))
            steps += 10
            if time.perf_counter() >= t_end:
                break
        el, cpu = time.perf_counter() - t0, time.thread_time() - c0
    finally:
        envs.close()
    return {"env_steps_per_s": steps * ENVS / el, "env_steps_per_cpu_s": steps * ENVS / cpu,
            "batched_steps": steps, "elapsed_s": el, "cpu_s": cpu}


def make_actor(cfg: Any, node: Any, run: str, name: str) -> Any:
    from zenrl.actor.service import ApexActor

    return ApexActor(cfg, node, run, name, slot=0, num_slots=cfg.actor.num_actors)


def actor_rate(cfg: Any, node: Any, run: str, name: str, warmup_s: float, duration_s: float) -> dict[str, Any]:
    """Env steps/s of an ApexActor, read from its counter after a warm-up. The actor runs in
    this (the main) thread, as in ``zenrl actor``: torch's thread setting is per thread, and a
    second thread would run torch with its default pool; a helper thread reads the counter and
    stops the run."""
    actor = make_actor(cfg, node, run, name)
    stop = threading.Event()
    marks: list[tuple[int, float, float]] = []
    clock = time.pthread_getcpuclockid(threading.get_ident())  # this thread's CPU time

    def monitor() -> None:
        deadline = time.monotonic() + 60
        while actor.env_steps == 0 and not stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)
        if not stop.wait(warmup_s):
            marks.append((actor.env_steps, time.perf_counter(), time.clock_gettime(clock)))
            if not stop.wait(duration_s):
                marks.append((actor.env_steps, time.perf_counter(), time.clock_gettime(clock)))
        stop.set()

    mon = threading.Thread(target=monitor, name="monitor", daemon=True)
    mon.start()
    try:
        actor.run(stop)
    finally:
        stop.set()
        mon.join(timeout=10)
    if len(marks) < 2:
        raise RuntimeError("the actor stopped before the measurement window ended")
    (s0, t0, c0), (s1, t1, c1) = marks
    return {"env_steps_per_s": (s1 - s0) / (t1 - t0), "env_steps_per_cpu_s": (s1 - s0) / (c1 - c0),
            "elapsed_s": t1 - t0, "cpu_s": c1 - c0,
            "sent_transitions": actor.sent_transitions, "sent_chunks": actor.replay.sent_chunks,
            "undelivered_chunks": actor.replay.undelivered_chunks, "env_steps_total": actor.env_steps}


# --------------------------------------------------------------------------------------------
# profile
# --------------------------------------------------------------------------------------------
#: (label, file suffix, function name) whose cumulative time is reported as a share of the run
BUCKETS = [
    ("env_step (EnvBatch.step, incl. gym + stacking)", "actor/batch_env.py", "step"),
    ("gym env.step/reset called by EnvBatch.step", None, "gym"),  # from the callers table
    ("stack_flat (obs list -> array)", "actor/batch_env.py", "stack_flat"),
    ("q_forward (numpy or torch)", "actor/policies.py", "__call__"),
    ("n-step blocks: record each step + emit (incl. priorities)", "actor/nstep.py", "add"),
    ("n-step blocks: emit (per block)", "actor/nstep.py", "_emit"),
    ("send (encode, put)", "actor/adders.py", "_send"),
    ("replay_client.insert (encode + put)", "common/replay_client.py", "insert"),
    ("TransitionBatch.encode", "common/protocol.py", "encode"),
    ("zenoh put", "common/replay_client.py", "_put"),
    ("weights.maybe_load", "actor/weights.py", "maybe_load"),
    ("episode/stats report", "common/roles.py", "_report"),
]


def profile_actor(cfg: Any, node: Any, run: str, duration_s: float) -> dict[str, Any]:
    """cProfile one actor run (in this thread) for ``duration_s`` after its start-up."""
    actor = make_actor(cfg, node, run, "bench-actor-prof")
    stop = threading.Event()
    timer_started = threading.Event()

    def stopper() -> None:
        wait_until(lambda: actor.env_steps > 0, 60, "the actor's first step", 0.01)
        timer_started.set()
        time.sleep(duration_s)
        stop.set()

    threading.Thread(target=stopper, daemon=True).start()
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    try:
        actor.run(stop)
    finally:
        prof.disable()
    wall = time.perf_counter() - t0
    st = pstats.Stats(prof)
    entries = st.stats  # {(file, line, func): (cc, nc, tt, ct, callers)}
    # the run loop's own cumulative time (excludes the start-up query for weights)
    run_ct = next((v[3] for k, v in entries.items() if k[0].endswith("common/roles.py") and k[2] == "run"), wall)
    init_ct = sum(v[3] for k, v in entries.items() if k[0].endswith("actor/weights.py") and k[2] == "fetch_initial")
    loop_ct = max(run_ct - init_ct, 1e-9)
    buckets = {}
    for label, suffix, func in BUCKETS:
        if suffix is None:  # gymnasium's outermost step/reset as called from EnvBatch.step
            ct = sum(c[3] for k, v in entries.items() if "gymnasium" in k[0] and k[2] in ("step", "reset")
                     for ck, c in v[4].items() if ck[0].endswith("actor/batch_env.py") and ck[2] == "step")
        else:
            ct = sum(v[3] for k, v in entries.items() if k[0].endswith(suffix) and k[2] == func)
        buckets[label] = {"s": round(ct, 3), "share_of_loop": round(ct / loop_ct, 3)}
    top = sorted(entries.items(), key=lambda kv: kv[1][2], reverse=True)[:15]
    top_list = [{"func": f"{Path(k[0]).name}:{k[1]}({k[2]})", "tottime_s": round(v[2], 3), "cumtime_s": round(v[3], 3),
                 "calls": v[1]} for k, v in top]
    return {"profiled_s": round(wall, 2), "loop_s": round(loop_ct, 2), "initial_weights_query_s": round(init_ct, 2),
            "env_steps": actor.env_steps, "env_steps_per_s_under_profiler": round(actor.env_steps / loop_ct),
            "buckets": buckets, "top_tottime": top_list}


# --------------------------------------------------------------------------------------------
def orchestrate(args: argparse.Namespace) -> int:
    import torch

    from zenrl.common import protocol as P
    from zenrl.common.config import load_config
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port

    t_start = time.perf_counter()
    rounds, warmup_s, dur_s = (1, 1.0, 3.0) if args.quick else (3, 1.5, 8.0)
    ep = f"tcp/127.0.0.1:{free_port()}"
    run = f"bench{uuid.uuid4().hex[:8]}"
    keys = P.Keys(run)
    tmp = Path(tempfile.mkdtemp(prefix="zenrl-bench-actor-"))
    overrides = [f"actor.envs_per_actor={ENVS}", f"transport.router={ep}", f"run_id={run}",
                 f"runs_dir={tmp / 'runs'}"] + list(args.set)
    cfg = load_config(CONFIG, overrides)
    out: dict[str, Any] = {"bench": "actor_throughput", "quick": bool(args.quick), "error": None}
    router = open_router([ep])
    procs = Procs(tmp)
    node = None
    try:
        node = Node(ep, 10.0)
        rstats = ReplayStats(node, keys)
        log(f"router {ep}, run {run}, logs in {tmp}")
        procs.start("replay", ["-m", "zenrl.cli", "replay", "--config", str(CONFIG), "--router", ep, "--run-id", run,
                               "--set", "replay.stats_interval_s=0.25"])
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 1.0), 60, "replay service")
        base, act = [], []
        for r in range(rounds):
            b = baseline_rate(cfg, warmup_s, dur_s, seed=1000 + r)
            log(f"round {r} baseline (EnvBatch, random actions): {b['env_steps_per_s']:,.0f} env steps/s")
            base.append(b)
            a = actor_rate(cfg, node, run, f"bench-actor-{r}", warmup_s, dur_s)
            log(f"round {r} ApexActor: {a['env_steps_per_s']:,.0f} env steps/s, "
                f"{a['sent_transitions']} transitions sent")
            act.append(a)
        sent_total = sum(a["sent_transitions"] for a in act)
        try:
            wait_until(lambda: rstats.latest.get("inserted_total", 0) >= sent_total, 15, "replay to ingest everything")
        except RuntimeError as e:
            log(str(e))
        base_med = statistics.median(x["env_steps_per_s"] for x in base)
        act_med = statistics.median(x["env_steps_per_s"] for x in act)
        eff = act_med / base_med
        eff_cpu = (statistics.median(x["env_steps_per_cpu_s"] for x in act)
                   / statistics.median(x["env_steps_per_cpu_s"] for x in base))
        out.update({
            "actor_efficiency": round(eff, 3),
            "target_efficiency": TARGET,
            "actor_efficiency_cpu": round(eff_cpu, 3),
            "actor_env_steps_per_s": round(act_med),
            "baseline_env_steps_per_s": round(base_med),
            "envs_per_actor": ENVS,
            "env": cfg.env.id,
            "network_hidden": list(cfg.network.hidden),
            "n_step": cfg.actor.n_step,
            "chunk_size": cfg.actor.chunk_size,
            "torch_threads": cfg.actor.torch_threads,
            "transitions_sent": sent_total,
            "replay_inserted_total": rstats.latest.get("inserted_total"),
            "replay_rejected_total": rstats.latest.get("rejected_total"),
            "rounds": {"baseline": base, "actor": act},
        })
        if min(eff, eff_cpu) < TARGET or args.profile:
            log("profiling one more actor run (cProfile)")
            out["profile"] = profile_actor(cfg, node, run, 3.0 if args.quick else 6.0)
        out.update({
            "notes": ("one process, one thread stepping; rates between two instants after a warm-up; "
                      "actor_efficiency_cpu compares env steps per CPU-second of the stepping thread (steadier "
                      "than wall time on a loaded machine; excludes Zenoh's own threads and the replay); "
                      "medians of alternating rounds; the replay service (a separate process) and the router "
                      "(in this process) use CPU during the actor rounds only; 2-core machine shared with "
                      "other work"),
            "torch": torch.__version__,
            **machine_info(t_start),
        })
    except BaseException as e:
        record_error(out, e)
    finally:
        shut_down(procs, node, router)
    return emit(out)



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one short round")
    ap.add_argument("--profile", action="store_true", help="profile the actor even if it meets the target")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override (repeatable), e.g. --set actor.chunk_size=1024")
    args = ap.parse_args(argv)
    stop_on_sigterm()
    return orchestrate(args)


if __name__ == "__main__":
    sys.exit(main())
