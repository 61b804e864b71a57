"""The league's assignment tickets (league/tickets.py), alone: a result answers one open
assignment of its actor for its pairing, once; the per-actor rate and the memory bounds."""

import numpy as np
import pytest

from zenrl.league.tickets import TicketBook


class Clock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


def book(clock, **kw):
    args = dict(rate_per_s=1.0, burst=3, open_per_actor=4, max_actors=2)
    args.update(kw)
    return TicketBook(rng=np.random.default_rng(0), clock=clock, **args)


def test_one_result_per_assignment_of_that_actor_and_pairing():
    b = book(Clock())
    t = b.issue("a0", "main", "cheese", -1)
    assert t is not None and t > 0
    assert b.redeem("a1", t, "main", "cheese", -1)[0] == "ticket_unknown"   # another actor's
    assert b.redeem("a0", t, "main", "cheese", -1) is None
    assert b.redeem("a0", t, "main", "cheese", -1)[0] == "ticket_unknown"   # spent
    t2 = b.issue("a0", "main", "main-s3", 7)
    assert b.redeem("a0", t2, "main", "main-s3", 8)[0] == "ticket_mismatch"  # another version
    assert b.redeem("a0", t2, "main", "main-s3", 7)[0] == "ticket_unknown"   # a misused ticket is spent
    assert b.redeem("a0", 0, "main", "cheese", -1)[0] == "ticket_unknown"


def test_the_rate_refills_with_time_and_a_clock_set_back_adds_nothing():
    c = Clock(100.0)
    b = book(c, open_per_actor=100)
    assert [b.issue("a0", "main", "cheese", -1) is not None for _ in range(4)] == [True] * 3 + [False]
    c.t += 0.5
    assert b.issue("a0", "main", "cheese", -1) is None
    c.t += 0.5
    assert b.issue("a0", "main", "cheese", -1) is not None
    c.t -= 50.0
    assert b.issue("a0", "main", "cheese", -1) is None
    c.t += 1000.0
    assert [b.issue("a0", "main", "cheese", -1) is not None for _ in range(4)] == [True] * 3 + [False]  # burst caps


def test_open_tickets_and_actor_ids_are_bounded():
    c = Clock()
    b = book(c, burst=100, rate_per_s=100.0)
    first = [b.issue("a0", "main", "cheese", -1) for _ in range(6)]
    assert b.open_count("a0") == 4 and b.dropped_tickets == 2
    assert b.redeem("a0", first[0], "main", "cheese", -1)[0] == "ticket_unknown"  # the oldest went
    assert b.redeem("a0", first[-1], "main", "cheese", -1) is None
    b.issue("a1", "main", "cheese", -1)
    b.issue("a0", "main", "cheese", -1)   # a0 seen last: a1 is the least recent
    b.issue("a2", "main", "cheese", -1)   # a third id: a1 is dropped with its ticket
    assert len(b) == 2 and b.dropped_actors == 1 and b.open_count("a1") == 0
    assert b.open_count() == b.open_count("a0") + b.open_count("a2")


def test_tickets_are_distinct_and_limits_positive():
    b = book(Clock(), burst=1000, rate_per_s=1.0, open_per_actor=1000)
    ts = [b.issue("a0", "main", "cheese", -1) for _ in range(500)]
    assert len(set(ts)) == 500 and min(ts) >= 1
    with pytest.raises(ValueError):
        TicketBook(0.0, 1, 1, 1)
