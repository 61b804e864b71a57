"""The replay service (``zenrl replay``): a prioritized replay behind Zenoh, run as a
:class:`~zenrl.common.roles.Worker` by the role loop (which holds ``alive/replay/<id>`` and
publishes :class:`Stats` on ``stats/replay/<id>`` every ``replay.stats_interval_s``).

Keys (see :class:`zenrl.common.protocol.Keys`) and who handles them:

* ``transitions/*`` (:class:`TransitionBatch`) -> :mod:`zenrl.replay.ingest`: chunks wait in a
  bounded Zenoh FIFO (:meth:`~zenrl.common.transport.Node.inbox`) that the ingest thread (started
  through the supervisor, so a stall shows in the stats as ``stalled``) pulls from, then decodes,
  checks and inserts into the storage (:mod:`zenrl.replay.store`); a relief thread drops what
  waits while the ingest thread is stuck (so that Zenoh never closes the link);
* ``replay/sample`` and ``replay/priorities`` -> :mod:`zenrl.replay.sampling`;
* ``quarantine/<actor>``: a liveliness token held while a source is quarantined, so that slot
  claims (``zenrl.actor.slots``) treat its exploration slot as free.

With ``replay.durable`` every inserted chunk is logged and the storage is restored from the log
at start (:mod:`zenrl.replay.journal`). With ``replay.check_semantics`` (default) chunks are also
checked against the run's env spec (:mod:`zenrl.replay.checks`) and a source that keeps failing
is quarantined (its chunks dropped unread as they are taken).

On stop (:meth:`ReplayService.close`): the transitions subscriber is undeclared (its FIFO closed),
the ingest thread inserts what was waiting in it, then the log is flushed and the final snapshot
written; the caller closes the session.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
import threading
from pathlib import Path
from typing import Any

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.errors import TransportError
from zenrl.common.league_reset import GenerationWatch
from zenrl.common.roles import Cadence, RoleLoop, Supervisor, WatchedThread
from zenrl.common.transport import Node
from zenrl.replay.checks import Checker, ChunkChecker, SequenceChecker
from zenrl.replay.ingest import Ingest
from zenrl.replay.journal import Journal
from zenrl.replay.sampling import Origins, Sampler

log = logging.getLogger(__name__)


class ReplayService:
    """The replay's wiring: builds the ingest, journal and sampler around one lock (shared by the
    ingest thread and the Zenoh callbacks), declares what they listen to and reports their
    stats. ``node`` may be None to use :meth:`ingest` in process (tests, benchmarks). ``stop``:
    the role's stop event, which ends :meth:`step`'s idle wait at once (a prompt shutdown)."""

    def __init__(self, cfg: RunConfig, node: Node | None, run_id: str, service_id: str = "replay",
                 stop: threading.Event | None = None, shard: int | None = None) -> None:
        self.cfg = cfg
        self.rcfg = rcfg = cfg.replay
        self.node = node
        #: which shard of a sharded replay (``replay.shards`` > 1) this is: its keys and log folder
        self.shard = P.replay_shard(shard, rcfg.shards)
        self.keys = P.Keys(run_id, self.shard)
        self.id = service_id
        self.max_bytes = cfg.transport.max_message_bytes
        self._lock = threading.Lock()
        self.journal: Journal | None = None
        #: the durable log's folder (None: not durable)
        self.log_dir: Path | None = None
        if rcfg.durable:
            log_dir = rcfg.log_dir or str(Path(cfg.runs_dir) / run_id / "replay")
            if self.shard is not None:
                log_dir = str(Path(log_dir) / f"shard-{self.shard}")
            self.log_dir = Path(log_dir)
            self.journal = Journal(log_dir, rcfg.segment_items or max(1, rcfg.capacity // 8), rcfg.flush_interval_s,
                                   rcfg.snapshot_interval_s, rcfg.durable_retry_s, rcfg.durable_backlog_bytes)
        checker = make_checker(cfg) if rcfg.check_semantics else None
        self.ingestor = Ingest(rcfg, cfg.seed, min(rcfg.max_chunk_bytes, self.max_bytes), checker, self._lock,
                               self.journal)
        self.ingestor.origins = origins = Origins()
        self.sampler = Sampler(rcfg, cfg.seed, self.max_bytes, self._lock, lambda: self.buffer, self.ingestor.rejects,
                               self.keys.sample, checker is not None, origins, self.ingestor.reject)
        self.restored_items = self.journal.restore(self.ingestor, self.max_bytes) if self.journal is not None else 0
        #: set by close(): the ingest thread drains the queue and ends
        self._stop = threading.Event()
        self._role_stop = stop or self._stop
        self._tx_sub: Any = None
        self._ingest_thread: WatchedThread | None = None
        self._relief_thread: WatchedThread | None = None
        self._quarantine_tokens: dict[str, Any] = {}

    # -- what tests and tools reach -------------------------------------------------------------
    @property
    def buffer(self) -> Any:
        """The storage (:class:`InMemoryReplay` or :class:`FrameReplay`), None before the first chunk."""
        store = self.ingestor.store
        return None if store is None else store.buffer

    @property
    def checker(self) -> ChunkChecker | None:
        return self.ingestor.checker

    @checker.setter
    def checker(self, checker: ChunkChecker | None) -> None:
        self.ingestor.checker = checker
        self.sampler.check_priorities = checker is not None

    @property
    def rejects(self) -> Any:
        return self.ingestor.rejects

    @property
    def rejected_by_source(self) -> Any:
        return self.ingestor.ledger.by_source

    @property
    def inserted(self) -> Any:
        return self.ingestor.inserted

    @property
    def quarantine(self) -> Any:
        return self.ingestor.quarantine

    def ingest(self, payload: bytes, source: str = "") -> int:
        """Decode, check and insert one :class:`TransitionBatch`; returns items inserted (0 if rejected)."""
        return self.ingestor.ingest_many([(payload, source)])

    def ingest_many(self, items: list[tuple[bytes, str]]) -> int:
        """:meth:`Ingest.ingest_many` (``(payload, source)`` pairs; returns items inserted)."""
        return self.ingestor.ingest_many(items)

    def sample_reply(self, req: P.SampleRequest) -> P.SampleReply:
        return self.sampler.reply(req)

    # -- the Worker -----------------------------------------------------------------------------
    def start(self, node: Node, sup: Supervisor) -> None:
        """Declare the transitions inbox, start the ingest and relief threads, then declare the
        priorities subscription and the sample queryable."""
        self.node = node
        inbox = node.inbox(self.keys.transitions_all, self.ingestor.inbox_capacity)
        self.ingestor.inbox = inbox
        self._tx_sub = inbox.subscription
        self._ingest_thread = sup.thread("replay-ingest", self.ingestor.unit, self._stop,
                                         pending=self.ingestor.pending, drain=self.ingestor.drain)
        # no input of its own: it counts as stalled only if it dies
        self._relief_thread = sup.thread("replay-relief", self.ingestor.relief_unit, self._stop, pending=lambda: 0)
        node.subscribe(self.keys.priorities, self.sampler.on_priorities)
        node.queryable(self.keys.sample, self.sampler.on_sample)
        log.info("replay service %s up on %s", self.id, self.keys.prefix)

    def step(self, timeout_s: float) -> bool:
        """The periodic duties (the ingest thread does the work): fsync the log when due while no
        chunk comes to do it (or retry a log the disk failed), hold the quarantine tokens; then
        wait ``timeout_s``. Raises the ingest thread's :class:`MemoryTooSmall` (the role ends on it)."""
        if self.ingestor.fatal is not None:
            raise self.ingestor.fatal
        if self.journal is not None:
            with self._lock:
                self.journal.tick(self.buffer)
        self.update_quarantine()
        self._role_stop.wait(timeout_s)
        return False

    def done(self) -> bool:
        return False

    def progress(self) -> int:
        b = self.buffer
        return 0 if b is None else b.inserts_total

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        vals = self.stats_values()
        log.debug("replay stats %s", vals)
        return vals, None

    def save(self) -> None:
        """Nothing: the journal is the replay's saved state, written as chunks arrive."""

    def close(self) -> None:
        """Stop in an order that cannot stall under ingest load: undeclare the transitions
        subscriber (its inbox closes: a waiting ingest thread wakes), let the ingest thread insert
        what already waits in it, then flush the log and write the final snapshot. The session is
        closed by the caller after this returns."""
        self.ingestor.closing.set()
        if self._tx_sub is not None:
            self.node.withdraw(self._tx_sub)  # never raises: the session may be gone (router down)
            self._tx_sub = None
        self._stop.set()
        if self._ingest_thread is not None:
            self._ingest_thread.join(timeout=5)
        if self._relief_thread is not None:
            self._relief_thread.join(timeout=1)
        if self.journal is not None:
            with self._lock:
                self.journal.finish(self.buffer)
            b = self.buffer
            log.info("replay log flushed: %d items inserted, %d stored", 0 if b is None else b.inserts_total,
                     0 if b is None else b.size)

    # -- stats ----------------------------------------------------------------------------------
    def stats_values(self) -> dict[str, Any]:
        """The replay's stats values (see docs/operations.md for their meaning)."""
        with self._lock:
            store = self.ingestor.store
            b = None if store is None else store.buffer
            v: dict[str, Any] = {
                "size": 0 if b is None else b.size,
                "capacity": self.rcfg.capacity if b is None else b.capacity,
                "bytes": 0 if b is None else b.nbytes,
                "inserted_total": 0 if b is None else b.inserts_total,
                "stale_priority_updates": 0 if b is None else b.stale_updates,
            }
            if store is not None:
                v.update(store.stats())
        v.update(self.sampler.stats_values())
        v["restored_items"] = self.restored_items
        if self.journal is not None:
            v.update(self.journal.stats_values())
        v.update(self.ingestor.stats_values())
        return v

    def update_quarantine(self) -> None:
        """Hold a liveliness token ``quarantine/<source>`` while a source is quarantined, so
        that slot claims (see zenrl.actor.slots) treat its exploration slot as free."""
        ing = self.ingestor
        with ing.ledger.lock:
            released = ing.quarantine.expire()
            active = list(ing.quarantine.active)
        for src in released:
            tok = self._quarantine_tokens.pop(src, None)
            log.info("source %s released from quarantine", src)
            if tok is not None and self.node is not None:
                self.node.withdraw(tok)
        if self.node is None:
            return
        for src in active:
            if src not in self._quarantine_tokens:
                try:
                    self._quarantine_tokens[src] = self.node.token(self.keys.quarantined(src))
                except (TransportError, P.ProtocolError) as e:
                    log.warning("could not declare the quarantine token of %s: %s", src, e)


