"""Durable replay (issue 4): ingest cost of the append-only log, and what a SIGKILL loses.

Two measurements:

  * ``durable_ingest_ratio`` - transitions/s through ``ReplayService.ingest()`` (decode, validate,
    insert; in this process, no network) with ``replay.durable=true`` divided by the same with
    it off, on the same pre-encoded CartPole chunks (64 transitions with priorities). Each round
    builds a fresh service (a fresh log directory on the same disk as /tmp) and ingests for a
    fixed time that spans ``replay.flush_interval_s`` (fsyncs) and ``replay.snapshot_interval_s``
    (a priority snapshot) at their defaults. Rounds alternate off/on; medians are compared
    (target >= 0.8).
  * ``lost_seconds_after_kill`` - a ``zenrl replay`` process with ``replay.durable=true`` takes
    a stream from a publisher process at a steady rate; the replay is SIGKILLed mid-stream and
    restarted on the same log directory; lost = (items sent before the kill - items restored) /
    stream rate. "Sent before the kill" is counted by a subscriber on the same key in this
    process, at the moment the kill returns (so chunks in flight to the replay count as lost);
    "restored" is read from the restarted replay's log line ``replay restored N items`` (or its
    stats ``restored_items``). Several trials kill at different phases of the flush cycle; the
    worst is reported (target <= 5 s).

Progress goes to stderr; the last stdout line is one JSON object.

    python bench/durability.py            # full run (~1.5-2 min)
    python bench/durability.py --quick    # short rounds, one kill (~30 s)

Internal role (started by the benchmark itself): ``--role pub``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from _common import Procs, emit, log, machine_info, record_error, shut_down, stop_on_sigterm, wait_until  # noqa: E402  (bench/ is on sys.path when run as a script)

CHUNK = 64
TARGET_RATIO = 0.8
TARGET_LOST_S = 5.0
STREAM_CHUNKS_PER_S = 200  # 12,800 transitions/s
RESTORED_RE = re.compile(r"replay restored (\d+) items \(keys up to (-?\d+)\)")


def cartpole_batches(seed: int, count: int) -> list[tuple[dict[str, np.ndarray], np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        b = CHUNK
        batch = {
            "obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),  # inside CartPole's bounds (the replay checks them)
            "action": rng.integers(0, 2, b).astype(np.int64),
            "reward": (rng.random(b) * 3).astype(np.float32),
            "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
            "terminated": rng.random(b) < 0.02,
            "truncated": np.zeros(b, bool),
            "n": np.full(b, 3, np.uint8),
        }
        out.append((batch, (rng.random(b) + 0.01).astype(np.float32)))
    return out


# --------------------------------------------------------------------------------------------
# role: a publisher at a steady rate
# --------------------------------------------------------------------------------------------
def role_pub(args: argparse.Namespace) -> int:
    from zenrl.common import protocol as P
    from zenrl.common.replay_client import ZenohReplayClient
    from zenrl.common.signals import install_stop_signals
    from zenrl.common.transport import Node

    stop = threading.Event()
    install_stop_signals(stop)  # not a lambda: a handler that sets the event can deadlock
    parent = int(os.environ.get("BENCH_PARENT_PID", "0") or 0)
    keys = P.Keys(args.run)
    batches = cartpole_batches(args.seed, 64)
    sent = 0
    with Node(args.router, 20.0) as node:
        client = ZenohReplayClient(node, keys, args.id)
        deadline = time.monotonic() + 60
        while not node.alive_now(keys.alive_role("replay"), 1.0):
            if time.monotonic() > deadline or stop.is_set():
                return 3
        period = 1.0 / args.rate
        nxt = time.perf_counter()
        while not stop.is_set():
            b, p = batches[sent % len(batches)]
            client.insert(b, p, policy_version=0)
            sent += 1
            nxt += period
            delay = nxt - time.perf_counter()
            if delay > 0:
                stop.wait(delay)
            if parent and sent % 100 == 0 and os.getppid() != parent:
                break
    print(json.dumps({"sent_chunks": sent}), flush=True)
    return 0


# --------------------------------------------------------------------------------------------
# part A: ingest cost of the log, in process
# --------------------------------------------------------------------------------------------
def ingest_round(durable: bool, payloads: list[bytes], log_dir: Path, duration_s: float) -> dict[str, Any]:
    from zenrl.common.config import load_config
    from zenrl.replay.service import ReplayService

    cfg = load_config(None, [f"replay.durable={'true' if durable else 'false'}", f"replay.log_dir={log_dir}",
                             "replay.capacity=100000"])
    svc = ReplayService(cfg, None, "benchdur")  # ingest() needs no network
    n_pool = len(payloads)
    for p in payloads[:8]:  # allocate storage, warm caches
        svc.ingest(p)
    items = 0
    i = 0
    t0, c0 = time.perf_counter(), time.thread_time()
    t_end = t0 + duration_s
    while True:
        for _ in range(32):
            items += svc.ingest(payloads[i % n_pool])
            i += 1
        if time.perf_counter() >= t_end:
            break
    el, cpu = time.perf_counter() - t0, time.thread_time() - c0
    res = {"items_per_s": items / el, "items_per_cpu_s": items / cpu, "items": items, "elapsed_s": el, "cpu_s": cpu,
           "rejected": svc.rejects.as_values().get("rejected_total", 0)}
    if durable:
        res.update({"log_bytes_written": svc.journal.bytes_written, "durable_through": svc.journal.durable_through})
        t = time.perf_counter()
        svc.close()  # final snapshot + flush: outside the window
        res["shutdown_s"] = time.perf_counter() - t
    return res


def part_a(rounds: int, duration_s: float, tmp: Path) -> dict[str, Any]:
    from zenrl.common import protocol as P

    payloads = [P.TransitionBatch(actor_id="bench", policy_version=0, seq=i, data=b, priorities=p).encode()
                for i, (b, p) in enumerate(cartpole_batches(7, 256))]
    off, on = [], []
    for r in range(rounds):
        res = ingest_round(False, payloads, tmp / f"off-{r}", duration_s)
        log(f"round {r} durable off: {res['items_per_s']:,.0f} items/s")
        off.append(res)
        d = tmp / f"on-{r}"
        res = ingest_round(True, payloads, d, duration_s)
        log(f"round {r} durable on:  {res['items_per_s']:,.0f} items/s ({res['log_bytes_written'] / 1e6:.0f} MB logged)")
        on.append(res)
        shutil.rmtree(d, ignore_errors=True)
    ratio = statistics.median(x["items_per_s"] for x in on) / statistics.median(x["items_per_s"] for x in off)
    ratio_cpu = statistics.median(x["items_per_cpu_s"] for x in on) / statistics.median(x["items_per_cpu_s"] for x in off)
    return {"ratio": ratio, "ratio_cpu": ratio_cpu, "off": off, "on": on,
            "chunk_bytes": len(payloads[0])}


# --------------------------------------------------------------------------------------------
# part B: loss window after SIGKILL
# --------------------------------------------------------------------------------------------
class Counter:
    """Counts transitions chunks seen on ``transitions/*`` (items and receipt times)."""

    def __init__(self, node: Any, keys: Any) -> None:
        self.items = 0
        self.first: float | None = None
        self.last: float | None = None
        self._lock = threading.Lock()
        node.subscribe(keys.transitions_all, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        t = time.perf_counter()
        with self._lock:
            self.items += CHUNK
            if self.first is None:
                self.first = t
            self.last = t

    def snapshot(self) -> tuple[int, float | None, float | None]:
        with self._lock:
            return self.items, self.first, self.last


class ReplayStats:
    def __init__(self, node: Any, keys: Any) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self.latest: dict[str, Any] | None = None
        node.subscribe(keys.stats("replay", "replay"), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        self.latest = dict(self._P.Stats.decode(payload).values)


def kill_trial(procs: Procs, node: Any, ep: str, trial: int, kill_after_s: float, tmp: Path) -> dict[str, Any]:
    from zenrl.common import protocol as P

    run = f"benchkill{uuid.uuid4().hex[:6]}"
    keys = P.Keys(run)
    log_dir = tmp / f"kill-{trial}"
    counter = Counter(node, keys)
    rstats = ReplayStats(node, keys)
    replay_args = ["-m", "zenrl.cli", "replay", "--router", ep, "--run-id", run,
                   "--set", "replay.durable=true", "--set", f"replay.log_dir={log_dir}",
                   "--set", "replay.capacity=200000", "--set", "replay.stats_interval_s=0.1"]
    replay = procs.start(f"replay-{trial}a", replay_args)
    wait_until(lambda: node.alive_now(keys.alive_role("replay"), 1.0), 60, "replay service")
    pub = procs.start(f"pub-{trial}", [str(Path(__file__).resolve()), "--role", "pub", "--router", ep, "--run", run,
                                       "--id", "pub0", "--rate", str(STREAM_CHUNKS_PER_S)], capture=True)
    wait_until(lambda: counter.snapshot()[0] > 0, 60, "the stream to start")
    wait_until(lambda: (rstats.latest or {}).get("inserted_total", 0) > 0, 60, "the replay to ingest")
    time.sleep(kill_after_s)
    last_stats = dict(rstats.latest or {})
    replay.kill()  # SIGKILL
    sent_items, first, last = counter.snapshot()
    replay.wait()
    t_kill = time.perf_counter()
    stream_rate = (sent_items - CHUNK) / (last - first) if last and first and last > first else None
    procs.stop(pub)
    pub_out = pub.stdout.read() if pub.stdout else ""
    # restart on the same log directory
    rstats.latest = None
    replay2 = procs.start(f"replay-{trial}b", replay_args)
    restored_log = None

    def restored() -> bool:
        nonlocal restored_log
        m = RESTORED_RE.search(procs.log_text(f"replay-{trial}b"))
        if m:
            restored_log = int(m.group(1))
        return restored_log is not None or rstats.latest is not None

    wait_until(restored, 120, "the restarted replay to restore")
    restart_s = time.perf_counter() - t_kill
    if restored_log is None:  # no log line (nothing restored?): its stats say how many
        wait_until(lambda: rstats.latest is not None, 30, "restarted replay stats")
    restored_stats = (rstats.latest or {}).get("restored_items") if rstats.latest else None
    restored_items = restored_log if restored_log is not None else int(restored_stats or 0)
    procs.stop(replay2)
    lost_items = sent_items - restored_items
    # what was inserted but not yet fsynced at the last stats before the kill: a SIGKILL keeps
    # what the process had written (the page cache survives it), an OS crash or power cut would not
    unsynced = None
    if last_stats.get("durable_through") is not None and stream_rate:
        unsynced = (last_stats["inserted_total"] - last_stats["durable_through"]) / stream_rate
    return {"unsynced_seconds_at_last_stats": unsynced,"kill_after_s": kill_after_s, "items_sent_before_kill": sent_items, "items_restored": restored_items,
            "restored_stats_items": restored_stats, "items_lost": lost_items,
            "stream_items_per_s": stream_rate,
            "lost_seconds": lost_items / stream_rate if stream_rate else None,
            "last_stats_before_kill": {k: last_stats.get(k) for k in ("inserted_total", "durable_through",
                                                                       "ingest_queue", "log_bytes_written")},
            "restart_to_restored_s": restart_s, "publisher": pub_out.strip()[-200:]}


def part_b(kill_times: list[float], tmp: Path) -> dict[str, Any]:
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port

    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([ep])
    procs = Procs(tmp)
    node = None
    trials = []
    try:
        node = Node(ep, 10.0)
        for i, k in enumerate(kill_times):
            tr = kill_trial(procs, node, ep, i, k, tmp)
            log(f"kill trial {i}: sent {tr['items_sent_before_kill']}, restored {tr['items_restored']}, "
                f"lost {tr['items_lost']} = {tr['lost_seconds']:.2f} s of stream")
            trials.append(tr)
    finally:
        shut_down(procs, node, router)
    return {"trials": trials}


# --------------------------------------------------------------------------------------------
def orchestrate(args: argparse.Namespace) -> int:
    from zenrl.common.config import ReplayConfig

    t_start = time.perf_counter()
    if args.quick:
        rounds, dur_s, kill_times = 1, 2.5, [2.3]
    else:
        rounds, dur_s, kill_times = 2, 10.5, [3.0, 4.35, 5.7]
    tmp = Path(tempfile.mkdtemp(prefix="zenrl-bench-durable-"))
    out: dict[str, Any] = {"bench": "durability", "quick": bool(args.quick), "error": None}
    try:
        log(f"part A: ReplayService.ingest in process, durable off vs on ({rounds} x {dur_s} s each); dir {tmp}")
        a = part_a(rounds, dur_s, tmp)
        log(f"part B: SIGKILL of a durable replay at {kill_times} s into a {STREAM_CHUNKS_PER_S * CHUNK} items/s stream")
        b = part_b(kill_times, tmp)
        lost = [t["lost_seconds"] for t in b["trials"] if t["lost_seconds"] is not None]
        rc = ReplayConfig()
        out.update({
            "durable_ingest_ratio": round(a["ratio"], 3),
            "target_durable_ingest_ratio": TARGET_RATIO,
            "durable_ingest_ratio_cpu": round(a["ratio_cpu"], 3),
            "ingest_items_per_s_off": round(statistics.median(x["items_per_s"] for x in a["off"])),
            "ingest_items_per_s_on": round(statistics.median(x["items_per_s"] for x in a["on"])),
            "lost_seconds_after_kill": round(max(lost), 3) if lost else None,
            "lost_seconds_mean": round(statistics.mean(lost), 3) if lost else None,
            "target_lost_seconds": TARGET_LOST_S,
            "unsynced_seconds_max": (round(max(t["unsynced_seconds_at_last_stats"] for t in b["trials"]), 3)
                                     if all(t["unsynced_seconds_at_last_stats"] is not None for t in b["trials"]) else None),
            "flush_interval_s": rc.flush_interval_s,
            "snapshot_interval_s": rc.snapshot_interval_s,
            "stream_items_per_s_nominal": STREAM_CHUNKS_PER_S * CHUNK,
            "chunk_items": CHUNK,
            "chunk_bytes": a["chunk_bytes"],
            "ingest_rounds": {"off": a["off"], "on": a["on"]},
            "kill_trials": b["trials"],
            "notes": ("ratio: in-process ReplayService.ingest on the same pre-encoded chunks, fresh service per "
                      "round, log on the ext4 disk holding /tmp, default flush (fsync) and snapshot intervals, "
                      "medians of alternating rounds; *_cpu uses the ingest thread's CPU time (fsync waits are "
                      "not CPU). lost_seconds_after_kill is the worst trial; a SIGKILL loses only what the process had not yet written (data written but not fsynced survives in the page cache), unsynced_seconds_max is the not-yet-fsynced part at the last stats before the kill, what an OS crash or power cut could lose; 2-core machine shared with other work"),
            **machine_info(t_start),
        })
    except BaseException as e:
        record_error(out, e)
    finally:
        if out.get("error"):
            log(f"logs kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return emit(out)



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short rounds, one kill")
    ap.add_argument("--role", choices=["pub"], help=argparse.SUPPRESS)
    ap.add_argument("--router", help=argparse.SUPPRESS)
    ap.add_argument("--run", help=argparse.SUPPRESS)
    ap.add_argument("--id", default="pub0", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=STREAM_CHUNKS_PER_S, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "pub":
        return role_pub(args)
    stop_on_sigterm()
    return orchestrate(args)


if __name__ == "__main__":
    sys.exit(main())
