"""Replay service throughput over Zenoh (issues 2, 37): a real ``zenrl replay`` process vs raw Zenoh.

Measures, in one run, on loopback through an in-process Zenoh router (every other party is a
separate OS process, all Zenoh clients of that router, all with the transport settings a zenrl
role gets from its config: shared memory off unless ``--shm``, the replay's receive cap on the
receivers):

  * ``ingest`` - transitions/s inserted by a ``zenrl replay`` process fed by 2 publisher
    processes (``ZenohReplayClient.insert``: CartPole-sized chunks of actor.chunk_size (default
    256) transitions with priorities), measured at the receiver from the service's own stats
    (``inserted_total`` with ``replay.stats_interval_s`` = 0.05 s);
  * ``raw`` - the same byte stream (the same encoded ``transitions`` messages, put with the
    same BLOCK publisher settings) from 2 publisher processes to a raw Zenoh subscriber process
    that only takes the bytes (``payload.to_bytes()``) and counts, measured at the receiver
    (first to last receipt);
  * ``store_only`` (``--images``) - the ceiling of any receiver that keeps what it gets: the
    same publishers as ``ingest`` (``ZenohReplayClient``) to a subscriber process that takes the
    bytes and copies them into a pre-touched ring of the replay's frame bytes, nothing else;
    ``service_fraction_of_store_only`` = median service rate / median store-only rate (target
    >= 0.8), with a learner-like sampler (batch 128, 4 requests in flight, ``SamplePrefetcher``
    over the replay's queryable; ``--sample-rate`` caps it, ``--sample-rate learner`` caps it at
    the Ape-X learner's own update rate for that kind's observations on this machine, measured
    first in memory with nothing else running (``learner_updates_per_s``: an upper bound of what
    a learner sharing the machine would take), ``--no-sampler`` leaves it out) running through
    every service round;
  * ``store_only_sampled`` (``--images --ceiling``) - store-only rounds with the same sampler
    sampling another replay, filled once before the rounds: ``ceiling_fraction_of_store_only``
    = median of those / median store-only rate, the most any replay sampled as the service is can
    take on this machine (its own ingest free), and ``service_fraction_of_ceiling``;
  * ``threads`` - per thread of the receiving process (the replay, the store-only receiver), over
    each round: CPU, wake-ups, preemptions and minor page faults per chunk (``/proc``; zenrl's
    threads are named, Zenoh's runtime names its own: ``rx-0``, ``tx-0``, ...);
  * ``checks`` - CPU time per chunk of the service's ingest path (decode, validate, insert) with
    ``replay.check_semantics`` on and off, in process: ``checks_overhead_ratio`` (target <= 1.05);
  * ``sample`` - batches/s of 512 served by the replay to one client process keeping 4 requests
    in flight (``SamplePrefetcher``), after the ingest rounds filled it (CartPole mode).

Rounds alternate (raw, [store-only,] service, ...) and medians are compared:
``ingest_ratio_vs_raw_zenoh`` = median service rate / median raw rate (target >= 0.7).
``--baseline DIR`` adds, in the same rounds, service rounds on the replay of another zenrl
checkout (run with DIR/.venv): ``service_vs_baseline`` is an A/B of the replay's code on the same
machine, publishers and router. With ``--images`` it also runs the in-process ingest of each
kind with each checkout's code, each in a process of its own, alternating:
``inprocess_cpu_baseline_vs_service`` (> 1: this checkout's ingest costs less CPU per chunk).

Progress goes to stderr; the last stdout line is one JSON object.

    python bench/replay_service.py            # full run (~1.5-2 min)
    python bench/replay_service.py --quick    # one short round each (~30 s)
    python bench/replay_service.py --images   # image mode: 64x64x3 and 84x84x4-stack chunks (~5 min)
    python bench/replay_service.py --images --baseline ../main   # ... and main's replay, same rounds
    python bench/replay_service.py --images --ceiling --sample-rate learner   # ... and the ceiling
    python bench/replay_service.py --checks-only   # the semantic checks' cost per chunk (~25 s)

For diagnosis: ``--kinds``, ``--rounds``, ``--service-only``, ``--service-set KEY=VALUE`` (an
option for this checkout's replay only), ``--codec lz4``, ``--shm``.

Internal roles (started by the benchmark itself): ``--role pub``, ``--role rawsub``,
``--role sampler``, ``--role inproc``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from _common import ROOT, Procs, ab_cpu_us, emit, log, machine_info, record_error, shut_down, stop_on_sigterm, wait_until  # noqa: E402  (bench/ is on sys.path when run as a script)
from zenrl.common.config import ActorConfig  # noqa: E402

CHUNK = ActorConfig().chunk_size  # what actors send by default
#: transitions per image chunk (--images): configs/burgerwar_image_apex.yaml sends 32
IMAGE_CHUNK = 64
IMAGE_N_STEP = 3
IMAGE_STACK = 4
#: --images: the Burger War camera (64x64x3, one frame per observation) and Atari-style
#: 4-frame stacks of 84x84 frames, both in frame mode (docs/protocol.md)
IMAGE_KINDS = ("cam64", "atari84")
#: --images: the replay's capacity (transitions); the store-only receiver gets a ring of the
#: same frame bytes, so both write into memory far larger than the caches
IMAGE_CAPACITY = 20000


def chunk_items(kind: str) -> int:
    return CHUNK if kind == "cartpole" else IMAGE_CHUNK
SAMPLE_BATCH = 512
IN_FLIGHT = 4
#: --images: the sampler that runs through the service rounds samples as the Ape-X learner does
#: at its defaults (learner.batch_size, learner.requests_in_flight)
LEARNER_BATCH = 128
LEARNER_IN_FLIGHT = 4
N_PUBLISHERS = 2


# ---------------------------------------------------------------------------------------------
# helpers shared by the roles
# ---------------------------------------------------------------------------------------------
def watch_parent(stop: threading.Event) -> None:
    """Role processes end by themselves if the benchmark that started them is gone."""
    from zenrl.common.signals import install_stop_signals

    parent = int(os.environ.get("BENCH_PARENT_PID", "0") or 0)
    install_stop_signals(stop)  # not a lambda: a handler that sets the event can deadlock
    if not parent:
        return

    def loop() -> None:
        while not stop.wait(0.5):
            if os.getppid() != parent:
                stop.set()
                time.sleep(5)
                os._exit(3)

    threading.Thread(target=loop, daemon=True).start()


def bench_node(router: str, shm: bool, receiver: bool = False) -> Any:
    """A node with the transport settings a zenrl role gets from its config: shared memory as
    ``--shm`` says (off, the zenrl default, unless given), and for a receiver of chunks the
    replay's receive cap. Every party of a round (publishers, receivers, the replay, the sampler)
    uses the same settings, so that a rate compared with another was carried the same way."""
    from zenrl.common.config import load_config
    from zenrl.common.transport import Node
    from zenrl.replay.service import rx_cap

    cfg = load_config(None, [f"transport.router={router}", f"transport.shared_memory={str(shm).lower()}",
                             "transport.connect_timeout_s=20"])
    return Node.from_config(cfg.transport, max_rx_bytes=rx_cap(cfg) if receiver else None)


def task_cpu(pid: int | str = "self") -> dict[int, tuple[str, float, int, int, int]]:
    """Per thread of process ``pid``: ``(name, CPU seconds, voluntary, involuntary context
    switches, minor page faults)`` from ``/proc`` (Linux; empty elsewhere). A voluntary switch is
    a wait: a wake-up; a minor fault is mostly a first touch of fresh memory."""
    out: dict[int, tuple[str, float, int, int, int]] = {}
    base = f"/proc/{pid}/task"
    try:
        tids = os.listdir(base)
    except OSError:
        return out
    tick = os.sysconf("SC_CLK_TCK")
    for tid in tids:
        try:
            with open(f"{base}/{tid}/stat") as f:
                st = f.read()
            with open(f"{base}/{tid}/status") as f:
                status = dict(line.split(":", 1) for line in f.read().splitlines() if ":" in line)
        except OSError:
            continue  # ended meanwhile
        rest = st[st.rindex(")") + 2:].split()  # fields 3.. of proc(5); minflt is 10, utime, stime 14, 15
        out[int(tid)] = (st[st.index("(") + 1:st.rindex(")")], (int(rest[11]) + int(rest[12])) / tick,
                         int(status.get("voluntary_ctxt_switches", 0)), int(status.get("nonvoluntary_ctxt_switches", 0)),
                         int(rest[7]))
    return out


def thread_breakdown(before: dict[int, tuple[str, float, int, int, int]],
                     after: dict[int, tuple[str, float, int, int, int]], chunks: int, span_s: float) -> dict[str, Any]:
    """CPU and wake-ups of a process's threads between two :func:`task_cpu` snapshots, grouped
    by thread name (Zenoh's runtime names its threads, e.g. ``rx-0``; zenrl names its watched
    threads): per group ``cores`` (CPU s / ``span_s``), ``us_per_chunk``, ``wakeups_per_chunk``,
    ``preempted_per_chunk`` and ``faults_per_chunk`` (minor page faults)."""
    groups: dict[str, list[float]] = {}
    for tid, (name, cpu, vol, invol, flt) in after.items():
        _, cpu0, vol0, invol0, flt0 = before.get(tid, (name, 0.0, 0, 0, 0))
        g = groups.setdefault(name, [0.0, 0, 0, 0, 0])
        g[0] += cpu - cpu0
        g[1] += vol - vol0
        g[2] += invol - invol0
        g[3] += flt - flt0
        g[4] += 1
    n = max(chunks, 1)
    out = {name: {"cores": round(c / span_s, 3) if span_s > 0 else None, "us_per_chunk": round(c / n * 1e6, 1),
                  "wakeups_per_chunk": round(v / n, 2), "preempted_per_chunk": round(iv / n, 2),
                  "faults_per_chunk": round(f / n, 1), "threads": int(k)}
           for name, (c, v, iv, f, k) in sorted(groups.items(), key=lambda kv: -kv[1][0]) if c > 0 or v > 0}
    total = sum(g[0] for g in groups.values())
    return {"chunks": chunks, "span_s": round(span_s, 2), "cores": round(total / span_s, 3) if span_s > 0 else None,
            "us_per_chunk": round(total / n * 1e6, 1), "by_thread": out}


def cartpole_batches(seed: int, count: int) -> list[tuple[dict[str, np.ndarray], np.ndarray]]:
    """``count`` distinct CartPole-sized Ape-X chunks of CHUNK transitions with priorities."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        b = CHUNK
        batch = {
            # inside CartPole's observation bounds, which the replay checks
            "obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
            "action": rng.integers(0, 2, b).astype(np.int64),
            "reward": rng.random(b).astype(np.float32) * 3,
            "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
            "terminated": rng.random(b) < 0.02,
            "truncated": np.zeros(b, bool),
            "n": np.full(b, 3, np.uint8),
        }
        out.append((batch, (rng.random(b) + 0.01).astype(np.float32)))
    return out


