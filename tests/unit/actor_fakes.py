"""An in-memory stand-in for zenrl.common.transport.Node, enough to run the actor workers in
RoleLoop within one process: records what is published per key, serves one weights payload to
queries and holds the broadcast subscription's newest value."""

import contextlib
import threading
import time

from zenrl.common.errors import RemoteTimeout
from zenrl.common import protocol as P
from zenrl.common.networks import arch_fingerprint, params_to_arrays
from zenrl.common.transport import LatestValue


class Matching:
    matching = True


class FakePub:
    def __init__(self):
        self.sent = []
        self.matching_status = Matching()  # a replay subscribes: chunks go out, no backlog

    def put(self, payload):
        self.sent.append(payload)


class FakeNode:
    def __init__(self, weights_payload=None):
        self.pubs = {}
        self.tokens = []
        self.latest = LatestValue()
        self.weights_payload = weights_payload

    def publisher(self, key, low_priority=False, express=False):
        return self.pubs.setdefault(key, FakePub())

    def sent(self, key):
        return self.pubs[key].sent if key in self.pubs else []

    def subscribe_latest(self, key):
        return self.latest

    def query(self, key, payload=None, timeout_s=5.0):
        if self.weights_payload is None:
            raise RemoteTimeout("no learner")
        return self.weights_payload

    def token(self, key):
        self.tokens.append(key)


def wait_for(cond, timeout_s=60.0, what="condition"):
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


@contextlib.contextmanager
def running(run):
    """``run(stop)`` in a thread for the ``with`` block, then stop it and wait for it to return;
    re-raises what it raised."""
    stop, err = threading.Event(), []

    def target():
        try:
            run(stop)
        except BaseException as e:  # noqa: BLE001 - handed to the test
            err.append(e)

    t = threading.Thread(target=target, daemon=True)
    t.start()
    try:
        yield t
    finally:
        stop.set()
        t.join(30)
    if err:
        raise err[0]
    assert not t.is_alive(), "the worker did not stop"


def run_until(run, cond, timeout_s=60.0, what="condition"):
    """``run(stop)`` in a thread until ``cond()`` holds (or the deadline), then stopped."""
    with running(run) as t:
        wait_for(lambda: cond() or not t.is_alive(), timeout_s, what)
    assert cond(), f"the worker ended before {what}"


def step_until(worker, cond, max_steps=10_000):
    """Call a started ``worker``'s step() until ``cond()`` (without RoleLoop)."""
    for _ in range(max_steps):
        if cond():
            return
        worker.step(0.05)
    raise AssertionError("condition not reached")


def weights_payload(net, version, updates=5):
    """``net``'s parameters as the learner broadcasts them."""
    return P.Weights(version=version, learner_id="learner", arch=arch_fingerprint(net), updates=updates,
                     params=params_to_arrays(net)).encode()
