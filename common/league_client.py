"""An actor's side of the league (``zenrl league``): the league chooses each match's opponent
and hears each match's result.

:class:`LeagueChooser` is a chooser for :class:`~zenrl.common.opponents.OpponentWrapper`
(``chooser(pool, rng) -> name | None``) and its ``on_result`` callback:

* it keeps ``league.prefetch`` opponent assignments requested ahead (``league/opponent``
  queries in flight, answered on Zenoh's thread into a queue), so that a reset takes a ready
  one and never waits for the network;
* a policy opponent (a frozen snapshot, or a learning agent's served weights) is fetched once
  per (player, version) from ``league/weights``, checked against this actor's network
  (architecture fingerprint, finite values), built and added to the pool as
  ``league:<player>@<version>``; older versions of the same player leave the pool;
* while the league is away (or before the first answer) a reset falls back to the last
  opponent played, or to the env's own draw from ``env.kwargs.opponents`` (the bots);
* a ``frozen`` opponent is this actor's own ``opponents.pool`` entry of that name (a policy
  file it loaded at start, as every actor of the run does);
* every finished match the league assigned is published as a
  :class:`~zenrl.common.protocol.MatchResult` on ``league/results/<actor>``, citing the
  assignment's ticket (league/tickets.py: the league counts one result per assignment); a match
  the league did not assign (a fallback to the last opponent, the env's own draw) has no ticket
  to cite and is not reported (``league/unticketed``). "busy" (asking faster than the league's
  rate) backs off for a second, as a timeout does.

The network work (decoding weights, building a network) happens in the actor's thread, at a
reset; the Zenoh callbacks only append to a deque.
"""

from __future__ import annotations

import collections
import logging
import time
from typing import Any, Callable

import numpy as np
import torch

from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.errors import ProtocolError
from zenrl.common.networks import arch_fingerprint, arrays_to_params
from zenrl.common.opponents import MatchResult as LocalResult
from zenrl.common.opponents import Opponent, OpponentPool

log = logging.getLogger(__name__)

#: prefix of the pool names of the league's opponents
LEAGUE_PREFIX = "league:"
_OUTCOMES = {"win": 1, "draw": 0, "loss": -1}


def pool_name(player: str, version: int) -> str:
    return f"{LEAGUE_PREFIX}{player}@{version}"


def parse_pool_name(name: str) -> tuple[str, int] | None:
    """``league:<player>@<version>`` -> (player, version); None for another name."""
    if not name.startswith(LEAGUE_PREFIX) or "@" not in name:
        return None
    player, _, v = name[len(LEAGUE_PREFIX):].rpartition("@")
    try:
        return player, int(v)
    except ValueError:
        return None


