"""``zenrl run``: one machine, one command. Opens an in-process Zenoh router, starts the replay
service (Ape-X), the learner, N actors and the evaluator as separate OS processes (fresh
interpreters, never forked from a process holding a Zenoh session), shows live progress, and
stops everything on Ctrl-C, a step/update/time budget, or when the eval return reaches the
target. A child that dies is restarted (the learner with ``--resume``). Children also stop by
themselves if the launcher disappears (they watch their parent pid), so nothing is orphaned.

``runs/<run-id>/`` holds ``config.yaml`` (resolved), ``metrics.jsonl`` and ``tb/`` (metrics),
``checkpoints/``, ``logs/<process>.log`` and ``summary.json``.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.transport import Node, open_router
from zenrl.placement import describe, plan, usable_cpus

log = logging.getLogger(__name__)

PARENT_ENV = "ZENRL_PARENT_PID"
RATE_WINDOW_S = 5.0  # env steps/s in the progress display is measured over this window


def new_run_id(cfg: RunConfig) -> str:
    env = cfg.env.id.split("/")[-1].replace(":", "-")
    return f"{env}-{cfg.algo}-{time.strftime('%Y%m%d-%H%M%S')}-s{cfg.seed}"


def _port_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
            return True
        except OSError:
            return False


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _split_endpoint(ep: str) -> tuple[str, str, int]:
    proto, rest = ep.split("/", 1)
    host, port = rest.rsplit(":", 1)
    return proto, host, int(port)


@dataclass
class Child:
    name: str
    role: str
    args: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    log_path: Path | None = None


@dataclass
class Progress:
    """What the monitor has heard (from the Zenoh stats/episodes/eval keys)."""

    start: float = field(default_factory=time.monotonic)
    first_step_t: float | None = None
    actor_steps: dict[str, int] = field(default_factory=dict)
    learner: dict[str, Any] = field(default_factory=dict)
    replay: dict[str, Any] = field(default_factory=dict)
    evals: list[dict[str, Any]] = field(default_factory=list)
    recent_returns: list[float] = field(default_factory=list)
    env_steps_rate: float = 0.0
    # (time, total env steps) whenever the total changed, the last RATE_WINDOW_S seconds of them
    # (plus one older as the base): actors report about once a second, so a rate over two
    # consecutive 0.5 s ticks was mostly 0 and otherwise double
    _steps_seen: deque[tuple[float, int]] = field(default_factory=deque)
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def env_steps(self) -> int:
        return sum(self.actor_steps.values())

    def on_message(self, key: str, payload: bytes) -> None:
        try:
            msg = P.decode_any(payload)
        except P.ProtocolError:
            return
        with self.lock:
            if isinstance(msg, P.Stats):
                if msg.role == "actor":
                    self._actor(msg.id, int(msg.values.get("env_steps", 0)))
                elif msg.role == "learner":
                    self.learner = dict(msg.values)
                elif msg.role == "replay":
                    self.replay = dict(msg.values)
            elif isinstance(msg, P.EpisodeStats):
                self._actor(msg.actor_id, msg.env_steps)
                self.recent_returns = (self.recent_returns + [float(x) for x in msg.returns])[-100:]
            elif isinstance(msg, P.EvalResult):
                self.evals.append({"t": time.monotonic() - self.start, "version": msg.version, "updates": msg.updates,
                                   "env_steps": self.env_steps, "mean": float(msg.returns.mean()),
                                   "std": float(msg.returns.std()), "n": int(msg.returns.size),
                                   "win_rate": None if msg.outcomes is None else float((msg.outcomes == 1).mean()),
                                   "since_first_step": None if self.first_step_t is None else time.monotonic() - self.first_step_t})

    def _actor(self, actor_id: str, steps: int) -> None:
        if steps > 0 and self.first_step_t is None:
            self.first_step_t = time.monotonic()
        self.actor_steps[actor_id] = max(steps, self.actor_steps.get(actor_id, 0))

    def tick_rate(self, now: float | None = None) -> None:
        """Update ``env_steps_rate``: env steps/s between the changes of the total seen over the
        last :data:`RATE_WINDOW_S` seconds; 0 once nothing has changed for that long."""
        now = time.monotonic() if now is None else now
        seen, s = self._steps_seen, self.env_steps
        if not seen or s != seen[-1][1]:
            seen.append((now, s))
        while len(seen) > 2 and now - seen[1][0] > RATE_WINDOW_S:
            seen.popleft()
        if now - seen[-1][0] > RATE_WINDOW_S:
            self.env_steps_rate = 0.0
        elif len(seen) >= 2:
            (t0, s0), (t1, s1) = seen[0], seen[-1]
            self.env_steps_rate = (s1 - s0) / max(t1 - t0, 1e-9)

    @property
    def last_eval(self) -> float | None:
        return self.evals[-1]["mean"] if self.evals else None


class Launcher:
    def __init__(self, cfg: RunConfig, resume: bool = False) -> None:
        self.run_id = cfg.run_id or new_run_id(cfg)
        self.cfg = cfg.model_copy(update={"run_id": self.run_id})
        self.resume = resume
        self.run_dir = Path(cfg.runs_dir) / self.run_id
        self.stop = threading.Event()
        self.progress = Progress()
        self.children: list[Child] = []
        self.max_restarts = 5
        self.stop_reason = ""
        self.placement = plan(self.cfg.cpu_placement, self.cfg.algo, self.cfg.learner.torch_threads, usable_cpus())

    # -- processes ---------------------------------------------------------------------------
    def _endpoints(self) -> tuple[list[str], str]:
        listen = list(self.cfg.transport.listen)
        proto, host, port = _split_endpoint(listen[0])
        if self.cfg.transport.router_config is None and not _port_free(host if host != "0.0.0.0" else "127.0.0.1", port):
            port = free_port()
            log.info("port %d is busy; the embedded router listens on %d instead", _split_endpoint(listen[0])[2], port)
            listen = [f"{proto}/{host}:{port}"]
        connect_host = "127.0.0.1" if host in ("0.0.0.0", "[::]") else host
        return listen, f"{proto}/{connect_host}:{port}"

    def _spawn(self, c: Child, extra: list[str] | None = None) -> None:
        cmd = [sys.executable, "-m", "zenrl.cli", c.role, "--config", str(self.run_dir / "config.yaml"),
               "--run-id", self.run_id, "--router", self.endpoint, *c.args, *(extra or [])]
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})
        if self.placement is not None and c.role in self.placement:
            env.update(self.placement[c.role].env())
        c.log_path = self.run_dir / "logs" / f"{c.name}.log"
        with open(c.log_path, "ab") as f:
            c.proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        log.debug("started %s (pid %d): %s", c.name, c.proc.pid, " ".join(cmd))

    def _plan(self) -> list[Child]:
        kids = []
        if self.cfg.algo == "apex":
            kids.append(Child("replay", "replay", []))
        kids.append(Child("learner", "learner", ["--resume"] if self.resume else []))
        for i in range(self.cfg.actor.num_actors):
            kids.append(Child(f"actor-{i}", "actor", ["--id", f"actor-{i}", "--slot", str(i)]))
        if self.cfg.evaluator.enabled:
            kids.append(Child("evaluator", "evaluator", []))
        return kids

    def _supervise(self) -> None:
        for c in self.children:
            if c.proc is None or c.proc.poll() is None or self.stop.is_set():
                continue
            rc = c.proc.returncode
            if c.restarts >= self.max_restarts:
                log.error("%s exited with %s and was restarted %d times already; stopping the run (see %s)", c.name, rc, c.restarts, c.log_path)
                self.stop_reason = f"{c.name} keeps failing"
                self.stop.set()
                return
            c.restarts += 1
            log.warning("%s exited with code %s; restarting (%d/%d), log %s", c.name, rc, c.restarts, self.max_restarts, c.log_path)
            self._spawn(c, ["--auto-resume"] if c.role == "learner" and "--resume" not in c.args else None)

    def _terminate(self) -> None:
        # the replay last, so that actors' final chunks reach it; the learner needs nothing from
        # the actors to save its checkpoint, so it stops with them (one exit wait, ~1-1.5 s on 2
        # cores with torch's interpreter teardown, instead of two in a row)
        order = [[c for c in self.children if c.role in ("actor", "evaluator", "learner")],
                 [c for c in self.children if c.role == "replay"]]
        for group in order:
            for c in group:
                if c.proc is not None and c.proc.poll() is None:
                    c.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + 20
            for c in group:
                if c.proc is None:
                    continue
                try:
                    c.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop within 20 s; killing it", c.name)
                    c.proc.kill()
                    c.proc.wait()

    # -- stop conditions ---------------------------------------------------------------------
    def _check_done(self) -> None:
        cfg, p = self.cfg, self.progress
        if cfg.max_env_steps is not None and p.env_steps >= cfg.max_env_steps:
            self.stop_reason = f"max_env_steps {cfg.max_env_steps} reached"
        elif cfg.max_updates is not None and int(p.learner.get("updates", 0)) >= cfg.max_updates:
            self.stop_reason = f"max_updates {cfg.max_updates} reached"
        elif cfg.max_wall_s is not None and time.monotonic() - p.start >= cfg.max_wall_s:
            self.stop_reason = f"max_wall_s {cfg.max_wall_s} reached"
        elif cfg.target_return is not None and p.last_eval is not None and p.last_eval >= cfg.target_return:
            self.stop_reason = f"eval return {p.last_eval:.1f} >= target {cfg.target_return}"
        if self.stop_reason:
            self.stop.set()

    def _status_line(self) -> dict[str, Any]:
        p = self.progress
        return {"elapsed_s": round(time.monotonic() - p.start, 1), "env_steps": p.env_steps,
                "env_steps_per_s": round(p.env_steps_rate, 1), "updates": p.learner.get("updates", 0),
                "updates_per_s": round(float(p.learner.get("updates_per_s", 0.0)), 1),
                "replay_size": p.replay.get("size", 0), "weights_version": p.learner.get("version", 0),
                "train_return_100": round(float(np.mean(p.recent_returns)), 1) if p.recent_returns else None,
                "eval_return": None if p.last_eval is None else round(p.last_eval, 1),
                **({"eval_win_rate": round(p.evals[-1]["win_rate"], 2)}
                   if p.evals and p.evals[-1].get("win_rate") is not None else {})}

    # -- main --------------------------------------------------------------------------------
    def run(self) -> int:
        from zenrl.common.transport import install_stop_signals

        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(self.cfg.model_dump(mode="json"), sort_keys=False))
        install_stop_signals(self.stop)
        listen, self.endpoint = self._endpoints()
        every_cpu = usable_cpus()
        if self.placement is not None:
            # on Linux this sets the calling thread's CPUs: the router's threads, started by
            # open_router, inherit them and share the non-learner CPUs ...
            os.sched_setaffinity(0, self.placement["router"].cpus)
            log.info("cpu placement (cpu_placement=auto; off leaves it to the OS): %s", describe(self.placement))
        try:
            router = open_router(listen, self.cfg.transport.router_config)
        finally:
            if self.placement is not None:
                # ... while the children start on every CPU (their imports run in parallel) and
                # place themselves once imported (zenrl.placement.apply_from_env)
                os.sched_setaffinity(0, every_cpu)
        log.info("run %s: router on %s, logs in %s", self.run_id, listen, self.run_dir / "logs")
        node = Node(session=router)
        rc = 0
        try:
            k = P.Keys(self.run_id)
            for key in (k.stats_all, k.episodes_all, k.eval):
                node.subscribe(key, self.progress.on_message)
            self.children = self._plan()
            for c in self.children:
                self._spawn(c)
            self._loop()
        except KeyboardInterrupt:
            self.stop_reason = self.stop_reason or "interrupted"
        finally:
            self.stop.set()
            self._terminate()
            self._write_summary()
            node.close()
        if self.stop_reason.endswith("keeps failing"):
            rc = 1
        log.info("run %s stopped: %s", self.run_id, self.stop_reason or "stopped")
        return rc

    def _loop(self) -> None:
        live = None
        console = None
        if self.cfg.progress:
            from rich.console import Console

            console = Console(stderr=True)
            if console.is_terminal:
                from rich.live import Live

                live = Live(self._table(), console=console, refresh_per_second=2, transient=False)
                live.start()
        last_plain = 0.0
        try:
            while not self.stop.wait(0.5):
                self.progress.tick_rate()
                self._supervise()
                self._check_done()
                if live is not None:
                    live.update(self._table())
                elif self.cfg.progress and time.monotonic() - last_plain >= 5.0:
                    last_plain = time.monotonic()
                    log.info("progress %s", json.dumps(self._status_line()))
        finally:
            if live is not None:
                live.update(self._table())
                live.stop()

    def _table(self):
        from rich.table import Table

        t = Table(title=f"zenrl run {self.run_id}", show_header=False)
        for k, v in self._status_line().items():
            t.add_row(k.replace("_", " "), "-" if v is None else str(v))
        if self.stop_reason:
            t.add_row("stopped", self.stop_reason)
        return t

    def _write_summary(self) -> None:
        p = self.progress
        solved = None
        if self.cfg.target_return is not None:
            solved = next((e for e in p.evals if e["mean"] >= self.cfg.target_return), None)
        summary = {"run_id": self.run_id, "stop_reason": self.stop_reason, "wall_s": time.monotonic() - p.start,
                   "startup_s": None if p.first_step_t is None else p.first_step_t - p.start,
                   "env_steps": p.env_steps, "learner": p.learner, "replay": p.replay, "evals": p.evals,
                   "target_return": self.cfg.target_return, "solved": solved is not None,
                   "solve_s_since_first_step": None if solved is None else solved["since_first_step"],
                   "restarts": {c.name: c.restarts for c in self.children}}
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=float))


def launch(cfg: RunConfig, resume_dir: str | None = None) -> int:
    """Entry point of ``zenrl run``."""
    if resume_dir is not None:
        rd = Path(resume_dir)
        if not (rd / "config.yaml").is_file():
            from zenrl.common.errors import CheckpointError

            raise CheckpointError(f"{resume_dir!r} is not a run directory (no config.yaml)")
        cfg = cfg.model_copy(update={"run_id": rd.name, "runs_dir": str(rd.parent)})
    return Launcher(cfg, resume=resume_dir is not None).run()


def status(cfg: RunConfig, run_id: str, as_json: bool = False, wait_s: float = 3.0) -> int:
    """``zenrl status``: live processes (liveliness tokens) and their latest stats."""
    stats: dict[str, dict[str, Any]] = {}
    lock = threading.Lock()

    def on_stats(key: str, payload: bytes) -> None:
        try:
            m = P.Stats.decode(payload)
        except P.ProtocolError:
            return
        with lock:
            stats[f"{m.role}/{m.id}"] = m.values

    k = P.Keys(run_id)
    with Node(cfg.transport.router, min(cfg.transport.connect_timeout_s, 5.0), config_file=cfg.transport.client_config) as node:
        node.subscribe(k.stats_all, on_stats)
        alive = [k.parse_alive(x) for x in node.alive_now(k.alive_all)]
        time.sleep(wait_s)  # stats arrive every few seconds; collect one round
    rows = []
    for role, pid in sorted(alive):
        rows.append({"role": role, "id": pid, **stats.get(f"{role}/{pid}", {})})
    out = {"run_id": run_id, "processes": rows}
    if as_json:
        sys.stdout.write(json.dumps(out, default=float) + "\n")
    else:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"zenrl run {run_id}")
        for col in ("role", "id", "rate", "weights", "size / lag"):
            t.add_column(col)
        lv = next((r.get("version") for r in rows if r["role"] == "learner"), None)
        for r in rows:
            rate = r.get("updates_per_s") or r.get("inserts_per_s") or r.get("env_steps")
            extra = r.get("size") if r["role"] == "replay" else (
                None if lv is None or r.get("policy_version") is None else lv - r["policy_version"])
            t.add_row(r["role"], r["id"], "-" if rate is None else f"{rate:.1f}" if isinstance(rate, float) else str(rate),
                      str(r.get("version", r.get("policy_version", "-"))), "-" if extra is None else str(extra))
        Console().print(t)
    return 0 if rows else 1
