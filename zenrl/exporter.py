"""``zenrl exporter``: one run's stats and health as Prometheus metrics on an HTTP port.

One Zenoh client process subscribes ``zenrl/<run>/stats/**``, ``eval`` and ``episodes/*``,
polls the liveliness tokens ``alive/<role>/<id>`` once a second, and renders what it last heard
in the Prometheus text format (``/metrics``) through ``prometheus_client`` whenever Prometheus
scrapes it::

    zenrl exporter --config run.yaml --run-id RUN --router tcp/host:7447 --port 9464
    zenrl run --config run.yaml --exporter-port 9464      # the same, as one more child

**Why one exporter per run, not an endpoint in every process.** Zenoh already fans every
process's stats in to one key space: whoever subscribes ``stats/**`` hears all of them, so a
second, HTTP fan-in path inside each process would duplicate what the bus does. One exporter is
one scrape target per run, whatever the number of actors, so Prometheus needs no service
discovery of short-lived actor processes (actor ids change with every restart). And the
processes need no listening port: an actor behind NAT, in a container without published ports
or on another site reaches the router outbound and is still scraped. The cost is one more
subscriber of messages published every few seconds, and staleness bounded by the roles' own
stats intervals (2 s by default), which is below any useful scrape interval.

**Conventions.** Every name starts ``zenrl_``, carries its unit (``_seconds``, ``_bytes``,
``_items``, ``_versions``, ``_ratio``), counters end ``_total``; labels ``run``, ``role``, ``id``
(plus ``reason``, ``type``, ``thread``, ``source`` where a stat is per reason, error type, thread
or sender). A process's running totals (``updates``, ``env_steps``, ``inserted_total``) are
counters: they restart at zero with the process (the learner's continue from its checkpoint),
which ``rate()`` handles. Stats the table below does not name still appear, as
``zenrl_stat{stat="<name>"}`` gauges, so a new stat is visible before it gets a proper name.

**Bounded series.** Metrics are rendered at scrape time by :class:`RunCollector` from the
latest stats of each process (no registered Gauge per value): a process's series exist while
its liveliness token does (and for a few seconds after its last stats, so a process's last
report is not lost to a race with its token), and vanish with it. Per-reason, per-type,
per-thread and per-source labels come from bounded sets in the roles (rejection reasons, error
types, thread names, the replay's top rejecting sources). Run-level series (processes alive
per role, restarts per role, the learner's last update time, eval results) do not depend on
any one process and survive its death, which is what the alert rules need
(deploy/monitoring/rules.yml, docs/monitoring.md).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector, CollectorRegistry

from zenrl.common import protocol as P
from zenrl.common.errors import ConfigError

log = logging.getLogger("zenrl.exporter")

#: default HTTP port of the exporter
DEFAULT_PORT = 9464
#: the roles whose live processes are counted even when none is alive (0 is a value to alert on)
ROLES = ("actor", "learner", "replay", "evaluator")
#: a process's series are kept this long after its last stats even without its token
GRACE_S = 10.0
#: at most this many (role, id) pairs are remembered to tell a restart from a new process
MAX_REMEMBERED = 10_000

COUNTER, GAUGE = "counter", "gauge"

#: stats value -> (metric name without the ``zenrl_<role>_`` prefix, kind, help), per role.
#: Counters are named without ``_total`` here: prometheus_client appends it.
STATS: dict[str, dict[str, tuple[str, str, str]]] = {
    "actor": {
        "env_steps": ("env_steps", COUNTER, "Env steps this actor process has taken."),
        "policy_version": ("weights_version", GAUGE, "Version of the weights the actor acts with."),
        "slot": ("slot", GAUGE, "The actor's exploration slot."),
        "sent_transitions": ("sent_transitions", COUNTER, "Transitions sent to the replay."),
        "sent_chunks": ("sent_chunks", COUNTER, "Transition chunks sent to the replay."),
        "failed_chunks": ("failed_chunks", COUNTER, "Chunks whose send failed (retried from the backlog)."),
        "undelivered_chunks": ("undelivered_chunks", COUNTER, "Chunks no replay could take (lost)."),
        "split_chunks": ("split_chunks", COUNTER, "Chunks over replay.max_chunk_bytes sent as two halves."),
        "oversized_chunks": ("oversized_chunks", COUNTER, "Chunks over replay.max_chunk_bytes that could not be split (frame mode, one item): not sent."),
        "backlog_chunks": ("backlog_chunks", GAUGE, "Chunks waiting in the actor's send backlog."),
        "weights_rejected": ("rejected_weights", COUNTER, "Weights messages the actor refused."),
        "sent_gradients": ("sent_gradients", COUNTER, "Gradient messages sent (A3C workers)."),
        "guard_actions": ("guard_actions", COUNTER, "Steps acted with the match env's guard turn instead of the policy's action (actor.guard_share)."),
    },
    "learner": {
        "updates": ("updates", COUNTER, "Gradient updates applied by the learner."),
        "version": ("weights_version", GAUGE, "Version of the learner's latest weights."),
        "updates_per_s": ("updates_per_second", GAUGE, "Updates per second over the learner's last report interval."),
        "transitions_per_s": ("transitions_per_second", GAUGE, "Transitions trained on per second (Ape-X)."),
        "env_steps_per_s": ("env_steps_per_second", GAUGE, "Env steps trained on per second (A3C)."),
        "env_steps_trained": ("env_steps_trained", COUNTER, "Env steps trained on (A3C)."),
        "transitions_consumed": ("transitions_consumed", COUNTER, "Transitions trained on (Ape-X)."),
        "policy_lag": ("policy_lag_versions", GAUGE, "Mean versions between the data's policy and the learner's."),
        "loss": ("loss", GAUGE, "Mean loss over the last report interval."),
        "q_mean": ("q_mean", GAUGE, "Mean Q(s, a) over the last report interval."),
        "guard_fired": ("guard_fired_ratio", GAUGE, "Share of sampled states where the match env's guard rule fires (learner.guard_imitation)."),
        "guard_margin_loss": ("guard_margin_loss", GAUGE, "Mean large-margin imitation loss on the states where the guard rule fires (learner.guard_imitation)."),
        "grad_norm": ("grad_norm", GAUGE, "Mean gradient norm (before clipping) over the last report interval."),
        "beta": ("per_beta", GAUGE, "Prioritized replay's importance-sampling exponent."),
        "lr": ("learning_rate", GAUGE, "Current learning rate."),
        "wait_fraction": ("wait_ratio", GAUGE, "Fraction of the last interval spent waiting for samples."),
        "not_ready": ("sample_not_ready", COUNTER, "Sample requests the replay answered not ready."),
        "sample_timeouts": ("sample_timeouts", COUNTER, "Sample requests that timed out."),
        "sample_errors": ("sample_errors", COUNTER, "Sample requests that failed."),
        "send_dropped": ("send_dropped", COUNTER, "Outgoing messages dropped by the sender (queue full)."),
        "send_failed": ("send_failed", COUNTER, "Outgoing messages whose send failed."),
        "skipped_updates": ("skipped_updates", COUNTER, "Updates skipped by the guard (non-finite loss or gradient)."),
        "rollbacks": ("rollbacks", COUNTER, "Rollbacks to the last good parameters."),
        "params_unpublishable": ("unpublishable_params", COUNTER, "Weights not published because they were not finite."),
        "stale_dropped": ("stale_gradients_dropped", COUNTER, "Gradients dropped as too stale (A3C)."),
        "unknown_version_dropped": ("unknown_version_dropped", COUNTER, "Gradients of an unknown version dropped (A3C)."),
        "queue_dropped": ("queue_dropped", COUNTER, "Gradients dropped on a full queue (A3C)."),
        "queue_len": ("queue_length_messages", GAUGE, "Gradient messages waiting in the learner's queue (A3C)."),
        "params_restored": ("params_restored", COUNTER, "Parameters restored after a bad update (A3C)."),
        "poisoned_items": ("poisoned_items", COUNTER, "Sampled items left out of an update as poison (out-of-range observation, non-finite value or TD, or found by bisection) and reported to the replay."),
        "repaired_updates": ("repaired_updates", COUNTER, "Updates taken on the rest of a batch after poisoned items were left out."),
        "poisoned_unrolls": ("poisoned_unrolls", COUNTER, "Unrolls left out of an update because they alone made it non-finite (IMPALA)."),
    },
    "replay": {
        "size": ("size_items", GAUGE, "Transitions held by the replay."),
        "capacity": ("capacity_items", GAUGE, "Transitions the replay can hold."),
        "bytes": ("size_bytes", GAUGE, "Bytes of stored transitions."),
        "inserted_total": ("inserted_items", COUNTER, "Transitions inserted."),
        "inserts_per_s": ("inserted_items_per_second", GAUGE, "Transitions inserted per second over the replay's last interval."),
        "sample_batches_per_s": ("sample_batches_per_second", GAUGE, "Sample batches served per second."),
        "sample_batches_total": ("sampled_batches", COUNTER, "Sample batches served."),
        "stale_priority_updates": ("stale_priority_updates", COUNTER, "Priority updates for evicted items."),
        "not_ready_replies": ("not_ready_replies", COUNTER, "Sample requests answered not ready."),
        "priority_mass": ("priority_mass", GAUGE, "Sum of the stored items' sampling priorities (p^alpha): a sharded learner draws from each shard in proportion to it."),
        "priority_updates_total": ("priority_update_messages", COUNTER, "Priority update messages taken from the learner."),
        "priority_keys_total": ("priority_update_keys", COUNTER, "Keys named in the priority updates taken."),
        "poison_removed": ("poison_removed_items", COUNTER, "Items the learner reported as poison, removed from sampling and charged to their sender."),
        "poison_stale": ("poison_stale_keys", COUNTER, "Poisoned keys reported after their item was evicted or removed."),
        "dropped_queue_full": ("dropped_queue_full", COUNTER, "Chunks dropped while the ingest thread was stuck (its inbox full)."),
        "dropped_quarantined": ("dropped_quarantined", COUNTER, "Chunks dropped from quarantined senders."),
        "ingest_queue": ("ingest_queue_chunks", GAUGE, "Chunks the ingest thread holds, not yet inserted."),
        "restored_items": ("restored_items", GAUGE, "Transitions restored from the replay log at start."),
        "quarantined": ("quarantined_sources", GAUGE, "Senders quarantined now."),
        "quarantines_total": ("quarantines", COUNTER, "Quarantines imposed since the replay started."),
        "frames_stored": ("frames_stored", GAUGE, "Image frames stored (frame replay)."),
        "frames_unresolved_items": ("frames_unresolved_items", GAUGE, "Items whose frames are not all stored yet."),
        "evicted_by_frames": ("evicted_by_frames", COUNTER, "Items evicted with their frames."),
        "log_bytes_written": ("log_written_bytes", COUNTER, "Bytes written to the replay log."),
        "log_disk_bytes": ("log_disk_bytes", GAUGE, "Bytes the replay log takes on disk."),
        "log_torn_records": ("log_torn_records", COUNTER, "Torn records found in the replay log."),
        "durable_through": ("durable_through", GAUGE, "Sequence number the replay log is durable through."),
        "durable_degraded": ("durable_degraded", GAUGE, "1 while the replay log cannot be written (disk full, EIO): ingest goes on in memory."),
        "durable_disk_errors": ("durable_disk_errors", COUNTER, "Failed writes, fsyncs or renames of the replay log."),
        "durable_backlog_items": ("durable_backlog_items", GAUGE, "Transitions inserted but not yet logged while the log is degraded."),
        "durable_lost_items": ("durable_lost_items", COUNTER, "Transitions dropped from the degraded log's backlog (over replay.durable_backlog_bytes)."),
        "durable_resumes": ("durable_resumes", COUNTER, "Times the replay log resumed after a disk error."),
        "log_corrupt_records": ("log_corrupt_records", COUNTER, "Bad records skipped inside the replay log at start."),
        "log_skipped_items": ("log_skipped_items", GAUGE, "Logged transitions not restored at start (before a gap in the log's keys)."),
        "log_snapshot_unreadable": ("log_snapshot_unreadable", COUNTER, "Priority snapshots found unreadable at start."),
    },
}

#: values handled by the generic health/fault rendering (any role), not by ``zenrl_stat``
HANDLED = {"errors_total", "stalled", "quarantined_sources", "rejected_total"}


def _num(v: Any) -> float | None:
    if isinstance(v, bool):
        return float(v)
    if isinstance(v, (int, float)):
        return float(v)
    return None


@dataclass
class _Proc:
    """What the exporter last heard from one process."""

    values: dict[str, Any] = field(default_factory=dict)
    heard_at: float | None = None           # exporter's clock (not the sender's: clocks differ)
    episodes: int = 0
    episode_return_mean: float | None = None
    epsilon: float | None = None


class RunState:
    """Thread-safe store of one run's latest stats, eval results and live processes, fed by
    Zenoh callbacks (:meth:`on_stats`, :meth:`on_eval`, :meth:`on_episodes`) and the liveliness
    poller (:meth:`set_alive`). ``clock``: wall-clock seconds (injectable for tests)."""

    def __init__(self, run_id: str, expected_actors: int | None = None, clock: Callable[[], float] = time.time,
                 grace_s: float = GRACE_S) -> None:
        self.run_id = run_id
        self.expected_actors = expected_actors
        self.clock = clock
        self.grace_s = grace_s
        self.lock = threading.Lock()
        self.procs: dict[tuple[str, str], _Proc] = {}
        self.alive: set[tuple[str, str]] = set()
        self.polled = False
        self.remembered: OrderedDict[tuple[str, str], None] = OrderedDict()
        self.restarts: dict[str, int] = {}
        self.learner_updates: dict[str, float] = {}
        # no update heard yet: count from the exporter's start (the alert's clock starts here)
        self.last_update_at = clock()
        self.messages = 0
        self.undecodable = 0
        self.eval: P.EvalResult | None = None
        self.eval_at: float | None = None
        self.eval_rounds = 0

    # -- inputs -------------------------------------------------------------------------------
    def on_stats(self, _key: str, payload: bytes) -> None:
        try:
            m = P.Stats.decode(payload)
        except P.ProtocolError:
            with self.lock:
                self.undecodable += 1
            return
        now = self.clock()
        with self.lock:
            self.messages += 1
            p = self.procs.setdefault((m.role, m.id), _Proc())
            p.values, p.heard_at = dict(m.values), now
            if m.role == "learner":
                u = _num(m.values.get("updates"))
                if u is not None:
                    before = self.learner_updates.get(m.id)
                    if before is not None and u > before:
                        self.last_update_at = now
                    self.learner_updates[m.id] = u

    def on_eval(self, _key: str, payload: bytes) -> None:
        try:
            m = P.EvalResult.decode(payload)
        except P.ProtocolError:
            with self.lock:
                self.undecodable += 1
            return
        with self.lock:
            self.eval, self.eval_at = m, self.clock()
            self.eval_rounds += 1

    def on_episodes(self, _key: str, payload: bytes) -> None:
        try:
            m = P.EpisodeStats.decode(payload)
        except P.ProtocolError:
            with self.lock:
                self.undecodable += 1
            return
        with self.lock:
            p = self.procs.setdefault(("actor", m.actor_id), _Proc())
            p.episodes += int(m.returns.size)
            if m.returns.size:
                p.episode_return_mean = float(m.returns.mean())
            p.epsilon = float(m.epsilon)
            if p.heard_at is None:
                p.heard_at = self.clock()

    def set_alive(self, alive: Iterable[tuple[str, str]]) -> None:
        """The processes whose tokens the router holds now. A pair seen before that comes back
        after it was gone counts as a restart of its role; processes gone (no token, no stats
        within ``grace_s``) are forgotten."""
        now_alive = set(alive)
        now = self.clock()
        with self.lock:
            for pair in now_alive - self.alive:
                if self.polled and pair in self.remembered:
                    self.restarts[pair[0]] = self.restarts.get(pair[0], 0) + 1
                self.remembered[pair] = None
                self.remembered.move_to_end(pair)
            while len(self.remembered) > MAX_REMEMBERED:
                self.remembered.popitem(last=False)
            self.alive, self.polled = now_alive, True
            for pair in list(self.procs):
                p = self.procs[pair]
                if pair not in now_alive and (p.heard_at is None or now - p.heard_at > self.grace_s):
                    del self.procs[pair]
                    if pair[0] == "learner":
                        self.learner_updates.pop(pair[1], None)

    # -- output -------------------------------------------------------------------------------
    def collect(self) -> list[Metric]:
        """The metric families of this run now (called at scrape time)."""
        now = self.clock()
        with self.lock:
            return list(_render(self, now))


class _Families:
    """Metric families created on first use, in a stable order."""

    def __init__(self) -> None:
        self.fams: dict[str, Metric] = {}

    def add(self, name: str, kind: str, help_: str, labels: dict[str, str], value: float) -> None:
        fam = self.fams.get(name)
        if fam is None:
            cls = CounterMetricFamily if kind == COUNTER else GaugeMetricFamily
            fam = self.fams[name] = cls(name, help_, labels=list(labels))
        fam.add_metric(list(labels.values()), value)


def _render(s: RunState, now: float) -> Iterator[Metric]:
    f = _Families()
    run = s.run_id
    shown = sorted(set(s.alive) | set(s.procs))
    learner_version = max((v for (r, _), p in s.procs.items() if r == "learner"
                           for v in [_num(p.values.get("version"))] if v is not None), default=None)
    per_role = {r: 0 for r in ROLES}
    for role, _ in s.alive:
        per_role[role] = per_role.get(role, 0) + 1
    for role, n in sorted(per_role.items()):
        f.add("zenrl_processes_alive", GAUGE, "Processes of a role whose liveliness token the router holds.",
              {"run": run, "role": role}, n)
    if s.expected_actors is not None:
        f.add("zenrl_actors_expected", GAUGE, "Actor processes the run is configured for.", {"run": run},
              s.expected_actors)
    for role in sorted(set(per_role) | set(s.restarts)):
        f.add("zenrl_process_restarts", COUNTER,
              "Processes of a role that came back (their token reappeared) since the exporter started.",
              {"run": run, "role": role}, s.restarts.get(role, 0))
    f.add("zenrl_learner_last_update_timestamp_seconds", GAUGE,
          "Unix time the learner's update count last grew (the exporter's start until then).", {"run": run},
          s.last_update_at)
    f.add("zenrl_exporter_stats_messages", COUNTER, "Stats messages the exporter received.", {"run": run},
          s.messages)
    f.add("zenrl_exporter_undecodable_messages", COUNTER, "Messages the exporter could not decode.", {"run": run},
          s.undecodable)
    for role, ident in shown:
        lab = {"run": run, "role": role, "id": ident}
        p = s.procs.get((role, ident))
        f.add("zenrl_up", GAUGE, "1 while the process's liveliness token is held by the router.", lab,
              1.0 if (role, ident) in s.alive else 0.0)
        if p is None:
            continue
        if p.heard_at is not None and p.values:
            f.add("zenrl_stats_age_seconds", GAUGE, "Seconds since the process's last stats message.", lab,
                  max(0.0, now - p.heard_at))
        _render_values(f, role, lab, p.values, learner_version)
        if role == "actor" and p.episode_return_mean is not None:
            f.add("zenrl_actor_episodes", COUNTER, "Training episodes the actor finished (heard by the exporter).",
                  lab, p.episodes)
            f.add("zenrl_actor_episode_return_mean", GAUGE, "Mean return of the actor's latest finished episodes.",
                  lab, p.episode_return_mean)
        if role == "actor" and p.epsilon is not None:
            f.add("zenrl_actor_epsilon_ratio", GAUGE, "The actor's mean exploration epsilon.", lab, p.epsilon)
    if s.eval is not None:
        lab = {"run": run, "role": "evaluator"}
        m = s.eval
        f.add("zenrl_eval_return_mean", GAUGE, "Mean greedy return of the latest evaluation round.", lab,
              float(m.returns.mean()))
        f.add("zenrl_eval_return_std", GAUGE, "Standard deviation of the latest round's returns.", lab,
              float(m.returns.std()))
        f.add("zenrl_eval_episodes", GAUGE, "Episodes in the latest evaluation round.", lab, int(m.returns.size))
        f.add("zenrl_eval_weights_version", GAUGE, "Weights version the latest round evaluated.", lab, m.version)
        f.add("zenrl_eval_learner_updates", GAUGE, "Learner updates behind the weights of the latest round.", lab,
              m.updates)
        f.add("zenrl_eval_rounds", COUNTER, "Evaluation rounds heard since the exporter started.", lab,
              s.eval_rounds)
        f.add("zenrl_eval_last_timestamp_seconds", GAUGE, "Unix time the latest evaluation round was heard.", lab,
              s.eval_at or 0.0)
        if m.outcomes is not None:
            f.add("zenrl_eval_win_rate_ratio", GAUGE, "Fraction of the latest round's matches won.", lab,
                  float((m.outcomes == 1).mean()))
    yield from f.fams.values()


def _render_values(f: _Families, role: str, lab: dict[str, str], values: dict[str, Any],
                   learner_version: float | None) -> None:
    table = STATS.get(role, {})
    stalled = values.get("stalled")
    if isinstance(stalled, str):
        names = [x for x in stalled.split(",") if x]
        f.add("zenrl_stalled_threads", GAUGE, "Threads of the process that made no progress for too long.", lab,
              len(names))
        for t in names:
            f.add("zenrl_thread_stalled", GAUGE, "1 for each stalled thread of the process.", {**lab, "thread": t}, 1)
    for k, v in values.items():
        x = _num(v)
        if x is None or k in HANDLED:
            continue
        if k in table:
            suffix, kind, help_ = table[k]
            f.add(f"zenrl_{role}_{suffix}", kind, help_, lab, x)
        elif k.startswith("errors/"):
            f.add("zenrl_errors_by_type", COUNTER, "Exceptions the process's loop caught, by type.",
                  {**lab, "type": k.split("/", 1)[1]}, x)
        elif k.startswith("rejected_from/"):
            f.add(f"zenrl_{role}_rejected_from_source", COUNTER, "Rejected messages of the top rejecting senders.",
                  {**lab, "source": k.split("/", 1)[1]}, x)
        elif k.startswith("rejected_"):
            f.add("zenrl_rejected_messages", COUNTER, "Messages refused by validation, by reason.",
                  {**lab, "reason": k[len("rejected_"):]}, x)
        else:
            f.add("zenrl_stat", GAUGE, "A stats value without a metric of its own (the stat label names it).",
                  {**lab, "stat": k}, x)
    if _num(values.get("errors_total")) is not None:
        f.add("zenrl_errors", COUNTER, "Exceptions the process's loop caught (all types).", lab,
              _num(values["errors_total"]))
    if role == "actor" and learner_version is not None and _num(values.get("policy_version")) is not None:
        # the learner's version is as old as its last report: an actor may already act with newer
        # weights, which is no lag
        f.add("zenrl_actor_policy_lag_versions", GAUGE, "Learner's weights version minus the actor's (at least 0).",
              lab, max(0.0, learner_version - _num(values["policy_version"])))


class RunCollector(Collector):
    """A ``prometheus_client`` collector rendering a :class:`RunState` at scrape time."""

    def __init__(self, state: RunState) -> None:
        self.state = state

    def collect(self) -> Iterator[Metric]:
        yield from self.state.collect()

    def describe(self) -> list[Metric]:
        return []  # families depend on what was heard: registering must not call collect()


def registry_for(state: RunState) -> CollectorRegistry:
    """A registry holding only this run's collector (no exporter-process metrics mixed in)."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(RunCollector(state))
    return reg


