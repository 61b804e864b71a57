"""``zenrl run``'s supervisor: checks that the env can be made, opens an in-process Zenoh
router, starts the children as fresh interpreters (never forked from a process holding a Zenoh
session), restarts a crashed one (the learner from its checkpoint) unless it failed on its
configuration, and stops everything on Ctrl-C, a budget, or a solved eval."""

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
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from zenrl import EXIT_CONFIG
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.errors import ConfigError, EnvOutputError
from zenrl.actor.batch_env import stack_flat
from zenrl.actor.env_guard import EnvGuard
from zenrl.launcher.display import (ENV_TROUBLES, MAX_KEPT_EVALS, Progress, TroubleWatch, crowding_warnings,
                                    endless_warning, render_table)
from zenrl.launcher.runfolder import (SUMMARY_FILE, earlier_segments, holds_a_run, last_error_line, lock_run_folder,
                                      read_summary, remove_launcher_info, unlock_run_folder, write_json_atomic,
                                      write_launcher_info)
from zenrl.placement import describe, plan, usable_cpus

log = logging.getLogger("zenrl.launcher")

PARENT_ENV = "ZENRL_PARENT_PID"
#: how often progress is logged (no terminal) and written to metrics.jsonl
PROGRESS_EVERY_S = 5.0
#: how often summary.json is rewritten while the run goes on (so that a killed launcher leaves one)
SUMMARY_EVERY_S = 30.0
#: the stop reason a summary written while the run goes on carries
RUNNING = "still running (or its launcher was killed)"


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


def _first_line(text: str) -> str:
    return next((x.strip() for x in str(text).splitlines() if x.strip()), "")


