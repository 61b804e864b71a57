"""The league's logic, pure (no network, no clock of its own: every rule takes ``now``).

After AlphaStar (Vinyals et al., Nature 2019, and its published pseudocode):

* **players**: scripted bots, frozen policy files (``opponents.pool``: checkpoints or exported
  files that every actor loads itself), frozen snapshots (weights that never change, held by
  the league) and learning agents (``main``, exploiters) whose weights the learners broadcast;
* **payoff table**: wins / draws / losses per ordered pair ``(a, b)`` from ``a``'s side; every
  reported match is folded into both ``(a, b)`` and ``(b, a)``. Raw integer counts (what
  ratings and ``zenrl league status`` read) and decayed counts (each new match of a pair
  multiplies that pair's earlier counts by ``decay``: what PFSP reads, so that a learning
  agent's old results fade);
* **PFSP** (prioritized fictitious self-play): an opponent ``b`` of ``a`` is drawn with
  probability proportional to ``f(x)``, ``x`` = P[a beats b] = (wins + draws / 2 + prior_rate *
  prior_games) / (games + prior_games) over the decayed counts; ``f_hard(x) = (1 - x) ** p``,
  ``f_var(x) = x (1 - x)``; all-zero weights fall back to uniform;
* **roles**: the main agent plays itself (``selfplay_share``), the exploiters' live weights
  (``exploiter_share``) or PFSP over every frozen player (bots and snapshots); an exploiter
  plays only the current main agent;
* **snapshots and resets**: a learning agent's current weights join as a frozen snapshot every
  ``snapshot_interval_s``, or sooner (after ``min_snapshot_interval_s``) once its win rate since
  its last snapshot passes ``snapshot_win_rate`` over at least ``min_games``; an exploiter is
  reset (a new generation: fresh weights, empty replay) every ``exploiter_reset_s`` or once it
  beats the main agent at ``exploiter_win_rate`` since its reset, leaving a snapshot;
* **persistence**: :meth:`League.to_state` / :meth:`League.from_state` give a JSON-ready dict;
  the weights of snapshots are kept apart (the service stores each as one file).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np

from zenrl.common.config import LeagueConfig

#: the kinds of player: a scripted bot of the env; a policy file of ``opponents.pool`` that each
#: actor loads itself (``frozen``); a snapshot whose weights the league holds; a learning agent
BOT, FROZEN, SNAPSHOT, LEARNER = "bot", "frozen", "snapshot", "learner"
KINDS = (BOT, FROZEN, SNAPSHOT, LEARNER)
#: match outcomes from the reporting side
WIN, DRAW, LOSS = 1, 0, -1
#: version of the persisted state's layout
STATE_FORMAT = 1


def agent_run_id(league_run_id: str, agent: str) -> str:
    """The run id of a learning agent's own processes (replay, learner, actors): its keys are
    ``zenrl/<league run>.<agent>/...``, apart from every other agent's."""
    rid = f"{league_run_id}.{agent}"
    if len(rid) > 64:
        raise ValueError(f"run id {rid!r} of league agent {agent!r} is longer than 64 characters; "
                         f"use a shorter run id")
    return rid


@dataclass
class Player:
    """One player. ``role``: "bot", or the learning agent's role ("main", "exploiter") for a
    learner and for the snapshots taken of it. ``parent``: a snapshot's learning agent.
    ``version`` / ``updates``: a snapshot's weights (for a learner: of the weights it serves now,
    -1 while none was heard). ``generation``: a learner's resets so far (a snapshot: the
    generation it was taken from). A learner also carries its timers (``last_snapshot_at``,
    ``reset_at``, wall-clock seconds) and ``snapshots`` taken."""

    id: str
    kind: str
    role: str
    created_at: float
    parent: str | None = None
    version: int = -1
    updates: int = 0
    generation: int = 0
    last_snapshot_at: float = 0.0
    reset_at: float = 0.0
    snapshots: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Player":
        p = cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})
        if p.kind not in KINDS:
            raise ValueError(f"player {p.id!r} has unknown kind {p.kind!r}")
        return p