def poll_alive(node: Any, keys: P.Keys, state: RunState, stop: threading.Event, every_s: float = 1.0) -> None:
    """Feed ``state`` the live tokens of the run every ``every_s`` seconds until ``stop``."""
    while not stop.is_set():
        try:
            pairs = []
            for key in node.alive_now(keys.alive_all, min(2.0, every_s * 2)):
                try:
                    pairs.append(keys.parse_alive(key))
                except P.ProtocolError:
                    continue
            state.set_alive(pairs)
        except Exception as e:  # a router gone for a while: keep the last view, try again
            log.warning("liveliness poll failed: %s", e)
        stop.wait(every_s)


def serve(cfg: Any, run_id: str, stop: threading.Event, port: int = DEFAULT_PORT, host: str = "0.0.0.0",
          expected_actors: int | None = None, poll_s: float = 1.0) -> None:
    """Entry point of ``zenrl exporter``: subscribe the run, serve ``/metrics`` until ``stop``."""
    from prometheus_client import start_http_server

    from zenrl.common.transport import Node

    keys = P.Keys(run_id)
    state = RunState(run_id, cfg.actor.num_actors if expected_actors is None else expected_actors)
    with Node.from_config(cfg.transport) as node:
        node.subscribe(keys.stats_all, state.on_stats)
        node.subscribe(keys.eval, state.on_eval)
        node.subscribe(keys.episodes_all, state.on_episodes)
        try:
            server, thread = start_http_server(port, addr=host, registry=registry_for(state))
        except OSError as e:  # a busy port is the operator's to fix: no restart loop
            raise ConfigError(f"exporter: cannot listen on {host}:{port}: {e}") from None
        log.info("exporter of run %s serving http://%s:%d/metrics", run_id, host, port)
        try:
            poll_alive(node, keys, state, stop, poll_s)
        finally:
            server.shutdown()
            server.server_close()
            thread.join(5)
