"""Learner throughput (issue 7): updates/s of the Ape-X learner fed over Zenoh vs in memory.

Measures, in one run and one process (CartPole-v1 network from ``configs/cartpole_apex.yaml``,
``learner.batch_size=512``, one torch thread as configured):

  * ``service``  - updates/s of :class:`ApexLearner` doing everything it does in a run:
                   ``SamplePrefetcher`` (4 sample queries in flight) against a ``zenrl replay``
                   process pre-filled with CartPole transitions, ``batch_to_tensors`` +
                   ``DQNLearner.update``, priorities sent back from the background sender,
                   weights broadcast every ``publish_every_updates``;
  * ``baseline`` - updates/s of the same :class:`DQNLearner` on synthetic batches of the same
                   layout already in memory (``batch_to_tensors`` + ``update``), nothing sent;
  * ``guard``    - CPU time per update with and without the learner's guard (non-finite loss or
                   gradient skips the step; parameters checked finite before each broadcast):
                   ``guard_overhead_ratio`` (target <= 1.02).

Rounds alternate (baseline, service, baseline, service, ...); medians are compared:
``learner_efficiency`` = median service rate / median baseline rate (target >= 0.9). Rates are
read from the update counter between two instants after a warm-up (start-up, the first weights
broadcast and the final checkpoint are outside the window). ``learner_efficiency_cpu`` compares
updates per CPU-second of the training thread, steadier on a loaded machine.

When the efficiency (wall or CPU) is below target (or with ``--profile``), one more service run is profiled
with cProfile (``profile``), plus the learner's own ``wait_fraction`` (time blocked on the
prefetcher).

Progress goes to stderr; the last stdout line is one JSON object.

    python bench/learner_throughput.py            # full run (~1.5-2 min)
    python bench/learner_throughput.py --quick    # one short round (~40 s)
    python bench/learner_throughput.py --guard-only   # the learner guard's cost per update (~35 s)
    python bench/learner_throughput.py --poison       # 1% in-bounds poison vs none; the checks' cost
    python bench/learner_throughput.py --r2d2         # the R2D2 learner on sequences (~2 min)

``--r2d2`` (issue #34): the same comparison for :class:`R2D2Learner` with
``configs/stateless_cartpole_r2d2.yaml`` (its batch of 32 sequences of 20 steps, burn-in 10):
the replay process is pre-filled with sequences cut by the actor's ``SequenceBuilder`` from
StatelessCartPole episodes (random actions); ``baseline`` is ``R2D2Core`` on sampled batches
already in memory, ``inmem_replay`` the same core sampling an ``InMemoryReplay`` holding the same
sequences and writing the priorities back in the same thread (what a single-process learner would
do). ``learner_efficiency`` = service / baseline (Ape-X's definition, target >= 0.85 here);
``learner_efficiency_vs_replay`` = service / inmem_replay.
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
from typing import Any, Callable

import numpy as np

from _common import ROOT, Procs, ab_cpu_us, emit, log, machine_info, record_error, shut_down, stop_on_sigterm, wait_until  # noqa: E402  (bench/ is on sys.path when run as a script)

CONFIG = ROOT / "configs" / "cartpole_apex.yaml"
BATCH = 512
TARGET = 0.9
PREFILL = 50_000
CHUNK = 64


class StatsWatch:
    """Latest stats of one role/id."""

    def __init__(self, node: Any, key: str) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self.latest: dict[str, Any] = {}
        self.history: list[dict[str, Any]] = []
        node.subscribe(key, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        self.latest = dict(self._P.Stats.decode(payload).values)
        self.history.append(self.latest)


def cartpole_batch(rng: np.random.Generator, b: int) -> dict[str, np.ndarray]:
    return {
        "obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),  # inside CartPole's bounds (the replay checks them)
        "action": rng.integers(0, 2, b).astype(np.int64),
        "reward": (rng.random(b) * 3).astype(np.float32),
        "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
        "terminated": rng.random(b) < 0.02,
        "truncated": np.zeros(b, bool),
        "n": np.full(b, 3, np.uint8),
    }


def prefill(node: Any, keys: Any, rstats: StatsWatch, n_items: int) -> None:
    from zenrl.common.replay_client import ZenohReplayClient

    client = ZenohReplayClient(node, keys, "bench-prefill")
    rng = np.random.default_rng(0)
    sent = 0
    while sent < n_items:
        client.insert(cartpole_batch(rng, CHUNK), (rng.random(CHUNK) + 0.01).astype(np.float32), policy_version=0)
        sent += CHUNK
    client.flush_backlog()
    wait_until(lambda: rstats.latest.get("inserted_total", 0) >= sent, 120, f"replay to hold {sent} items")


def baseline_rate(cfg: Any, spec: Any, n_actions: int, warmup_s: float, duration_s: float) -> dict[str, Any]:
    """Updates/s of a DQNLearner on synthetic batches in memory (batch_to_tensors + update)."""
    import torch

    from zenrl.common.networks import resolve_device
    from zenrl.learner.dqn import DQNLearner

    torch.set_num_threads(cfg.learner.torch_threads)
    torch.manual_seed(cfg.seed)
    dqn = DQNLearner(spec, n_actions, cfg.network, cfg.learner, resolve_device(cfg.learner.device))
    rng = np.random.default_rng(1)
    batches = []
    for _ in range(8):
        d = cartpole_batch(rng, BATCH)
        d["meta/policy_version"] = np.zeros(BATCH, np.int64)
        batches.append((d, (rng.random(BATCH) * 0.9 + 0.1).astype(np.float32)))
    i = 0
    t_end = time.perf_counter() + warmup_s
    while time.perf_counter() < t_end:
        dqn.update(dqn.batch_to_tensors(*batches[i % 8]))
        i += 1
    n = 0
    t0, c0 = time.perf_counter(), time.thread_time()
    t_end = t0 + duration_s
    while time.perf_counter() < t_end:
        d, w = batches[i % 8]
        dqn.update(dqn.batch_to_tensors(d, w))
        i += 1
        n += 1
    el, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return {"updates_per_s": n / el, "updates_per_cpu_s": n / cpu, "updates": n, "elapsed_s": el, "cpu_s": cpu}


def guard_overhead(cfg: Any, spec: Any, n_actions: int, rounds: int, round_s: float) -> dict[str, Any]:
    """CPU time per update of ``DQNLearner.update`` with the learner's guard (the finite check of
    loss and gradient norm, plus the parameters' finite check the service makes before each
    weights broadcast, every ``publish_every_updates``) and without it (the guard's ``accept``
    replaced by one that always agrees, no parameter check); rounds alternate, in this process.
    ``guard_overhead_ratio`` = median guarded / median unguarded (target <= 1.02)."""
    import torch

    from zenrl.common.networks import resolve_device
    from zenrl.learner.dqn import DQNLearner

    torch.set_num_threads(cfg.learner.torch_threads)
    learners = {}
    for guarded in (True, False):
        torch.manual_seed(cfg.seed)
        learners[guarded] = DQNLearner(spec, n_actions, cfg.network, cfg.learner, resolve_device(cfg.learner.device))
    learners[False].guard.accept = lambda _loss, _norm: True
    rng = np.random.default_rng(2)
    batches = []
    for _ in range(8):
        d = cartpole_batch(rng, BATCH)
        d["meta/policy_version"] = np.zeros(BATCH, np.int64)
        batches.append(learners[True].batch_to_tensors(d, (rng.random(BATCH) * 0.9 + 0.1).astype(np.float32)))
    every = cfg.learner.publish_every_updates

    def guarded(n: int) -> None:  # with the finite check each broadcast would make
        learners[True].update(batches[n % 8])
        if (n + 1) % every == 0 and not learners[True].params_finite():
            raise RuntimeError("the benchmark's learner diverged")

    us = ab_cpu_us({True: guarded, False: lambda n: learners[False].update(batches[n % 8])}, rounds, round_s)
    on, off = us[True], us[False]
    return {"guard_overhead_ratio": round(on / off, 4), "update_us_guarded": round(on, 1),
            "update_us_unguarded": round(off, 1), "guard_rounds": rounds, "target_guard_overhead_ratio": 1.02}


POISON_FRACTION = 0.01
POISON_TARGET = 0.9
CHECKS_TARGET = 1.02
ORIGINS_TARGET = 1.05


def poisoned_chunk(rng: np.random.Generator, b: int, fraction: float, value: float) -> dict[str, np.ndarray]:
    """A CartPole chunk in which each item has, with probability ``fraction``, ``value`` (e.g.
    float32's max, inside CartPole's Box) as one of its velocities (obs or next_obs)."""
    d = cartpole_batch(rng, b)
    for i in np.flatnonzero(rng.random(b) < fraction):
        d["obs" if rng.random() < 0.5 else "next_obs"][i, 1 if rng.random() < 0.5 else 3] = value * rng.choice([-1, 1])
    d["meta/policy_version"] = np.zeros(b, np.int64)
    return d


def poison_loop(cfg: Any, spec: Any, n_actions: int, fraction: float, value: float, seed: int) -> tuple[Any, Any]:
    """One step of the learner's loop against an in-memory replay, and the learner: insert a
    chunk of ``CHUNK`` items (``fraction`` of them poisoned), sample a batch of ``BATCH``,
    ``batch_to_tensors`` + ``update``, the priorities of the kept items back and the poisoned
    ones removed (what the replay does with a ``poisoned`` report)."""
    import torch

    from zenrl.common.networks import resolve_device
    from zenrl.common.specs import spec_of_batch
    from zenrl.learner.dqn import DQNLearner
    from zenrl.replay.buffer import InMemoryReplay

    torch.manual_seed(cfg.seed)
    dqn = DQNLearner(spec, n_actions, cfg.network, cfg.learner, resolve_device(cfg.learner.device),
                     max_priority=cfg.replay.max_priority)
    rng = np.random.default_rng(seed)
    first = poisoned_chunk(rng, 4 * CHUNK, fraction, value)
    rb = InMemoryReplay(spec_of_batch(first), capacity=cfg.replay.capacity, alpha=cfg.replay.alpha, seed=seed)
    while rb.size < cfg.replay.capacity:
        rb.insert(poisoned_chunk(rng, 4 * CHUNK, fraction, value))

    def step(_n: int) -> None:
        rb.insert(poisoned_chunk(rng, CHUNK, fraction, value))
        s = rb.sample(BATCH, dqn.beta(), rng)
        _, prios = dqn.update(dqn.batch_to_tensors(s.data, s.weights))
        bad = dqn.poisoned
        if bad.size:
            rb.remove(s.keys[bad])
        if prios is not None:
            keep = np.ones(BATCH, bool)
            keep[bad] = False
            rb.update_priorities(s.keys[keep], prios[keep])

    return step, dqn


def unchecked_update(dqn: Any) -> Callable[[Any], None]:
    """The step with no check at all, for the cost of the checks: no observation screen, no |TD|
    bound, no guard (forward, loss, backward, clip, optimizer step, priorities)."""
    import torch

    from zenrl.common.networks import rename_prefix, to_tensors
    from zenrl.learner.dqn import double_dqn_target, dqn_loss

    def run(pair: tuple[dict[str, np.ndarray], np.ndarray]) -> None:
        data, w = pair
        t = to_tensors({k: v for k, v in data.items() if k in ("action", "reward", "n", "terminated")}, dqn.device)
        obs = to_tensors({k: data[k] for k in dqn.obs_spec}, dqn.device)
        nxt = to_tensors(rename_prefix(data, "next_obs", "obs"), dqn.device)
        weights = torch.from_numpy(np.array(w, np.float32))
        with torch.no_grad():
            y = double_dqn_target(dqn.online(nxt), dqn.target(nxt), t["reward"].float(), t["n"], t["terminated"],
                                  dqn.cfg.gamma)
        loss, td_abs, q_sa = dqn_loss(dqn.online(obs), t["action"], y, weights, dqn.cfg.huber_delta)
        dqn.opt.zero_grad(set_to_none=True)
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(dqn.online.parameters(), dqn.cfg.grad_clip)
        float(loss.item()), float(norm.item()), float(q_sa.mean().item())
        dqn.opt.step()
        td_abs.numpy().astype(np.float32)

    return run


def poison_bench(cfg: Any, spec: Any, n_actions: int, rounds: int, round_s: float) -> dict[str, Any]:
    """Issue #32 item 2, in this process, CPU time of this thread per step (rounds alternate):

    * ``poison_ratio``: the learner loop (:func:`poison_loop`) with 1% of the inserted items at
      float32's max in a velocity (left out by the observation screen), clean / poisoned
      (target >= 0.9); ``poison_ratio_in_step``: the same without the screen, so that the step
      itself must find and leave out the items (a second forward on the others);
    * ``checks_overhead_ratio``: ``batch_to_tensors`` + ``update`` of the learner as it is /
      the same learner with the observation screen, the |TD| bound and the guard turned off, on
      clean batches (target <= 1.02); ``checks_overhead_ratio_vs_bare``: / the step written out
      with no check and no bookkeeping at all (:func:`unchecked_update`);
    * ``origins_overhead_ratio``: the replay's ingest of a chunk with / without the record of
      who sent each item (target <= 1.05)."""
    import torch

    from zenrl.common import protocol as P
    from zenrl.common.config import load_config
    from zenrl.common.networks import resolve_device
    from zenrl.learner.dqn import DQNLearner
    from zenrl.replay.service import ReplayService

    torch.set_num_threads(cfg.learner.torch_threads)
    f32max = float(np.finfo(np.float32).max)
    unscreened = cfg.model_copy(update={"learner": cfg.learner.model_copy(update={"max_abs_obs": 1e39})})
    loops = {"clean": poison_loop(cfg, spec, n_actions, 0.0, 0.0, 5),
             "poisoned": poison_loop(cfg, spec, n_actions, POISON_FRACTION, f32max, 5),
             "in_step": poison_loop(unscreened, spec, n_actions, POISON_FRACTION, f32max, 5)}
    us = ab_cpu_us({k: v[0] for k, v in loops.items()}, rounds, round_s)
    out: dict[str, Any] = {
        "poison_ratio": round(us["clean"] / us["poisoned"], 4),
        "poison_ratio_in_step": round(us["clean"] / us["in_step"], 4),
        "poison_step_us": {k: round(v, 1) for k, v in us.items()},
        "poisoned_items": {k: v[1].poisoned_total for k, v in loops.items()},
        "repaired_updates": {k: v[1].repaired_updates for k, v in loops.items()},
        "skipped_updates": {k: v[1].guard.skipped for k, v in loops.items()},
        "updates": {k: v[1].updates for k, v in loops.items()},
        "poison_fraction": POISON_FRACTION, "target_poison_ratio": POISON_TARGET,
    }
    # the checks' cost per update, on clean batches
    torch.manual_seed(cfg.seed)
    dev = resolve_device(cfg.learner.device)
    checked = DQNLearner(spec, n_actions, cfg.network, cfg.learner, dev, max_priority=cfg.replay.max_priority)
    off = DQNLearner(spec, n_actions, cfg.network, cfg.learner, dev)  # no |TD| bound
    off.screen = lambda data, w, _fields: (data, w, {"_rows": None, "_screened": np.zeros(0, np.int64), "_n": len(w)})
    off.guard.accept = lambda _loss, _norm: True
    bare_step = unchecked_update(DQNLearner(spec, n_actions, cfg.network, cfg.learner, dev))
    rng = np.random.default_rng(3)
    pairs = [(poisoned_chunk(rng, BATCH, 0.0, 0.0), (rng.random(BATCH) * 0.9 + 0.1).astype(np.float32)) for _ in range(8)]
    us = ab_cpu_us({"checked": lambda n: checked.update(checked.batch_to_tensors(*pairs[n % 8])),
                    "off": lambda n: off.update(off.batch_to_tensors(*pairs[n % 8])),
                    "bare": lambda n: bare_step(pairs[n % 8])}, rounds * 2, round_s)
    out.update({"checks_overhead_ratio": round(us["checked"] / us["off"], 4),
                "checks_overhead_ratio_vs_bare": round(us["checked"] / us["bare"], 4),
                "update_us_checked": round(us["checked"], 1), "update_us_checks_off": round(us["off"], 1),
                "update_us_bare": round(us["bare"], 1), "target_checks_overhead_ratio": CHECKS_TARGET})
    # the replay's record of who sent each item, per chunk of 256
    rcfg = load_config(CONFIG, ["replay.capacity=100000", "replay.min_size=1"], environ={})
    svcs = {True: ReplayService(rcfg, None, "bench"), False: ReplayService(rcfg, None, "bench")}
    svcs[False].ingestor.origins = None
    payloads = [P.TransitionBatch("a0", 0, i, {k: v for k, v in poisoned_chunk(rng, 256, 0.0, 0.0).items()
                                               if k != "meta/policy_version"}).encode() for i in range(16)]
    us = ab_cpu_us({k: (lambda n, svc=svc: svc.ingest(payloads[n % 16], "zenrl/bench/transitions/a0"))
                    for k, svc in svcs.items()}, rounds * 2, round_s)
    out.update({"origins_overhead_ratio": round(us[True] / us[False], 4), "ingest_us_per_chunk": round(us[True], 1),
                "ingest_us_per_chunk_without_origins": round(us[False], 1), "target_origins_overhead_ratio": ORIGINS_TARGET})
    return out


def make_service(cfg: Any, node: Any, run: str, name: str) -> Any:
    """The learner of ``cfg.algo`` (Ape-X or R2D2), fed by the replay service."""
    if cfg.algo == "r2d2":
        from zenrl.learner.r2d2 import R2D2Learner

        return R2D2Learner(cfg, node, run, resume="never", learner_id=name)
    from zenrl.learner.apex import ApexLearner

    return ApexLearner(cfg, node, run, resume="never", learner_id=name)


def service_rate(cfg: Any, node: Any, run: str, name: str, warmup_s: float, duration_s: float,
                 lstats: StatsWatch) -> dict[str, Any]:
    """Updates/s of ApexLearner.run in this (the main) thread, read from its update counter
    by a helper thread, which also stops it."""
    svc = make_service(cfg, node, run, name)
    stop = threading.Event()
    marks: list[tuple[int, float, float]] = []
    clock = time.pthread_getcpuclockid(threading.get_ident())
    n_hist = len(lstats.history)

    def monitor() -> None:
        deadline = time.monotonic() + 60
        while svc.dqn.updates == 0 and not stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)
        if not stop.wait(warmup_s):
            marks.append((svc.dqn.updates, time.perf_counter(), time.clock_gettime(clock)))
            if not stop.wait(duration_s):
                marks.append((svc.dqn.updates, time.perf_counter(), time.clock_gettime(clock)))
        stop.set()

    mon = threading.Thread(target=monitor, name="monitor", daemon=True)
    mon.start()
    try:
        svc.run(stop)
    finally:
        stop.set()
        mon.join(timeout=10)
    if len(marks) < 2:
        raise RuntimeError("the learner made no update (replay not serving?) or stopped early")
    (u0, t0, c0), (u1, t1, c1) = marks
    own = [h for h in lstats.history[n_hist:] if h.get("updates", 0) > 0]
    return {"updates_per_s": (u1 - u0) / (t1 - t0), "updates_per_cpu_s": (u1 - u0) / (c1 - c0),
            "updates": u1 - u0, "elapsed_s": t1 - t0, "cpu_s": c1 - c0,
            "wait_fraction": statistics.mean(h["wait_fraction"] for h in own) if own else None,
            "not_ready": own[-1].get("not_ready") if own else None,
            "sample_timeouts": own[-1].get("sample_timeouts") if own else None,
            "send_dropped": own[-1].get("send_dropped") if own else None,
            "policy_lag": own[-1].get("policy_lag") if own else None}


BUCKETS = [
    ("waiting on prefetcher (SamplePrefetcher.get)", "common/replay_client.py", "get"),
    ("batch_to_tensors (0 here: it runs in the reply callback)", "learner/dqn.py", "batch_to_tensors"),
    ("DQNLearner.update", "learner/dqn.py", "update"),
    ("encode (PriorityUpdate: on the sender thread)", "common/protocol.py", "encode"),
    ("weights encode (_encode_weights)", "learner/apex.py", "_encode_weights"),
    ("write_version_mark", "learner/checkpoint.py", "write_version_mark"),
    ("BackgroundSender.send_priorities", "learner/sender.py", "send_priorities"),
    ("stats/metrics (MetricsWriter.write)", "common/metrics.py", "write"),
]


def profile_service(cfg: Any, node: Any, run: str, duration_s: float) -> dict[str, Any]:
    svc = make_service(cfg, node, run, "bench-learner-prof")
    stop = threading.Event()
    loop_t: list[float] = []

    def stopper() -> None:
        wait_until(lambda: svc.dqn.updates > 0, 60, "first update", 0.01)
        loop_t.append(time.perf_counter())
        u0 = svc.dqn.updates
        time.sleep(duration_s)
        loop_t.append(time.perf_counter())
        loop_t.append(svc.dqn.updates - u0)
        stop.set()

    threading.Thread(target=stopper, daemon=True).start()
    prof = cProfile.Profile()
    prof.enable()
    try:
        svc.run(stop)
    finally:
        prof.disable()
    entries = pstats.Stats(prof).stats
    run_ct = next((v[3] for k, v in entries.items() if k[0].endswith("learner/base.py") and k[2] == "run"), 1.0)
    buckets = {}
    for label, suffix, func in BUCKETS:
        ct = sum(v[3] for k, v in entries.items() if k[0].endswith(suffix) and k[2] == func)
        buckets[label] = {"s": round(ct, 3), "share_of_run": round(ct / run_ct, 3)}
    top = sorted(entries.items(), key=lambda kv: kv[1][2], reverse=True)[:15]
    return {"run_s": round(run_ct, 2), "updates": svc.dqn.updates,
            "updates_per_s_under_profiler": round(loop_t[2] / (loop_t[1] - loop_t[0]), 1) if len(loop_t) == 3 else None,
            "buckets": buckets,
            "top_tottime": [{"func": f"{Path(k[0]).name}:{k[1]}({k[2]})", "tottime_s": round(v[2], 3),
                             "cumtime_s": round(v[3], 3), "calls": v[1]} for k, v in top],
            "note": "run_s includes start-up (first weights broadcast) and the final checkpoint"}


# -- R2D2 (issue #34) ----------------------------------------------------------------------------
R2D2_CONFIG = ROOT / "configs" / "stateless_cartpole_r2d2.yaml"
R2D2_TARGET = 0.85
R2D2_PREFILL = 4000  # sequences (the config's replay.capacity)


def make_sequences(cfg: Any, n: int, seed: int = 0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``n`` sequences as an R2D2 actor sends them (fields of :mod:`zenrl.actor.sequences`), cut
    by :class:`SequenceBuilder` from ``cfg.env`` episodes under random actions; the acting Q values
    and LSTM state are random (|h| < 1, zero at an episode's first step): the learner's cost does
    not depend on them. Returns (fields [n, ...], initial priorities float32[n])."""
    from zenrl.actor.batch_env import EnvBatch
    from zenrl.actor.sequences import SequenceBuilder

    r = cfg.r2d2
    E, H = cfg.actor.envs_per_actor, r.lstm_size
    envs = EnvBatch(cfg.env, E, seed=seed)
    n_act = int(envs.single_action_space.n)
    b = SequenceBuilder(E, r.sequence_length, r.n_step, cfg.learner.gamma, burn_in=r.burn_in, eta=r.eta,
                        eps=r.value_rescale_eps, block_steps=r.block_steps)
    rng = np.random.default_rng(seed)
    obs, parts, prios, got = envs.reset(), [], [], 0
    while got < n:
        start = (b.ep == 0)[:, None]
        h = np.where(start, 0.0, np.tanh(rng.normal(size=(E, H)))).astype(np.float32)
        c = np.where(start, 0.0, rng.normal(size=(E, H))).astype(np.float32)
        q = rng.normal(size=(E, n_act)).astype(np.float32)
        act = rng.integers(0, n_act, E)
        res = envs.step(act)
        block = b.add(obs, q, (h, c), act, res.rewards, res.next_obs, res.terminated, res.truncated,
                      lambda idx: rng.normal(size=(len(idx), n_act)).astype(np.float32))
        obs = res.obs
        if block is not None and len(block):
            parts.append(block.data)
            prios.append(block.priorities)
            got += len(block)
    envs.close()
    data = {k: np.concatenate([d[k] for d in parts])[:n] for k in parts[0]}
    return data, np.concatenate(prios)[:n].astype(np.float32)


