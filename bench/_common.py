"""Helpers shared by the benchmark scripts: stderr logging, child processes that are always
stopped, and waiting on a condition with a deadline. (Benchmarks print their JSON result as the
last stdout line; everything else goes to stderr.)"""

from __future__ import annotations

import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def wait_until(cond: Callable[[], Any], timeout_s: float, what: str, interval_s: float = 0.05) -> Any:
    """Poll ``cond`` until it returns something truthy; raise naming ``what`` at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)


class Procs:
    """OS processes started by a benchmark (``python ARGV`` in the repo root, logs in ``tmp``);
    all stopped in :meth:`stop_all` (SIGTERM, then SIGKILL after a grace period). Children see
    ``ZENRL_PARENT_PID``/``BENCH_PARENT_PID`` and stop by themselves if the benchmark dies."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []

    def start(self, name: str, argv: list[str], capture: bool = False, checkout: Path | None = None) -> subprocess.Popen:
        """``capture``: stdout is a text pipe (for a child that prints a JSON result); ``checkout``:
        run in another checkout of zenrl with its ``.venv`` (default: this one, this interpreter),
        for an A/B of its code against this one's."""
        python = sys.executable if checkout is None else str(checkout / ".venv" / "bin" / "python")
        with open(self.tmp / f"{name}.log", "ab") as logf:
            env = dict(os.environ, ZENRL_PARENT_PID=str(os.getpid()), BENCH_PARENT_PID=str(os.getpid()))
            p = subprocess.Popen([python, *argv], cwd=checkout or ROOT, env=env, stderr=logf,
                                 stdout=subprocess.PIPE if capture else logf, text=capture or None)
        self.procs.append(p)
        return p

    def log_text(self, name: str) -> str:
        p = self.tmp / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def stop(self, p: subprocess.Popen, grace_s: float = 15.0) -> None:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def stop_all(self, grace_s: float = 15.0) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for p in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def other_python_missing(python: str, imports: str, what: str, env_var: str, flag: str) -> str | None:
    """Why the Python of another virtual environment (a baseline framework's, e.g. Sample
    Factory's or RLlib's) cannot run ``import <imports>``; None when it can."""
    if not os.path.isfile(python) or not os.access(python, os.X_OK):
        return f"no {what} python at {python} (set {flag} or {env_var})"
    p = subprocess.run([python, "-c", f"import {imports}"], capture_output=True, text=True, timeout=300)
    if p.returncode != 0:
        return f"{python} cannot import {what}: {(p.stderr.strip().splitlines() or ['?'])[-1]}"
    return None


def print_skipped(bench: str, why: str) -> None:
    """A bench that cannot run here: one line saying why, and the JSON result saying so."""
    print(f"skipped: {why}", file=sys.stderr)
    print(json.dumps({"bench": bench, "skipped": why}))


def machine_info(t_start: float) -> dict[str, Any]:
    """Fields every benchmark reports about the run (``t_start``: ``time.perf_counter()``)."""
    return {"python": platform.python_version(), "cpus": os.cpu_count(), "load_avg_1m": os.getloadavg()[0],
            "wall_s": round(time.perf_counter() - t_start, 1)}


def record_error(out: dict[str, Any], e: BaseException) -> None:
    out["error"] = f"{type(e).__name__}: {e}"[:2000]
    log(f"benchmark failed: {out['error']}")


def shut_down(procs: "Procs", node: Any, router: Any) -> None:
    """The end of every networked benchmark: child processes, then its client node (if it got
    one), then the router it opened."""
    procs.stop_all()
    if node is not None:
        node.close()
    router.close()


def ab_cpu_us(steps: dict[Any, Callable[[int], Any]], rounds: int, round_s: float, items_per_call: int = 1
              ) -> dict[Any, float]:
    """Median CPU microseconds (this thread) per item of each variant in ``steps`` (each called
    with a running call count, ``items_per_call`` items a call). The variants take turns, their
    order reversed every round, so that a drift in the machine's load hits them alike."""
    per_item: dict[Any, list[float]] = {k: [] for k in steps}
    keys = list(steps)
    for r in range(rounds):
        for k in (keys if r % 2 == 0 else keys[::-1]):
            step, n = steps[k], 0
            t0, c0 = time.perf_counter(), time.thread_time()
            while time.perf_counter() - t0 < round_s:
                step(n)
                n += 1
            per_item[k].append((time.thread_time() - c0) / (n * items_per_call) * 1e6)
    return {k: statistics.median(v) for k, v in per_item.items()}


def emit(out: dict[str, Any]) -> int:
    """Print the result as the last stdout line; the exit code says whether it failed."""
    print(json.dumps(out))
    return 1 if out.get("error") else 0


def _interrupt(*_: Any) -> None:
    raise KeyboardInterrupt


def stop_on_sigterm() -> None:
    """SIGTERM ends a benchmark like Ctrl-C: its ``finally`` stops every child process."""
    signal.signal(signal.SIGTERM, _interrupt)