class LeagueChooser:
    """One per actor process, shared by its envs (see the module docstring). ``node``: the
    actor's transport node; ``make_net()``: a fresh policy network of this actor's architecture
    (the opponent's weights are loaded into it); ``version_fn()``: the weights version the actor
    acts with now (reported with each result)."""

    def __init__(self, cfg: RunConfig, node: Any, actor_id: str, make_net: Callable[[], torch.nn.Module],
                 version_fn: Callable[[], int] = lambda: -1, clock: Callable[[], float] = time.monotonic) -> None:
        lc = cfg.league
        if lc.run_id is None or lc.player is None:
            raise ValueError("a league chooser needs league.run_id and league.player (zenrl run sets them)")
        self.cfg, self.node, self.actor_id = cfg, node, actor_id
        self.keys = P.LeagueKeys(lc.run_id)
        self.player = lc.player
        self.prefetch = lc.prefetch
        self.first_wait_s = lc.first_wait_s
        self.epsilon = lc.opponent_epsilon
        self.bots = set(lc.bots)
        self.frozen = set(cfg.opponents.pool)
        self.timeout_s = cfg.transport.query_timeout_s
        self.max_bytes = min(cfg.transport.max_message_bytes, lc.max_weights_bytes)
        self.make_net, self.version_fn, self.clock = make_net, version_fn, clock
        self.arch: str | None = None
        self.generation: int | None = None  # pinned at the first answer: results carry it
        self._replies: collections.deque[tuple[str, bytes | None]] = collections.deque()
        self._inflight = 0
        self._waiting: list[tuple[str, str, int, int]] = []   # (player, kind, version, ticket) whose weights are on the way
        self._fetching: set[tuple[str, int]] = set()
        self.ready: collections.deque[tuple[str, int]] = collections.deque()  # (pool name, ticket), in the order assigned
        # tickets of the assignments handed to an episode and not reported yet, by pool name (the
        # league only checks a ticket's pairing, so any open ticket of that name answers a match of it)
        self._open: dict[str, collections.deque[int]] = {}
        self.last: str | None = None
        self.counts: collections.Counter[str] = collections.Counter()
        self._retry_at = 0.0

    # -- the chooser ------------------------------------------------------------------------------
    def __call__(self, pool: OpponentPool, rng: np.random.Generator) -> str | None:
        """The next episode's opponent: the next ready assignment, else the last opponent, else
        None (the env's own draw). Only the very first call (before any env step) waits, at
        most ``league.first_wait_s``, for the league's first answer."""
        self.pump(pool)
        if self.last is None and not self.ready and self.first_wait_s > 0:
            deadline = self.clock() + self.first_wait_s
            self.first_wait_s = 0.0
            while not self.ready and (self._inflight > 0 or self._waiting) and self.clock() < deadline:
                time.sleep(0.02)
                self.pump(pool)
        while self.ready:
            name, ticket = self.ready.popleft()
            if name in pool:
                self.last = name
                self.counts["assigned"] += 1
                self._open.setdefault(name, collections.deque(maxlen=1024)).append(ticket)
                return name
        self.counts["fallback"] += 1
        return self.last if self.last in pool else None

    def pump(self, pool: OpponentPool) -> None:
        """Handle the replies that came, then ask for more assignments up to ``prefetch``."""
        while self._replies:
            what, payload = self._replies.popleft()
            if what == "opponent":
                self._inflight -= 1
                self._on_opponent(pool, payload)
            else:
                self._on_weights(pool, what, payload)
        want = self.prefetch - self._inflight - len(self.ready) - len(self._waiting)
        if want > 0 and self.clock() >= self._retry_at:
            req = P.OpponentRequest(self.player, self.actor_id).encode()
            for _ in range(want):
                self._inflight += 1
                self.node.query_async(self.keys.opponent, req, self.timeout_s,
                                      lambda p: self._replies.append(("opponent", p)))

    def _on_opponent(self, pool: OpponentPool, payload: bytes | None) -> None:
        if payload is None:
            self.counts["timeouts"] += 1
            self._retry_at = self.clock() + 1.0  # the league is away: ask again a little later
            return
        try:
            rep = P.OpponentReply.decode(payload, 4096)
        except ProtocolError as e:
            self.counts["bad_replies"] += 1
            log.warning("league reply rejected: %s", e)
            return
        if rep.status != "ok":
            self.counts[f"reply_{rep.status}"] += 1
            if rep.status == "busy":
                self._retry_at = self.clock() + 1.0
            if rep.status == "unknown" and self.counts["reply_unknown"] == 1:  # once: the config is wrong
                log.error("the league does not know player %s: %s; playing the env's own opponents",
                          self.player, rep.reason)
            return
        if self.generation is None:
            self.generation = rep.generation
        if rep.kind == "frozen":  # a policy file of opponents.pool, loaded by this actor at start
            if rep.opponent in pool:
                self.ready.append((rep.opponent, rep.ticket))
            else:
                self.counts["frozen_missing"] += 1
            return
        if rep.kind == "bot":
            name = pool_name(rep.opponent, -1)
            if name not in pool:
                pool.add(Opponent(name, "bot", 0.0, bot=rep.opponent))
            self.ready.append((name, rep.ticket))
            return
        name = pool_name(rep.opponent, rep.version)
        if name in pool:
            self.ready.append((name, rep.ticket))
            return
        self._waiting.append((rep.opponent, rep.kind, rep.version, rep.ticket))
        if (rep.opponent, rep.version) not in self._fetching:
            self._fetching.add((rep.opponent, rep.version))
            req = P.PlayerWeightsRequest(rep.opponent, rep.version).encode()
            tag = f"weights:{rep.opponent}@{rep.version}"
            self.node.query_async(self.keys.weights, req, self.timeout_s, lambda p: self._replies.append((tag, p)))

    def _on_weights(self, pool: OpponentPool, tag: str, payload: bytes | None) -> None:
        player, _, v = tag[len("weights:"):].rpartition("@")
        asked = (player, int(v))
        self._fetching.discard(asked)
        name = None
        try:
            if payload is None:
                raise ProtocolError("reply", "no weights came before the timeout", "timeout")
            w = P.PlayerWeights.decode(payload, self.max_bytes)
            if w.status != "ok" or w.params is None:
                raise ProtocolError("status", f"{w.player}: {w.reason or w.status}", "missing")
            net = self.make_net()
            arch = arch_fingerprint(net)
            if w.arch != arch:
                raise ProtocolError("arch", f"weights for {w.arch}, this actor's network is {arch}", "arch")
            arrays_to_params(net, w.params)
            net.eval()
            name = pool_name(w.player, w.version)
            for old in [n for n in pool.names() if (parse_pool_name(n) or ("", 0))[0] == w.player and n != name]:
                pool.remove(old)
            pool.add(Opponent(name, "snapshot", 0.0, net=net, epsilon=self.epsilon))
            self.counts["weights_loaded"] += 1
        except (ProtocolError, ValueError, RuntimeError) as e:
            self.counts["weights_rejected"] += 1
            log.warning("league weights for %s@%s not used: %s", *asked, e)
        # assignments waiting for these weights: ready if the pool holds the player now
        keep = []
        for pid, kind, ver, ticket in self._waiting:
            if (pid, ver) == asked:
                if name is not None:
                    self.ready.append((name, ticket))
            else:
                keep.append((pid, kind, ver, ticket))
        self._waiting = keep

    # -- results ----------------------------------------------------------------------------------
    def report(self, r: LocalResult) -> None:
        """Publish one finished match (``on_result`` of the wrapper) with the ticket of its
        assignment. A match against an opponent that is no league player is not reported
        (``unreported``), nor one the league did not assign (``unticketed``)."""
        parsed = parse_pool_name(r.opponent)
        if parsed is None:
            if r.opponent not in self.bots and r.opponent not in self.frozen:
                self.counts["unreported"] += 1
                return
            parsed = (r.opponent, -1)
        opponent, version = parsed
        tickets = self._open.get(r.opponent)
        if not tickets:
            self.counts["unticketed"] += 1
            return
        ticket = tickets.popleft()
        if not tickets:  # (a live player's names change with its versions: no key is kept empty)
            del self._open[r.opponent]
        msg = P.MatchResult(actor_id=self.actor_id, player=self.player, generation=self.generation or 0,
                            player_version=max(-1, int(self.version_fn())), opponent=opponent,
                            opponent_version=version, outcome=_OUTCOMES[r.outcome],
                            my_score=max(0, min(int(r.my_score), P.MAX_MATCH_SCORE)),
                            enemy_score=max(0, min(int(r.enemy_score), P.MAX_MATCH_SCORE)), ticket=ticket)
        self.node.put(self.keys.results(self.actor_id), msg.encode())
        self.counts["reported"] += 1

    def values(self) -> dict[str, int]:
        """Stats: ``league/<counter>``."""
        return {f"league/{k}": int(v) for k, v in self.counts.items()}