def make_checker(cfg: RunConfig) -> Checker:
    """The semantic checks for this run's env, built from the config as the learner builds its
    network (an env is made once to read its spaces, then closed): of n-step transitions, or of
    sequences for ``algo: r2d2``."""
    env = make_env(cfg.env)
    try:
        if cfg.algo == "r2d2":
            return SequenceChecker.from_spaces(env.observation_space, env.action_space, cfg.r2d2.sequence_length,
                                               cfg.r2d2.lstm_size, cfg.replay.max_abs_reward, cfg.replay.max_priority,
                                               cfg.replay.check_obs_bounds, frame_stack=cfg.actor.frame_stack)
        return ChunkChecker.from_spaces(env.observation_space, env.action_space, cfg.actor.n_step,
                                        cfg.replay.max_abs_reward, cfg.replay.max_priority, cfg.replay.check_obs_bounds,
                                        frame_stack=cfg.actor.frame_stack)
    finally:
        env.close()


#: what the replay's session must take besides chunks: a priority update of the largest batch
#: (65,536 keys and priorities) and sample requests are well below this
_CONTROL_BYTES = 2 * 1024 * 1024


def rx_cap(cfg: RunConfig) -> int:
    """The largest message the replay's session receives: chunks up to ``replay.max_chunk_bytes``
    (and the small control messages), never more than the transport's cap."""
    return min(cfg.transport.max_message_bytes, max(cfg.replay.max_chunk_bytes, _CONTROL_BYTES))