def image_batches(kind: str, seed: int, count: int) -> list[tuple[dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray]]]:
    """``count`` frame-mode chunks of IMAGE_CHUNK transitions of one env, each carrying every
    frame it names (ids from 0; shifted by the chunk's frame_base when sent): random uint8
    frames, so compression would not help and the bytes are the image bytes."""
    rng = np.random.default_rng(seed)
    b, n = IMAGE_CHUNK, IMAGE_N_STEP
    out = []
    for _ in range(count):
        if kind == "cam64":
            frames = rng.integers(0, 256, (b + n, 64, 64, 3), dtype=np.uint8)
            obs = np.arange(b, dtype=np.int64)
        elif kind == "atari84":
            frames = rng.integers(0, 256, (b + n + IMAGE_STACK - 1, 84, 84), dtype=np.uint8)
            obs = np.arange(b, dtype=np.int64)[:, None] + np.arange(IMAGE_STACK)
        else:
            raise ValueError(f"unknown image kind {kind!r}")
        batch = {"obs": obs, "action": rng.integers(0, 6, b).astype(np.int64),
                 "reward": rng.random(b).astype(np.float32), "next_obs": obs + n,
                 "terminated": rng.random(b) < 0.01, "truncated": np.zeros(b, bool), "n": np.full(b, n, np.uint8)}
        out.append((batch, (rng.random(b) + 0.01).astype(np.float32), {"obs": frames}))
    return out


def ring_mb(kind: str) -> float:
    """MB of frames the replay keeps for IMAGE_CAPACITY transitions of ``kind`` (one new frame
    per transition): the store-only receiver's ring."""
    frame = image_batches(kind, 0, 1)[0][2]["obs"][0].nbytes
    return IMAGE_CAPACITY * frame / 1e6


def kind_batches(kind: str, seed: int, count: int) -> list[tuple[dict[str, np.ndarray], np.ndarray, Any]]:
    if kind == "cartpole":
        return [(b, p, None) for b, p in cartpole_batches(seed, count)]
    return image_batches(kind, seed, count)


def shifted(batch: dict[str, np.ndarray], frames: Any, base: int) -> dict[str, np.ndarray]:
    """A frame-mode chunk's ids moved to start at ``base`` (the chunk's frame_base)."""
    if frames is None:
        return batch
    return {k: (v + base if k in ("obs", "next_obs") else v) for k, v in batch.items()}


def encoded_pool(seed: int, count: int, actor_id: str, kind: str = "cartpole", codec: str | None = None) -> list[bytes]:
    from zenrl.common import protocol as P

    out = []
    base = 0
    for i, (b, p, f) in enumerate(kind_batches(kind, seed, count)):
        out.append(P.TransitionBatch(actor_id=actor_id, policy_version=0, seq=i, data=shifted(b, f, base), priorities=p,
                                     frames=f, frame_base=None if f is None else base).encode(codec=codec))
        base += 0 if f is None else len(f["obs"])
    return out


def wait_for_go(node: Any, keys: Any, pub_id: str, stop: threading.Event, timeout_s: float = 60) -> bool:
    go = node.subscribe_latest(f"{keys.prefix}/bench/go")
    node.token(keys.alive("benchpub", pub_id))
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        if go.wait(0.1) is not None:
            return True
        if time.monotonic() > deadline:
            return False
    return False


# ---------------------------------------------------------------------------------------------
# roles
# ---------------------------------------------------------------------------------------------
def role_pub(args: argparse.Namespace) -> int:
    """Publish for ``--duration`` s after the go signal; ``--mode raw`` puts pre-encoded
    ``transitions`` messages, ``--mode client`` inserts the same batches with ZenohReplayClient."""
    from zenrl.common import protocol as P
    from zenrl.common.replay_client import ZenohReplayClient

    stop = threading.Event()
    watch_parent(stop)
    keys = P.Keys(args.run)
    pool_n = 64 if args.kind == "cartpole" else 16
    sent_warm = 0
    base = 0  # frame mode: the next chunk's frame_base
    with bench_node(args.router, args.shm) as node:
        deadline = time.monotonic() + 30
        if args.mode == "raw":
            payloads = encoded_pool(args.seed, pool_n, args.id, args.kind, args.codec)
            pub = node.publisher(keys.transitions(args.id))
            while not pub.matching_status.matching:  # the raw subscriber is there
                if time.monotonic() > deadline or stop.is_set():
                    return 3
                time.sleep(0.05)
        else:
            batches = kind_batches(args.kind, args.seed, pool_n)
            client = ZenohReplayClient(node, keys, args.id, codec=args.codec)
            while not node.alive_now(keys.alive_role("replay"), 1.0):
                if time.monotonic() > deadline or stop.is_set():
                    return 3
        if args.mode == "client":
            b, p, f = batches[0]
            client.insert(shifted(b, f, base), p, policy_version=0, frames=f, frame_base=None if f is None else base)
            base += 0 if f is None else len(f["obs"])  # (the first insert declares the publisher)
            sent_warm = 1
            time.sleep(0.3)
        if not wait_for_go(node, keys, args.id, stop):
            return 4
        i = 0
        t0 = time.perf_counter()
        end = t0 + args.duration
        if args.mode == "raw":
            while not stop.is_set():
                for _ in range(32):
                    pub.put(payloads[i % pool_n])
                    i += 1
                if time.perf_counter() >= end:
                    break
        else:
            while not stop.is_set():
                for _ in range(32):
                    b, p, f = batches[i % pool_n]
                    if f is None:
                        client.insert(b, p, policy_version=0)
                    else:
                        client.insert(shifted(b, f, base), p, policy_version=0, frames=f, frame_base=base)
                        base += len(f["obs"])
                    i += 1
                if time.perf_counter() >= end:
                    break
            client.flush_backlog()
        elapsed = time.perf_counter() - t0
        extra = {}
        if args.mode == "client":
            extra = {"sent_chunks_client": client.sent_chunks, "undelivered": client.undelivered_chunks,
                     "backlog": client.backlog, "warmup_chunks": sent_warm}
        res = {"sent_chunks": i + sent_warm, "loop_chunks": i, "elapsed_s": elapsed,
               "send_rate_items_s": i * chunk_items(args.kind) / elapsed, **extra}
        # Closing the session while messages are still queued on their way loses them, so stay
        # until the benchmark has seen them arrive (it says so on bench/release).
        release = node.subscribe_latest(f"{keys.prefix}/bench/release")
        node.put(f"{keys.prefix}/bench/sent/{args.id}", json.dumps(res).encode())
        deadline = time.monotonic() + 120
        while not stop.is_set() and time.monotonic() < deadline and release.wait(0.1) is None:
            pass
    print(json.dumps(res), flush=True)
    return 0


