"""A hostile A3C worker, run as its own OS process by test_a3c_flood.py: sends gradients on
``gradients/<--id>`` as fast as it can until SIGTERM. Of every 10 messages, 8 are well formed
(the learner's parameter names and shapes, tiny values, the newest version heard, ``--steps``
env steps), 1 claims 2**62 env steps and 1 claims another worker's id. Prints
``FLOOD <messages sent>`` at the end."""

from __future__ import annotations

import argparse
import signal
import sys
import threading

import numpy as np


def main() -> int:
    from zenrl.common import protocol as P
    from zenrl.common.transport import Node

    p = argparse.ArgumentParser()
    p.add_argument("--router", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--id", default="flood")
    p.add_argument("--steps", type=int, required=True)
    args = p.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    keys = P.Keys(args.run)
    sent = 0
    with Node(args.router, 30.0) as node:
        latest = node.subscribe_latest(keys.weights)
        w = None
        while w is None and not stop.is_set():
            try:
                w = P.Weights.decode(node.query(keys.weights_query, None, 2.0))
            except Exception:  # noqa: BLE001 - the learner is not up yet: ask again
                stop.wait(0.2)
        if w is None:
            return 3
        grads = {k: np.full(v.shape, 1e-4, np.float32) for k, v in w.params.items()}
        version = w.version
        pub = node.publisher(keys.gradients(args.id))
        while not stop.is_set():
            raw = latest.take()
            if raw is not None:
                version = P.Weights.decode(raw).version
            kind = sent % 10
            steps = 2**62 if kind == 8 else args.steps
            who = "honest" if kind == 9 else args.id
            pub.put(P.Gradients(worker_id=who, version=version, steps=steps, grads=grads).encode())
            sent += 1
    sys.stdout.write(f"FLOOD {sent}\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