def _outcome_index(outcome: int) -> int:
    if outcome not in (WIN, DRAW, LOSS):
        raise ValueError(f"outcome must be +1, 0 or -1, got {outcome!r}")
    return {WIN: 0, DRAW: 1, LOSS: 2}[outcome]


class Payoff:
    """Results per ordered pair: ``counts[(a, b)]`` = [wins, draws, losses] of ``a`` against
    ``b`` (ints), ``decayed[(a, b)]`` the same with older matches of the pair weighted down by
    ``decay`` per newer match (floats). :meth:`record` folds one match into both sides; a
    player against itself (self-play) is recorded once."""

    def __init__(self, decay: float = 1.0) -> None:
        self.decay = float(decay)
        self.counts: dict[tuple[str, str], list[int]] = {}
        self.decayed: dict[tuple[str, str], list[float]] = {}

    def record(self, a: str, b: str, outcome: int) -> None:
        i = _outcome_index(outcome)
        pairs = [(a, b, i)] if a == b else [(a, b, i), (b, a, 2 - i)]
        for x, y, j in pairs:
            c = self.counts.setdefault((x, y), [0, 0, 0])
            c[j] += 1
            d = self.decayed.setdefault((x, y), [0.0, 0.0, 0.0])
            for k in range(3):
                d[k] *= self.decay
            d[j] += 1.0

    def games(self, a: str, b: str) -> int:
        return sum(self.counts.get((a, b), (0, 0, 0)))

    def wdl(self, a: str, b: str) -> tuple[int, int, int]:
        w, d, l = self.counts.get((a, b), (0, 0, 0))
        return int(w), int(d), int(l)

    def win_rate(self, a: str, b: str, prior_rate: float = 0.5, prior_games: float = 1.0, decayed: bool = True) -> float:
        """P[a beats b], draws counting half, with ``prior_games`` matches at ``prior_rate``
        mixed in (so an unplayed pair reads ``prior_rate``)."""
        w, d, l = (self.decayed if decayed else self.counts).get((a, b), (0.0, 0.0, 0.0))
        return (w + 0.5 * d + prior_rate * prior_games) / (w + d + l + prior_games)

    def remove(self, player: str) -> None:
        """Forget every pair ``player`` is part of."""
        for table in (self.counts, self.decayed):
            for k in [k for k in table if player in k]:
                del table[k]

    def to_state(self) -> dict[str, Any]:
        return {"decay": self.decay,
                "counts": [[a, b, *c] for (a, b), c in sorted(self.counts.items())],
                "decayed": [[a, b, *c] for (a, b), c in sorted(self.decayed.items())]}

    @classmethod
    def from_state(cls, s: Mapping[str, Any], decay: float) -> "Payoff":
        p = cls(decay)
        for a, b, w, d, l in s.get("counts", []):
            p.counts[(str(a), str(b))] = [int(w), int(d), int(l)]
        for a, b, w, d, l in s.get("decayed", []):
            p.decayed[(str(a), str(b))] = [float(w), float(d), float(l)]
        return p


def pfsp_weights(win_rates: Iterable[float], weighting: str = "hard", p: float = 2.0) -> np.ndarray:
    """float64[K] probabilities of K opponents beaten with probabilities ``win_rates``:
    proportional to ``(1 - x) ** p`` ("hard") or ``x (1 - x)`` ("var"); uniform when every
    weight is 0 (e.g. every opponent beaten for sure)."""
    x = np.clip(np.asarray(list(win_rates), dtype=np.float64), 0.0, 1.0)
    if x.size == 0:
        return x
    if weighting == "hard":
        f = (1.0 - x) ** p
    elif weighting == "var":
        f = x * (1.0 - x)
    else:
        raise ValueError(f"unknown PFSP weighting {weighting!r} (hard or var)")
    total = f.sum()
    return f / total if total > 0 else np.full(x.size, 1.0 / x.size)