def prefill_sequences(node: Any, keys: Any, rstats: StatsWatch, data: dict[str, np.ndarray], prios: np.ndarray,
                      per_chunk: int) -> None:
    from zenrl.common.replay_client import ZenohReplayClient

    client = ZenohReplayClient(node, keys, "bench-prefill")
    n = len(prios)
    for i in range(0, n, per_chunk):
        client.insert({k: v[i:i + per_chunk] for k, v in data.items()}, prios[i:i + per_chunk], policy_version=0)
    client.flush_backlog()
    wait_until(lambda: rstats.latest.get("inserted_total", 0) >= n, 120, f"replay to hold {n} sequences")


def r2d2_memory_rate(cfg: Any, spec: Any, n_actions: int, data: dict[str, np.ndarray], prios: np.ndarray,
                     sample: bool, warmup_s: float, duration_s: float) -> dict[str, Any]:
    """Updates/s of an :class:`R2D2Core` in this thread. ``sample`` False: on 8 batches sampled
    once from an in-memory replay (``batch_to_tensors`` + ``update``, nothing else); True: each
    step samples the in-memory replay, updates and writes the priorities back."""
    import torch

    from zenrl.common.networks import resolve_device
    from zenrl.common.specs import spec_of_batch
    from zenrl.learner.r2d2 import R2D2Core
    from zenrl.replay.buffer import InMemoryReplay

    torch.set_num_threads(cfg.learner.torch_threads)
    torch.manual_seed(cfg.seed)
    core = R2D2Core(spec, n_actions, cfg.network, cfg.learner, cfg.r2d2, resolve_device(cfg.learner.device),
                    cfg.replay.max_priority)
    rb = InMemoryReplay(spec_of_batch(data), capacity=len(prios), alpha=cfg.replay.alpha, seed=1)
    rb.insert(data, prios)
    rng = np.random.default_rng(1)
    B = cfg.learner.batch_size
    fixed = [rb.sample(B, core.beta(), rng) for _ in range(8)]

    def step(i: int) -> None:
        s = rb.sample(B, core.beta(), rng) if sample else fixed[i % 8]
        _, p = core.update(core.batch_to_tensors(s.data, s.weights))
        if sample and p is not None:
            rb.update_priorities(s.keys, p)

    i = 0
    t_end = time.perf_counter() + warmup_s
    while time.perf_counter() < t_end:
        step(i)
        i += 1
    n = 0
    t0, c0 = time.perf_counter(), time.thread_time()
    while time.perf_counter() < t0 + duration_s:
        step(i)
        i += 1
        n += 1
    el, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return {"updates_per_s": n / el, "updates_per_cpu_s": n / cpu, "updates": n, "elapsed_s": el, "cpu_s": cpu}


