"""The small interfaces every zenrl role implements, and the one loop that runs them.

A role's algorithm is a :class:`Worker`: it declares what it listens to (:meth:`Worker.start`),
does one unit of work per :meth:`Worker.step` (an update, a gradient applied, a batch of env
steps), reports what it did since the last report (:meth:`Worker.report`), saves its training
state if it has one (:meth:`Worker.save`) and lets go of what it holds (:meth:`Worker.close`).
:class:`RoleLoop` owns everything around that, the same for every role: the liveliness token
``alive/<role>/<id>``, the stats publisher and metrics, the log and checkpoint cadence, the
budget wait, an orderly stop, and **supervision**::

    worker = ApexLearner(cfg, node, run_id)          # or ApexActor, ReplayService, ...
    RoleLoop(node, keys, "learner", worker.id, cadence, metrics).run(worker, stop)
    # -> worker.start(node, sup); while not stop: worker.step(idle_s) ... report/save on cadence
    #    finally: worker.save(); worker.close(); one last report

Supervision: an exception in one unit of work (a step, a report, a save) is caught, counted by
type (``errors_total`` and ``errors/<Type>`` in the role's stats), logged with its traceback
(at most one traceback per type per ``Supervisor.log_every_s``) and the loop goes on. A loop that
cannot go on (every unit failing for ``Supervisor.give_up_s``, or a watched thread gone) raises
:class:`RoleFailed`; the role's entry point then exits non-zero so that ``zenrl run`` or the
container engine restarts it. Threads a worker starts (the replay's ingest, the learner's
sender, the prefetcher's helper) are started with :meth:`Supervisor.thread`, which runs their
units of work under the same rules and keeps a heartbeat: a thread that has not finished a unit
for ``stall_s`` while its input waits is reported in the stats (``stalled``), where
``zenrl.health`` sees it. No process may be alive but deaf.

The loop needs only ``publisher``, ``token`` and ``put`` of a transport node, so it is unit
tested with an in-memory one; it imports no network library.
"""

from __future__ import annotations

import collections
import ctypes
import ctypes.util
import logging
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from zenrl.common import protocol as P
from zenrl.common.errors import RunningConfigError, ZenrlError

log = logging.getLogger(__name__)


class RoleFailed(ZenrlError):
    """The role's loop cannot go on (a unit of work keeps failing, or a watched thread is gone):
    the process must exit non-zero so that it is restarted."""


class Worker(Protocol):
    """One role's algorithm, driven by :class:`RoleLoop`."""

    #: the id this process publishes under (``stats/<role>/<id>``, ``alive/<role>/<id>``)
    id: str

    def start(self, node: Any, sup: "Supervisor") -> None:
        """Declare subscriptions, queryables and publishers; start threads through ``sup``;
        publish initial state."""

    def step(self, timeout_s: float) -> bool:
        """Do one unit of work, waiting at most ``timeout_s`` for its input; False if none came."""

    def done(self) -> bool:
        """True once the worker's own budget is spent (it then idles until stopped)."""

    def progress(self) -> int:
        """The step counter metrics are recorded against (updates for a learner)."""

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        """Stats values since the last report (rates over ``interval_s``) and a log line, or
        None when there is nothing worth a line."""

    def save(self) -> Any:
        """Write the training state, if the role has one."""

    def close(self) -> None:
        """Release what :meth:`start` declared and flush what is pending."""


@dataclass(frozen=True)
class Cadence:
    """How often the loop reports and saves. ``checkpoint_interval_s`` None: never on a timer
    (roles without training state)."""

    log_interval_s: float
    checkpoint_interval_s: float | None = None
    #: how long one idle wait lasts (a step with no input, or a spent budget)
    idle_s: float = 0.5


_PR_SET_NAME = 15