def catches_signal(pid: int, sig: int) -> bool:
    """Whether process ``pid`` has a handler for ``sig`` (Linux: ``SigCgt`` of
    /proc/PID/status); False where that cannot be read."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) >> (int(sig) - 1) & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


#: a summary.json that cannot be written (a full disk) is said at most this often
DISK_TROUBLE_EVERY_S = 60.0

#: the launcher says so when making and resetting the env once at start takes this long
CHECK_ENV_SLOW_S = 30.0


def check_env(cfg: RunConfig, slow_s: float = CHECK_ENV_SLOW_S) -> None:
    """:func:`check_env_now`, with a warning holding where it waits when the env takes ``slow_s``
    to be made and reset: an env waiting for a simulator that is not there would otherwise leave
    ``zenrl run`` silent before it has started anything."""
    done = threading.Event()
    caller = threading.get_ident()

    def tell() -> None:
        if done.wait(slow_s):
            return
        frame = sys._current_frames().get(caller)
        where = "".join(traceback.format_stack(frame)) if frame is not None else "(unknown)\n"
        log.warning("making and resetting env %s once to check it has taken %.0f s (still waiting; Ctrl-C stops): "
                    "does it wait for a simulator or a connection? It waits here:\n%s", cfg.env.id, slow_s, where.rstrip())

    threading.Thread(target=tell, name="check-env-watch", daemon=True).start()
    try:
        check_env_now(cfg)
    finally:
        done.set()


def check_env_now(cfg: RunConfig) -> None:
    """Make, inspect and reset the run's env once, here, before anything starts: a mistake in
    ``env.id`` / ``env.kwargs`` or an env zenrl cannot learn (continuous actions) is then one
    :class:`ConfigError` line instead of every child failing in its log; so are a
    ``learner.device`` this machine lacks and a network whose weights no message can carry."""
    from zenrl.common.checkpoints import check_weights_fit
    from zenrl.common.env_factory import make_env
    from zenrl.common.networks import action_size, obs_spec, resolve_device
    from zenrl.common.opponents import check_opponents
    from zenrl.tools.loading import quiet_native_imports

    quiet_native_imports()  # pybullet's build-time banner is noise in the launcher's terminal
    resolve_device(cfg.learner.device)  # a device this machine lacks: one line now, not the learner's exit
    where = f"env.id={cfg.env.id!r}"
    try:
        env = make_env(cfg.env)
    except ConfigError as e:
        raise ConfigError(_first_line(str(e))) from None
    except Exception as e:  # an env's own constructor may raise anything for bad kwargs
        raise ConfigError(f"{where} with env.kwargs={cfg.env.kwargs!r} cannot be made: "
                          f"{type(e).__name__}: {_first_line(str(e))}") from None
    try:
        n_actions = action_size(env.action_space, cfg.algo)
        spec = obs_spec(env.observation_space)
        obs, _ = env.reset(seed=cfg.seed)
        # what the actors will check of every observation: before any child starts
        EnvGuard(cfg.env.id, env.observation_space).conform(stack_flat([obs]))
    except Exception as e:  # as above: the env's code, not ours
        env.close()
        if isinstance(e, EnvOutputError):  # names the env already
            raise ConfigError(_first_line(str(e))) from None
        raise ConfigError(f"{where}: {_first_line(str(e)) or type(e).__name__}") from None
    try:
        check_weights_fit(cfg, spec, n_actions)  # the network's weights fit one message (ConfigError)
        check_opponents(cfg, env)  # every opponents.pool file loads and fits the env, before any child starts
    finally:
        env.close()


@dataclass
class Child:
    name: str
    role: str
    args: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    log_path: Path | None = None
    #: a league agent's process: its own config file and run id (default: the run's)
    config: Path | None = None
    run_id: str | None = None
    #: why the launcher killed it (a silent actor), said when it is restarted; None otherwise
    killed_for: str | None = None
    #: the league agent it belongs to
    agent: str | None = None
    #: monotonic time its process was started; whether the launcher has said it has not been heard from since
    spawned_at: float = 0.0
    unheard_told: bool = False


def _reaches(e: Any, target: float | None) -> bool:
    """Whether evaluation ``e`` (a summary.json entry, maybe of an older version) reached ``target``."""
    return (target is not None and isinstance(e, dict) and isinstance(e.get("mean"), (int, float))
            and e["mean"] >= target)


def replay_children(shards: int, prefix: str = "", **kw: Any) -> list[Child]:
    """The replay service, or with ``replay.shards`` = N > 1 one per shard (``replay-<k>``, each
    with its own id, stats, log file and durable log folder ``shard-<k>``)."""
    if shards == 1:
        return [Child(f"{prefix}replay", "replay", [], **kw)]
    return [Child(f"{prefix}replay-{k}", "replay", ["--shard", str(k), "--id", f"replay-{k}"], **kw) for k in range(shards)]


#: a Ctrl-C this long after the first (or later) kills what has not stopped yet
HURRY_AFTER_S = 0.5


class Launcher:
    def __init__(self, cfg: RunConfig, resume: bool = False, exporter_port: int | None = None) -> None:
        self.exporter_port = exporter_port  # also start `zenrl exporter` there (Prometheus metrics)
        self.run_id = cfg.run_id or new_run_id(cfg)
        self.cfg = cfg.model_copy(update={"run_id": self.run_id})
        self.resume = resume
        self.run_dir = Path(cfg.runs_dir) / self.run_id
        self.stop = threading.Event()
        #: a second Ctrl-C while stopping: kill what has not stopped yet instead of waiting
        self.hurry = threading.Event()
        self._first_interrupt: float | None = None
        before = read_summary(self.run_dir) if resume else None
        self.earlier = earlier_segments(before)
        # evaluations of the earlier segments: summary.json keeps the newest MAX_KEPT_EVALS, their
        # count, and the first at or above target_return whenever it came
        earlier_evals = [e for e in (before or {}).get("evals", []) if isinstance(e, dict)]
        total = (before or {}).get("evals_total")
        self.earlier_evals_total = total if type(total) is int and total >= len(earlier_evals) else len(earlier_evals)
        self.earlier_evals = earlier_evals[-MAX_KEPT_EVALS:]
        target = cfg.target_return
        first = (before or {}).get("first_solved")
        self.earlier_solved = next((e for e in (first, *earlier_evals) if _reaches(e, target)), None)
        self.progress = Progress(base_env_steps=sum(int(s.get("env_steps") or 0) for s in self.earlier),
                                 base_elapsed_s=sum(float(s.get("wall_s") or 0.0) for s in self.earlier),
                                 target=target)
        if before and isinstance(before.get("learner"), dict):
            # the learner's counters continue from its checkpoint: show the last ones heard until
            # it reports again (the replay's size is not carried: it restarts empty unless durable)
            self.progress.learner = dict(before["learner"])
        self.started_at = time.time()
        self.children: list[Child] = []
        self.max_restarts = 5
        self.stop_reason = ""
        self.exit_code = 0
        self._summary_said: float | None = None  # when the terminal last said summary.json could not be written
        # updates when this launch began: the learner resumes from its checkpoint, which may be
        # older than the last count an earlier segment heard
        self.updates_at_start: int | None = None if resume else 0
        # imported here: the registry imports every role (and torch), which `zenrl status`, a
        # user of this package too, does not need
        from zenrl.algorithms import algorithm

        self.algorithm = algorithm(self.cfg.algo)
        self.placement = plan(self.cfg.cpu_placement, self.algorithm.places_learner,
                              self.cfg.learner.torch_threads, usable_cpus())
        self.endpoint = ""
        self._metrics = None
        #: league runs: each learning agent's resolved config, and the generations applied (resets)
        self.agents: dict[str, RunConfig] = {}
        self.applied: dict[str, int] = {}
        self._league_seen: dict[str, int] = {}
        if self.cfg.league.enabled:
            from zenrl.launcher.league_run import agent_configs

            # this launcher restarts a reset agent's processes itself: they must not exit on their own
            self.agents = {a: c.model_copy(update={"league": c.league.model_copy(update={"self_reset": False})})
                           for a, c in agent_configs(self.cfg, self.run_id).items()}
            self.placement = None  # several learners share the CPUs: left to the OS
        #: the replay services this launcher starts on this machine: each one's memory check
        #: gets its share of the machine (replay.replays_per_machine)
        self.replays_here = 0 if not self.algorithm.uses_replay else (
            sum(a.replay.shards for a in self.agents.values()) if self.agents else self.cfg.replay.shards)

    def _stop_with(self, reason: str, exit_code: int = 0) -> None:
        """Stop the run for ``reason`` (the first reason given wins)."""
        if not self.stop_reason:
            self.stop_reason = reason
            self.exit_code = exit_code
        self.stop.set()

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
        cmd = [sys.executable, "-m", "zenrl.cli", c.role, "--config", str(c.config or self.run_dir / "config.yaml"),
               "--run-id", c.run_id or self.run_id, "--router", self.endpoint, *c.args, *(extra or [])]
        if c.role == "replay" and self.replays_here > 1:
            cmd += ["--set", f"replay.replays_per_machine={self.replays_here}"]
        # PYTHONSAFEPATH: `-m` would put the working directory first on sys.path, where a source
        # checkout's zenrl/ folder shadows the installed package (zenrl.common lives elsewhere)
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid()), "PYTHONSAFEPATH": "1"})
        if self.placement is not None and c.role in self.placement:
            env.update(self.placement[c.role].env())
        c.log_path = self.run_dir / "logs" / f"{c.name}.log"
        with open(c.log_path, "ab") as f:
            c.proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        # a new process: not heard yet (the last stats were its predecessor's, which a slow start
        # would otherwise outlive into a kill as "stuck")
        c.spawned_at, c.unheard_told = time.monotonic(), False
        self._forget(c)
        log.debug("started %s (pid %d): %s", c.name, c.proc.pid, " ".join(cmd))

    def _agent_children(self, aid: str, fresh: bool = False, init: Path | None = None) -> list[Child]:
        """The replay, learner, actors (and, for the main agent, evaluator) of league agent
        ``aid``, on its own config and run id; ``fresh``: its learner starts from scratch (from
        the weights in checkpoint ``init``, if given)."""
        acfg = self.agents[aid]
        conf = self.run_dir / "agents" / f"{aid}.yaml"
        kw = {"config": conf, "run_id": acfg.run_id, "agent": aid}
        learner_args = [] if fresh or not self.resume else ["--auto-resume"]
        if init is not None:
            learner_args += ["--set", f"learner.init_from={init}"]
        kids = [*(replay_children(acfg.replay.shards, f"{aid}-", **kw) if self.algorithm.uses_replay else []),
                Child(f"{aid}-learner", "learner", learner_args, **kw)]
        for i in range(acfg.actor.num_actors):
            kids.append(Child(f"{aid}-actor-{i}", "actor", ["--id", f"{aid}-actor-{i}", "--slot", str(i)], **kw))
        if acfg.evaluator.enabled:
            kids.append(Child(f"{aid}-evaluator", "evaluator", [], **kw))
        return kids

    def _plan(self) -> list[Child]:
        kids = []
        if self.agents:
            from zenrl.launcher.league_run import exploiter_init

            kids.append(Child("league", "league", []))
            for aid in self.agents:
                # a resumed run's exploiter past its first generation starts as its reset would
                # have, should it have no checkpoint of its own yet (one of its own wins)
                init = exploiter_init(self.agents, aid, self.run_dir) if self.resume and self.applied.get(aid, 0) >= 1 else None
                kids.extend(self._agent_children(aid, init=init))
            if self.exporter_port is not None:
                host = _split_endpoint(self.cfg.transport.listen[0])[1].strip("[]") or "0.0.0.0"
                kids.append(Child("exporter", "exporter", ["--port", str(self.exporter_port), "--host", host]))
            return kids
        if self.algorithm.uses_replay:
            kids.extend(replay_children(self.cfg.replay.shards))
        kids.append(Child("learner", "learner", ["--resume"] if self.resume else []))
        for i in range(self.cfg.actor.num_actors):
            kids.append(Child(f"actor-{i}", "actor", ["--id", f"actor-{i}", "--slot", str(i)]))
        if self.cfg.evaluator.enabled:
            kids.append(Child("evaluator", "evaluator", []))
        if self.exporter_port is not None:  # reachable where the run's router is (loopback by default)
            host = _split_endpoint(self.cfg.transport.listen[0])[1].strip("[]") or "0.0.0.0"
            kids.append(Child("exporter", "exporter", ["--port", str(self.exporter_port), "--host", host]))
        return kids

    def _supervise(self) -> None:
        for c in self.children:
            if c.proc is None or c.proc.poll() is None or self.stop.is_set():
                continue
            rc = c.proc.returncode
            why = c.killed_for or last_error_line(c.log_path) or "(empty log)"
            c.killed_for = None
            if rc == EXIT_CONFIG:
                log.error("%s stopped on a configuration error (not restarted): %s  [log %s]", c.name, why, c.log_path)
                self._stop_with(f"{c.name} failed on its configuration: {why}", 2)
                return
            if c.restarts >= self.max_restarts:
                log.error("%s exited with code %s and was restarted %d times already; stopping the run. "
                          "Last error: %s  [log %s]", c.name, rc, c.restarts, why, c.log_path)
                self._stop_with(f"{c.name} keeps failing (exit code {rc}): {why}", 1)
                return
            c.restarts += 1
            log.warning("%s exited with code %s (%s); restarting (%d/%d), log %s", c.name, rc, why, c.restarts,
                        self.max_restarts, c.log_path)
            self._spawn(c, ["--auto-resume"] if c.role == "learner" and not {"--resume", "--auto-resume"} & set(c.args)
                        else None)

    def _hears(self, c: Child) -> bool:
        """Whether this launcher subscribes to ``c``'s stats: every actor's (in a league run, each
        agent's, :meth:`_listen`), the evaluator's (the main agent's only one)."""
        return not self.agents or c.role == "actor" or c.agent == self.cfg.league.main_id

    def _listen(self, node: Any) -> None:
        """Subscribe the live display to the run's stats, episodes and evaluations (in a league
        run the main agent's, the league's, and the other agents' actors' to hear them alive)."""
        k = P.Keys(self.run_id)
        if self.agents:  # the live figures are the main agent's; the league's stats carry resets
            main = self.cfg.league.main_id
            k = P.Keys(self.agents[main].run_id or "")
            node.subscribe(P.Keys(self.run_id).stats("league", "league"), self._on_league_stats)
            for aid, acfg in self.agents.items():
                if aid != main:
                    node.subscribe(f"{P.Keys(acfg.run_id or '').prefix}/stats/actor/*", self.progress.on_actor_stats)
        for key in (k.stats_all, k.episodes_all, k.eval):
            node.subscribe(key, self.progress.on_message)

    def _silence_limit(self, c: Child) -> float:
        """Seconds without stats after which ``c`` counts as silent: ``actor.silent_restart_s``,
        for the evaluator at least three of its report intervals (``evaluator.interval_s``)."""
        limit = self.cfg.actor.silent_restart_s
        return max(limit, 3 * self.cfg.evaluator.interval_s) if c.role == "evaluator" else limit

    def _last_heard(self, c: Child) -> float | None:
        p = self.progress
        return p.evaluator_seen if c.role == "evaluator" else p.actor_seen.get(c.name)

    def _forget(self, c: Child) -> None:
        """Until the restarted process reports."""
        if c.role == "evaluator":
            self.progress.evaluator_seen = None
        else:
            self.progress.actor_seen.pop(c.name, None)

    def _watch_silent(self, now: float | None = None) -> None:
        """Actors and the evaluator silent for :meth:`_silence_limit` while their process runs
        (their role loop publishes nothing while it waits in an env's step, reset or constructor):

        * one that has published stats and then none is stuck: its threads' stacks go to its log
          (SIGUSR1: faulthandler), then it is killed; :meth:`_supervise` restarts it, as it
          restarts a child that died;
        * one not heard from since its process started (its first stats come once its envs are
          made and reset) may be stuck in its env's constructor (a simulator it waits for) or only
          slow to start on a loaded machine: it is not restarted, but the terminal says so once and
          its stacks go to its log (SIGUSR1 only when the process has its handler already: before
          it, the signal would kill it)."""
        if self.stop.is_set():
            return
        now = time.monotonic() if now is None else now
        for c in self.children:
            if c.role not in ("actor", "evaluator") or c.proc is None or c.proc.poll() is not None or not self._hears(c):
                continue
            last, limit = self._last_heard(c), self._silence_limit(c)
            if last is not None and now - last >= limit:
                self._forget(c)
                c.killed_for = f"killed by the launcher: no stats for {now - last:.0f} s, stuck"
                log.warning("%s has published no stats for %.0f s although its process runs: stuck (in its env's step "
                            "or reset?). Its threads' stacks go to %s; restarting it", c.name, now - last, c.log_path)
                try:
                    c.proc.send_signal(signal.SIGUSR1)
                    time.sleep(0.5)  # faulthandler writes from a signal handler: a moment
                finally:
                    c.proc.kill()
                    c.proc.wait()
            elif last is None and not c.unheard_told and now - c.spawned_at >= limit:
                c.unheard_told = True
                dumped = catches_signal(c.proc.pid, signal.SIGUSR1)
                if dumped:
                    c.proc.send_signal(signal.SIGUSR1)
                log.warning("%s has published nothing in the %.0f s since it started: its env may hang in its "
                            "constructor or first reset (a simulator it waits for?), or the machine is slow to start "
                            "it; %s. Waiting on", c.name, now - c.spawned_at,
                            f"its threads' stacks are in {c.log_path}" if dumped else f"its log: {c.log_path}")

    def _terminate(self, children: list[Child] | None = None, grace_s: float = 20.0) -> None:
        # the replay last, so that actors' final chunks reach it; the learner needs nothing from
        # the actors to save its checkpoint, so it stops with them (one exit wait instead of two);
        # the league with the replays, after the actors' last results
        kids = self.children if children is None else children
        order = [[c for c in kids if c.role in ("actor", "evaluator", "learner", "exporter")],
                 [c for c in kids if c.role in ("replay", "league")]]
        for group in order:
            for c in group:
                if c.proc is not None and c.proc.poll() is None:
                    c.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + grace_s
            for c in group:
                if c.proc is None:
                    continue
                while c.proc.poll() is None and time.monotonic() < deadline and not self.hurry.is_set():
                    self.hurry.wait(min(0.05, max(0.0, deadline - time.monotonic())))
                if c.proc.poll() is None:
                    if not self.hurry.is_set():
                        log.warning("%s did not stop within %.0f s; killing it", c.name, grace_s)
                    c.proc.kill()
                    c.proc.wait()

    # -- stop conditions ---------------------------------------------------------------------
    def _check_done(self) -> None:
        cfg, p = self.cfg, self.progress
        updates = int(p.learner.get("updates", 0))
        if cfg.max_env_steps is not None and p.env_steps >= cfg.max_env_steps:
            self._stop_with(f"max_env_steps {cfg.max_env_steps} reached ({p.env_steps} env steps)")
        elif cfg.max_updates is not None and updates >= cfg.max_updates:
            self._stop_with(f"max_updates {cfg.max_updates} reached ({updates} updates)")
        elif cfg.max_wall_s is not None and time.monotonic() - p.start >= cfg.max_wall_s:
            self._stop_with(f"max_wall_s {cfg.max_wall_s} reached (this launch's wall-clock budget)")
        elif cfg.target_return is not None and p.last_eval is not None and p.last_eval >= cfg.target_return:
            self._stop_with(f"solved: eval return {p.last_eval:.1f} >= target_return {cfg.target_return}")

    def _on_signal(self, signum: int) -> None:
        # called on the stop-signal relay's thread (zenrl.common.signals), not in a signal handler
        if signum == signal.SIGINT and self._first_interrupt is not None:
            # one Ctrl-C can arrive twice at once (`timeout -s INT` signals the process and its
            # group): only a press a moment later is a second one
            if time.monotonic() - self._first_interrupt >= HURRY_AFTER_S and not self.hurry.is_set():
                log.warning("Ctrl-C again: killing the processes that have not stopped yet (their last "
                            "checkpoint or log flush may be missing)")
                self.hurry.set()
            return
        if signum == signal.SIGINT:
            self._first_interrupt = time.monotonic()
            self._stop_with("interrupted by user (Ctrl-C)")
        elif signum == signal.SIGHUP:
            self._stop_with("its terminal hung up (SIGHUP)")
        else:
            self._stop_with(f"stopped by {signal.Signals(signum).name} (e.g. docker stop, kill)")

    # -- main --------------------------------------------------------------------------------
    def run(self) -> int:
        from zenrl.common.metrics import MetricsWriter
        from zenrl.common.signals import on_stop_signals
        from zenrl.common.transport import Node, open_router
        from zenrl.replay.store import machine_memory

        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(self.cfg.model_dump(mode="json"), sort_keys=False))
        if self.agents:
            from zenrl.launcher.league_run import read_applied

            (self.run_dir / "agents").mkdir(exist_ok=True)
            for aid, acfg in self.agents.items():
                (self.run_dir / "agents" / f"{aid}.yaml").write_text(yaml.safe_dump(acfg.model_dump(mode="json"),
                                                                                    sort_keys=False))
            self.applied = read_applied(self.run_dir)
        on_stop_signals(self._on_signal)
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
        node = Node(session=router)
        try:
            write_launcher_info(self.run_dir, self.run_id, self.endpoint)
            log.info("run %s: router on %s, logs in %s (zenrl status %s)", self.run_id, listen, self.run_dir / "logs",
                     self.run_dir)
            self._metrics = MetricsWriter(self.run_dir)
            self._listen(node)
            self.children = self._plan()
            for line in crowding_warnings(sum(c.role == "actor" for c in self.children), len(every_cpu),
                                          machine_memory()):
                log.warning("%s", line)
            for c in self.children:
                self._spawn(c)
            self._loop()
        except KeyboardInterrupt:
            self._stop_with("interrupted by user (Ctrl-C)")
        finally:
            self.stop.set()
            try:
                self._terminate()
                self._write_summary(final=True)
                remove_launcher_info(self.run_dir)
                if self._metrics is not None:
                    self._metrics.close()
            finally:
                node.close()  # an open session's threads would keep this process from exiting
        log.info("run %s stopped: %s", self.run_id, self.stop_reason or "stopped")
        return self.exit_code

    def _loop(self) -> None:
        live = None
        if self.cfg.progress:
            from rich.console import Console

            console = Console(stderr=True)
            if console.is_terminal:
                from rich.live import Live

                live = Live(self._table(), console=console, refresh_per_second=2, transient=False)
                live.start()
        last_progress = last_summary = time.monotonic()
        trouble = TroubleWatch()
        endless_said = False
        try:
            while not self.stop.wait(0.5):
                p = self.progress
                p.tick_rate()
                news = trouble.news(p.troubles())
                if news:
                    log.warning("%s", news)
                if not endless_said and not self.agents:
                    line = endless_warning(p, self.cfg.env.id)
                    if line:
                        log.warning("%s", line)
                        endless_said = True
                if self.updates_at_start is None and "updates" in p.learner:
                    self.updates_at_start = int(p.learner["updates"])
                self._supervise()
                self._watch_silent()
                self._apply_resets()
                self._check_done()
                if live is not None:
                    live.update(self._table())
                if time.monotonic() - last_progress >= PROGRESS_EVERY_S:
                    last_progress = time.monotonic()
                    line = p.status_line()
                    if live is None and self.cfg.progress:
                        log.info("progress %s", json.dumps(line))
                    if p.segment_env_steps:
                        self._metrics.write("launcher", p.env_steps, {"env_steps": p.env_steps,
                                                                      "env_steps_per_s": p.env_steps_rate})
                if time.monotonic() - last_summary >= SUMMARY_EVERY_S:
                    last_summary = time.monotonic()
                    self._write_summary()
        finally:
            if live is not None:
                live.update(self._table())
                live.stop()
            elif self.cfg.progress:  # the final counters, however short the run
                log.info("progress %s", json.dumps(self.progress.status_line()))

    # -- league runs -------------------------------------------------------------------------
    def _on_league_stats(self, key: str, payload: bytes) -> None:
        from zenrl.common import protocol as P
        from zenrl.common.league_reset import generations

        try:
            m = P.Stats.decode(payload)
        except P.ProtocolError:
            return
        seen = generations(m.values)
        with self.progress.lock:
            self._league_seen.update({a: g for a, g in seen.items() if a in self.agents})
            self.progress.league = {k: v for k, v in m.values.items() if not k.startswith(("errors/", "rejected_"))}

    def _apply_resets(self) -> None:
        """Restart an agent afresh whose generation the league moved past the applied one."""
        from zenrl.launcher.league_run import exploiter_init, write_applied

        with self.progress.lock:
            seen = dict(self._league_seen)
        for aid, gen in seen.items():
            applied = self.applied.get(aid)
            if applied is None:  # first word from the league in this run: nothing to catch up on
                self.applied[aid] = gen
                write_applied(self.run_dir, self.applied)
                continue
            if gen <= applied or self.stop.is_set():
                continue
            log.info("league: %s reset to generation %d: restarting its replay, learner and actors afresh", aid, gen)
            old = [c for c in self.children if c.agent == aid]
            self._terminate(old, grace_s=5.0)  # what they hold is discarded: no long wait for a final save
            import shutil

            shutil.rmtree(self.run_dir / "agents" / (self.agents[aid].run_id or ""), ignore_errors=True)
            self.children = [c for c in self.children if c.agent != aid]
            fresh = self._agent_children(aid, fresh=True, init=exploiter_init(self.agents, aid, self.run_dir))
            for c in fresh:
                self._spawn(c)
            self.children.extend(fresh)
            self.applied[aid] = gen
            write_applied(self.run_dir, self.applied)

    def _table(self):
        return render_table(self.run_id, self.progress.status_line(), self.stop_reason)

    def summary(self) -> dict[str, Any]:
        """``summary.json``: the whole run, over this launch and the earlier segments of a
        resumed run (``segments``, oldest first)."""
        p = self.progress
        now = time.monotonic()
        reason = self.stop_reason or RUNNING
        updates = p.learner.get("updates")
        segment = {"started_at": self.started_at, "ended_at": time.time(), "wall_s": now - p.start,
                   "env_steps": p.segment_env_steps, "updates_at_start": self.updates_at_start,
                   "updates_at_end": updates, "stop_reason": reason, "resumed": self.resume,
                   "startup_s": None if p.first_step_t is None else p.first_step_t - p.start,
                   "restarts": {c.name: c.restarts for c in self.children}}
        evals = (self.earlier_evals + [dict(e, segment=len(self.earlier)) for e in p.evals])[-MAX_KEPT_EVALS:]
        solved = self.earlier_solved
        if solved is None and p.first_solved is not None:
            solved = dict(p.first_solved, segment=len(self.earlier))
        return {"run_id": self.run_id, "stop_reason": reason, "wall_s": p.elapsed_s(now),
                "startup_s": segment["startup_s"], "env_steps": p.env_steps, "learner": p.learner,
                "replay": p.replay, **({"replays": p.replays} if len(p.replays) > 1 else {}),
                **({"league": p.league} if p.league else {}), "evals": evals,
                "evals_total": self.earlier_evals_total + p.evals_total, "target_return": self.cfg.target_return,
                "solved": solved is not None, "first_solved": solved,
                "solve_s_since_first_step": None if solved is None else solved.get("since_first_step"),
                "restarts": segment["restarts"], "segments": [*self.earlier, segment],
                # this launch's actors' counts of their envs' problems (zenrl.actor.env_guard)
                "env_troubles": {k: v for k, v in p.troubles().items() if k in ENV_TROUBLES}}

    def _write_summary(self, final: bool = False) -> None:
        """``summary.json``; where it cannot be written (a full disk) the terminal says so, at
        most once a minute while the run goes on, and the run goes on: its children's
        checkpoints, logs and metrics on the same disk then fail as well, which they survive."""
        try:
            write_json_atomic(self.run_dir / SUMMARY_FILE, self.summary())
        except OSError as e:
            now = time.monotonic()
            if final or self._summary_said is None or now - self._summary_said >= DISK_TROUBLE_EVERY_S:
                self._summary_said = now
                log.error("cannot write %s: %s. %s", self.run_dir / SUMMARY_FILE, e,
                          "This run's summary is lost; its last checkpoint is the newest in checkpoints/" if final
                          else "The run goes on, but its checkpoints, logs and metrics on that disk fail too "
                               "until there is room")


def launch(cfg: RunConfig, resume_dir: str | None = None, exporter_port: int | None = None) -> int:
    """Entry point of ``zenrl run``: the env is checked before anything is created on disk."""
    if resume_dir is not None:
        rd = Path(resume_dir)
        cfg = cfg.model_copy(update={"run_id": rd.name, "runs_dir": str(rd.parent)})
    check_env(cfg)
    if cfg.league.enabled:
        from zenrl.launcher.league_run import check_league

        check_league(cfg)
    if exporter_port is not None and not _port_free("0.0.0.0", exporter_port):
        raise ConfigError(f"--exporter-port {exporter_port}: the port is in use")
    launcher = Launcher(cfg, resume=resume_dir is not None, exporter_port=exporter_port)
    lock = lock_run_folder(launcher.run_dir)  # held until this launch is over
    try:
        if resume_dir is None and holds_a_run(launcher.run_dir):
            raise ConfigError(f"run folder {launcher.run_dir} holds a run already (run id {launcher.run_id!r}): "
                              f"continue it with zenrl run --resume {launcher.run_dir}, or give another --run-id")
        return launcher.run()
    finally:
        unlock_run_folder(lock)