def r2d2_bench(args: argparse.Namespace) -> int:
    """``--r2d2``: service (replay process + Zenoh) vs in memory, rounds alternating."""
    import torch

    from zenrl.actor.r2d2 import sequences_per_chunk
    from zenrl.common import protocol as P
    from zenrl.common.config import load_config
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port
    from zenrl.learner.base import env_facts

    t_start = time.perf_counter()
    rounds, warmup_s, dur_s = (1, 2.0, 5.0) if args.quick else (3, 3.0, 8.0)
    ep = f"tcp/127.0.0.1:{free_port()}"
    run = f"bench{uuid.uuid4().hex[:8]}"
    keys = P.Keys(run)
    tmp = Path(tempfile.mkdtemp(prefix="zenrl-bench-learner-r2d2-"))
    cfg = load_config(R2D2_CONFIG, [f"transport.router={ep}", f"run_id={run}", f"runs_dir={tmp / 'runs'}",
                                    "learner.log_interval_s=1.0", "learner.device=cpu", *args.set])
    out: dict[str, Any] = {"bench": "learner_throughput", "mode": "r2d2", "quick": bool(args.quick), "error": None}
    router = open_router([ep])
    procs = Procs(tmp)
    node = None
    try:
        node = Node(ep, 10.0)
        rstats = StatsWatch(node, keys.stats("replay", "replay"))
        lstats = StatsWatch(node, f"{keys.prefix}/stats/learner/*")
        log(f"router {ep}, run {run}, logs in {tmp}")
        procs.start("replay", ["-m", "zenrl.cli", "replay", "--config", str(R2D2_CONFIG), "--router", ep,
                               "--run-id", run, "--set", "replay.stats_interval_s=0.25",
                               "--set", f"replay.capacity={R2D2_PREFILL}", *sum((["--set", x] for x in args.set), [])])
        data, prios = make_sequences(cfg, R2D2_PREFILL)
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 1.0), 60, "replay service")
        prefill_sequences(node, keys, rstats, data, prios, sequences_per_chunk(cfg.actor.chunk_size, cfg.r2d2.sequence_length))
        log(f"replay pre-filled: {rstats.latest.get('size')} sequences")
        spec, n_actions, _ = env_facts(cfg)
        base, mem, svc = [], [], []
        for r in range(rounds):
            b = r2d2_memory_rate(cfg, spec, n_actions, data, prios, False, warmup_s, dur_s)
            log(f"round {r} baseline (R2D2Core, in-memory batches): {b['updates_per_s']:.1f} updates/s")
            base.append(b)
            s = service_rate(cfg, node, run, f"bench-learner-{r}", warmup_s, dur_s, lstats)
            log(f"round {r} R2D2Learner: {s['updates_per_s']:.1f} updates/s, wait fraction {s['wait_fraction']}")
            svc.append(s)
            m = r2d2_memory_rate(cfg, spec, n_actions, data, prios, True, warmup_s, dur_s)
            log(f"round {r} R2D2Core + InMemoryReplay: {m['updates_per_s']:.1f} updates/s")
            mem.append(m)

        def med(xs: list[dict[str, Any]], k: str = "updates_per_s") -> float:
            return statistics.median(x[k] for x in xs)

        eff, eff_cpu = med(svc) / med(base), med(svc, "updates_per_cpu_s") / med(base, "updates_per_cpu_s")
        out.update({
            "learner_efficiency": round(eff, 3),
            "learner_efficiency_cpu": round(eff_cpu, 3),
            "learner_efficiency_vs_replay": round(med(svc) / med(mem), 3),
            "target_efficiency": R2D2_TARGET,
            "service_updates_per_s": round(med(svc), 1),
            "baseline_updates_per_s": round(med(base), 1),
            "inmem_replay_updates_per_s": round(med(mem), 1),
            "batch_size": cfg.learner.batch_size,
            "sequence_length": cfg.r2d2.sequence_length,
            "burn_in": cfg.r2d2.burn_in,
            "lstm_size": cfg.r2d2.lstm_size,
            "requests_in_flight": cfg.learner.requests_in_flight,
            "publish_every_updates": cfg.learner.publish_every_updates,
            "torch_threads": cfg.learner.torch_threads,
            "replay_size": rstats.latest.get("size"),
            "rounds": {"baseline": base, "service": svc, "inmem_replay": mem},
        })
        if min(eff, eff_cpu) < R2D2_TARGET or args.profile:
            log("profiling one more learner run (cProfile)")
            out["profile"] = profile_service(cfg, node, run, 4.0 if args.quick else 8.0)
        out.update({"notes": ("rates between two instants after a warm-up, medians of alternating rounds; the "
                              "replay (a separate process) and the router (in this process) work during service "
                              "rounds only; 2-core machine shared with other work"),
                    "torch": torch.__version__, **machine_info(t_start)})
    except BaseException as e:
        record_error(out, e)
    finally:
        shut_down(procs, node, router)
    return emit(out)


