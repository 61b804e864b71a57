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
        client = ZenohReplayClient(node, P.Keys(args.run), args.actor)
        # wait until the replay service is reachable (its liveliness token), not a bare sleep
        deadline = time.monotonic() + 20
        while not node.alive_now(P.Keys(args.run).alive_role("replay"), 1.0):
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
    s = sub.add_parser("claim")
    s.add_argument("--router", required=True)
    s.add_argument("--run", required=True)
    s.add_argument("--actor", required=True)
    args = p.parse_args()
    return {"publish": publish, "claim": claim}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
