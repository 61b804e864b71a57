"""The league service (``zenrl league``): the players, the payoff table and matchmaking of one
league, a process of its own behind Zenoh, run by the role loop (``alive/league/<id>``, stats on
``stats/league/<id>``, its state saved every ``league.save_interval_s`` and on stop).

Keys (:class:`zenrl.common.protocol.LeagueKeys`, under ``zenrl/<run>/league/``):

* ``opponent`` (queryable): :class:`OpponentRequest` -> :class:`OpponentReply`, an opponent
  drawn from the requesting learning agent's mix (:meth:`League.distribution`), with a ticket
  (:mod:`zenrl.league.tickets`); an actor id that asks faster than ``league.ticket_rate_per_s``
  gets "busy" (counted as ``rejected_request_rate``);
* ``weights`` (queryable): :class:`PlayerWeightsRequest` -> :class:`PlayerWeights`, the
  weights of a snapshot or the served copy of a learning agent's (actors cache them by id and
  version);
* ``table`` (queryable): the players and the payoff table, for ``zenrl league status``;
* ``results/*`` (subscriber): :class:`MatchResult` of every finished match; a result that does
  not decode, names a player or opponent the league does not hold, an opponent version it never
  served, a generation ahead of the player's, or cites no ticket open for that actor and that
  pairing (``ticket_unknown``, ``ticket_mismatch``), is rejected and counted by reason
  (``rejected_<reason>``), nothing else changes;
* each learning agent's weights broadcast (``zenrl/<run>.<agent>/weights``, the agent's own
  run id): only the newest payload is kept in the callback; it is decoded in the role's step,
  where the snapshot and reset rules run too.

The Zenoh callbacks only take the league's lock for dictionary work (a draw, a count); weights
are decoded and files written outside them. Resets of an exploiter are carried out by whoever
runs its processes (``zenrl run``: it restarts the exploiter's replay, learner and actors
afresh when ``generation/<agent>`` in the league's stats goes up).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.errors import ProtocolError
from zenrl.common.metrics import RateMeter, RejectCounter
from zenrl.common.roles import Cadence, RoleLoop, Supervisor
from zenrl.common.transport import Node
from zenrl.league.core import BOT, FROZEN, LEARNER, SNAPSHOT, League, LearnerWeights, agent_run_id
from zenrl.league.store import LeagueStore
from zenrl.league.tickets import TicketBook

log = logging.getLogger(__name__)


def league_dir(cfg: RunConfig, run_id: str) -> Path:
    """Where the league of run ``run_id`` keeps its state."""
    return Path(cfg.runs_dir) / run_id / "league"


class LeagueService:
    """The league's wiring as a :class:`~zenrl.common.roles.Worker`. ``clock``: wall-clock
    seconds (the snapshot and reset timers survive a restart)."""

    def __init__(self, cfg: RunConfig, node: Any, run_id: str, service_id: str = "league",
                 directory: str | Path | None = None, clock: Any = time.time) -> None:
        self.cfg = cfg
        self.lcfg = cfg.league
        self.node = node
        self.run_id = run_id
        self.id = service_id
        self.keys = P.Keys(run_id)
        self.lkeys = P.LeagueKeys(run_id)
        self.clock = clock
        self.max_bytes = min(cfg.transport.max_message_bytes, self.lcfg.max_weights_bytes)
        self.store = LeagueStore(directory or league_dir(cfg, run_id), self.max_bytes)
        now = clock()
        frozen = list(cfg.opponents.pool)  # policy files every actor loads itself
        loaded = self.store.load(self.lcfg, now, frozen)
        self.league = loaded if loaded is not None else League(self.lcfg, now, frozen)
        self.restored = loaded is not None
        if self.restored:
            log.info("league restored from %s: %d players, %d results", self.store.dir, len(self.league.players),
                     self.league.results_total)
        self.rng = np.random.default_rng(cfg.seed)
        lc = self.lcfg
        # ticket numbers must not be guessable: their own stream, from the OS, not the run's seed
        self.tickets = TicketBook(lc.ticket_rate_per_s, lc.ticket_burst, lc.open_tickets_per_actor,
                                  lc.max_ticket_actors, np.random.default_rng(), clock)
        self.lock = threading.Lock()
        self.rejects = RejectCounter(log, "league input")
        self.results_rate, self.requests_rate = RateMeter(), RateMeter()
        self.weights_served = 0
        self.weights_heard: dict[str, int] = {}
        self._latest: dict[str, Any] = {}
        self._encoded: dict[tuple[str, int], bytes] = {}
        self._wake = threading.Event()
        self._dirty = False
        self.events: list[tuple[str, str, str | None, str]] = []

    # -- the role loop's Worker ---------------------------------------------------------------
    def start(self, node: Node, sup: Supervisor | None = None) -> None:
        for aid in self.lcfg.agents:
            self._latest[aid] = node.subscribe_latest(P.Keys(agent_run_id(self.run_id, aid)).weights)
        node.subscribe(self.lkeys.results_all, self.on_result)
        node.queryable(self.lkeys.opponent, self.on_opponent)
        node.queryable(self.lkeys.weights, self.on_weights)
        node.queryable(self.lkeys.table, lambda _req: self.table().encode(self.max_bytes))
        self.save()  # the initial state is on disk before anything is answered
        log.info("league %s: players %s", self.run_id, ", ".join(self.league.players))

    def step(self, timeout_s: float) -> bool:
        """Take the learners' newest weights, then apply the snapshot and reset rules."""
        self._wake.wait(timeout_s)
        self._wake.clear()
        did = False
        now = self.clock()
        for aid, lv in self._latest.items():
            payload = lv.take()
            if payload is None:
                continue
            try:
                w = P.Weights.decode(payload, self.max_bytes)
            except ProtocolError as e:
                self.rejects.reject(f"weights_{e.reason}", str(e), aid)
                continue
            with self.lock:
                if self.league.hear_weights(aid, LearnerWeights(w.version, w.updates, w.arch, dict(w.params)), now):
                    self.weights_heard[aid] = self.weights_heard.get(aid, 0) + 1
                    did = True
        with self.lock:
            events = self.league.tick(now)
        for ev in events:
            log.info("league: %s of %s (%s)%s", ev[0], ev[1], ev[3], f": {ev[2]} joins" if ev[2] else "")
        if events:
            self.events.extend(events)
            self.save()  # a new player or generation is durable before anyone is told of it
        return did or bool(events)

    def done(self) -> bool:
        return False

    def progress(self) -> int:
        return self.league.results_total

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        with self.lock:
            lg = self.league
            v: dict[str, Any] = {"players": len(lg.players), "snapshots": len(lg.weights),
                                 "results_total": lg.results_total, "weights_served": self.weights_served}
            for aid in lg.learners():
                p = lg.players[aid]
                rate, n = lg.since_rate(aid, [lg.main_id] if p.role == "exploiter" else None)
                v[f"generation/{aid}"] = p.generation
                v[f"version/{aid}"] = p.version
                v[f"since_games/{aid}"] = n
                v[f"since_win_rate/{aid}"] = round(rate, 4)
            dist = lg.distribution(lg.main_id)
            v["tickets_open"] = self.tickets.open_count()
            v["tickets_dropped"] = self.tickets.dropped_tickets
        v["results_per_s"] = self.results_rate.rate()
        v["requests_per_s"] = self.requests_rate.rate()
        v["main_pfsp_entropy"] = -sum(p * math.log(p) for p in dist.values() if p > 0)
        v.update(self.rejects.as_values())
        line = (f"league: {v['players']} players, {v['results_total']} results, "
                f"{v['results_per_s']:.2f} results/s, {v['rejected_total']} rejected")
        return v, line

    def save(self) -> None:
        with self.lock:
            self.store.save(self.league, self.clock())

    def close(self) -> None:
        """Nothing is pending: results are folded in as they come (the role loop saves last)."""

    # -- Zenoh callbacks (short: a lock, a draw, a count) -----------------------------------------
    def on_result(self, key: str, payload: bytes) -> None:
        try:
            self._on_result(key, payload)
        except Exception as e:  # noqa: BLE001 - one message costs only itself; counted by type
            self.rejects.reject(f"internal/{type(e).__name__}", str(e), key.rsplit("/", 1)[-1])

    def _on_result(self, key: str, payload: bytes) -> None:
        source = key.rsplit("/", 1)[-1]
        try:
            m = P.MatchResult.decode(payload, 64 * 1024)
        except ProtocolError as e:
            self.rejects.reject(e.reason, str(e), source)
            return
        if m.actor_id != source:
            self.rejects.reject("actor_id", f"actor_id {m.actor_id!r} differs from the key's {source!r}", source)
            return
        with self.lock:
            why = self._check_result(m)
            if why is None:
                self.league.record(m.player, m.opponent, m.outcome, m.generation)
        if why is not None:
            self.rejects.reject(why[0], why[1], source)
            return
        self.results_rate.add()
        self._wake.set()

    def _check_result(self, m: P.MatchResult) -> tuple[str, str] | None:
        """(reason, detail) why ``m`` cannot be counted, or None. Called under the lock."""
        lg = self.league
        p = lg.players.get(m.player)
        if p is None or p.kind != LEARNER:
            return "unknown_player", f"{m.player!r} is not a learning agent of this league"
        o = lg.players.get(m.opponent)
        if o is None:
            return "unknown_opponent", f"{m.opponent!r} is not a player of this league (a snapshot that left?)"
        if m.generation > p.generation:
            return "generation", f"generation {m.generation} of {m.player} is ahead of the league's {p.generation}"
        if o.kind in (BOT, FROZEN) and m.opponent_version != -1:
            return "opponent_version", f"{o.kind} {m.opponent} has no version, got {m.opponent_version}"
        if o.kind == SNAPSHOT and m.opponent_version != o.version:
            return "opponent_version", f"snapshot {m.opponent} is version {o.version}, got {m.opponent_version}"
        if o.kind == LEARNER:
            live = lg.live.get(m.opponent)
            if live is not None and m.opponent_version > live.version:
                return "opponent_version", f"{m.opponent} was never served version {m.opponent_version}"
        # a learning opponent's weights are served at their newest: an actor that fetched them
        # after a new version came plays that one (checked above against what was served)
        return self.tickets.redeem(m.actor_id, m.ticket, m.player, m.opponent, m.opponent_version,
                                   newer_ok=o.kind == LEARNER)

    def _answer(self, handler: Callable[[bytes], bytes | None], payload: bytes) -> bytes | None:
        """``handler(payload)``; an unexpected error costs only this query (no reply: the asker
        times out) and is counted as ``request_internal/<type>``."""
        try:
            return handler(payload)
        except Exception as e:  # noqa: BLE001 - one query costs only itself; counted by type
            self.rejects.reject(f"request_internal/{type(e).__name__}", str(e))
            return None

    def on_opponent(self, payload: bytes) -> bytes | None:
        return self._answer(self._on_opponent, payload)

    def _on_opponent(self, payload: bytes) -> bytes | None:
        try:
            req = P.OpponentRequest.decode(payload, 4096)
        except ProtocolError as e:
            self.rejects.reject(f"request_{e.reason}", str(e))
            return None  # no reply: the asker times out, the league goes on
        self.requests_rate.add()
        with self.lock:
            lg = self.league
            p = lg.players.get(req.player)
            if p is None or p.kind != LEARNER:
                reply = P.OpponentReply("unknown", req.player, reason=f"{req.player!r} is not a learning agent here")
            else:
                oid = lg.choose(req.player, self.rng)
                if oid is None:
                    reply = P.OpponentReply("none", req.player, p.generation, reason="no player can be played yet")
                else:
                    o = lg.players[oid]
                    w = lg.weights_of(oid)
                    version = -1 if w is None else w.version
                    ticket = self.tickets.issue(req.actor_id, req.player, oid, version)
                    if ticket is None:
                        reply = P.OpponentReply("busy", req.player, p.generation, reason=(
                            f"{req.actor_id} asks faster than league.ticket_rate_per_s "
                            f"{self.lcfg.ticket_rate_per_s:g}/s"))
                    else:
                        reply = P.OpponentReply("ok", req.player, p.generation, oid, o.kind, version, ticket=ticket)
        if reply.status == "unknown":
            self.rejects.reject("request_unknown_player", reply.reason, req.actor_id)
        elif reply.status == "busy":
            self.rejects.reject("request_rate", reply.reason, req.actor_id)
        return reply.encode()

    def on_weights(self, payload: bytes) -> bytes | None:
        return self._answer(self._on_weights, payload)

    def _on_weights(self, payload: bytes) -> bytes | None:
        try:
            req = P.PlayerWeightsRequest.decode(payload, 4096)
        except ProtocolError as e:
            self.rejects.reject(f"request_{e.reason}", str(e))
            return None
        with self.lock:
            w = self.league.weights_of(req.player)
            if w is None:
                return P.PlayerWeights("missing", req.player, reason=f"{req.player!r} has no weights served").encode()
            key = (req.player, w.version)
            out = self._encoded.get(key)
            if out is None:
                out = P.PlayerWeights("ok", req.player, w.version, w.updates, w.arch, params=w.params).encode(self.max_bytes)
                if len(self._encoded) >= 64:
                    self._encoded.clear()
                self._encoded[key] = out
            self.weights_served += 1
            return out

    def table(self) -> P.LeagueTable:
        with self.lock:
            msg = table_message(self.league, {"time": self.clock()})
        return dataclasses.replace(msg, values={**msg.values, **self.rejects.as_values()})


