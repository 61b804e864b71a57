"""Helper programs the integration tests run as separate OS processes."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def publish(args: argparse.Namespace) -> int:
    from zenrl.common import protocol as P
    from zenrl.common.replay_client import ZenohReplayClient
    from zenrl.common.transport import Node

    rng = np.random.default_rng(args.seed)
    with Node(args.router, 10.0) as node:
        client = ZenohReplayClient(node, P.Keys(args.run, args.shard), args.actor)
        # wait until the replay service is reachable (its liveliness token), not a bare sleep
        deadline = time.monotonic() + 20
        want = P.Keys(args.run).alive("replay", "replay" if args.shard is None else f"replay-{args.shard}")
        while not node.alive_now(want, 1.0):
            if time.monotonic() > deadline:
                return 3
        for i in range(args.chunks):
            b = args.chunk
            base = args.seed * 1_000_000 + i * b
            batch = {
                # inside CartPole's observation bounds (the replay checks them)
                "obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
                "action": rng.integers(0, 2, b),
                "reward": (rng.uniform(-1, 1, b) if args.plain else np.arange(base, base + b)).astype(np.float32),
                "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
                "terminated": np.zeros(b, bool),
                "n": np.full(b, 3, np.uint8),
            }
            client.insert(batch, rng.random(b).astype(np.float32) + 0.1, policy_version=i)
            if args.pause_s:
                time.sleep(args.pause_s)  # pacing a steady stream, not waiting on a condition
        if client.flush_backlog(10.0):
            return 4  # chunks left undelivered
    return 0


def claim(args: argparse.Namespace) -> int:
    """Claim an elastic slot, print it, hold it until SIGTERM."""
    import signal
    import threading

    from zenrl.actor.slots import claim_slot
    from zenrl.common import protocol as P
    from zenrl.common.transport import Node

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Node(args.router, 10.0) as node:
        slot, _ = claim_slot(node, P.Keys(args.run), args.actor)
        sys.stdout.write(f"SLOT {slot}\n")
        sys.stdout.flush()
        stop.wait(120)
    return 0


def poison(args: argparse.Namespace) -> int:
    """A hostile actor: sends poisoned CartPole chunks (out-of-range actions, huge rewards,
    out-of-bounds observations, wrong n, absurd priorities, in turn) at ``--fraction`` of all the
    transitions the replay takes in, changing its actor id every 10 chunks (so quarantine never
    spares the checks), until SIGTERM or the replay goes away. Prints ``POISON <chunks sent>``."""
    import signal
    import threading

    from zenrl.common import protocol as P
    from zenrl.common.transport import Node

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    keys = P.Keys(args.run)
    rng = np.random.default_rng(args.seed)
    b, sent = 256, 0
    with Node(args.router, 30.0) as node:
        latest = node.subscribe_latest(keys.stats("replay", "replay"))
        honest = 0
        seen_replay = False
        while not stop.is_set():
            raw = latest.wait(0.2)
            if raw is not None:
                seen_replay = True
                honest = int(P.Stats.decode(raw).values.get("inserted_total", 0))
            elif seen_replay and not node.alive_now(keys.alive_role("replay"), 1.0):
                break  # the run is over
            # poison / (poison + honest) = fraction
            while sent * b < honest * args.fraction / (1 - args.fraction) and not stop.is_set():
                kind = sent % 6
                d = {"obs": rng.uniform(-0.2, 0.2, (b, 4)).astype(np.float32), "action": rng.integers(0, 2, b),
                     "reward": np.ones(b, np.float32), "next_obs": rng.uniform(-0.2, 0.2, (b, 4)).astype(np.float32),
                     "terminated": np.zeros(b, bool), "truncated": np.zeros(b, bool), "n": np.full(b, 3, np.uint8)}
                prio = np.ones(b, np.float32)
                rows = rng.integers(0, b, 8)
                if kind == 0:
                    d["action"][rows] = 7
                elif kind == 1:
                    d["reward"][rows] = 3e38
                elif kind == 2:
                    d["obs"][rows, 2] = 3.0
                elif kind == 3:
                    d["n"][rows] = 0
                elif kind == 4:
                    d["n"][rows] = 99
                else:
                    prio[rows] = 1e30
                who = f"hostile{sent // 10}"
                node.put(keys.transitions(who), P.TransitionBatch(who, 0, sent, d, prio).encode())
                sent += 1
    sys.stdout.write(f"POISON {sent}\n")
    sys.stdout.flush()
    return 0


def inbounds(args: argparse.Namespace) -> int:
    """A hostile actor whose poison passes every check: CartPole chunks of 8 transitions, each
    with a velocity at float32's max (inside CartPole's Box: its velocity bounds are float32's
    max) in one of the observations, at ``--fraction`` of all the transitions the replay takes
    in, its actor id ``inbounds<k>`` changed every 10 chunks, until SIGTERM or the replay goes
    away. Prints ``INBOUNDS <chunks sent>``."""
    import signal
    import threading

    from zenrl.common import protocol as P
    from zenrl.common.transport import Node

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    keys = P.Keys(args.run)
    rng = np.random.default_rng(args.seed)
    big = float(np.finfo(np.float32).max)
    b, sent = 8, 0
    with Node(args.router, 30.0) as node:
        latest = node.subscribe_latest(keys.stats("replay", "replay"))
        honest = 0
        seen_replay = False
        while not stop.is_set():
            raw = latest.wait(0.2)
            if raw is not None:
                seen_replay = True
                honest = int(P.Stats.decode(raw).values.get("inserted_total", 0))
            elif seen_replay and not node.alive_now(keys.alive_role("replay"), 1.0):
                break  # the run is over
            while sent * b < honest * args.fraction and not stop.is_set():
                d = {"obs": rng.uniform(-0.2, 0.2, (b, 4)).astype(np.float32), "action": rng.integers(0, 2, b),
                     "reward": np.ones(b, np.float32), "next_obs": rng.uniform(-0.2, 0.2, (b, 4)).astype(np.float32),
                     "terminated": np.zeros(b, bool), "truncated": np.zeros(b, bool), "n": np.full(b, 5, np.uint8)}
                for i in range(b):  # every field and sign in turn: cart or pole velocity, now or next
                    k = (sent * b + i) % 8
                    d["obs" if k < 4 else "next_obs"][i, 1 if k % 2 else 3] = big if k % 4 < 2 else -big
                who = f"inbounds{sent // 10}"
                node.put(keys.transitions(who), P.TransitionBatch(who, 0, sent, d).encode())
                sent += 1
    sys.stdout.write(f"INBOUNDS {sent}\n")
    sys.stdout.flush()
    return 0


def main() -> int:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("publish")
    s.add_argument("--router", required=True)
    s.add_argument("--run", required=True)
    s.add_argument("--actor", required=True)
    s.add_argument("--chunks", type=int, default=20)
    s.add_argument("--chunk", type=int, default=50)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--plain", action="store_true", help="ordinary rewards in [-1, 1] (default: tagged by seed)")
    s.add_argument("--pause-s", type=float, default=0.0, help="pause between chunks")
    s.add_argument("--shard", type=int, default=None, help="the replay shard to write to (replay.shards > 1)")
    s = sub.add_parser("claim")
    s.add_argument("--router", required=True)
    s.add_argument("--run", required=True)
    s.add_argument("--actor", required=True)
    s = sub.add_parser("poison")
    s.add_argument("--router", required=True)
    s.add_argument("--run", required=True)
    s.add_argument("--fraction", type=float, default=0.1)
    s.add_argument("--seed", type=int, default=1)
    s = sub.add_parser("inbounds")
    s.add_argument("--router", required=True)
    s.add_argument("--run", required=True)
    s.add_argument("--fraction", type=float, default=0.01)
    s.add_argument("--seed", type=int, default=1)
    args = p.parse_args()
    return {"publish": publish, "claim": claim, "poison": poison, "inbounds": inbounds}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
