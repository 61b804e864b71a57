"""The role loop (common/roles.py) with an in-memory node: cadence, budget, stats, shutdown."""

import threading
import time

import pytest

from zenrl.common import protocol as P
from zenrl.common.roles import Cadence, RoleFailed, RoleLoop, Supervisor


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
        self.failed_writes = 0

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

    def start(self, node, sup=None):
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
    assert stats[-1].values == {"steps": 5, "note": "text", "errors_total": 0, "stalled": ""} and stats[-1].role == "learner"
    assert metrics.rows[-1][:2] == ("learner", 5) and metrics.closed
    # no checkpoint timer: saved exactly once, on stop, before close
    assert w.calls == ["start", "save", "close"]


def test_loop_saves_on_its_cadence():
    stop = threading.Event()
    w = CountingWorker(stop, budget=3, idle_after_done=3)
    RoleLoop(FakeNode(), P.Keys("r1"), "learner", w.id, Cadence(log_interval_s=1e9, checkpoint_interval_s=0.0, idle_s=0.01)).run(w, stop)
    assert w.saves >= 3 + 1, "every pass saves with interval 0, plus the final save"
    assert w.calls[-2:] == ["save", "close"]


def test_a_failing_step_is_counted_by_type_and_the_loop_goes_on():
    stop = threading.Event()
    node = FakeNode()
    w = CountingWorker(stop, budget=10, fail_at=2)
    metrics = FakeMetrics()
    loop = RoleLoop(node, P.Keys("r1"), "actor", w.id, Cadence(log_interval_s=0.0, idle_s=0.01), metrics)
    loop.run(w, stop)
    assert w.steps == 10, "the steps after the failing one must still run"
    stats = [P.Stats.decode(p) for k, p in node.sent if k == P.Keys("r1").stats("actor", "w1")]
    assert stats[-1].values["errors_total"] == 1 and stats[-1].values["errors/RuntimeError"] == 1
    assert stats[-1].values["stalled"] == ""
    assert w.calls == ["start", "save", "close"] and metrics.closed


class AlwaysFailing(CountingWorker):
    def step(self, timeout_s):
        self.steps += 1
        raise KeyError("always")


def test_a_loop_whose_every_step_fails_gives_up_with_role_failed_after_saving():
    stop = threading.Event()
    w = AlwaysFailing(stop, budget=10**9)
    sup = Supervisor(log_every_s=60.0, give_up_s=0.05)
    with pytest.raises(RoleFailed, match="step has failed every time"):
        RoleLoop(FakeNode(), P.Keys("r1"), "actor", w.id, Cadence(log_interval_s=1e9, idle_s=0.001), supervisor=sup).run(w, stop)
    assert w.steps >= 2 and sup.errors["KeyError"] == w.steps
    assert w.calls == ["start", "save", "close"]


def test_tracebacks_are_rate_limited_per_type(caplog):
    sup = Supervisor(log_every_s=1e9)
    for _ in range(50):
        sup.call("unit", lambda: 1 / 0)
    sup.call("unit", lambda: [][1])
    logged = [r for r in caplog.records if "failed" in r.getMessage()]
    assert len(logged) == 2, "one traceback per exception type, the rest counted"
    assert sup.errors == {"ZeroDivisionError": 50, "IndexError": 1}


def test_watched_thread_survives_bad_units_reports_a_stall_and_a_death():
    sup = Supervisor(log_every_s=1e9, stall_s=0.05)
    stop = threading.Event()
    seen, waiting = [], [0]
    gate = threading.Event()

    def unit():
        n = len(seen)
        seen.append(n)
        if n % 2 == 0:
            raise ValueError(f"bad {n}")
        if n >= 7:
            gate.wait()  # stuck in one unit of work
    t = sup.thread("ingest", unit, stop, pending=lambda: waiting[0])
    deadline = time.monotonic() + 10
    while len(seen) < 8 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert len(seen) == 8 and sup.errors["ValueError"] == 4, "a failing unit must not end the thread"
    time.sleep(0.1)
    assert sup.values()["stalled"] == "", "nothing waits: not stalled"
    waiting[0] = 3
    assert sup.values()["stalled"] == "ingest", "input waits and no unit finished for stall_s"
    sup.check()  # stalled but alive: the role goes on (health reports it)
    gate.set()
    stop.set()
    t.join(5)
    sup.check()  # stopped on purpose: not a failure


def test_a_thread_that_dies_fails_the_role():
    sup = Supervisor()
    stop = threading.Event()

    def unit():
        raise SystemExit("gone")  # not an Exception: the thread ends
    t = sup.thread("sender", unit, stop)
    t.join(5)
    with pytest.raises(RoleFailed, match="sender"):
        sup.check()
    assert sup.values()["stalled"] == "sender"


def test_failed_metrics_writes_are_in_the_stats():
    """A full disk under the run folder: the count of refused metrics writes goes out with the
    stats (the log saying so is on the same disk)."""
    metrics, sent = FakeMetrics(), []
    w = CountingWorker(threading.Event(), budget=3)
    loop = RoleLoop(FakeNode(), P.Keys("r1"), "learner", w.id, Cadence(log_interval_s=0.0, idle_s=0.01), metrics)
    metrics.failed_writes = 4
    loop._report(w, FakePublisher("k", sent), 1.0)
    assert P.Stats.decode(sent[-1][1]).values["metrics_failed_writes"] == 4
    metrics.failed_writes = 0
    loop._report(w, FakePublisher("k", sent), 1.0)
    assert "metrics_failed_writes" not in P.Stats.decode(sent[-1][1]).values