# --------------------------------------------------------------------------------------------
def orchestrate(args: argparse.Namespace) -> int:
    import torch

    from zenrl.common import protocol as P
    from zenrl.common.config import load_config
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port
    from zenrl.learner.base import env_facts

    t_start = time.perf_counter()
    rounds, warmup_s, dur_s = (1, 1.5, 4.0) if args.quick else (3, 2.0, 8.0)
    ep = f"tcp/127.0.0.1:{free_port()}"
    run = f"bench{uuid.uuid4().hex[:8]}"
    keys = P.Keys(run)
    tmp = Path(tempfile.mkdtemp(prefix="zenrl-bench-learner-"))
    cfg = load_config(CONFIG, [f"learner.batch_size={BATCH}", f"transport.router={ep}", f"run_id={run}",
                               f"runs_dir={tmp / 'runs'}", "learner.log_interval_s=1.0", "learner.device=cpu", *args.set])
    out: dict[str, Any] = {"bench": "learner_throughput", "quick": bool(args.quick), "error": None}
    if args.poison:
        out["mode"] = "poison"
        try:
            spec, n_actions, _ = env_facts(cfg)
            out.update(poison_bench(cfg, spec, n_actions, 2 if args.quick else 4, 3.0))
            log(f"poison: ratio {out['poison_ratio']} (screened), {out['poison_ratio_in_step']} (in the step); "
                f"checks {out['checks_overhead_ratio']}; origins {out['origins_overhead_ratio']}")
            out.update({"batch_size": BATCH, "chunk": CHUNK, "torch": torch.__version__, **machine_info(t_start)})
        except BaseException as e:
            record_error(out, e)
        return emit(out)
    if args.guard_only:
        out["mode"] = "guard_only"
        try:
            spec, n_actions, _ = env_facts(cfg)
            out.update(guard_overhead(cfg, spec, n_actions, 8, 2.0))
            log(f"learner guard: {out['update_us_guarded']} vs {out['update_us_unguarded']} us per update, "
                f"ratio {out['guard_overhead_ratio']}")
            out.update({"batch_size": BATCH, "torch": torch.__version__, **machine_info(t_start)})
        except BaseException as e:
            record_error(out, e)
        return emit(out)
    router = open_router([ep])
    procs = Procs(tmp)
    node = None
    try:
        node = Node(ep, 10.0)
        rstats = StatsWatch(node, keys.stats("replay", "replay"))
        lstats = StatsWatch(node, f"{keys.prefix}/stats/learner/*")
        log(f"router {ep}, run {run}, logs in {tmp}")
        procs.start("replay", ["-m", "zenrl.cli", "replay", "--config", str(CONFIG), "--router", ep, "--run-id", run,
                               "--set", "replay.stats_interval_s=0.25",
                               "--set", f"replay.capacity={2 * PREFILL}"])  # holds the whole prefill
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 1.0), 60, "replay service")
        prefill(node, keys, rstats, PREFILL)
        log(f"replay pre-filled: {rstats.latest.get('size')} items")
        spec, n_actions, _ = env_facts(cfg)
        base, svc = [], []
        for r in range(rounds):
            b = baseline_rate(cfg, spec, n_actions, warmup_s, dur_s)
            log(f"round {r} baseline (DQNLearner, in-memory batches): {b['updates_per_s']:.1f} updates/s")
            base.append(b)
            s = service_rate(cfg, node, run, f"bench-learner-{r}", warmup_s, dur_s, lstats)
            log(f"round {r} ApexLearner: {s['updates_per_s']:.1f} updates/s, wait fraction {s['wait_fraction']}")
            svc.append(s)
        guard = guard_overhead(cfg, spec, n_actions, 2 if args.quick else 6, 1.5)
        log(f"learner guard: ratio {guard['guard_overhead_ratio']} (CPU per update, guarded / unguarded)")
        out.update(guard)
        base_med = statistics.median(x["updates_per_s"] for x in base)
        svc_med = statistics.median(x["updates_per_s"] for x in svc)
        eff = svc_med / base_med
        eff_cpu = (statistics.median(x["updates_per_cpu_s"] for x in svc)
                   / statistics.median(x["updates_per_cpu_s"] for x in base))
        out.update({
            "learner_efficiency": round(eff, 3),
            "target_efficiency": TARGET,
            "learner_efficiency_cpu": round(eff_cpu, 3),
            "service_updates_per_s": round(svc_med, 1),
            "baseline_updates_per_s": round(base_med, 1),
            "batch_size": BATCH,
            "requests_in_flight": cfg.learner.requests_in_flight,
            "publish_every_updates": cfg.learner.publish_every_updates,
            "network_hidden": list(cfg.network.hidden),
            "torch_threads": cfg.learner.torch_threads,
            "replay_size": rstats.latest.get("size"),
            "rounds": {"baseline": base, "service": svc},
        })
        if min(eff, eff_cpu) < TARGET or args.profile:
            log("profiling one more learner run (cProfile)")
            out["profile"] = profile_service(cfg, node, run, 3.0 if args.quick else 6.0)
        out.update({
            "notes": ("rates between two instants after a warm-up, medians of alternating rounds; the replay "
                      "(a separate process) and the router (in this process) work during service rounds only; "
                      "learner_efficiency_cpu = updates per CPU-second of the training thread; 2-core machine "
                      "shared with other work"),
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
    ap.add_argument("--profile", action="store_true", help="profile the learner even if it meets the target")
    ap.add_argument("--guard-only", action="store_true", help="only the learner guard's cost per update, in process (~35 s)")
    ap.add_argument("--poison", action="store_true",
                    help="issue #32 item 2: the learner loop with 1%% in-bounds poison vs none, the checks' cost (~2 min)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override (repeatable), e.g. --set learner.requests_in_flight=8")
    ap.add_argument("--r2d2", action="store_true",
                    help="issue #34: the R2D2 learner on sequences over Zenoh vs in memory (~2 min)")
    args = ap.parse_args(argv)
    stop_on_sigterm()
    if args.r2d2:
        return r2d2_bench(args)
    return orchestrate(args)


if __name__ == "__main__":
    sys.exit(main())