@dataclass
class LearnerWeights:
    """The newest weights heard from a learning agent (``params``: ``{name: array}``)."""

    version: int
    updates: int
    arch: str
    params: dict[str, np.ndarray] = field(repr=False)


class League:
    """Players, payoff and the rules of one league (see the module docstring). ``cfg``: the
    run's :class:`~zenrl.common.config.LeagueConfig`. Snapshot weights live in ``weights``
    (``{player id: LearnerWeights}``), a learning agent's newest heard weights in ``live``; the
    served weights of a learning agent (``served``) move to its newest only every
    ``live_refresh_s``, so that actors that cache by (id, version) fetch them that often."""

    def __init__(self, cfg: LeagueConfig, now: float, frozen: Iterable[str] = ()) -> None:
        self.cfg = cfg
        self.players: dict[str, Player] = {}
        self.payoff = Payoff(cfg.decay)
        #: per learning agent: [wins, draws, losses] per opponent since its last snapshot (main) or reset (exploiter)
        self.since: dict[str, dict[str, list[int]]] = {}
        self.weights: dict[str, LearnerWeights] = {}
        self.live: dict[str, LearnerWeights] = {}
        self.served: dict[str, LearnerWeights] = {}
        self._served_at: dict[str, float] = {}
        #: per learning agent after a reset: weights with ``updates`` at or above this come from the old learner
        self._stale_updates: dict[str, int] = {}
        #: per reset learning agent: added to its learner's versions, so that a version the league
        #: serves never repeats one of an earlier generation (actors cache weights by id and version)
        self._version_offset: dict[str, int] = {}
        self.results_total = 0
        for b in cfg.bots:
            self.players[b] = Player(b, BOT, BOT, now)
        for f in frozen:
            self.players[f] = Player(f, FROZEN, FROZEN, now)
        for aid, a in cfg.agents.items():
            self.players[aid] = Player(aid, LEARNER, a.role, now, last_snapshot_at=now, reset_at=now)
            self.since[aid] = {}

    # -- who is who ----------------------------------------------------------------------------
    @property
    def main_id(self) -> str:
        return self.cfg.main_id

    def learners(self) -> list[str]:
        return [p.id for p in self.players.values() if p.kind == LEARNER]

    def frozen(self) -> list[str]:
        """Bots, frozen files and snapshots, in the order they joined."""
        return [p.id for p in self.players.values() if p.kind in (BOT, FROZEN, SNAPSHOT)]

    def available(self, pid: str) -> bool:
        """Whether ``pid`` can be played now: a bot always, a snapshot with its weights, a
        learning agent once its weights were heard."""
        p = self.players.get(pid)
        if p is None:
            return False
        if p.kind in (BOT, FROZEN):
            return True
        if p.kind == SNAPSHOT:
            return pid in self.weights
        return pid in self.served

    # -- matchmaking ---------------------------------------------------------------------------
    def pfsp(self, player: str, candidates: list[str]) -> dict[str, float]:
        """PFSP probabilities of ``candidates`` as ``player``'s opponents."""
        c = self.cfg
        x = [self.payoff.win_rate(player, o, c.prior_win_rate, c.prior_games) for o in candidates]
        return dict(zip(candidates, pfsp_weights(x, c.pfsp_weighting, c.pfsp_p).tolist()))

    def distribution(self, player: str) -> dict[str, float]:
        """``{opponent: probability}`` of ``player``'s next opponent, over the players
        available now. Main: ``selfplay_share`` itself, ``bot_share`` PFSP over the bots alone,
        ``exploiter_share`` the exploiters' live weights (evenly), the rest PFSP over every frozen
        player (a share whose players are not available goes to the others in proportion; all of
        it to whichever side is the only one available). Exploiter: the current main agent. An
        empty dict when nobody can be played (then the caller falls back to a bot). ``KeyError``
        for a player that is not a learning agent."""
        p = self.players[player]
        if p.kind != LEARNER:
            raise KeyError(player)
        if p.role == "exploiter":
            return {self.main_id: 1.0} if self.available(self.main_id) else {}
        frozen = [o for o in self.frozen() if self.available(o)]
        share = self.cfg.selfplay_share if self.available(player) else 0.0
        live = [o for o, q in self.players.items()
                if q.kind == LEARNER and q.role == "exploiter" and self.available(o)]
        ex_share = self.cfg.exploiter_share if live else 0.0
        if not frozen:
            out = {o: ex_share / len(live) for o in live} if ex_share > 0 else {}
            if share > 0:
                out[player] = share
            total = sum(out.values())
            return {o: q / total for o, q in out.items()} if total > 0 else {}
        bots = [o for o in frozen if self.players[o].kind == BOT]
        bot_share = self.cfg.bot_share if bots else 0.0
        out = {o: (1.0 - share - bot_share - ex_share) * q for o, q in self.pfsp(player, frozen).items()}
        for o, q in (self.pfsp(player, bots).items() if bot_share > 0 else ()):
            out[o] += bot_share * q
        for o in live if ex_share > 0 else ():
            out[o] = ex_share / len(live)
        if share > 0:
            out[player] = out.get(player, 0.0) + share
        return out

    def choose(self, player: str, rng: np.random.Generator) -> str | None:
        """Draw ``player``'s next opponent from :meth:`distribution` (None when nobody can be played)."""
        dist = self.distribution(player)
        if not dist:
            return None
        ids = list(dist)
        probs = np.asarray([dist[i] for i in ids], dtype=np.float64)
        return ids[int(rng.choice(len(ids), p=probs / probs.sum()))]

    # -- results -------------------------------------------------------------------------------
    def record(self, player: str, opponent: str, outcome: int, generation: int | None = None) -> bool:
        """Fold one match of learning agent ``player`` against ``opponent`` into the table.
        ``generation``: the player's generation the actor played with; a match of an earlier
        generation (an exploiter's actors not yet restarted after its reset) counts in the table
        but not towards the rules. ``ValueError`` for an unknown player, opponent or outcome;
        True if it counted towards the rules."""
        p = self.players.get(player)
        if p is None or p.kind != LEARNER:
            raise ValueError(f"player {player!r} is not a learning agent of this league")
        if opponent not in self.players:
            raise ValueError(f"opponent {opponent!r} is not a player of this league")
        _outcome_index(outcome)
        self.payoff.record(player, opponent, outcome)
        self.results_total += 1
        if generation is not None and generation != p.generation:
            return False
        c = self.since.setdefault(player, {}).setdefault(opponent, [0, 0, 0])
        c[_outcome_index(outcome)] += 1
        return True

    def since_rate(self, player: str, opponents: Iterable[str] | None = None) -> tuple[float, int]:
        """(win rate, games) of ``player`` since its last snapshot or reset, against
        ``opponents`` (default: everyone but itself); draws count half; (0, 0) without games."""
        rows = self.since.get(player, {})
        keys = [o for o in rows if o != player] if opponents is None else [o for o in opponents if o in rows]
        w = sum(rows[o][0] for o in keys)
        d = sum(rows[o][1] for o in keys)
        n = sum(sum(rows[o]) for o in keys)
        return ((w + 0.5 * d) / n if n else 0.0), n

    # -- weights of learning agents ---------------------------------------------------------------
    def hear_weights(self, player: str, w: LearnerWeights, now: float) -> bool:
        """A broadcast of ``player``'s learner: kept as its newest if newer (after a reset, only
        once a fresh learner's weights come: ``updates`` below the old learner's last). The served
        copy follows at most every ``live_refresh_s`` (at once when none is served)."""
        if player not in self.players or self.players[player].kind != LEARNER:
            return False
        if self._version_offset.get(player):
            w = LearnerWeights(w.version + self._version_offset[player], w.updates, w.arch, w.params)
        stale = self._stale_updates.get(player)
        old = self.live.get(player)
        if stale is not None:
            if w.updates >= stale:
                return False
            del self._stale_updates[player]
        elif old is not None and w.version <= old.version:
            return False
        self.live[player] = w
        if player not in self.served or now - self._served_at.get(player, -math.inf) >= self.cfg.live_refresh_s:
            self.served[player] = w
            self._served_at[player] = now
            p = self.players[player]
            p.version, p.updates = w.version, w.updates
        return True

    def weights_of(self, pid: str) -> LearnerWeights | None:
        """The weights served for ``pid`` (a snapshot's, or a learning agent's served copy)."""
        p = self.players.get(pid)
        if p is None or p.kind in (BOT, FROZEN):
            return None
        return self.weights.get(pid) if p.kind == SNAPSHOT else self.served.get(pid)

    # -- snapshots and resets --------------------------------------------------------------------
    def snapshot_due(self, player: str, now: float) -> str | None:
        """Why a snapshot of main agent ``player`` is due now ("timer" or "win_rate"), or None."""
        p = self.players[player]
        if p.role != "main" or player not in self.live:
            return None
        age = now - p.last_snapshot_at
        if age >= self.cfg.snapshot_interval_s:
            return "timer"
        rate, n = self.since_rate(player)
        if age >= self.cfg.min_snapshot_interval_s and n >= self.cfg.min_games and rate >= self.cfg.snapshot_win_rate:
            return "win_rate"
        return None

    def reset_due(self, player: str, now: float) -> str | None:
        """Why exploiter ``player`` is due for a reset now ("timer" or "win_rate"), or None."""
        p = self.players[player]
        if p.role != "exploiter":
            return None
        rate, n = self.since_rate(player, [self.main_id])
        if n >= self.cfg.min_games and rate >= self.cfg.exploiter_win_rate:
            return "win_rate"
        if now - p.reset_at >= self.cfg.exploiter_reset_s:
            return "timer"
        return None

    def add_snapshot(self, player: str, now: float) -> str | None:
        """Freeze ``player``'s newest weights as a new snapshot player; its id, or None without
        weights. Beyond ``max_snapshots`` the oldest snapshot leaves (with its table rows)."""
        w = self.live.get(player)
        if w is None:
            return None
        p = self.players[player]
        p.snapshots += 1
        sid = f"{player}-g{p.generation}-s{p.snapshots}" if p.role == "exploiter" else f"{player}-s{p.snapshots}"
        self.players[sid] = Player(sid, SNAPSHOT, p.role, now, parent=player, version=w.version, updates=w.updates,
                                   generation=p.generation)
        self.weights[sid] = w
        p.last_snapshot_at = now
        if p.role == "main":
            self.since[player] = {}
        snaps = [q.id for q in self.players.values() if q.kind == SNAPSHOT]
        for old in snaps[:max(0, len(snaps) - self.cfg.max_snapshots)]:
            self.remove(old)
        return sid

    def reset(self, player: str, now: float, reason: str) -> str | None:
        """Reset exploiter ``player``: a snapshot of its weights joins (for a "win_rate" reset,
        or on the timer with ``exploiter_snapshot_on_timeout``), its generation goes up, its
        results since the reset and its weights are forgotten (the next ones must come from a
        fresh learner). Returns the snapshot's id, if one joined."""
        p = self.players[player]
        sid = None
        if reason == "win_rate" or self.cfg.exploiter_snapshot_on_timeout:
            sid = self.add_snapshot(player, now)
        old = self.live.pop(player, None)
        self.served.pop(player, None)
        if old is not None:
            self._stale_updates[player] = old.updates
            self._version_offset[player] = old.version + 1
        p.generation += 1
        p.reset_at = p.last_snapshot_at = now
        p.version, p.updates = -1, 0
        p.snapshots = 0
        self.since[player] = {}
        return sid

    def remove(self, pid: str) -> None:
        self.players.pop(pid, None)
        self.weights.pop(pid, None)
        self.payoff.remove(pid)
        for rows in self.since.values():
            rows.pop(pid, None)

    def tick(self, now: float) -> list[tuple[str, str, str | None, str]]:
        """Apply the snapshot and reset rules: ``[(event, player, snapshot id or None, reason)]``
        with event "snapshot" or "reset"."""
        events = []
        for pid in self.learners():
            p = self.players[pid]
            if p.role == "main":
                why = self.snapshot_due(pid, now)
                if why is not None:
                    events.append(("snapshot", pid, self.add_snapshot(pid, now), why))
            else:
                why = self.reset_due(pid, now)
                if why is not None:
                    events.append(("reset", pid, self.reset(pid, now, why), why))
        return events

    # -- persistence -------------------------------------------------------------------------------
    def to_state(self, now: float | None = None) -> dict[str, Any]:
        """JSON-ready state (snapshot weights excluded: stored by the caller, one file each);
        ``now``: when it is saved (a restored league's timers skip the time it was down)."""
        return {"format": STATE_FORMAT, "saved_at": now, "players": [p.to_dict() for p in self.players.values()],
                "payoff": self.payoff.to_state(), "since": self.since, "results_total": self.results_total,
                "stale_updates": self._stale_updates, "version_offset": self._version_offset}

    @classmethod
    def from_state(cls, cfg: LeagueConfig, state: Mapping[str, Any], weights: Mapping[str, LearnerWeights],
                   now: float, frozen: Iterable[str] = ()) -> "League":
        """The league saved in ``state`` with snapshot ``weights`` (a snapshot whose weights are
        missing is dropped, so is a bot, frozen file or agent the config no longer names, with
        their table rows). Players the config names that the state lacks join; learning agents
        serve nothing until their learners are heard again."""
        if state.get("format") != STATE_FORMAT:
            raise ValueError(f"league state format {state.get('format')!r} is not {STATE_FORMAT}")
        frozen = list(frozen)
        lg = cls(cfg, now, frozen)
        saved = [Player.from_dict(d) for d in state.get("players", [])]
        fresh = lg.players
        lg.players = {}
        # the snapshot and reset timers count the league's running time: skip the downtime
        down = max(0.0, now - float(state["saved_at"])) if state.get("saved_at") is not None else 0.0
        for p in saved:
            p.last_snapshot_at += down
            p.reset_at += down
            if p.kind == SNAPSHOT and p.id not in weights:
                continue
            if (p.kind == LEARNER and p.id not in cfg.agents) or (p.kind == BOT and p.id not in cfg.bots) \
                    or (p.kind == FROZEN and p.id not in frozen):
                continue
            lg.players[p.id] = p
        for pid, p in fresh.items():
            lg.players.setdefault(pid, p)
        lg.payoff = Payoff.from_state(state.get("payoff", {}), cfg.decay)
        lg.since = {k: {o: [int(x) for x in c] for o, c in v.items()} for k, v in state.get("since", {}).items()}
        lg.results_total = int(state.get("results_total", 0))
        lg._stale_updates = {k: int(v) for k, v in state.get("stale_updates", {}).items()}
        lg._version_offset = {k: int(v) for k, v in state.get("version_offset", {}).items()}
        lg.weights = {k: v for k, v in weights.items() if k in lg.players}
        gone = {a for pair in lg.payoff.counts for a in pair} - set(lg.players)  # rows of players that left
        for pid in gone:
            lg.payoff.remove(pid)
        return lg

    # -- what status shows ---------------------------------------------------------------------------
    def table(self) -> dict[str, Any]:
        """Players (id, kind, role, version, games) and the W/D/L matrix, in join order."""
        ids = list(self.players)
        counts = np.zeros((len(ids), len(ids), 3), dtype=np.int64)
        for i, a in enumerate(ids):
            for j, b in enumerate(ids):
                counts[i, j] = self.payoff.wdl(a, b)
        return {"ids": ids, "counts": counts}
