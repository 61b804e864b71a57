"""Local (in-process) prioritized replay throughput: zenrl InMemoryReplay vs cpprb.

Measures, per case:
  * inserts/s   - transitions/s when inserting chunks with explicit priorities into a
                  replay that is already full (ring overwrite; warm pages);
  * sample+update batches/s - ``sample(512, beta)`` followed by ``update_priorities`` of the
                  512 sampled items with fresh priorities.

Cases: a 1M-capacity replay of CartPole-sized transitions and a 50k-capacity replay of
84x84x4 uint8 frames (obs and next_obs stored separately in both libraries). Then frames stored
once: a 50k-capacity FrameReplay of an Atari-like stream (4-frame stacks of 84x84 frames,
episodes of 100-400 steps) against ``cpprb.PrioritizedReplayBuffer(next_of="obs",
stack_compress="obs")`` filled with the same episodes (sample+update batches/s, and the bytes per
transition vs naive obs/next_obs storage), plus the Burger War camera's bytes per transition. Both
replays are prefilled to the same size with the same alpha, then timed in interleaved rounds
(ours, peer, ours, peer, ...) and the median round is reported, which keeps the comparison
fair on a shared, noisy machine.

Peer: ``cpprb.PrioritizedReplayBuffer`` (``pip install cpprb``, the ``bench`` extra). If it is
missing, only our figures are reported with ``"peer": null`` and ``"peer_error"``.

Progress goes to stderr; the last stdout line is one JSON object.

    python bench/replay_local.py            # full run (~1-2 min)
    python bench/replay_local.py --quick    # small capacities, a few seconds
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import sys
import time
from typing import Any, Callable

import numpy as np

from zenrl.common.specs import ArraySpec
from zenrl.replay.buffer import InMemoryReplay

ALPHA = 0.6
BETA = 0.4
BATCH = 512


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def cartpole_spec() -> dict[str, ArraySpec]:
    return {
        "obs": ArraySpec((4,), "float32"),
        "action": ArraySpec((), "int64"),
        "reward": ArraySpec((), "float32"),
        "next_obs": ArraySpec((4,), "float32"),
        "terminated": ArraySpec((), "bool"),
        "n": ArraySpec((), "uint8"),
    }


def atari_spec() -> dict[str, ArraySpec]:
    return {
        "obs": ArraySpec((84, 84, 4), "uint8"),
        "action": ArraySpec((), "int64"),
        "reward": ArraySpec((), "float32"),
        "next_obs": ArraySpec((84, 84, 4), "uint8"),
        "terminated": ArraySpec((), "bool"),
        "n": ArraySpec((), "uint8"),
    }


def random_batch(spec: dict[str, ArraySpec], n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    out = {}
    for name, s in spec.items():
        shape = (n, *s.shape)
        dt = np.dtype(s.dtype)
        if dt == np.bool_:
            out[name] = rng.random(shape) < 0.05
        elif dt.kind == "f":
            out[name] = rng.standard_normal(shape).astype(dt)
        else:
            out[name] = rng.integers(0, 200, size=shape).astype(dt)
    return out


# ------------------------------------------------------------------ adapters
class Ours:
    name = "zenrl"

    def __init__(self, spec: dict[str, ArraySpec], capacity: int) -> None:
        self.rb = InMemoryReplay(spec, capacity, alpha=ALPHA, seed=0)
        self.rng = np.random.default_rng(1)

    def insert(self, batch: dict[str, np.ndarray], prio: np.ndarray) -> None:
        self.rb.insert(batch, prio)

    def sample_update(self, new_prio: np.ndarray) -> None:
        s = self.rb.sample(BATCH, BETA, rng=self.rng)
        self.rb.update_priorities(s.keys, new_prio)

    def sample_update_out(self, new_prio: np.ndarray) -> None:
        """Same, gathering into reused output buffers (``sample(..., out=...)``)."""
        s = self.rb.sample(BATCH, BETA, rng=self.rng, out=self.out)
        self.rb.update_priorities(s.keys, new_prio)

    @property
    def out(self) -> dict[str, np.ndarray]:
        if not hasattr(self, "_out"):
            self._out = {k: np.empty((BATCH, *s.shape), s.dtype) for k, s in self.rb.spec.items()}
        return self._out

    @property
    def size(self) -> int:
        return self.rb.size


class Cpprb:
    name = "cpprb"

    def __init__(self, spec: dict[str, ArraySpec], capacity: int) -> None:
        from cpprb import PrioritizedReplayBuffer

        env_dict = {k: {"shape": s.shape or 1, "dtype": np.dtype(s.dtype).type} for k, s in spec.items()}
        self.rb = PrioritizedReplayBuffer(capacity, env_dict, alpha=ALPHA)

    def insert(self, batch: dict[str, np.ndarray], prio: np.ndarray) -> None:
        self.rb.add(**batch, priorities=prio)

    def sample_update(self, new_prio: np.ndarray) -> None:
        s = self.rb.sample(BATCH, beta=BETA)
        self.rb.update_priorities(s["indexes"], new_prio)

    @property
    def size(self) -> int:
        return int(self.rb.get_stored_size())


def peer_factory() -> tuple[Callable[..., Any] | None, str | None, str | None]:
    try:
        import cpprb  # noqa: F401
        from importlib.metadata import version

        return Cpprb, f"cpprb {version('cpprb')} PrioritizedReplayBuffer", None
    except Exception as e:  # ImportError, or a broken binary wheel
        return None, None, f"cpprb unavailable: {type(e).__name__}: {e}"


# ------------------------------------------------------------------ measurements
def prefill(rb: Any, chunk: dict[str, np.ndarray], prio: np.ndarray, target: int) -> float:
    t0 = time.perf_counter()
    while rb.size < target:
        rb.insert(chunk, prio)
    return time.perf_counter() - t0


def timed_rounds(
    impls: list[Any], fn_name: str, args_for: Callable[[int], tuple], iters: int, rounds: int
) -> dict[str, list[float]]:
    """Interleave ``rounds`` rounds of ``iters`` calls per impl; returns seconds per round."""
    out: dict[str, list[float]] = {impl.name: [] for impl in impls}
    for r in range(rounds):
        for impl in impls:
            fn = getattr(impl, fn_name)
            gc.collect()
            t0 = time.perf_counter()
            for i in range(iters):
                fn(*args_for(i))
            out[impl.name].append(time.perf_counter() - t0)
    return out


def run_case(name: str, spec: dict[str, ArraySpec], capacity: int, chunk_size: int,
             insert_iters: int, su_iters: int, rounds: int, peer_cls: Any) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    chunk = random_batch(spec, chunk_size, rng)
    prio_pool = [rng.random(chunk_size) * 2.0 for _ in range(16)]
    new_prio_pool = [rng.random(BATCH) * 2.0 for _ in range(16)]

    # Setup = construction + prefill: cpprb touches its storage in the constructor, we touch
    # pages lazily on first insert, so only the sum of the two is comparable.
    classes: list[Any] = [Ours] + ([peer_cls] if peer_cls is not None else [])
    impls: list[Any] = []
    setup_s = {}
    for cls in classes:
        t0 = time.perf_counter()
        impl = cls(spec, capacity)
        prefill(impl, chunk, prio_pool[0], capacity)
        setup_s[impl.name] = time.perf_counter() - t0
        impls.append(impl)
        log(f"[{name}] {impl.name}: built and prefilled {impl.size} items in {setup_s[impl.name]:.2f}s")

    ins = timed_rounds(impls, "insert", lambda i: (chunk, prio_pool[i % 16]), insert_iters, rounds)
    su = timed_rounds(impls, "sample_update", lambda i: (new_prio_pool[i % 16],), su_iters, rounds)
    su_out = timed_rounds(impls[:1], "sample_update_out", lambda i: (new_prio_pool[i % 16],), su_iters, rounds)

    res: dict[str, Any] = {
        "capacity": capacity,
        "prefilled": impls[0].size,
        "bytes_per_item": impls[0].rb.bytes_per_item,
        "insert_chunk": chunk_size,
        "rounds": rounds,
    }
    for impl in impls:
        key = "ours" if impl.name == "zenrl" else "peer"
        med_ins = statistics.median(ins[impl.name])
        med_su = statistics.median(su[impl.name])
        res[key] = {
            "inserts_per_s": insert_iters * chunk_size / med_ins,
            "sample_update_batches_per_s": su_iters / med_su,
            "sample_update_ms": 1e3 * med_su / su_iters,
            "setup_s": round(setup_s[impl.name], 3),
        }
        if impl.name == "zenrl":
            res[key]["sample_update_out_batches_per_s"] = su_iters / statistics.median(su_out["zenrl"])
        log(f"[{name}] {impl.name}: {res[key]['inserts_per_s']:,.0f} inserts/s, "
            f"{res[key]['sample_update_batches_per_s']:,.1f} sample+update batches/s")
    if peer_cls is not None:
        res["ratio_insert"] = res["ours"]["inserts_per_s"] / res["peer"]["inserts_per_s"]
        res["ratio_sample_update"] = (
            res["ours"]["sample_update_batches_per_s"] / res["peer"]["sample_update_batches_per_s"]
        )
    del impls
    gc.collect()
    return res


# ------------------------------------------------------------------ frames stored once
STACK = 4


def image_stream(capacity: int, seed: int = 0):
    """Episodes (lengths 100-400) of an Atari-like stream: per episode its L + 1 frames (84x84
    uint8, from a pool: content does not matter to either store), the obs and next_obs stacks of
    its L transitions as frame ids (reset padding repeats the first frame), and n = 1."""
    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 256, size=(256, 84, 84), dtype=np.uint8)
    total = 0
    fid = 0
    while total < capacity:
        L = int(rng.integers(100, 401))
        frames = pool[(np.arange(fid, fid + L + 1)) % 256]
        t = np.arange(L + 1)
        stack = np.maximum(t[:, None] + np.arange(-STACK + 1, 1)[None, :], 0)  # [L+1, 4] local ids
        batch = {
            "action": rng.integers(0, 6, L).astype(np.int64),
            "reward": rng.standard_normal(L).astype(np.float32),
            "terminated": np.arange(L) == L - 1,
            "n": np.ones(L, np.uint8),
        }
        yield fid, frames, stack[:-1], stack[1:], batch, rng.random(L) * 2.0
        fid += L + 1
        total += L


class OursFrames:
    name = "zenrl"

    def __init__(self, capacity: int) -> None:
        from zenrl.replay.frames import FrameReplay

        item = {"action": ArraySpec((), "int64"), "reward": ArraySpec((), "float32"),
                "terminated": ArraySpec((), "bool"), "n": ArraySpec((), "uint8")}
        self.rb = FrameReplay(item, {"obs": ArraySpec((84, 84), "uint8")}, {"obs": STACK, "next_obs": STACK},
                              capacity, frames_per_item=1.05, alpha=ALPHA, seed=0)
        self.rng = np.random.default_rng(1)

    def add_episode(self, fid, frames, obs_ids, next_ids, batch, prio) -> None:
        self.rb.insert("a0", fid, {"obs": frames}, batch, {"obs": obs_ids + fid, "next_obs": next_ids + fid}, prio)

    def sample_update(self, new_prio: np.ndarray) -> None:
        s = self.rb.sample(BATCH, BETA, rng=self.rng)
        self.rb.update_priorities(s.keys, new_prio)


class CpprbFrames:
    name = "cpprb"

    def __init__(self, capacity: int) -> None:
        from cpprb import PrioritizedReplayBuffer

        env = {"obs": {"shape": (84, 84, STACK), "dtype": np.uint8}, "action": {"dtype": np.int64},
               "reward": {"dtype": np.float32}, "terminated": {"dtype": np.bool_}, "n": {"dtype": np.uint8}}
        self.rb = PrioritizedReplayBuffer(capacity, env, alpha=ALPHA, next_of="obs", stack_compress="obs")

    def add_episode(self, fid, frames, obs_ids, next_ids, batch, prio) -> None:
        # cpprb stacks on the last axis: [L, 84, 84, 4]
        obs = np.ascontiguousarray(np.moveaxis(frames[obs_ids], 1, -1))
        nxt = np.ascontiguousarray(np.moveaxis(frames[next_ids], 1, -1))
        self.rb.add(obs=obs, next_obs=nxt, **batch, priorities=prio)
        self.rb.on_episode_end()

    def sample_update(self, new_prio: np.ndarray) -> None:
        s = self.rb.sample(BATCH, beta=BETA)
        self.rb.update_priorities(s["indexes"], new_prio)


def burgerwar_bytes() -> dict[str, Any]:
    """Bytes per transition slot for the Burger War camera env (zenrl/BurgerWarImage-v0, 64x64x3
    plus its vector observations): full obs/next_obs (InMemoryReplay) vs frames once."""
    from zenrl.replay.frames import FrameReplay

    obs = {"obs/game": ArraySpec((4,), "float32"), "obs/image": ArraySpec((64, 64, 3), "uint8"),
           "obs/lidar": ArraySpec((360,), "float32"), "obs/mask": ArraySpec((18,), "float32"),
           "obs/pose": ArraySpec((4,), "float32")}
    cols = {"action": ArraySpec((), "int64"), "reward": ArraySpec((), "float32"), "terminated": ArraySpec((), "bool"),
            "truncated": ArraySpec((), "bool"), "n": ArraySpec((), "uint8"), "meta/policy_version": ArraySpec((), "int64")}
    naive = InMemoryReplay({**obs, **{"next_" + k: v for k, v in obs.items()}, **cols}, 1000)
    framed = FrameReplay(cols, obs, {**{k: 0 for k in obs}, **{"next_" + k: 0 for k in obs}}, 1000,
                         frames_per_item=1.05)
    return {"naive_bytes_per_item": naive.bytes_per_item, "frames_bytes_per_item": framed.bytes_per_item,
            "ratio": framed.bytes_per_item / naive.bytes_per_item, "frames_per_item": 1.05}


def run_image_case(capacity: int, su_iters: int, rounds: int, peer: bool) -> dict[str, Any]:
    impls: list[Any] = [OursFrames(capacity)] + ([CpprbFrames(capacity)] if peer else [])
    setup_s = {}
    for impl in impls:
        t0 = time.perf_counter()
        for ep in image_stream(capacity):
            impl.add_episode(*ep)
        setup_s[impl.name] = round(time.perf_counter() - t0, 3)
        log(f"[frames_{capacity}] {impl.name}: filled in {setup_s[impl.name]:.2f}s")
    ours = impls[0].rb
    naive = InMemoryReplay(atari_spec(), 10).bytes_per_item
    rng = np.random.default_rng(2)
    new_prio_pool = [rng.random(BATCH) * 2.0 for _ in range(16)]
    su = timed_rounds(impls, "sample_update", lambda i: (new_prio_pool[i % 16],), su_iters, rounds)
    res: dict[str, Any] = {
        "capacity": capacity, "stored": ours.size, "frames_stored": ours.frames_stored,
        "naive_bytes_per_item": naive,
        "allocated_bytes_per_item": ours.bytes_per_item,
        "held_bytes_per_item": ours.nbytes / max(ours.size, 1),
        "bytes_ratio_vs_naive": ours.bytes_per_item / naive,
        "setup_s": setup_s,
    }
    for impl in impls:
        res[impl.name] = {"sample_update_batches_per_s": su_iters / statistics.median(su[impl.name])}
        log(f"[frames_{capacity}] {impl.name}: {res[impl.name]['sample_update_batches_per_s']:,.1f} sample+update batches/s")
    if peer:
        res["sample_ratio_vs_cpprb"] = (res["zenrl"]["sample_update_batches_per_s"]
                                        / res["cpprb"]["sample_update_batches_per_s"])
    del impls
    gc.collect()
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small capacities and few rounds")
    ap.add_argument("--no-peer", action="store_true", help="skip cpprb")
    args = ap.parse_args(argv)

    t_start = time.perf_counter()
    peer_cls, peer_desc, peer_err = (None, None, "disabled by --no-peer") if args.no_peer else peer_factory()
    if peer_err:
        log(peer_err)

    if args.quick:
        cases = [
            ("cartpole_100k", cartpole_spec(), 100_000, 256, 100, 50, 3),
            ("atari_2k", atari_spec(), 2_000, 64, 10, 5, 3),
        ]
    else:
        cases = [
            ("cartpole_1m", cartpole_spec(), 1_000_000, 256, 400, 200, 5),
            ("atari_50k", atari_spec(), 50_000, 64, 30, 15, 5),
        ]
    results = {}
    for name, spec, cap, chunk, ins_it, su_it, rounds in cases:
        results[name] = run_case(name, spec, cap, chunk, ins_it, su_it, rounds, peer_cls)
    img_cap, img_iters, img_rounds = (4_000, 5, 3) if args.quick else (50_000, 15, 5)
    image = run_image_case(img_cap, img_iters, img_rounds, peer_cls is not None)
    bw = burgerwar_bytes()

    first = results[cases[0][0]]
    out = {
        "bench": "replay_local",
        "quick": bool(args.quick),
        "alpha": ALPHA,
        "beta": BETA,
        "batch_size": BATCH,
        "peer": peer_desc,
        "ratio_vs_peer": first.get("ratio_sample_update"),
        "ratios": {
            n: {"sample_update": r.get("ratio_sample_update"), "insert": r.get("ratio_insert")}
            for n, r in results.items()
        },
        "cases": results,
        "frames_once": image,
        "burgerwar_camera_bytes": bw,
        "notes": (
            "ratio = ours/peer throughput (median of interleaved rounds), both with fresh "
            "output arrays per sample; sample_update_out_* is ours gathering into reused "
            "buffers (sample(out=...)), not part of the ratio. IS weights: ours normalise by "
            "the batch max weight, cpprb by the global min priority. setup_s = construction "
            "+ prefill (cpprb touches memory in its constructor, we on first insert)."
        ),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "wall_s": round(time.perf_counter() - t_start, 2),
    }
    if peer_err:
        out["peer_error"] = peer_err
    # last, as the issue asks: frames stored once (84x84x4 stacks) vs naive obs/next_obs, and
    # sampling vs cpprb's next_of + stack_compress on the same episodes
    out["burgerwar_bytes_ratio_vs_today"] = round(bw["ratio"], 4)
    out["image_bytes_ratio_vs_naive"] = round(image["bytes_ratio_vs_naive"], 4)
    out["image_sample_ratio_vs_cpprb"] = (None if image.get("sample_ratio_vs_cpprb") is None
                                          else round(image["sample_ratio_vs_cpprb"], 3))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