def name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` (its first 15 bytes) in the OS as well, so that per-thread
    tools (``top -H``, ``/proc/<pid>/task/*/comm``, py-spy-less CPU breakdowns) tell it from the
    interpreter's other threads. Linux only; a no-op elsewhere or if it fails."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)
    except (OSError, AttributeError):  # no libc or no prctl: names are a convenience
        pass


class WatchedThread:
    """A thread that runs ``unit()`` until ``stop`` is set, each call under the supervisor's
    rules (an exception is counted and logged, the next unit runs). ``unit`` waits for its own
    input with a short timeout. ``pending()`` (optional) says how much input waits: the thread is
    *stalled* when input waits and no unit has finished for ``stall_s``. ``drain()`` (optional)
    runs once after ``stop``, under the same rules, to finish what was queued."""

    def __init__(self, sup: "Supervisor", name: str, unit: Callable[[], Any], stop: threading.Event,
                 pending: Callable[[], int] | None = None, drain: Callable[[], Any] | None = None) -> None:
        self.sup, self.name, self.unit, self.stop = sup, name, unit, stop
        self.pending, self.drain = pending, drain
        self.last_beat = time.monotonic()
        self.units = 0
        #: set when the thread gave up (its units kept failing for ``give_up_s``)
        self.failed: str | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> "WatchedThread":
        self._thread.start()
        return self

    def _run(self) -> None:
        name_os_thread(self.name)
        try:
            while not self.stop.is_set():
                self.sup.call(self.name, self.unit)
                self.last_beat = time.monotonic()
                self.units += 1
                if self.sup.hopeless(self.name):
                    self.failed = self.sup.why_hopeless(self.name)
                    log.error("thread %s gives up: %s", self.name, self.failed)
                    return
            if self.drain is not None:
                self.sup.call(self.name, self.drain)
        except BaseException as e:  # noqa: BLE001 - the thread is gone; say why where it is watched
            self.failed = f"{type(e).__name__}: {e}"
            log.exception("thread %s died", self.name)

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def stalled(self, stall_s: float, now: float | None = None) -> bool:
        """No unit finished for ``stall_s`` while input waits (or the thread is gone early)."""
        if not self._thread.is_alive():
            return not self.stop.is_set()
        waiting = self.pending() if self.pending is not None else 1
        return waiting > 0 and (now or time.monotonic()) - self.last_beat > stall_s


class Supervisor:
    """Runs units of work so that one failure costs one unit: counts exceptions by type, logs
    each type's traceback at most once per ``log_every_s`` (the rest as a count), and decides
    when a unit keeps failing long enough (``give_up_s`` of failures with no success) that the
    role cannot go on. Threads started with :meth:`thread` are watched by :meth:`check`."""

    def __init__(self, log_every_s: float = 30.0, give_up_s: float = 300.0, stall_s: float = 60.0) -> None:
        self.log_every_s, self.give_up_s, self.stall_s = log_every_s, give_up_s, stall_s
        self.errors: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._last_logged: dict[str, float] = {}
        self._suppressed: collections.Counter[str] = collections.Counter()
        #: per unit name: monotonic time of the first failure since its last success
        self._failing_since: dict[str, float] = {}
        self.threads: list[WatchedThread] = []

    def call(self, name: str, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``; an exception is counted and logged and None returned, except a
        :class:`~zenrl.common.errors.RunningConfigError` (an env that gives what the run cannot
        use on every step, a replay larger than its memory): it ends the role, as a configuration
        error does."""
        try:
            out = fn(*args)
        except RunningConfigError:
            raise
        except Exception as e:  # noqa: BLE001 - supervision: one failure costs one unit of work
            self.record(name, e)
            return None
        if self._failing_since:
            self._failing_since.pop(name, None)
        return out

    def record(self, name: str, e: BaseException) -> None:
        """Count ``e`` raised by unit ``name`` and log it (rate-limited per exception type)."""
        t = type(e).__name__
        now = time.monotonic()
        with self._lock:
            self.errors[t] += 1
            self._failing_since.setdefault(name, now)
            last = self._last_logged.get(t)
            if last is not None and now - last < self.log_every_s:
                self._suppressed[t] += 1
                return
            self._last_logged[t] = now
            skipped = self._suppressed.pop(t, 0)
        log.error("%s failed (%s; %d more like it not shown); going on", name, t, skipped, exc_info=e)

    def hopeless(self, name: str) -> bool:
        since = self._failing_since.get(name)
        return since is not None and time.monotonic() - since >= self.give_up_s

    def why_hopeless(self, name: str) -> str:
        return f"{name} has failed every time for {self.give_up_s:.0f} s (errors: {dict(self.errors)})"

    def thread(self, name: str, unit: Callable[[], Any], stop: threading.Event,
               pending: Callable[[], int] | None = None, drain: Callable[[], Any] | None = None) -> WatchedThread:
        """Start a watched thread (see :class:`WatchedThread`)."""
        t = WatchedThread(self, name, unit, stop, pending, drain).start()
        self.threads.append(t)
        return t

    def check(self) -> None:
        """Raise :class:`RoleFailed` if a watched thread is gone or gave up."""
        for t in self.threads:
            if t.failed is not None:
                raise RoleFailed(f"thread {t.name} failed: {t.failed}")
            if not t.is_alive() and not t.stop.is_set():
                raise RoleFailed(f"thread {t.name} ended while the role runs")

    def values(self) -> dict[str, Any]:
        """Stats: ``errors_total``, ``errors/<Type>`` and ``stalled`` (the stalled threads' names,
        comma-separated; empty when none)."""
        now = time.monotonic()
        with self._lock:
            v: dict[str, Any] = {"errors_total": sum(self.errors.values())}
            v.update({f"errors/{t}": n for t, n in self.errors.items()})
        v["stalled"] = ",".join(t.name for t in self.threads if t.stalled(self.stall_s, now))
        return v


class RoleLoop:
    """Runs a :class:`Worker` until ``stop`` is set; see the module docstring."""

    def __init__(self, node: Any, keys: P.Keys, role: str, role_id: str, cadence: Cadence,
                 metrics: Any | None = None, supervisor: Supervisor | None = None) -> None:
        self.node, self.keys, self.role, self.id = node, keys, role, role_id
        self.cadence = cadence
        self.metrics = metrics
        self.sup = supervisor or Supervisor()
        self.reports = 0
        self.saves = 0

    def run(self, worker: Worker, stop: threading.Event) -> None:
        """Start ``worker`` and drive it until ``stop``; :class:`RoleFailed` if it cannot go on
        (after the final save and close). An exception from ``worker.start`` is not supervised:
        a role that cannot start fails at once."""
        c = self.cadence
        sup = self.sup
        started = False
        stats_pub = None
        last_log = time.monotonic()
        try:
            worker.start(self.node, sup)
            started = True
            stats_pub = self.node.publisher(self.keys.stats(self.role, self.id))
            self.node.token(self.keys.alive(self.role, self.id))
            last_log = last_save = time.monotonic()
            while not stop.is_set():
                if worker.done():
                    stop.wait(c.idle_s)  # the launcher stops the run once it sees the final count
                else:
                    sup.call("step", worker.step, c.idle_s)
                now = time.monotonic()
                if now - last_log >= c.log_interval_s:
                    sup.call("report", self._report, worker, stats_pub, now - last_log)
                    last_log = now
                if c.checkpoint_interval_s is not None and now - last_save >= c.checkpoint_interval_s:
                    sup.call("save", self._save, worker)
                    last_save = now
                for unit in ("step", "report", "save"):
                    if sup.hopeless(unit):
                        raise RoleFailed(sup.why_hopeless(unit))
                sup.check()
        finally:
            try:
                if started:
                    sup.call("save", self._save, worker)
            finally:
                try:
                    worker.close()
                finally:
                    # the totals after close's final flush (chunks left undelivered, ...) are reported once more
                    if stats_pub is not None:
                        sup.call("report", self._report, worker, stats_pub, max(time.monotonic() - last_log, 1e-6))
                    if self.metrics is not None:
                        self.metrics.close()

    def _report(self, worker: Worker, stats_pub: Any, interval_s: float) -> None:
        vals, line = worker.report(interval_s)
        vals = dict(vals)
        vals.update(self.sup.values())
        if self.metrics is not None and self.metrics.failed_writes:  # a full disk: said in stats, not only in a log on it
            vals["metrics_failed_writes"] = self.metrics.failed_writes
        stats_pub.put(P.Stats(role=self.role, id=self.id, time=time.time(), values=vals).encode())
        if self.metrics is not None:
            self.metrics.write(self.role, worker.progress(), vals)
        if line:
            log.info("%s", line)
        self.reports += 1

    def _save(self, worker: Worker) -> None:
        worker.save()
        self.saves += 1
