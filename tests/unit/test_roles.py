"""The role loop (common/roles.py) with an in-memory node: cadence, budget, stats, shutdown."""

import threading

import pytest

from zenrl.common import protocol as P
from zenrl.common.roles import Cadence, RoleLoop


class FakePublisher:
    def __init__(self, key, sink):
        self.key, self.sink = key, sink

    def put(self, payload):
        self.sink.append((self.key, payload))


class FakeNode:
    def __init__(self):
        self.sent, self.tokens = [], []

    def publisher(self, key, **_kw):
        return FakePublisher(key, self.sent)

    def token(self, key):
        self.tokens.append(key)


class FakeMetrics:
    def __init__(self):
        self.rows, self.closed = [], False

    def write(self, source, step, values):
        self.rows.append((source, step, dict(values)))

    def close(self):
        self.closed = True


class CountingWorker:
    """Steps until ``budget``, then stops the run itself after ``idle_after_done`` idle waits."""

    def __init__(self, stop, budget=5, fail_at=None, idle_after_done=2):
        self.id, self.stop, self.budget, self.fail_at = "w1", stop, budget, fail_at
        self.steps = self.saves = self.idles = 0
        self.calls: list[str] = []
        self.idle_after_done = idle_after_done

    def start(self, node):
        self.calls.append("start")

    def step(self, timeout_s):
        self.steps += 1
        if self.steps == self.fail_at:
            raise RuntimeError("boom")
        return True

    def done(self):
        if self.steps >= self.budget:
            self.idles += 1
            if self.idles > self.idle_after_done:
                self.stop.set()
            return True
        return False

    def progress(self):
        return self.steps

    def report(self, interval_s):
        return {"steps": self.steps, "note": "text"}, f"steps {self.steps}"

    def save(self):
        self.saves += 1
        self.calls.append("save")

    def close(self):
        self.calls.append("close")


def test_loop_reports_every_interval_idles_on_budget_and_saves_once_on_stop():
    stop = threading.Event()
    node, metrics = FakeNode(), FakeMetrics()
    w = CountingWorker(stop, budget=5)
    loop = RoleLoop(node, P.Keys("r1"), "learner", w.id, Cadence(log_interval_s=0.0, idle_s=0.01), metrics)
    loop.run(w, stop)
    assert w.steps == 5, "a spent budget must not take more steps"
    assert node.tokens == [P.Keys("r1").alive("learner", "w1")]
    stats = [P.Stats.decode(p) for k, p in node.sent if k == P.Keys("r1").stats("learner", "w1")]
    assert len(stats) == loop.reports and loop.reports >= 5
    assert stats[-1].values == {"steps": 5, "note": "text"} and stats[-1].role == "learner"
    assert metrics.rows[-1][:2] == ("learner", 5) and metrics.closed
    # no checkpoint timer: saved exactly once, on stop, before close
    assert w.calls == ["start", "save", "close"]


def test_loop_saves_on_its_cadence():
    stop = threading.Event()
    w = CountingWorker(stop, budget=3, idle_after_done=3)
    RoleLoop(FakeNode(), P.Keys("r1"), "learner", w.id, Cadence(log_interval_s=1e9, checkpoint_interval_s=0.0, idle_s=0.01)).run(w, stop)
    assert w.saves >= 3 + 1, "every pass saves with interval 0, plus the final save"
    assert w.calls[-2:] == ["save", "close"]


def test_a_failing_step_still_saves_and_closes():
    stop = threading.Event()
    w = CountingWorker(stop, budget=10, fail_at=2)
    metrics = FakeMetrics()
    with pytest.raises(RuntimeError, match="boom"):
        RoleLoop(FakeNode(), P.Keys("r1"), "actor", w.id, Cadence(log_interval_s=1e9, idle_s=0.01), metrics).run(w, stop)
    assert w.calls == ["start", "save", "close"] and metrics.closed