def table_message(lg: League, values: dict[str, Any] | None = None) -> P.LeagueTable:
    """The :class:`~zenrl.common.protocol.LeagueTable` of ``lg`` (``values`` added to its own)."""
    t = lg.table()
    ids = t["ids"]
    ps = [lg.players[i] for i in ids]
    dist = lg.distribution(lg.main_id)
    return P.LeagueTable(ids={i: n for n, i in enumerate(ids)}, kinds={p.id: p.kind for p in ps},
                         roles={p.id: p.role for p in ps}, versions={p.id: p.version for p in ps},
                         generations={p.id: p.generation for p in ps}, counts=t["counts"],
                         main_pfsp={k: float(v) for k, v in dist.items()},
                         values={"results_total": lg.results_total, **(values or {})})


def main(cfg: RunConfig, run_id: str, stop: threading.Event, service_id: str = "league") -> None:
    """Entry point of ``zenrl league``: build, run in the role loop until ``stop`` (the state is
    saved every ``league.save_interval_s`` and last on stop), close the session."""
    with Node.from_config(cfg.transport) as node:
        svc = LeagueService(cfg, node, run_id, service_id)
        cadence = Cadence(cfg.league.stats_interval_s, cfg.league.save_interval_s,
                          idle_s=min(0.5, cfg.league.stats_interval_s))
        RoleLoop(node, svc.keys, "league", svc.id, cadence).run(svc, stop)