def role_rawsub(args: argparse.Namespace) -> int:
    """Count messages on ``transitions/*``; print counts and first/last receipt times after the
    stream has been idle for ``--idle`` s (or on SIGTERM). ``--store-mb`` > 0: also stand in for
    the replay (its liveliness token, for client-mode publishers) and copy each payload into a
    ring of that size (pre-touched). Its session has the replay's transport settings
    (:func:`bench_node`); it reports its threads' CPU and wake-ups from the go signal to the
    last receipt (:func:`thread_breakdown`)."""
    from zenrl.common import protocol as P
    from zenrl.common.roles import name_os_thread

    stop = threading.Event()
    watch_parent(stop)
    keys = P.Keys(args.run)
    st = {"n": 0, "bytes": 0, "first": None, "last": None, "off": 0}
    lock = threading.Lock()
    store = None
    if args.store_mb > 0:
        store = np.ones(int(args.store_mb * 1e6), np.uint8)  # touched: no first-touch faults while measured

    named = threading.local()

    def cb(sample: Any) -> None:
        if not getattr(named, "done", False):  # Zenoh's callback thread, told apart in the breakdown
            name_os_thread("zenoh-callback")
            named.done = True
        data = sample.payload.to_bytes()
        if store is not None:
            a = np.frombuffer(data, np.uint8)
            o = st["off"] if st["off"] + a.size <= store.size else 0
            store[o:o + a.size] = a
            st["off"] = o + a.size
        t = time.perf_counter()
        with lock:
            if st["first"] is None:
                st["first"] = t
            st["last"] = t
            st["n"] += 1
            st["bytes"] += len(data)

    node = bench_node(args.router, args.shm, receiver=True)
    session = node.session
    cpu_at_go: list[Any] = []
    try:
        sub = session.declare_subscriber(keys.transitions_all, cb)
        expect: list[int] = []
        def on_go(_s: Any) -> None:  # a client-mode publisher's warm-up chunk came before: not counted
            with lock:
                st.update(n=0, bytes=0, first=None, last=None)
            cpu_at_go[:] = [task_cpu()]

        go_sub = session.declare_subscriber(f"{keys.prefix}/bench/go", on_go)
        exp_sub = session.declare_subscriber(f"{keys.prefix}/bench/expect",
                                             lambda smp: expect.append(int(smp.payload.to_bytes())))
        token = session.liveliness().declare_token(keys.alive("rawsub", "rawsub"))  # keep a reference
        token2 = session.liveliness().declare_token(keys.alive("replay", "storesub")) if store is not None else None
        deadline = time.monotonic() + args.max_s
        while not stop.wait(0.05):
            with lock:
                last, n = st["last"], st["n"]
            if expect and n >= expect[-1]:
                break
            if expect and (last is None or time.perf_counter() - last > args.idle):
                break  # some never came
            if time.monotonic() > deadline:
                break
        cpu_end = task_cpu()
        exp_sub.undeclare()
        go_sub.undeclare()
        token.undeclare()
        if token2 is not None:
            token2.undeclare()
        sub.undeclare()
    finally:
        node.close()
    n = st["n"]
    span = (st["last"] - st["first"]) if n > 1 else 0.0
    threads = thread_breakdown(cpu_at_go[0], cpu_end, n, span) if cpu_at_go and n else None
    print(json.dumps({"messages": n, "expected": expect[-1] if expect else None, "bytes": st["bytes"], "span_s": span,
                      "items_per_s": (n - 1) * chunk_items(args.kind) / span if span > 0 else None,
                      "mb_per_s": st["bytes"] / span / 1e6 if span > 0 else None, "threads": threads}), flush=True)
    return 0


