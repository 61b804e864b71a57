"""The entry points of the role processes whose loop depends on the algorithm: ``zenrl
learner`` and ``zenrl actor``. Each opens the transport node, picks the algorithm's part from
:data:`zenrl.algorithms.ALGORITHMS` and runs it until ``stop``. (``zenrl replay`` and ``zenrl
evaluator`` are the same for every algorithm: :func:`zenrl.replay.service.main`,
:func:`zenrl.actor.evaluator.main`.)
"""

from __future__ import annotations

import os
import re
import socket
import threading

from zenrl.actor.slots import claim_slot
from zenrl.algorithms import algorithm
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.league_reset import GenerationWatch
from zenrl.common.transport import Node


def learner_main(cfg: RunConfig, run_id: str, stop: threading.Event, resume: str = "never") -> None:
    """``zenrl learner``: the configured algorithm's learner in the role loop. ``resume``:
    "never", "require" (newest valid checkpoint, an error if none) or "auto" (resume if a
    checkpoint exists)."""
    with Node.from_config(cfg.transport) as node:
        algorithm(cfg.algo).learner(cfg, node, run_id, resume).run(stop)


def default_actor_id() -> str:
    """``actor-<host>-<pid>``, made a valid key chunk."""
    return re.sub(r"[^A-Za-z0-9_.-]", "-", f"actor-{socket.gethostname()}-{os.getpid()}")[:64]


def actor_main(cfg: RunConfig, run_id: str, stop: threading.Event, actor_id: str | None = None,
               slot: int | None = None, bound_slot: int | None = None) -> None:
    """``zenrl actor``: the configured algorithm's actor. Its exploration slot is ``slot``, else
    ``actor.slot``, else one claimed from the running system (elastic: the ladder's size is then
    not fixed, ``num_slots`` None). ``bound_slot``: claim exactly this slot (a secured actor's
    login ``actor-<i>`` may hold only slot ``i``; zenrl/identity.py)."""
    actor_id = actor_id or default_actor_id()
    num_slots: int | None = cfg.actor.ladder_size or cfg.actor.num_actors
    if slot is None and bound_slot is None:
        slot = cfg.actor.slot
    with Node.from_config(cfg.transport) as node:
        watch = GenerationWatch.for_config(cfg, node, run_id, "actor", stop, stateful=False)  # league.self_reset
        if slot is None:
            slot, _ = claim_slot(node, P.Keys(run_id), actor_id, only=bound_slot)
            num_slots = None
        algorithm(cfg.algo).actor(cfg, node, run_id, actor_id, slot, num_slots, stop)
        if watch is not None:
            watch.finish([])