#: glibc ``mallopt`` parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: allocations below this come from malloc's heaps, not a fresh ``mmap`` each (glibc's maximum)
KEEP_BELOW_BYTES = 32 * 1024 * 1024
#: free memory malloc keeps at a heap's top instead of handing it back to the OS
KEEP_FREE_BYTES = 256 * 1024 * 1024


def keep_freed_memory() -> bool:
    """Make glibc's malloc reuse freed memory in this process instead of returning it to the OS
    and faulting it in again: each chunk (and each sample reply) allocates and frees buffers of
    its own size, up to ``replay.max_chunk_bytes``, which malloc otherwise maps and unmaps anew
    (or trims off a heap) every time. On a VM where a page fault costs ~25 us, that re-faulting
    cost more CPU per chunk than decoding and storing it. The resident size stays at the peak
    of those buffers (bounded by the ingest limits, see docs/architecture.md). Returns whether
    it took (glibc only; elsewhere a no-op)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, KEEP_BELOW_BYTES) and libc.mallopt(_M_TRIM_THRESHOLD, KEEP_FREE_BYTES))
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False


def main(cfg: RunConfig, run_id: str, stop: threading.Event, service_id: str = "replay",
         shard: int | None = None) -> None:
    """Entry point of ``zenrl replay``: build, run in the role loop until ``stop``, close the
    session. ``shard``: this service's shard of ``replay.shards``. Raises
    :class:`~zenrl.common.roles.RoleFailed` when the ingest thread is gone."""
    P.replay_shard(shard, cfg.replay.shards)  # a shard number that does not fit: ConfigError before connecting
    if not keep_freed_memory():
        log.info("malloc tuning not available here: chunk buffers are allocated fresh each time")
    with Node.from_config(cfg.transport, max_rx_bytes=rx_cap(cfg)) as node:
        svc = ReplayService(cfg, node, run_id, service_id, stop, shard)
        watch = GenerationWatch.for_config(cfg, node, run_id, svc.id, stop)  # league.self_reset
        # idle waits no longer than the stats interval, so that a short one is kept
        cadence = Cadence(cfg.replay.stats_interval_s, idle_s=min(0.5, cfg.replay.stats_interval_s))
        RoleLoop(node, svc.keys, "replay", svc.id, cadence).run(svc, stop)
        if watch is not None:
            watch.finish([svc.log_dir] if svc.log_dir is not None else [])
