"""Assignment tickets: a match result counts only as the answer to an assignment the league made.

Without them an actor could report any number of results, against any opponent it names, and
steer the payoff table (PFSP's weights, the snapshot and reset rules) at will. With them:

* each opponent assignment (``league/opponent``) carries a ticket, a random 63-bit number the
  league remembers for the asking actor, with the (player, opponent, version) it assigned;
* a result (``league/results/<actor>``) counts only if it cites a ticket still open for that
  actor and for the same player, opponent and opponent version; the ticket is then closed, so
  a result cannot be replayed, nor reported against an opponent the league did not assign;
* each actor id gets assignments at most at ``rate_per_s`` (a token bucket of ``burst``), so
  the results an actor can report are bounded by the matches it could have played;
* each actor keeps at most ``open_per_actor`` open tickets (the oldest is dropped: an actor that
  restarted leaves its assignments behind) and the book tracks at most ``max_actors`` ids (the
  least recently seen is dropped), so a flood of requests under made-up ids holds bounded memory.

What tickets cannot do: check the outcome. An actor can still report a loss as a win for a
match it was assigned; under the secured router (docs/cluster.md) only under its own id, and
at most at its rate. Tickets live in the league process's memory: results of matches assigned
before a league restart are rejected (``ticket_unknown``), a few per actor.

Pure logic with an injectable clock; the league service calls it under its lock.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from typing import Callable

import numpy as np

#: a ticket's number is drawn from 1..TICKET_MAX (0 means "no ticket" on the wire)
TICKET_MAX = (1 << 63) - 1


@dataclasses.dataclass
class _Actor:
    tokens: float
    refilled_at: float
    open: collections.OrderedDict[int, tuple[str, str, int]] = dataclasses.field(default_factory=collections.OrderedDict)


class TicketBook:
    """The open tickets of every actor id (see the module docstring)."""

    def __init__(self, rate_per_s: float, burst: int, open_per_actor: int, max_actors: int,
                 rng: np.random.Generator | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        if rate_per_s <= 0 or burst < 1 or open_per_actor < 1 or max_actors < 1:
            raise ValueError("ticket limits must be positive")
        self.rate, self.burst = float(rate_per_s), float(burst)
        self.open_per_actor, self.max_actors = int(open_per_actor), int(max_actors)
        self.rng = rng if rng is not None else np.random.default_rng()
        self.clock = clock
        self._actors: collections.OrderedDict[str, _Actor] = collections.OrderedDict()
        self.dropped_tickets = 0   # open tickets dropped for room (per actor, or with their actor)
        self.dropped_actors = 0

    def _actor(self, actor_id: str) -> _Actor:
        a = self._actors.get(actor_id)
        if a is None:
            a = self._actors[actor_id] = _Actor(self.burst, self.clock())
            while len(self._actors) > self.max_actors:
                _, old = self._actors.popitem(last=False)
                self.dropped_actors += 1
                self.dropped_tickets += len(old.open)
        else:
            self._actors.move_to_end(actor_id)
        return a

    def issue(self, actor_id: str, player: str, opponent: str, version: int) -> int | None:
        """A new ticket for this assignment, or None when ``actor_id`` asks faster than its rate
        (nothing is recorded then)."""
        a = self._actor(actor_id)
        now = self.clock()
        a.tokens = min(self.burst, a.tokens + max(0.0, now - a.refilled_at) * self.rate)  # a clock set back adds nothing
        a.refilled_at = now
        if a.tokens < 1.0:
            return None
        a.tokens -= 1.0
        ticket = int(self.rng.integers(1, TICKET_MAX, dtype=np.int64))
        while ticket in a.open:  # 1 in 2^63; kept exact anyway
            ticket = int(self.rng.integers(1, TICKET_MAX, dtype=np.int64))
        a.open[ticket] = (player, opponent, int(version))
        while len(a.open) > self.open_per_actor:
            a.open.popitem(last=False)
            self.dropped_tickets += 1
        return ticket

    def redeem(self, actor_id: str, ticket: int, player: str, opponent: str, version: int,
               newer_ok: bool = False) -> tuple[str, str] | None:
        """Close ``ticket`` for a result of ``actor_id``: None if it was open for exactly this
        (player, opponent, version), or with ``newer_ok`` (a learning opponent, whose weights
        the league serves at their newest when asked) for that version or a later one; else
        (reason, detail). A ticket cited for another pair is closed all the same (it was misused)."""
        a = self._actors.get(actor_id)
        want = None if a is None else a.open.pop(ticket, None)
        if want is None:
            return ("ticket_unknown", f"ticket {ticket} is not open for {actor_id} (never assigned, already "
                    "reported, dropped, or assigned before a league restart)")
        if want[:2] != (player, opponent) or not (want[2] == int(version) or newer_ok and int(version) > want[2]):
            return ("ticket_mismatch", f"ticket {ticket} was assigned for {want[0]} vs {want[1]}@{want[2]}, "
                    f"the result is {player} vs {opponent}@{version}")
        return None

    def open_count(self, actor_id: str | None = None) -> int:
        """Open tickets of one actor, or of all."""
        if actor_id is not None:
            a = self._actors.get(actor_id)
            return 0 if a is None else len(a.open)
        return sum(len(a.open) for a in self._actors.values())

    def __len__(self) -> int:
        """Actor ids tracked."""
        return len(self._actors)