def role_sampler(args: argparse.Namespace) -> int:
    """Sample batches of ``--batch`` with ``--in-flight`` requests outstanding, as the Ape-X
    learner does (:class:`SamplePrefetcher` over the replay's Zenoh queryable), for
    ``--duration`` s after a warm-up (or until SIGTERM); ``--rate`` > 0 takes at most that many
    batches a second, as a learner whose updates take 1/rate s would."""
    from zenrl.common import protocol as P
    from zenrl.common.replay_client import SamplePrefetcher, ZenohReplayClient

    stop = threading.Event()
    watch_parent(stop)
    keys = P.Keys(args.run)
    with bench_node(args.router, args.shm) as node:
        client = ZenohReplayClient(node, keys, "bench-sampler", timeout_s=5.0)
        pf = SamplePrefetcher(client, args.batch, lambda: 0.4, args.in_flight).start()
        node.token(keys.alive("benchsampler", "sampler"))
        try:
            warm_end = time.perf_counter() + args.warmup
            while time.perf_counter() < warm_end and not stop.is_set():
                pf.get(0.5)
            n = items = 0
            t0 = time.perf_counter()
            end = t0 + args.duration
            while time.perf_counter() < end and not stop.is_set():
                s = pf.get(0.5)
                if s is not None:
                    n += 1
                    items += len(s.keys)
                    if args.rate > 0:  # the learner's update time
                        stop.wait(max(0.0, t0 + n / args.rate - time.perf_counter()))
            el = time.perf_counter() - t0
        finally:
            pf.stop()
    print(json.dumps({"batches": n, "elapsed_s": el, "batches_per_s": n / el, "items_per_s": items / el,
                      "not_ready": pf.not_ready, "timeouts": pf.timeouts, "errors": pf.errors}), flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# orchestration
# ---------------------------------------------------------------------------------------------
def last_json(text: str) -> dict[str, Any]:
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            return json.loads(line)
    raise RuntimeError(f"no JSON in output: {text[-500:]!r}")


def communicate(procs: Procs, name: str, p: subprocess.Popen, timeout_s: float) -> dict[str, Any]:
    try:
        out, _ = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        procs.stop(p)
        out, _ = p.communicate()
    if p.returncode != 0:
        raise RuntimeError(f"{name} exited with {p.returncode}: {procs.log_text(name)[-2000:]}")
    return last_json(out)


class StatsWatch:
    """Collects ``(time, values)`` of the replay's stats messages."""

    def __init__(self, node: Any, keys: Any) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self.samples: list[tuple[float, dict[str, Any]]] = []
        self._lock = threading.Lock()
        node.subscribe(keys.stats("replay", "replay"), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        s = self._P.Stats.decode(payload)
        with self._lock:
            self.samples.append((s.time, dict(s.values)))

    def snapshot(self) -> list[tuple[float, dict[str, Any]]]:
        with self._lock:
            return list(self.samples)

    def latest(self, name: str, default: Any = 0) -> Any:
        with self._lock:
            return self.samples[-1][1].get(name, default) if self.samples else default


class SentWatch:
    """The publishers' end-of-stream reports (``bench/sent/<id>``) of one run."""

    def __init__(self, node: Any, prefix: str) -> None:
        self.reports: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        node.subscribe(f"{prefix}/bench/sent/*", self._on)

    def _on(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.reports[key.rsplit("/", 1)[-1]] = json.loads(payload)

    def wait(self, n: int, timeout_s: float) -> list[dict[str, Any]]:
        wait_until(lambda: len(self.reports) >= n, timeout_s, f"{n} publishers to finish")
        with self._lock:
            return list(self.reports.values())


def go(node: Any, keys: Any, n: int) -> float:
    wait_until(lambda: len(node.alive_now(keys.alive_role("benchpub"), 1.0)) >= n, 60, f"{n} publishers ready")
    t = time.time()
    node.put(f"{keys.prefix}/bench/go", b"go")
    return t


def pub_argv(role_mode: str, ep: str, run: str, pid: str, seed: int, duration: float, kind: str = "cartpole",
             shm: bool = False, codec: str | None = None) -> list[str]:
    return [str(Path(__file__).resolve()), "--role", "pub", "--mode", role_mode, "--router", ep, "--run", run,
            "--id", pid, "--seed", str(seed), "--duration", str(duration), "--kind", kind, *(["--shm"] if shm else []),
            *(["--codec", codec] if codec else [])]


def raw_round(procs: Procs, node: Any, ep: str, run: str, r: int, duration: float, kind: str = "cartpole",
              store_mb: float = 0.0, pub_mode: str = "raw", shm: bool = False, codec: str | None = None,
              sampled: tuple[str, float] | None = None) -> dict[str, Any]:
    """One round of 2 publishers to a subscriber process (raw, or store-only with ``store_mb``).
    ``sampled``: ``(run id, rate)`` of another, already filled replay that a learner-like sampler
    samples through the round (what sampling costs the machine, beside a receiver that does no
    work of its own beyond the store-only receiver's)."""
    from zenrl.common import protocol as P

    rrun = f"{run}-raw{r}"
    keys = P.Keys(rrun)
    sent_watch = SentWatch(node, keys.prefix)
    sampler = None
    if sampled is not None:
        srun, rate = sampled
        sampler = start_sampler(procs, node, f"rawsampler{r}", ep, srun, shm, rate)
    sub = procs.start(f"rawsub{r}", [str(Path(__file__).resolve()), "--role", "rawsub", "--router", ep, "--run", rrun,
                                     "--idle", "5", "--max-s", str(duration + 120), "--kind", kind,
                                     "--store-mb", str(store_mb), *(["--shm"] if shm else [])], capture=True)
    wait_until(lambda: node.alive_now(keys.alive_role("rawsub"), 1.0), 60, "raw subscriber")
    pubs = [procs.start(f"rawpub{r}-{k}", pub_argv(pub_mode, ep, rrun, f"pub{k}", 100 + k, duration, kind, shm, codec),
                        capture=True) for k in range(N_PUBLISHERS)]
    go(node, keys, N_PUBLISHERS)
    # what is sent after the go signal: a client-mode publisher's warm-up chunk is not counted
    sent = sum(x["loop_chunks"] for x in sent_watch.wait(N_PUBLISHERS, duration + 60))
    node.put(f"{keys.prefix}/bench/expect", str(sent).encode())
    sres = communicate(procs, f"rawsub{r}", sub, 60)
    node.put(f"{keys.prefix}/bench/release", b"1")
    pres = [communicate(procs, f"rawpub{r}-{k}", p, 30) for k, p in enumerate(pubs)]
    out = {"items_per_s": sres["items_per_s"], "mb_per_s": sres["mb_per_s"], "received_chunks": sres["messages"],
           "sent_chunks": sent, "span_s": sres["span_s"],
           "sender_items_per_s": sum(x["send_rate_items_s"] for x in pres), "threads": sres.get("threads")}
    if sampler is not None:
        procs.stop(sampler)
        out["sampler"] = communicate(procs, f"rawsampler{r}", sampler, 30)
    return out


def service_rate(samples: list[tuple[float, dict[str, Any]]], t_go: float, final: int) -> tuple[float | None, float]:
    """Items/s between the last stats sample before inserts rose after ``t_go`` and the first
    one showing the final count."""
    pts = [(t, int(v.get("inserted_total", 0))) for t, v in samples]
    pre = [i for i, (t, _) in enumerate(pts) if t <= t_go]
    if not pre:
        return None, 0.0
    base_i = pre[-1]
    base_n = pts[base_i][1]
    start = None
    for i in range(base_i + 1, len(pts)):
        if pts[i][1] > base_n:
            start = i - 1
            break
    if start is None:
        return None, 0.0
    end = next((i for i in range(start, len(pts)) if pts[i][1] >= final), len(pts) - 1)
    dt = pts[end][0] - pts[start][0]
    return ((pts[end][1] - pts[start][1]) / dt if dt > 0 else None), dt


def sampler_argv(ep: str, run: str, shm: bool, rate: float, duration: float = 3600.0) -> list[str]:
    """The learner-like sampler (--role sampler) at LEARNER_BATCH, LEARNER_IN_FLIGHT."""
    return [str(Path(__file__).resolve()), "--role", "sampler", "--router", ep, "--run", run, "--duration",
            str(duration), "--warmup", "0", "--batch", str(LEARNER_BATCH), "--in-flight", str(LEARNER_IN_FLIGHT),
            "--rate", str(rate), *(["--shm"] if shm else [])]


def start_sampler(procs: Procs, node: Any, name: str, ep: str, run: str, shm: bool, rate: float) -> subprocess.Popen:
    """The learner-like sampler of :func:`sampler_argv` on the replay of ``run``, once it is up."""
    from zenrl.common import protocol as P

    p = procs.start(name, sampler_argv(ep, run, shm, rate), capture=True)
    wait_until(lambda: node.alive_now(P.Keys(run).alive_role("benchsampler"), 1.0), 60, "sampler")
    return p


def service_round(procs: Procs, node: Any, stats: StatsWatch, ep: str, run: str, r: int,
                  duration: float, kind: str = "cartpole", shm: bool = False, replay_pid: int | None = None,
                  sample_rate: float | None = None, tag: str = "", codec: str | None = None) -> dict[str, Any]:
    """One round of ``duration`` s of 2 client publishers into the replay of ``run``, the rate
    measured from its stats. ``replay_pid``: also its threads' CPU and wake-ups over the round.
    ``sample_rate`` (not None): a learner-like sampler runs through the round (0: as fast as the
    replay serves it; > 0: at most that many batches a second)."""
    from zenrl.common import protocol as P

    keys = P.Keys(run)
    sent_watch = SentWatch(node, keys.prefix)
    sampler = None
    if sample_rate is not None:
        sampler = start_sampler(procs, node, f"sampler{tag}{r}", ep, run, shm, sample_rate)
    pubs = [procs.start(f"svcpub{tag}{r}-{k}", pub_argv("client", ep, run, f"pub{r}-{k}", 100 + k, duration, kind, shm, codec),
                        capture=True) for k in range(N_PUBLISHERS)]
    # the publishers' warm-up chunks must be in before the clock starts
    wait_until(lambda: len(node.alive_now(keys.alive_role("benchpub"), 1.0)) >= N_PUBLISHERS, 60, "publishers ready")
    base_total = stats.latest("inserted_total")
    wait_until(lambda: stats.latest("inserted_total") >= base_total and stats.latest("ingest_queue", 1) == 0, 10,
               "replay idle")
    time.sleep(0.2)
    samples0 = stats.latest("sample_batches_total")
    t_go = go(node, keys, N_PUBLISHERS)
    cpu0 = task_cpu(replay_pid) if replay_pid else {}
    pres = sent_watch.wait(N_PUBLISHERS, duration + 60)
    pre_go = [v for t, v in stats.snapshot() if t <= t_go]
    expected = (pre_go[-1]["inserted_total"] if pre_go else 0) + sum(x["loop_chunks"] for x in pres) * chunk_items(kind)
    # the service's count once the stream is fully ingested (or has stopped changing for 5 s)
    last = [stats.latest("inserted_total"), time.monotonic()]

    def settled() -> bool:
        n = stats.latest("inserted_total")
        if n >= expected:
            return True
        if n != last[0]:
            last[0], last[1] = n, time.monotonic()
        return time.monotonic() - last[1] > 5.0

    wait_until(settled, 120, "replay to ingest the stream")
    t_end = time.time()
    cpu1 = task_cpu(replay_pid) if replay_pid else {}
    samples1 = stats.latest("sample_batches_total")
    time.sleep(0.1)
    node.put(f"{keys.prefix}/bench/release", b"1")
    for k, p in enumerate(pubs):
        communicate(procs, f"svcpub{tag}{r}-{k}", p, 30)
    smp = None
    if sampler is not None:
        procs.stop(sampler)
        smp = communicate(procs, f"sampler{tag}{r}", sampler, 30)
    final = stats.latest("inserted_total")
    rate, dt = service_rate(stats.snapshot(), t_go, final)
    sent = sum(x["loop_chunks"] for x in pres) * chunk_items(kind)
    ingested = final - (pre_go[-1]["inserted_total"] if pre_go else 0)
    out = {"items_per_s": rate, "window_s": dt, "sent_items": sent, "ingested_items": ingested,
           "sender_items_per_s": sum(x["send_rate_items_s"] for x in pres),
           "dropped_queue_full": stats.latest("dropped_queue_full"),
           "undelivered_chunks": sum(x.get("undelivered", 0) for x in pres)}
    if replay_pid:
        out["threads"] = thread_breakdown(cpu0, cpu1, ingested // chunk_items(kind), t_end - t_go)
    if sampler is not None:
        out["sample_batches_per_s"] = round((samples1 - samples0) / max(t_end - t_go, 1e-9), 1)
        out["sampler"] = smp
    return out


def inprocess_ingest(duration_s: float) -> dict[str, Any]:
    """Reference: ReplayService.ingest() on the same encoded chunks in this process, no network
    (the service's own ceiling: decode, validate, insert)."""
    from zenrl.common.config import load_config
    from zenrl.replay.service import ReplayService

    svc = ReplayService(load_config(None, ["replay.capacity=100000"]), None, "benchref")
    pool = encoded_pool(100, 64, "pub0")
    for p in pool[:8]:
        svc.ingest(p)
    items = i = 0
    t0, c0 = time.perf_counter(), time.thread_time()
    while time.perf_counter() - t0 < duration_s:
        for _ in range(32):
            items += svc.ingest(pool[i % 64])
            i += 1
    el, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return {"items_per_s": items / el, "items_per_cpu_s": items / cpu, "us_per_chunk_cpu": cpu / i * 1e6}


def inprocess_image_ingest(kind: str, duration_s: float, codec: str | None = None) -> dict[str, Any]:
    """Reference for --images: the service's ingest of ``kind`` frame-mode chunks in this process,
    no network, in batches of ``replay.ingest_batch_chunks`` as the ingest thread takes them from
    a busy queue (decode, insert into a warm ring): the replay's own ceiling on one core."""
    from zenrl.common.config import load_config
    from zenrl.replay.service import ReplayService

    cfg = load_config(None, [f"replay.capacity={IMAGE_CAPACITY}", "replay.check_semantics=false"])
    svc = ReplayService(cfg, None, "benchref")
    per = cfg.replay.ingest_batch_chunks
    pool = encoded_pool(100, 4 * per, "pub0", kind, codec)
    for _ in range(2):  # every ring page touched before the clock starts
        for j in range(0, len(pool), per):
            svc.ingest_many([(p, "pub0") for p in pool[j:j + per]])
    # each pass over the pool starts its frame ids again: the replay takes it as the actor
    # restarting, and every chunk names only its own frames, so every transition is stored
    items = chunks = 0
    t0, c0 = time.perf_counter(), time.thread_time()
    while time.perf_counter() - t0 < duration_s:
        for j in range(0, len(pool), per):
            items += svc.ingest_many([(p, "pub0") for p in pool[j:j + per]])
            chunks += per
    el, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return {"items_per_s": items / el, "us_per_chunk_cpu": cpu / chunks * 1e6}


def role_inproc(args: argparse.Namespace) -> int:
    """A child of ``--baseline`` A/Bs: :func:`inprocess_image_ingest` with the zenrl of the
    interpreter that runs it (this checkout's, or the baseline's), printed as one JSON line."""
    return emit(inprocess_image_ingest(args.kind, args.duration, args.codec))


def inprocess_ab(procs: Procs, args: argparse.Namespace, kind: str, rounds: int, duration_s: float) -> dict[str, Any]:
    """The in-process ingest of ``kind`` by this checkout's code and by ``--baseline``'s, each in a
    fresh process of its own interpreter, alternating: ``{variant: [us CPU per chunk, ...]}``."""
    out: dict[str, list[float]] = {}
    for r in range(rounds):
        for variant, checkout in variants(args).items():
            name = f"inproc-{kind}-{variant}-{r}"
            argv = [str(Path(__file__).resolve()), "--role", "inproc", "--kind", kind, "--duration", str(duration_s),
                    *(["--codec", args.codec] if args.codec else [])]
            res = communicate(procs, name, procs.start(name, argv, capture=True, checkout=checkout), 300)
            out.setdefault(variant, []).append(round(res["us_per_chunk_cpu"], 1))
    return out


def checks_overhead(rounds: int, round_s: float) -> dict[str, Any]:
    """CPU time per chunk of the replay's ingest path (decode, validate, insert; batches of
    ``replay.ingest_batch_chunks`` = 32 chunks, as the ingest thread does) with the semantic checks
    on and off, in this process, rounds alternating; ratio = median on / median off."""
    from zenrl.common.config import load_config
    from zenrl.replay.service import ReplayService

    svcs = {on: ReplayService(load_config(None, ["replay.capacity=100000", f"replay.check_semantics={str(on).lower()}"]),
                              None, "benchchk") for on in (True, False)}
    pool = encoded_pool(200, 64, "pub0")
    batches = [[(pool[(j * 32 + k) % 64], "zenrl/benchchk/transitions/pub0") for k in range(32)] for j in range(2)]
    for svc in svcs.values():
        if svc.ingest_many(batches[0]) != 32 * CHUNK:
            raise RuntimeError("the benchmark's chunks were rejected")
    us = ab_cpu_us({on: (lambda n, svc=svc: svc.ingest_many(batches[n % 2])) for on, svc in svcs.items()},
                   rounds, round_s, items_per_call=32)
    on, off = us[True], us[False]
    chk = svcs[True].checker
    d, p = cartpole_batches(201, 1)[0]
    t0, k = time.perf_counter(), 0
    while time.perf_counter() - t0 < 0.5:
        chk.check(d, p)
        k += 1
    return {"checks_overhead_ratio": round(on / off, 4), "ingest_us_per_chunk_checked": round(on, 1),
            "ingest_us_per_chunk_unchecked": round(off, 1), "check_us_per_chunk": round((time.perf_counter() - t0) / k * 1e6, 2),
            "checks_rounds": rounds, "target_checks_overhead_ratio": 1.05}


def orchestrate(args: argparse.Namespace) -> int:
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port

    t_start = time.perf_counter()
    if args.checks_only:
        out = {"bench": "replay_service", "mode": "checks_only", "error": None}
        try:
            out.update(checks_overhead(10, 1.0))
            log(f"semantic checks: {out['ingest_us_per_chunk_checked']} vs {out['ingest_us_per_chunk_unchecked']} "
                f"us per chunk, ratio {out['checks_overhead_ratio']}")
            out.update(machine_info(t_start))
        except BaseException as e:
            record_error(out, e)
        return emit(out)
    rounds, duration, sample_s = (1, 2.0, 3.0) if args.quick else (3, 6.0, 8.0)
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="zenrl-bench-replay-"))
    router = open_router([ep])
    procs = Procs(tmp)
    node = None
    out: dict[str, Any] = {"bench": "replay_service", "quick": bool(args.quick), "error": None}
    try:
        node = Node(ep, 10.0)
        log(f"router {ep}, logs in {tmp}, shared memory {'on' if args.shm else 'off'}")
        chk = checks_overhead(2 if args.quick else 6, 1.0)
        log(f"semantic checks: ingest CPU per chunk ratio on/off {chk['checks_overhead_ratio']}")
        ref = inprocess_ingest(1.0 if args.quick else 3.0)
        log(f"reference: ReplayService.ingest in process: {ref['items_per_s']:,.0f} items/s")
        replays = start_replays(procs, node, ep, args, "cartpole", 100000)
        run, _, stats = replays["service"]
        raw: list[dict[str, Any]] = []
        svcs: dict[str, list[dict[str, Any]]] = {v: [] for v in replays}
        for r in range(rounds):
            res = raw_round(procs, node, ep, run, r, duration, shm=args.shm)
            log(f"round {r} raw zenoh: {res['items_per_s']:,.0f} items/s ({res['mb_per_s']:.1f} MB/s), "
                f"{res['received_chunks']}/{res['sent_chunks']} chunks")
            raw.append(res)
            for variant in (list(replays) if r % 2 == 0 else list(replays)[::-1]):
                vrun, p, vstats = replays[variant]
                res = service_round(procs, node, vstats, ep, vrun, r, duration, shm=args.shm, replay_pid=p.pid, tag=variant)
                log(f"round {r} replay {variant}: {res['items_per_s'] or 0:,.0f} items/s, {res['ingested_items']}/"
                    f"{res['sent_items']} items ingested, dropped {res['dropped_queue_full']}, "
                    f"{res['threads']['us_per_chunk']} us CPU per chunk")
                svcs[variant].append(res)
        svc = svcs["service"]
        sampler = procs.start("sampler", [str(Path(__file__).resolve()), "--role", "sampler", "--router", ep,
                                          "--run", run, "--duration", str(sample_s), "--warmup", "1.0",
                                          *(["--shm"] if args.shm else [])], capture=True)
        smp = communicate(procs, "sampler", sampler, sample_s + 60)
        log(f"sampling: {smp['batches_per_s']:.1f} batches/s of {SAMPLE_BATCH}")
        raw_med = statistics.median(x["items_per_s"] for x in raw)
        svc_med = median_of(svc)
        ratio = svc_med / raw_med if svc_med and raw_med else None
        if "baseline" in svcs:
            base_med = median_of(svcs["baseline"])
            out.update({"baseline_service_ingest_items_per_s": None if base_med is None else round(base_med),
                        "baseline_service_us_per_chunk_cpu": median_of([x["threads"] for x in svcs["baseline"]], "us_per_chunk"),
                        "service_vs_baseline": round(svc_med / base_med, 3) if svc_med and base_med else None})
        out.update({
            "bench": "replay_service",
            "quick": bool(args.quick),
            "ingest_ratio_vs_raw_zenoh": None if ratio is None else round(ratio, 3),
            "target_ingest_ratio": 0.7,
            "service_ingest_items_per_s": None if svc_med is None else round(svc_med),
            "raw_zenoh_items_per_s": round(raw_med),
            "inprocess_ingest_items_per_s": round(ref["items_per_s"]),
            "inprocess_ingest_us_per_chunk_cpu": round(ref["us_per_chunk_cpu"], 1),
            **chk,
            "sample_batches_per_s": round(smp["batches_per_s"], 2),
            "sample_items_per_s": round(smp["items_per_s"]),
            "sample_batch_size": SAMPLE_BATCH,
            "sample_in_flight": IN_FLIGHT,
            "sample_not_ready": smp["not_ready"],
            "sample_timeouts": smp["timeouts"],
            "publishers": N_PUBLISHERS,
            "chunk_items": CHUNK,
            "chunk_bytes": len(encoded_pool(0, 1, "pub0")[0]),
            "service_us_per_chunk_cpu": median_of([x["threads"] for x in svc], "us_per_chunk"),
            "shared_memory": bool(args.shm),
            "rounds": {"raw": raw, **svcs},
            "final_replay_stats": stats.snapshot()[-1][1] if stats.snapshot() else None,
            "notes": ("rates measured at the receiver; raw = same encoded messages, same BLOCK publishers, "
                      "a subscriber process that only copies the payload out and counts; medians of "
                      "alternating rounds; router in the benchmark process; 2-core machine shared with "
                      "other work, so absolute figures are noisy, the ratio less so"),
            **machine_info(t_start),
        })
    except BaseException as e:
        record_error(out, e)
    finally:
        shut_down(procs, node, router)
    return emit(out)


def replay_argv(ep: str, run: str, capacity: int, shm: bool, *extra: str) -> list[str]:
    """A ``zenrl replay`` process for the benchmark (stats every 50 ms, ``transport.shared_memory``
    as ``--shm``); ``extra``: more ``--set`` options."""
    argv = ["-m", "zenrl.cli", "replay", "--router", ep, "--run-id", run, "--log-level", "INFO"]
    for kv in ("replay.stats_interval_s=0.05", "replay.min_size=1000", f"replay.capacity={capacity}",
               f"transport.shared_memory={str(shm).lower()}", *extra):
        argv += ["--set", kv]
    return argv


def variants(args: argparse.Namespace) -> dict[str, Path | None]:
    """The replays measured: this checkout's (``service``), and with ``--baseline DIR`` also the
    one of checkout DIR (run with DIR/.venv; ``baseline``)."""
    out: dict[str, Path | None] = {"service": None}
    if args.baseline:
        root = Path(args.baseline).resolve()
        if not (root / ".venv" / "bin" / "python").exists():
            raise RuntimeError(f"--baseline {root}: no .venv/bin/python there")
        out["baseline"] = root
    return out


def start_replays(procs: Procs, node: Any, ep: str, args: argparse.Namespace, name: str, capacity: int,
                  *extra: str) -> dict[str, tuple[str, Any, "StatsWatch"]]:
    """One replay process per variant: ``{variant: (run id, process, stats)}``."""
    from zenrl.common import protocol as P

    out = {}
    for variant, checkout in variants(args).items():
        run = f"bench{uuid.uuid4().hex[:8]}"
        keys = P.Keys(run)
        stats = StatsWatch(node, keys)
        mine = args.service_set if variant == "service" else []
        p = procs.start(f"replay-{name}-{variant}", replay_argv(ep, run, capacity, args.shm, *extra, *mine),
                        checkout=checkout)
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 1.0), 60, f"replay service ({variant})")
        out[variant] = (run, p, stats)
    return out


