"""The small interfaces every zenrl role implements, and the one loop that runs them.

A role's algorithm is a :class:`Worker`: it declares what it listens to (:meth:`Worker.start`),
does one unit of work per :meth:`Worker.step` (an update, a gradient applied, a batch of env
steps), reports what it did since the last report (:meth:`Worker.report`), saves its training
state if it has one (:meth:`Worker.save`) and lets go of what it holds (:meth:`Worker.close`).
:class:`RoleLoop` owns everything around that, the same for every role: the liveliness token
``alive/<role>/<id>``, the stats publisher and metrics, the log and checkpoint cadence, the
budget wait, and an orderly stop::

    worker = ApexLearner(cfg, node, run_id)          # or A3CLearner, ...
    RoleLoop(node, keys, "learner", worker.id, cadence, metrics).run(worker, stop)
    # -> worker.start(node); while not stop: worker.step(idle_s) ... report/save on cadence
    #    finally: worker.save(); worker.close()

The loop needs only ``publisher``, ``token`` and ``put`` of a transport node, so it is unit
tested with an in-memory one; it imports no network library.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

from zenrl.common import protocol as P

log = logging.getLogger(__name__)


class Worker(Protocol):
    """One role's algorithm, driven by :class:`RoleLoop`."""

    #: the id this process publishes under (``stats/<role>/<id>``, ``alive/<role>/<id>``)
    id: str

    def start(self, node: Any) -> None:
        """Declare subscriptions, queryables and publishers; publish initial state."""

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


class RoleLoop:
    """Runs a :class:`Worker` until ``stop`` is set; see the module docstring."""

    def __init__(self, node: Any, keys: P.Keys, role: str, role_id: str, cadence: Cadence,
                 metrics: Any | None = None) -> None:
        self.node, self.keys, self.role, self.id = node, keys, role, role_id
        self.cadence = cadence
        self.metrics = metrics
        self.reports = 0
        self.saves = 0

    def run(self, worker: Worker, stop: threading.Event) -> None:
        c = self.cadence
        worker.start(self.node)
        stats_pub = self.node.publisher(self.keys.stats(self.role, self.id))
        self.node.token(self.keys.alive(self.role, self.id))
        last_log = last_save = time.monotonic()
        try:
            while not stop.is_set():
                if worker.done():
                    stop.wait(c.idle_s)  # the launcher stops the run once it sees the final count
                else:
                    worker.step(c.idle_s)
                now = time.monotonic()
                if now - last_log >= c.log_interval_s:
                    self._report(worker, stats_pub, now - last_log)
                    last_log = now
                if c.checkpoint_interval_s is not None and now - last_save >= c.checkpoint_interval_s:
                    self._save(worker)
                    last_save = now
        finally:
            try:
                self._save(worker)
            finally:
                worker.close()
                if self.metrics is not None:
                    self.metrics.close()

    def _report(self, worker: Worker, stats_pub: Any, interval_s: float) -> None:
        vals, line = worker.report(interval_s)
        stats_pub.put(P.Stats(role=self.role, id=self.id, time=time.time(), values=dict(vals)).encode())
        if self.metrics is not None:
            self.metrics.write(self.role, worker.progress(), vals)
        if line:
            log.info("%s", line)
        self.reports += 1

    def _save(self, worker: Worker) -> None:
        worker.save()
        self.saves += 1

