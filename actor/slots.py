"""Elastic exploration slots: an actor claims the lowest free slot by declaring the liveliness
token ``slots/<k>/<actor-id>``. A slot whose holder the replay has quarantined (it holds
``quarantine/<actor-id>``) counts as free, so a well-behaved actor takes it over. Tokens vanish when an actor dies (at once on a crash, after the
lease when frozen), so slots are reused; no central service holds the assignment.

Claiming: read the tokens alive now, pick the lowest free slot (the previous one if it is still
free), declare the token, wait until it is listed, look again after a settle time, then keep
the slot only if this actor's id is the smallest among the slot's holders then listed;
otherwise withdraw and retry after a random back-off. A session lists its own tokens too, so
seeing one's own token does not prove the router has it; the second look, once a concurrent
rival's token has reached the router, is what makes two concurrent claims agree: both list
each other, and at most one of them keeps the slot.

A secured actor (login ``actor-<i>``, zenrl/identity.py) claims exactly slot ``i`` (``only``):
the router's access control lets that login hold no other slot token, and no other login hold
that one, so no actor can take another's slot.
"""

from __future__ import annotations

import logging
import random
import time
from typing import Any

from zenrl.common import protocol as P
from zenrl.common.errors import TransportError
from zenrl.common.transport import Node

log = logging.getLogger(__name__)


def _holders(node: Node, keys: P.Keys, slot: int | None = None) -> list[tuple[int, str]]:
    out = []
    for k in node.alive_now(keys.slot_holders(slot), timeout_s=2.0):
        try:
            out.append(keys.parse_slot(k))
        except P.ProtocolError:
            continue
    return out


def quarantined(node: Node, keys: P.Keys) -> set[str]:
    """Actor ids the replay drops now (it holds a ``quarantine/<actor>`` token for each)."""
    return {k.rsplit("/", 1)[-1] for k in node.alive_now(keys.quarantined_all, timeout_s=2.0)}


def claim_slot(node: Node, keys: P.Keys, actor_id: str, previous: int | None = None, visible_within_s: float = 10.0,
               attempts: int = 20, seed: int | None = None, only: int | None = None,
               settle_s: float = 0.3) -> tuple[int, Any]:
    """Claim a slot; returns ``(slot, token)`` (the token is undeclared when ``node`` closes).
    ``visible_within_s``: how long a declared token may take to be listed by the router.
    ``only``: claim this slot or none (:class:`TransportError` after ``attempts``).
    ``settle_s``: the wait before the second look at the slot's holders."""
    rng = random.Random(seed if seed is not None else actor_id)
    for _ in range(attempts):
        # a quarantined actor's slot counts as free: its data is dropped, so its slot explores nothing
        bad = quarantined(node, keys)
        used = {s for s, a in _holders(node, keys) if a != actor_id and a not in bad}
        if only is not None:
            cand = only
        elif previous is not None and previous not in used:
            cand = previous
        else:
            cand = next(i for i in range(len(used) + 1) if i not in used)
        token = node.token(keys.slot_token(cand, actor_id))
        deadline = time.monotonic() + visible_within_s
        while True:  # until the router lists our own token: then it lists every earlier claim too
            holders = sorted(a for _, a in _holders(node, keys, cand) if a not in bad)
            if actor_id in holders or time.monotonic() > deadline:
                break
            time.sleep(0.01)  # poll interval (each look is a round trip to the router)
        if actor_id in holders:
            # the session answers a liveliness query with its own tokens too, so seeing ours does
            # not prove the router had it: look once more after a settle time, by which a rival's
            # concurrent token has reached the router and both rivals list each other
            time.sleep(settle_s)
            holders = sorted(a for _, a in _holders(node, keys, cand) if a not in bad)
        if holders and holders[0] == actor_id:
            log.info("actor %s holds exploration slot %d", actor_id, cand)
            return cand, token
        node.withdraw(token)
        time.sleep(rng.uniform(0.05, 0.3))  # back off before the next try
    if only is not None:
        raise TransportError(f"actor {actor_id} could not claim its exploration slot {only} in {attempts} attempts "
                             f"(another actor holds it, or the router drops this login's token for it)")
    raise TransportError(f"actor {actor_id} could not claim an exploration slot in {attempts} attempts")