def median_of(rounds: list[dict[str, Any]], key: str = "items_per_s") -> float | None:
    vals = [x[key] for x in rounds if x.get(key)]
    return statistics.median(vals) if vals else None


def orchestrate_images(args: argparse.Namespace) -> int:
    """Image mode: per kind, fresh replay processes and alternating raw / store-only / service
    rounds on the same frame-mode chunks (each chunk carries all IMAGE_CHUNK + n (+ stack)
    frames it names), a learner-like sampler running through every service round."""
    from zenrl.common import protocol as P
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port

    t_start = time.perf_counter()
    rounds, duration = (1, 2.0) if args.quick else (3, 5.0)
    rounds = args.rounds or rounds
    sample_rate = None if args.no_sampler else args.sample_rate
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="zenrl-bench-replay-img-"))
    router = open_router([ep])
    procs = Procs(tmp)
    node = None
    out: dict[str, Any] = {"bench": "replay_service", "mode": "images", "quick": bool(args.quick), "error": None}
    try:
        node = Node(ep, 10.0)
        log(f"router {ep}, logs in {tmp}, shared memory {'on' if args.shm else 'off'}, codec {args.codec}, "
            f"sampler {'off' if sample_rate is None else (sample_rate if isinstance(sample_rate, str) else (f'{sample_rate:g}/s' if sample_rate else 'unthrottled'))}")
        kinds: dict[str, Any] = {}
        learner_rates: dict[str, Any] = {}
        for kind in args.kinds:
            kind_rate = sample_rate
            if sample_rate == "learner":  # before this kind's replays start: the learner alone
                learner_rates[kind] = learner_rate(kind, 1.0 if args.quick else 3.0, 4.0 if args.quick else 10.0)
                kind_rate = learner_rates[kind]["updates_per_s"]
                log(f"[{kind}] the Ape-X learner alone: {kind_rate:g} updates/s of {LEARNER_BATCH} "
                    f"({learner_rates[kind]['config']}): the sampler's rate")
            # synthetic chunks of no registered env (6 actions, bare frames): the env checks' cost
            # is --checks-only's
            replays = start_replays(procs, node, ep, args, kind, IMAGE_CAPACITY, "replay.check_semantics=false")
            ceiling = None
            if args.ceiling and not args.service_only:
                # a replay of its own, filled once, that the sampler of the store-only rounds samples
                crun = f"bench{uuid.uuid4().hex[:8]}"
                cproc = procs.start(f"replay-{kind}-ceiling", replay_argv(ep, crun, IMAGE_CAPACITY, args.shm,
                                                                        "replay.check_semantics=false"))
                wait_until(lambda: node.alive_now(P.Keys(crun).alive_role("replay"), 1.0), 60, "replay service (ceiling)")
                cstats = StatsWatch(node, P.Keys(crun))
                fill = service_round(procs, node, cstats, ep, crun, 0, duration, kind, shm=args.shm, tag="fill",
                                     codec=args.codec)
                log(f"[{kind}] the sampled replay filled: {fill['ingested_items']} items")
                ceiling = (crun, cproc)
            raw: list[dict[str, Any]] = []
            store: list[dict[str, Any]] = []
            store_sampled: list[dict[str, Any]] = []
            svc: dict[str, list[dict[str, Any]]] = {v: [] for v in replays}
            frames_mb = ring_mb(kind)
            for r in range(rounds):
                if not args.service_only:
                    res = raw_round(procs, node, ep, next(iter(replays.values()))[0], r, duration, kind, shm=args.shm,
                                    codec=args.codec)
                    log(f"[{kind}] round {r} raw zenoh: {res['items_per_s']:,.0f} items/s ({res['mb_per_s']:.1f} MB/s), "
                        f"{res['received_chunks']}/{res['sent_chunks']} chunks")
                    raw.append(res)
                    res = raw_round(procs, node, ep, f"{next(iter(replays.values()))[0]}s", r, duration, kind,
                                    store_mb=frames_mb, pub_mode="client", shm=args.shm, codec=args.codec)
                    log(f"[{kind}] round {r} store-only receiver: {res['items_per_s']:,.0f} items/s "
                        f"({res['mb_per_s']:.1f} MB/s), {res['received_chunks']}/{res['sent_chunks']} chunks, "
                        f"{res['threads'] and res['threads']['us_per_chunk']} us CPU per chunk")
                    store.append(res)
                    if ceiling is not None:
                        res = raw_round(procs, node, ep, f"{next(iter(replays.values()))[0]}c", r, duration, kind,
                                        store_mb=frames_mb, pub_mode="client", shm=args.shm, codec=args.codec,
                                        sampled=(ceiling[0], kind_rate or 0.0))
                        log(f"[{kind}] round {r} store-only receiver, sampler on another replay: "
                            f"{res['items_per_s']:,.0f} items/s, {res['received_chunks']}/{res['sent_chunks']} chunks, "
                            f"sampler {res['sampler'].get('batches_per_s', 0):.1f} batches/s")
                        store_sampled.append(res)
                order = list(replays) if r % 2 == 0 else list(replays)[::-1]
                for variant in order:
                    run, p, stats = replays[variant]
                    res = service_round(procs, node, stats, ep, run, r, duration, kind, shm=args.shm, replay_pid=p.pid,
                                        sample_rate=kind_rate, tag=variant, codec=args.codec)
                    log(f"[{kind}] round {r} replay {variant}: {res['items_per_s'] or 0:,.0f} items/s, "
                        f"{res['ingested_items']}/{res['sent_items']} items ingested, dropped {res['dropped_queue_full']}, "
                        f"{res['threads']['us_per_chunk']} us CPU per chunk, "
                        f"sampling {res.get('sample_batches_per_s')} batches/s")
                    svc[variant].append(res)
            for _, p, _ in replays.values():
                procs.stop(p)
            if ceiling is not None:
                procs.stop(ceiling[1])
            if args.service_only:
                kinds[kind] = {"rounds": svc}
                continue
            ref = inprocess_image_ingest(kind, 1.0 if args.quick else 3.0, args.codec)
            log(f"[{kind}] reference: the service's ingest in process: {ref['items_per_s']:,.0f} items/s "
                f"({ref['us_per_chunk_cpu']:.0f} us CPU per chunk)")
            ab = inprocess_ab(procs, args, kind, rounds, 1.0 if args.quick else 3.0) if args.baseline else None
            if ab:
                log(f"[{kind}] in process, each checkout in its own process: {ab}")
            raw_med = statistics.median(x["items_per_s"] for x in raw)
            store_med = statistics.median(x["items_per_s"] for x in store)
            chunk_bytes = len(encoded_pool(0, 1, "pub0", kind, args.codec)[0])
            k: dict[str, Any] = {
                "raw_zenoh_items_per_s": round(raw_med),
                # the ceiling of any receiver that keeps what it gets, on this machine, same transport
                "store_only_items_per_s": round(store_med),
                "store_only_ratio_vs_raw_zenoh": round(store_med / raw_med, 3),
            }
            for variant, rs in svc.items():
                med = median_of(rs)
                pre = "" if variant == "service" else f"{variant}_"
                k.update({
                    f"{pre}service_ingest_items_per_s": None if med is None else round(med),
                    f"{pre}service_fraction_of_store_only": None if not med else round(med / store_med, 3),
                    f"{pre}ingest_ratio_vs_raw_zenoh": None if not med else round(med / raw_med, 3),
                    f"{pre}sample_batches_per_s": median_of(rs, "sample_batches_per_s"),
                    f"{pre}service_us_per_chunk_cpu": median_of([x["threads"] for x in rs], "us_per_chunk"),
                })
            if store_sampled:
                # the most any replay can take while sampled as the service is: the store-only
                # receiver's rate with the same sampler on the same machine (its replies served
                # by another replay), as a fraction of the store-only receiver's rate
                ss_med = statistics.median(x["items_per_s"] for x in store_sampled)
                k["store_only_sampled_items_per_s"] = round(ss_med)
                k["ceiling_fraction_of_store_only"] = round(ss_med / store_med, 3)
                if k["service_ingest_items_per_s"]:
                    k["service_fraction_of_ceiling"] = round(k["service_ingest_items_per_s"] / ss_med, 3)
            if "baseline" in svc and k["service_ingest_items_per_s"] and k["baseline_service_ingest_items_per_s"]:
                k["service_vs_baseline"] = round(k["service_ingest_items_per_s"] / k["baseline_service_ingest_items_per_s"], 3)
            k.update({
                # the replay's own ceiling on one core (no network, no other process)
                "inprocess_items_per_s": round(ref["items_per_s"]),
                "inprocess_us_per_chunk_cpu": round(ref["us_per_chunk_cpu"], 1),
                "inprocess_ratio_vs_raw_zenoh": round(ref["items_per_s"] / raw_med, 3),
                "store_only_us_per_chunk_cpu": median_of([x["threads"] for x in store if x["threads"]], "us_per_chunk"),
                **({"inprocess_ab_us_per_chunk_cpu": ab,
                    # > 1: this checkout's ingest costs less CPU per chunk than the baseline's
                    "inprocess_cpu_baseline_vs_service": round(statistics.median(ab["baseline"])
                                                               / statistics.median(ab["service"]), 3)} if ab else {}),
                "chunk_items": IMAGE_CHUNK, "chunk_bytes": chunk_bytes,
                **({"learner_updates_per_s": learner_rates[kind]} if kind in learner_rates else {}),
                "final_replay_stats": {v: (st.snapshot()[-1][1] if st.snapshot() else None) for v, (_, _, st) in replays.items()},
                "rounds": {"raw": raw, "store_only": store, **({"store_only_sampled": store_sampled} if store_sampled else {}),
                           **svc},
            })
            kinds[kind] = k
        out.update({
            "kinds": kinds,
            "target_service_fraction_of_store_only": 0.8,
            "publishers": N_PUBLISHERS,
            "shared_memory": bool(args.shm),
            "codec": args.codec,
            "sampler": None if sample_rate is None else {"batch": LEARNER_BATCH, "in_flight": LEARNER_IN_FLIGHT,
                                                         "rate": ("each kind's learner_updates_per_s" if sample_rate == "learner"
                                                                  else sample_rate or "as served")},
            "notes": ("frame-mode chunks of random uint8 frames (lz4 cannot shrink them); rates at the receiver; "
                      "every party on the same transport settings (--shm); store-only = the same client "
                      "publishers to a subscriber process that copies each payload into a ring of the replay's "
                      "frame bytes; medians of alternating rounds; 2-core machine: noisy"),
            **machine_info(t_start),
        })
        for kind in ([] if args.service_only else args.kinds):  # last keys of the JSON line: the ratios
            out[f"{kind}_store_only_ratio_vs_raw_zenoh"] = kinds[kind]["store_only_ratio_vs_raw_zenoh"]
            out[f"{kind}_ingest_ratio_vs_raw_zenoh"] = kinds[kind]["ingest_ratio_vs_raw_zenoh"]
            if "ceiling_fraction_of_store_only" in kinds[kind]:
                out[f"{kind}_ceiling_fraction_of_store_only"] = kinds[kind]["ceiling_fraction_of_store_only"]
            if "baseline_service_fraction_of_store_only" in kinds[kind]:
                out[f"{kind}_baseline_service_fraction_of_store_only"] = kinds[kind]["baseline_service_fraction_of_store_only"]
            out[f"{kind}_service_fraction_of_store_only"] = kinds[kind]["service_fraction_of_store_only"]
    except BaseException as e:
        record_error(out, e)
    finally:
        shut_down(procs, node, router)
    return emit(out)


