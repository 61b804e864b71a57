"""What ``zenrl run`` shows while it runs: the figures heard from the run's processes (Zenoh
``stats``, ``episodes`` and ``eval`` keys) and the live table or periodic log line made of them."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenrl.common import protocol as P

RATE_WINDOW_S = 5.0  # env steps/s in the progress display is measured over this window
#: evaluations kept for summary.json, the newest (metrics.jsonl holds every one): at ~250
#: bytes each, an evaluator every 0.5 s would otherwise grow the file and the launcher's
#: memory ~40 MB a day, rewritten every 30 s
MAX_KEPT_EVALS = 1000


@dataclass
class Progress:
    """What the monitor has heard. A resumed run starts from the totals of its earlier segments
    (``base_env_steps``, ``base_elapsed_s``), so the display continues where they stopped."""

    start: float = field(default_factory=time.monotonic)
    base_env_steps: int = 0
    base_elapsed_s: float = 0.0
    first_step_t: float | None = None
    actor_steps: dict[str, int] = field(default_factory=dict)
    learner: dict[str, Any] = field(default_factory=dict)
    replay: dict[str, Any] = field(default_factory=dict)
    #: each replay service's last stats by id (several with replay.shards > 1; ``replay`` then
    #: sums their size, capacity and inserts)
    replays: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: a league run: the league service's last stats
    league: dict[str, Any] = field(default_factory=dict)
    #: each actor's counts of its envs' problems (``env_steps_cut``, ...: zenrl.actor.env_guard)
    actor_env: dict[str, dict[str, int]] = field(default_factory=dict)
    #: monotonic time of each actor's last stats (the launcher restarts one that falls silent)
    actor_seen: dict[str, float] = field(default_factory=dict)
    #: monotonic time of the evaluator's last stats (it reports every evaluator.interval_s)
    evaluator_seen: float | None = None
    #: the newest MAX_KEPT_EVALS evaluations; ``evals_total`` counts every one
    evals: list[dict[str, Any]] = field(default_factory=list)
    evals_total: int = 0
    #: set by the launcher (``target_return``): the first evaluation at or above it is kept in
    #: ``first_solved`` however many follow
    target: float | None = None
    first_solved: dict[str, Any] | None = None
    recent_returns: list[float] = field(default_factory=list)
    env_steps_rate: float = 0.0
    # (time, total env steps) whenever the total changed, the last RATE_WINDOW_S seconds of them
    # (plus one older as the base): actors report about once a second, so a rate over two
    # consecutive 0.5 s ticks was mostly 0 and otherwise double
    _steps_seen: deque[tuple[float, int]] = field(default_factory=deque)
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def segment_env_steps(self) -> int:
        """Env steps of this launch only."""
        return sum(self.actor_steps.values())

    @property
    def env_steps(self) -> int:
        """Env steps of the whole run (earlier segments included)."""
        return self.base_env_steps + self.segment_env_steps

    def elapsed_s(self, now: float | None = None) -> float:
        """Wall time of the whole run (earlier segments included)."""
        return self.base_elapsed_s + ((time.monotonic() if now is None else now) - self.start)

    def on_message(self, key: str, payload: bytes) -> None:
        try:
            msg = P.decode_any(payload)
        except P.ProtocolError:
            return
        with self.lock:
            if isinstance(msg, P.Stats):
                if msg.role == "actor":
                    self.actor_seen[msg.id] = time.monotonic()
                    self._actor(msg.id, int(msg.values.get("env_steps", 0)))
                    env = {k: int(v) for k, v in msg.values.items() if k in ENV_TROUBLES and isinstance(v, (int, float))}
                    if env:
                        self.actor_env[msg.id] = env
                elif msg.role == "evaluator":
                    self.evaluator_seen = time.monotonic()
                elif msg.role == "learner":
                    self.learner = dict(msg.values)
                elif msg.role == "replay":
                    self.replays[msg.id] = dict(msg.values)
                    if len(self.replays) == 1:
                        self.replay = dict(msg.values)
                    else:  # a sharded replay: its counts, sizes, rates and mass summed over the shards
                        tot: dict[str, Any] = {}
                        for v in self.replays.values():
                            for k, x in v.items():
                                if isinstance(x, (int, float)) and not isinstance(x, bool):
                                    tot[k] = tot.get(k, 0) + x
                        self.replay = {**tot, "shards": len(self.replays)}
            elif isinstance(msg, P.EpisodeStats):
                self._actor(msg.actor_id, msg.env_steps)
                self.recent_returns = (self.recent_returns + [float(x) for x in msg.returns])[-100:]
            elif isinstance(msg, P.EvalResult):
                e = {"t": self.elapsed_s(), "version": msg.version, "updates": msg.updates,
                     "env_steps": self.env_steps, "mean": float(msg.returns.mean()),
                     "std": float(msg.returns.std()), "n": int(msg.returns.size),
                     "win_rate": None if msg.outcomes is None else float((msg.outcomes == 1).mean()),
                     "since_first_step": None if self.first_step_t is None else time.monotonic() - self.first_step_t}
                self.evals.append(e)
                self.evals_total += 1
                if self.target is not None and self.first_solved is None and e["mean"] >= self.target:
                    self.first_solved = e
                if len(self.evals) > MAX_KEPT_EVALS:
                    del self.evals[0]

    def on_actor_stats(self, key: str, payload: bytes) -> None:
        """An actor's stats in a league run's other agent: only that it was heard (its env steps
        and troubles are its agent's, not the main agent's figures this display shows)."""
        try:
            msg = P.decode_any(payload)
        except P.ProtocolError:
            return
        if isinstance(msg, P.Stats) and msg.role == "actor":
            with self.lock:
                self.actor_seen[msg.id] = time.monotonic()

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

    def troubles(self) -> dict[str, Any]:
        """What went wrong with the run's data so far: the actors' envs (:data:`ENV_TROUBLES`,
        summed), the chunks or unrolls the replay and the learner rejected, the sources they
        hold in quarantine."""
        with self.lock:
            out: dict[str, Any] = {k: sum(a.get(k, 0) for a in self.actor_env.values()) for k in ENV_TROUBLES}
            out["rejected"] = int(self.replay.get("rejected_total") or 0) + int(self.learner.get("rejected_total") or 0)
            reasons: dict[str, int] = {}
            for src in (self.replay, self.learner):
                for k, v in src.items():
                    if k.startswith("rejected_") and k != "rejected_total" and "/" not in k and isinstance(v, int) and v:
                        reasons[k[len("rejected_"):]] = reasons.get(k[len("rejected_"):], 0) + v
            out["reasons"] = reasons
            q = [str(src.get("quarantined_sources") or "") for src in (self.replay, self.learner) if src.get("quarantined")]
            out["quarantined"] = ", ".join(x for x in q if x)
        return out

    @property
    def last_eval(self) -> float | None:
        return self.evals[-1]["mean"] if self.evals else None

    def status_line(self) -> dict[str, Any]:
        """The figures of the live display, JSON-ready (win rate as a fraction)."""
        return {"elapsed_s": round(self.elapsed_s(), 1), "env_steps": self.env_steps,
                "env_steps_per_s": round(self.env_steps_rate, 1), "updates": self.learner.get("updates", 0),
                "updates_per_s": round(float(self.learner.get("updates_per_s", 0.0)), 1),
                "replay_size": self.replay.get("size", 0), "weights_version": self.learner.get("version", 0),
                "train_return_100": round(float(np.mean(self.recent_returns)), 1) if self.recent_returns else None,
                "eval_return": None if self.last_eval is None else round(self.last_eval, 1),
                **({"eval_win_rate": round(self.evals[-1]["win_rate"], 3)}
                   if self.evals and self.evals[-1].get("win_rate") is not None else {}),
                **({f"league_{k.replace('/', '_')}": v for k, v in self.league.items()
                    if k in ("players", "snapshots", "results_total") or k.startswith("generation/")}
                   if self.league else {})}


#: the counts an actor reports of its envs' problems (zenrl.actor.env_guard), and what each means
ENV_TROUBLES = {"env_steps_cut": "steps cut for NaN or Inf", "env_obs_clipped": "observations clipped to the env's bounds",
                "env_resets_retried": "resets retried for NaN or Inf"}
#: the launcher repeats a warning about the run's data at most this often
TROUBLE_EVERY_S = 30.0


class TroubleWatch:
    """Turns :meth:`Progress.troubles` into a warning line for the launcher's terminal when a
    count has grown, at most once per :data:`TROUBLE_EVERY_S`: the details are in the roles'
    logs, where a user running ``zenrl run`` would not look unless told."""

    def __init__(self, every_s: float = TROUBLE_EVERY_S) -> None:
        self.every_s = every_s
        self.seen: dict[str, int] = {}
        self.last: float | None = None

    def news(self, t: dict[str, Any], now: float | None = None) -> str | None:
        now = time.monotonic() if now is None else now
        if self.last is not None and now - self.last < self.every_s:
            return None
        counts = {k: int(t.get(k, 0)) for k in (*ENV_TROUBLES, "rejected")}
        grown = [k for k, v in counts.items() if v > self.seen.get(k, 0)]
        if not grown:
            return None
        parts = [f"{counts[k]:,} {ENV_TROUBLES[k]}" for k in ENV_TROUBLES if k in grown]
        line = ""
        if parts:
            line = "the actors' envs misbehave: " + ", ".join(parts) + " (logs/actor-*.log say which and why)"
        if "rejected" in grown:
            why = ", ".join(f"{k} {v:,}" for k, v in sorted(t.get("reasons", {}).items(), key=lambda kv: -kv[1])[:3])
            rej = f"{counts['rejected']:,} chunks or unrolls rejected ({why or 'see the logs'})"
            if t.get("quarantined"):
                rej += f"; quarantined: {str(t['quarantined'])[:120]}"
            line = (line + "; " if line else "") + rej + " (logs/replay*.log, logs/learner.log)"
        self.seen, self.last = counts, now
        return line


#: a run whose actors have stepped this long without one episode ending is told so, once
ENDLESS_AFTER_S = 60.0


def endless_warning(p: Progress, env_id: str, now: float | None = None, after_s: float = ENDLESS_AFTER_S) -> str | None:
    """The line for a run whose envs have stepped for ``after_s`` since the first env step with no
    episode ended (no training return, no evaluation): an env without a step limit whose episodes
    need not end. None otherwise."""
    now = time.monotonic() if now is None else now
    with p.lock:
        if p.first_step_t is None or now - p.first_step_t < after_s or p.recent_returns or p.evals:
            return None
        steps = p.env_steps
    return (f"no episode has ended in {now - p.first_step_t:.0f} s ({steps:,} env steps): {env_id}'s episodes may "
            "never end (no step limit), and then no return is reported and no evaluation finishes; set "
            "env.max_episode_steps")


#: memory an actor process holds of its own (private, not shared with the others: Python, torch,
#: its envs), at least: a CartPole actor's is ~160 MB
ACTOR_PRIVATE_BYTES = 160 << 20
#: actor processes per usable CPU above which a run is told it has too many
ACTORS_PER_CPU = 4


def crowding_warnings(actors: int, cpus: int, memory: tuple[int, str] | None) -> list[str]:
    """Lines for a run that starts more actor processes than the machine holds: more than
    ACTORS_PER_CPU per usable CPU, or whose actors alone would take more than half of ``memory``
    (:func:`zenrl.replay.store.machine_memory`) at ACTOR_PRIVATE_BYTES each."""
    out = []
    fewer = "fewer actors with more envs each (actor.envs_per_actor) step as many envs for less"
    if cpus > 0 and actors > ACTORS_PER_CPU * cpus:
        out.append(f"{actors} actor processes on {cpus} CPU{'s' if cpus > 1 else ''}: each takes ~2 s of CPU to "
                   f"start and they share the CPUs with the learner and the replay; {fewer}")
    if memory is not None and actors * ACTOR_PRIVATE_BYTES > memory[0] // 2:
        need, have = actors * ACTOR_PRIVATE_BYTES / (1 << 30), memory[0] / (1 << 30)
        out.append(f"{actors} actor processes take {need:.1f} GiB or more of their own (~{ACTOR_PRIVATE_BYTES >> 20} MB "
                   f"each at least), and {memory[1]} is {have:.1f} GiB"
                   + (": the kernel will kill processes for memory" if need > have else "")
                   + f"; {fewer}")
    return out


def render_table(run_id: str, line: dict[str, Any], stop_reason: str = ""):
    """The live table of :meth:`Progress.status_line` (rates as rates, the win rate in %)."""
    from rich.table import Table

    t = Table(title=f"zenrl run {run_id}", show_header=False)
    for k, v in line.items():
        if v is None:
            text = "-"
        elif k == "eval_win_rate":
            text = f"{v:.0%}"
        else:
            text = str(v)
        t.add_row(k.replace("_", " "), text)
    if stop_reason:
        t.add_row("stopped", stop_reason)
    return t
