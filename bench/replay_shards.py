"""Sharded replay throughput (issue 37): 1 vs ``--shards`` (default 2) ``zenrl replay`` processes.

In one run, rounds of the two set-ups alternate (1, N, 1, N, ...), each on a fresh run id through
the same in-process Zenoh router, every other party a separate OS process:

  * ``--publishers`` (default 2) publisher processes insert CartPole-sized Ape-X chunks (256
    transitions with priorities, ``ZenohReplayClient.insert``) as fast as they can; publisher p
    writes to shard p % N, as actor slot p does;
  * one learner-like sampler process draws batches of 128 with 4 requests in flight
    (``SamplePrefetcher``; across the shards by priority mass, ``ShardedReplayClient``, when N > 1)
    and sends each batch's new priorities back, as fast as the replay answers;
  * the replays run with their defaults (semantic checks on) and publish stats every 0.1 s.

Both run at once for ``--duration`` s; over the window that leaves out the first and last 0.5 s,
``ingest`` is the transitions/s the replays inserted (summed over the shards, from their own
``inserted_total``) and ``sample`` the items/s the sampler got. Medians over the rounds of each
set-up are compared: ``ingest_ratio`` = N shards / 1 shard, ``sample_ratio`` likewise. Also
over the window: the replay processes' CPU time (/proc) per 1k items inserted
(``cpu_per_item_ratio``, N / 1: what sharding adds per item) and the busiest replay process's
CPU / wall (``busiest_replay_cpu_fraction_*``: near 1, a replay process is its own bound; well
below, the machine's cores are). And in process, the learner's CPU per batch of 128 to decode
one replay's reply vs N replies and combine them (``client_cost_ratio``).

Each shard is one process with its own interpreter, so shards add ingest capacity while CPU
cores are free; on a 2-core machine every process shares the same two cores and the ratio shows
the cost of the extra process and the sharded sampling rather than a gain (docs/benchmarks.md).

Progress goes to stderr; the last stdout line is one JSON object.

    python bench/replay_shards.py            # 3 rounds of each, 8 s (~2-3 min)
    python bench/replay_shards.py --quick    # 1 round of each, 4 s (~40 s)

Internal roles (started by the benchmark itself): ``--role pub``, ``--role sampler``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from _common import Procs, ab_cpu_us, emit, log, machine_info, record_error, shut_down, stop_on_sigterm, wait_until  # noqa: E402  (bench/ is on sys.path when run as a script)

CHUNK = 256
SAMPLE_BATCH = 128
IN_FLIGHT = 4
#: the part of each round left out of the rates at either end (start-up, drain)
EDGE_S = 0.5


def _watch_parent(stop: threading.Event) -> None:
    """Role processes end by themselves if the benchmark that started them is gone."""
    from zenrl.common.signals import install_stop_signals

    parent = int(os.environ.get("BENCH_PARENT_PID", "0") or 0)
    install_stop_signals(stop)  # not a lambda: a handler that sets the event can deadlock

    def loop() -> None:
        while not stop.wait(0.5):
            if parent and os.getppid() != parent:
                stop.set()
                time.sleep(5)
                os._exit(3)

    threading.Thread(target=loop, daemon=True).start()


def _chunks(seed: int, count: int) -> list[tuple[dict[str, np.ndarray], np.ndarray]]:
    """``count`` CartPole-sized Ape-X chunks (inside CartPole's bounds, which the replay checks)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        b = CHUNK
        out.append(({"obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
                     "action": rng.integers(0, 2, b).astype(np.int64),
                     "reward": rng.random(b).astype(np.float32) * 3,
                     "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
                     "terminated": rng.random(b) < 0.02, "truncated": np.zeros(b, bool),
                     "n": np.full(b, 3, np.uint8)},
                    (rng.random(b) + 0.01).astype(np.float32)))
    return out


# ---------------------------------------------------------------------------------------------
# roles
# ---------------------------------------------------------------------------------------------
def role_pub(args: argparse.Namespace) -> int:
    """Insert chunks into shard ``--slot % --shards`` from ``--start-at`` (epoch s) for ``--duration`` s."""
    from zenrl.common import protocol as P
    from zenrl.common.replay_client import ZenohReplayClient
    from zenrl.common.transport import Node

    stop = threading.Event()
    _watch_parent(stop)
    pool = _chunks(args.slot, 32)
    with Node(args.router, 20.0) as node:
        client = ZenohReplayClient(node, P.Keys(args.run, P.actor_shard(args.slot, args.shards)), f"pub{args.slot}")
        client.insert(*pool[0])  # declares the publisher and waits for its replay's subscription
        while time.time() < args.start_at and not stop.is_set():
            time.sleep(0.005)
        i, end = 0, args.start_at + args.duration
        while time.time() < end and not stop.is_set():
            client.insert(*pool[i % len(pool)])
            i += 1
        client.flush_backlog()
    print(json.dumps({"chunks": i, "undelivered": client.undelivered_chunks}), flush=True)
    return 0


def role_sampler(args: argparse.Namespace) -> int:
    """Sample batches of 128 with 4 in flight, priorities sent back; count items in the window."""
    from zenrl.common.replay_client import SamplePrefetcher, replay_client_for
    from zenrl.common.transport import Node

    stop = threading.Event()
    _watch_parent(stop)
    rng = np.random.default_rng(0)
    with Node(args.router, 20.0) as node:
        client = replay_client_for(node, args.run, args.shards, "bench-sampler", 5.0, 64 * 1024 * 1024, seed=1)
        pf = SamplePrefetcher(client, SAMPLE_BATCH, lambda: 0.4, IN_FLIGHT, backoff_s=0.01).start()
        lo, hi = args.start_at + EDGE_S, args.start_at + args.duration - EDGE_S
        items = batches = 0
        try:
            while not stop.is_set():
                now = time.time()
                if now >= hi:
                    break
                s = pf.get(0.2)
                if s is None:
                    continue
                client.update_priorities(s.keys, rng.random(len(s.keys)).astype(np.float32) + 0.01)
                if lo <= time.time() < hi:
                    items += len(s.keys)
                    batches += 1
        finally:
            pf.stop()
    out = {"items_per_s": items / (hi - lo), "batches": batches, "not_ready": pf.not_ready,
           "timeouts": pf.timeouts, "errors": pf.errors}
    if hasattr(client, "values"):
        out["shards"] = client.values()
    print(json.dumps(out), flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# orchestration
# ---------------------------------------------------------------------------------------------
class ReplayStats:
    """``(time, inserted_total)`` of each replay process of one run, from its stats."""

    def __init__(self, node: Any, run_id: str) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self.seen: dict[str, list[tuple[float, int]]] = {}
        self._lock = threading.Lock()
        node.subscribe(P.Keys(run_id).stats_all, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        s = self._P.Stats.decode(payload)
        if s.role == "replay":
            with self._lock:
                self.seen.setdefault(s.id, []).append((s.time, int(s.values.get("inserted_total", 0))))

    def rate(self, lo: float, hi: float) -> tuple[float, dict[str, float]]:
        """Inserted transitions/s over [lo, hi], summed over the replays (per replay too)."""
        per = {}
        with self._lock:
            for sid, pts in self.seen.items():
                inside = [(t, v) for t, v in pts if lo <= t <= hi]
                if len(inside) < 2:
                    raise RuntimeError(f"replay {sid} published {len(inside)} stats in the window")
                (t0, v0), (t1, v1) = inside[0], inside[-1]
                per[sid] = (v1 - v0) / (t1 - t0)
        return sum(per.values()), per


def one_round(procs: Procs, node: Any, endpoint: str, tmp: Path, shards: int, args: argparse.Namespace) -> dict[str, Any]:
    from zenrl.common import protocol as P

    run_id = f"shb{uuid.uuid4().hex[:8]}"
    conf = tmp / f"{run_id}.yaml"
    conf.write_text(f"replay:\n  capacity: 200000\n  min_size: 1000\n  stats_interval_s: 0.1\n  shards: {shards}\n")
    keys = P.Keys(run_id)
    watch = ReplayStats(node, run_id)
    mine = []
    for k in range(shards):
        extra = [] if shards == 1 else ["--shard", str(k)]
        mine.append(procs.start(f"{run_id}-replay{k}", ["-m", "zenrl.cli", "replay", "--config", str(conf), "--run-id",
                                                        run_id, "--router", endpoint, "--log-level", "WARNING", *extra]))
    wait_until(lambda: len(node.alive_now(keys.alive_role("replay"), 1.0)) == shards, 120, f"{shards} replay(s) up")
    start_at = time.time() + args.lead_s
    common = ["--run", run_id, "--router", endpoint, "--shards", str(shards), "--start-at", str(start_at),
              "--duration", str(args.duration)]
    pubs = [procs.start(f"{run_id}-pub{p}", [__file__, "--role", "pub", "--slot", str(p), *common], capture=True)
            for p in range(args.publishers)]
    sampler = procs.start(f"{run_id}-sampler", [__file__, "--role", "sampler", *common], capture=True)
    # the replays' CPU over the window (utime + stime from /proc): how the ingest work splits
    lo, hi = start_at + EDGE_S, start_at + args.duration - EDGE_S
    time.sleep(max(0.0, lo - time.time()))
    cpu0 = [_cpu_s(p.pid) for p in mine]
    time.sleep(max(0.0, hi - time.time()))
    cpu1 = [_cpu_s(p.pid) for p in mine]
    cpu = [b - a for a, b in zip(cpu0, cpu1)]
    outs = {}
    for name, p in [*((f"pub{i}", p) for i, p in enumerate(pubs)), ("sampler", sampler)]:
        out, _ = p.communicate(timeout=args.lead_s + args.duration + 120)
        if p.returncode != 0:
            raise RuntimeError(f"{name} exited with {p.returncode}: {procs.log_text(f'{run_id}-{name}')[-2000:]}")
        outs[name] = json.loads(out.strip().splitlines()[-1])
    time.sleep(0.3)  # the replays' next stats, past the window's end
    ingest, per = watch.rate(lo, hi)
    for p in mine:
        procs.stop(p)
    s = outs["sampler"]
    wall = hi - lo
    # CPU per 1k items inserted (all replay processes; sampling's share included) and the busiest
    # replay process's CPU / wall: near 1.0 that process is its own bound, well below it the
    # machine is (every process shares its cores)
    cpu_per_k = sum(cpu) / max(ingest * wall, 1.0) * 1000
    busiest = max(cpu) / wall
    log(f"  {shards} shard(s): ingest {ingest:,.0f} transitions/s {({k: round(v) for k, v in per.items()})}, "
        f"sample {s['items_per_s']:,.0f} items/s (not ready {s['not_ready']}, timeouts {s['timeouts']}); "
        f"replay CPU {[round(c / wall, 2) for c in cpu]} of a core, {cpu_per_k * 1e3:.1f} ms per 1k items")
    return {"shards": shards, "ingest_items_per_s": ingest, "ingest_per_shard": per, "sample_items_per_s": s["items_per_s"],
            "replay_cpu_ms_per_1k_items": cpu_per_k * 1e3, "replay_cpu_fraction_each": [c / wall for c in cpu],
            "busiest_replay_cpu_fraction": busiest, "sampler": s,
            "published_chunks": sum(o["chunks"] for k, o in outs.items() if k != "sampler")}


def client_cost(shards: int, rounds: int = 5, round_s: float = 0.3) -> dict[str, float]:
    """The learner's CPU per batch of SAMPLE_BATCH CartPole items, in process: decoding one
    replay's reply vs ``shards`` replies of a share each plus the sharded client's combine
    (keys, global probabilities, IS weights, concatenated data)."""
    from zenrl.common import protocol as P
    from zenrl.common.replay_client import ShardedReplayClient, ZenohReplayClient

    rng = np.random.default_rng(0)

    def reply(n: int) -> bytes:
        b, _ = _chunks(n, 1)[0]
        data = {k: v[:n] for k, v in b.items()}
        data["meta/policy_version"] = np.zeros(n, np.int64)
        return P.SampleReply(request_id=1, status="ok", replay_size=100_000, keys=rng.integers(0, 1 << 20, n),
                             probabilities=rng.random(n) * 1e-5 + 1e-6, weights=np.ones(n, np.float32), data=data,
                             mass=1000.0).encode()

    one = ZenohReplayClient(None, P.Keys("bench"))  # type: ignore[arg-type]  (decoding only: no node used)
    many = ShardedReplayClient(None, "bench", shards)  # type: ignore[arg-type]
    whole = reply(SAMPLE_BATCH)
    parts = [reply(SAMPLE_BATCH // shards) for _ in range(shards)]
    q = 1.0 / shards

    def sharded(_: int) -> None:
        got = [(k, q, one.parse_reply(p)) for k, p in enumerate(parts)]
        many.combine(got, 0.4)

    us = ab_cpu_us({"one": lambda _: one.parse_reply(whole), "sharded": sharded}, rounds, round_s)
    return {"client_us_per_batch_1": us["one"], f"client_us_per_batch_{shards}": us["sharded"],
            "client_cost_ratio": us["sharded"] / us["one"]}


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) process ``pid`` has used, from /proc (Linux)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--role", choices=("pub", "sampler"))
    ap.add_argument("--run")
    ap.add_argument("--router")
    ap.add_argument("--slot", type=int, default=0)
    ap.add_argument("--start-at", type=float, default=0.0)
    ap.add_argument("--shards", type=int, default=2, help="shards of the sharded set-up (default 2)")
    ap.add_argument("--publishers", type=int, default=2)
    ap.add_argument("--duration", type=float, default=8.0, help="seconds each round publishes and samples")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of each set-up")
    ap.add_argument("--lead-s", type=float, default=3.0, help="time the round's processes get to start")
    ap.add_argument("--quick", action="store_true", help="1 round of each, 4 s")
    args = ap.parse_args()
    if args.role == "pub":
        return role_pub(args)
    if args.role == "sampler":
        return role_sampler(args)
    if args.quick:
        args.rounds, args.duration = 1, 4.0
    if args.duration <= 2 * EDGE_S + 1:
        ap.error("--duration must leave at least 1 s between the edges")

    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port

    stop_on_sigterm()
    t_start = time.perf_counter()
    out: dict[str, Any] = {"bench": "replay_shards", "shards": args.shards, "publishers": args.publishers,
                           "duration_s": args.duration, "rounds": args.rounds, "sample_batch": SAMPLE_BATCH,
                           "in_flight": IN_FLIGHT, "load_avg_1m_start": os.getloadavg()[0]}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([endpoint])
    node = None
    tmp = Path(tempfile.mkdtemp(prefix="replay_shards_"))
    procs = Procs(tmp)
    rounds: list[dict[str, Any]] = []
    try:
        node = Node(endpoint, 20.0)
        out.update(client_cost(args.shards))
        log(f"learner's CPU per batch of {SAMPLE_BATCH}: one replay {out['client_us_per_batch_1']:.0f} us, "
            f"{args.shards} shards {out[f'client_us_per_batch_{args.shards}']:.0f} us")
        for r in range(args.rounds):
            for n in ((1, args.shards) if r % 2 == 0 else (args.shards, 1)):  # the order alternates
                log(f"round {r + 1}/{args.rounds}, {n} shard(s)")
                rounds.append(one_round(procs, node, endpoint, tmp, n, args))
        one = [x for x in rounds if x["shards"] == 1]
        many = [x for x in rounds if x["shards"] == args.shards]
        med = {k: {n: statistics.median(x[f"{k}_items_per_s"] for x in xs) for n, xs in ((1, one), (args.shards, many))}
               for k in ("ingest", "sample")}
        cpu = {n: statistics.median(x["replay_cpu_ms_per_1k_items"] for x in xs) for n, xs in ((1, one), (args.shards, many))}
        busy = {n: statistics.median(x["busiest_replay_cpu_fraction"] for x in xs) for n, xs in ((1, one), (args.shards, many))}
        out.update({"replay_cpu_ms_per_1k_items_1": cpu[1], f"replay_cpu_ms_per_1k_items_{args.shards}": cpu[args.shards],
                    "cpu_per_item_ratio": cpu[args.shards] / cpu[1],
                    "busiest_replay_cpu_fraction_1": busy[1], f"busiest_replay_cpu_fraction_{args.shards}": busy[args.shards]})
        out.update({"ingest_items_per_s_1": med["ingest"][1], f"ingest_items_per_s_{args.shards}": med["ingest"][args.shards],
                    "sample_items_per_s_1": med["sample"][1], f"sample_items_per_s_{args.shards}": med["sample"][args.shards],
                    "ingest_ratio": med["ingest"][args.shards] / med["ingest"][1],
                    "sample_ratio": med["sample"][args.shards] / med["sample"][1],
                    "rounds_detail": [{k: v for k, v in x.items() if k != "sampler"} | {"sampler": x["sampler"]}
                                      for x in rounds]})
    except BaseException as e:  # noqa: BLE001  (the JSON line still comes, naming the failure)
        record_error(out, e)
    finally:
        shut_down(procs, node, router)
    out.update(machine_info(t_start))
    return emit(out)


if __name__ == "__main__":
    sys.exit(main())