def _sample_rate(text: str) -> float | str:
    if text == "learner":
        return text
    v = float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"--sample-rate must be >= 0 or 'learner', got {text}")
    return v


#: the network each image kind is trained with: the shipped config of that observation
KIND_CONFIGS = {"cam64": "configs/burgerwar_image_apex.yaml", "atari84": "configs/pong_apex.yaml"}


def learner_rate(kind: str, warmup_s: float = 3.0, duration_s: float = 10.0) -> dict[str, Any]:
    """Updates/s of the Ape-X learner's update (``DQNLearner``: batch_to_tensors + update, batch
    LEARNER_BATCH, the kind's shipped network and torch threads) on synthetic batches of ``kind``
    already in memory, alone in this process: the most batches a learner would sample."""
    import gymnasium as gym
    import torch

    from zenrl.common.config import load_config
    from zenrl.common.networks import obs_spec, resolve_device
    from zenrl.learner.dqn import DQNLearner

    cfg = load_config(ROOT / KIND_CONFIGS[kind], [f"learner.batch_size={LEARNER_BATCH}"])
    shape = (64, 64, 3) if kind == "cam64" else (84, 84, IMAGE_STACK)
    spec = obs_spec(gym.spaces.Box(0, 255, shape, np.uint8))
    torch.set_num_threads(cfg.learner.torch_threads)
    dqn = DQNLearner(spec, 6, cfg.network, cfg.learner, resolve_device("cpu"))
    rng = np.random.default_rng(0)
    b = LEARNER_BATCH
    batches = [({"obs": rng.integers(0, 256, (b, *shape), dtype=np.uint8),
                 "next_obs": rng.integers(0, 256, (b, *shape), dtype=np.uint8),
                 "action": rng.integers(0, 6, b).astype(np.int64), "reward": rng.random(b).astype(np.float32),
                 "terminated": rng.random(b) < 0.01, "n": np.full(b, IMAGE_N_STEP, np.uint8),
                 "meta/policy_version": np.zeros(b, np.int64)},
                (rng.random(b) * 0.9 + 0.1).astype(np.float32)) for _ in range(4)]
    i = n = 0
    t_end = time.perf_counter() + warmup_s
    while time.perf_counter() < t_end:
        dqn.update(dqn.batch_to_tensors(*batches[i % 4]))
        i += 1
    t0 = time.perf_counter()
    while time.perf_counter() < t0 + duration_s:
        dqn.update(dqn.batch_to_tensors(*batches[i % 4]))
        i += 1
        n += 1
    el = time.perf_counter() - t0
    return {"updates_per_s": round(n / el, 2), "updates": n, "config": KIND_CONFIGS[kind],
            "torch_threads": cfg.learner.torch_threads}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one short round of each measurement")
    ap.add_argument("--checks-only", action="store_true", help="only the semantic checks' cost per chunk, in process (~25 s)")
    ap.add_argument("--role", choices=["pub", "rawsub", "sampler", "inproc"], help=argparse.SUPPRESS)
    ap.add_argument("--mode", choices=["raw", "client"], default="client", help=argparse.SUPPRESS)
    ap.add_argument("--router", help=argparse.SUPPRESS)
    ap.add_argument("--run", help=argparse.SUPPRESS)
    ap.add_argument("--id", default="pub0", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--duration", type=float, default=5.0, help=argparse.SUPPRESS)
    ap.add_argument("--warmup", type=float, default=1.0, help=argparse.SUPPRESS)
    ap.add_argument("--idle", type=float, default=1.5, help=argparse.SUPPRESS)
    ap.add_argument("--max-s", type=float, default=120.0, help=argparse.SUPPRESS)
    ap.add_argument("--store-mb", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--kind", choices=["cartpole", *IMAGE_KINDS], default="cartpole", help=argparse.SUPPRESS)
    ap.add_argument("--shm", action="store_true",
                    help="every party with Zenoh's shared memory on (transport.shared_memory; default off, as zenrl runs)")
    ap.add_argument("--sample-rate", type=_sample_rate, default=0.0,
                    help="--images: batches/s the learner-like sampler takes during service rounds (0: as fast as "
                         "served; 'learner': the Ape-X learner's own update rate for each kind on this machine)")
    ap.add_argument("--no-sampler", action="store_true", help="--images: no sampler during the service rounds")
    ap.add_argument("--baseline", default=None, metavar="DIR",
                    help="also measure the replay of the zenrl checkout DIR (run with DIR/.venv) in the same rounds: "
                         "an A/B of the replay's code, e.g. --baseline /path/to/main")
    ap.add_argument("--service-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a replay option for this checkout's replay only (not --baseline's), e.g. for an A/B of a setting")
    ap.add_argument("--codec", choices=["lz4"], default=None,
                    help="compress the chunks' uint8 arrays as actor.compress: lz4 does (--images)")
    ap.add_argument("--batch", type=int, default=SAMPLE_BATCH, help=argparse.SUPPRESS)
    ap.add_argument("--in-flight", type=int, default=IN_FLIGHT, help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--kinds", nargs="+", choices=IMAGE_KINDS, default=list(IMAGE_KINDS), help="--images: the kinds measured")
    ap.add_argument("--service-only", action="store_true",
                    help="--images: service rounds only (no raw, store-only or in-process reference; for diagnosis)")
    ap.add_argument("--ceiling", action="store_true",
                    help="--images: also store-only rounds with the learner-like sampler sampling another, filled "
                         "replay: ceiling_fraction_of_store_only, the most any replay sampled so can take")
    ap.add_argument("--rounds", type=int, default=None, help="rounds per measurement (default 3, 1 with --quick)")
    ap.add_argument("--images", action="store_true",
                    help="image mode: frame-mode chunks of 64x64x3 and of 84x84x4 stacks instead of CartPole chunks")
    args = ap.parse_args(argv)
    if args.role == "pub":
        return role_pub(args)
    if args.role == "rawsub":
        return role_rawsub(args)
    if args.role == "sampler":
        return role_sampler(args)
    if args.role == "inproc":
        return role_inproc(args)
    # SIGTERM on the benchmark itself still runs the cleanup in orchestrate's finally
    stop_on_sigterm()
    return orchestrate_images(args) if args.images else orchestrate(args)



if __name__ == "__main__":
    sys.exit(main())
