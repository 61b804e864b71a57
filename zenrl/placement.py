"""CPU placement of ``zenrl run``'s processes on small machines.

On a 2-core machine the OS shares the CPUs out evenly between every runnable process, so two
uncapped actors, the replay and the router leave the Ape-X learner about half a core: it trained
at ~97 updates/s there, against ~300 alone. With ``cpu_placement: auto`` (set by
``configs/cartpole_apex.yaml``; the default is ``off``) the launcher reserves the last
``learner.torch_threads`` CPUs for the learner, runs every other process and its own router on
the remaining CPUs, and lowers the actors' scheduling priority (nice +5) so that the replay, the
router and the evaluator, which share those CPUs with them, answer promptly.

The launcher computes a :class:`Placement` per process and passes it in the environment
(:data:`CPUS_ENV`, :data:`NICE_ENV`); the child applies it (:func:`apply_from_env`) once its
modules are imported (on every CPU, in parallel with the others) and before it starts a thread,
so every thread it starts inherits it. Linux only: elsewhere :func:`plan` places nothing.

It pays where data is cheap (CartPole's actors make ~15 k env steps/s, far more than the learner
consumes) and costs where it is dear: on the Burger War match (pybullet) it halved the env steps
in a 50 s run (11 k -> 6 k) without more updates, so the match configs leave it off.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

log = logging.getLogger(__name__)

CPUS_ENV = "ZENRL_CPUS"
NICE_ENV = "ZENRL_NICE"
ACTOR_NICE = 5
#: the exporter yields to every role that trains: monitoring must not cost training time
EXPORTER_NICE = 10
MAX_CPUS_AUTO = 4  # measured on 2 CPUs only; larger machines are left to the OS


@dataclass(frozen=True)
class Placement:
    """``cpus``: the CPU ids a process may run on (None: unchanged); ``nice``: added niceness."""

    cpus: tuple[int, ...] | None = None
    nice: int = 0

    def env(self) -> dict[str, str]:
        out = {}
        if self.cpus is not None:
            out[CPUS_ENV] = ",".join(str(c) for c in self.cpus)
        if self.nice:
            out[NICE_ENV] = str(self.nice)
        return out


def usable_cpus() -> list[int]:
    """CPU ids this process may run on (all of them where affinity is not supported)."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def plan(mode: str, places_learner: bool, learner_threads: int, cpus: list[int]) -> dict[str, Placement] | None:
    """Placement per role (``learner``, ``actor``, ``replay``, ``evaluator``, ``exporter``, and ``router``: the
    launcher's own Zenoh router), or None when
    ``mode`` is ``off``, the algorithm does not place its learner (A3C), affinity is unsupported, or ``cpus`` has more
    than :data:`MAX_CPUS_AUTO` or not more than ``learner_threads`` CPUs."""
    if mode != "auto" or not places_learner or not hasattr(os, "sched_setaffinity"):
        return None
    if len(cpus) > MAX_CPUS_AUTO or len(cpus) <= learner_threads:
        return None
    learner = tuple(cpus[-learner_threads:])
    rest = tuple(cpus[:-learner_threads])
    return {"learner": Placement(learner), "actor": Placement(rest, ACTOR_NICE),
            "replay": Placement(rest), "evaluator": Placement(rest), "router": Placement(rest),
            "exporter": Placement(rest, EXPORTER_NICE)}


def describe(p: dict[str, Placement]) -> str:
    """One log line: which CPUs each role gets."""
    parts = []
    for role, pl in p.items():
        cpus = ",".join(str(c) for c in pl.cpus or ())
        parts.append(f"{role} on CPU {cpus}" + (f" (nice +{pl.nice})" if pl.nice else ""))
    return "; ".join(parts)


def apply_from_env(environ: dict[str, str] | None = None) -> Placement | None:
    """Apply :data:`CPUS_ENV` / :data:`NICE_ENV` to this process (call before starting threads).
    Returns what was applied (each part on its own: CPUs applied and niceness refused gives the
    CPUs and nice 0), None if nothing was asked or applied. A malformed value or a refused call
    is logged and skipped: placement is an optimisation, never a reason not to run."""
    env = os.environ if environ is None else environ
    cpus_s, nice_s = env.get(CPUS_ENV, ""), env.get(NICE_ENV, "")
    cpus: tuple[int, ...] | None = None
    nice = 0
    if cpus_s:
        try:
            wanted = tuple(int(c) for c in cpus_s.split(","))
            os.sched_setaffinity(0, wanted)
            cpus = wanted
        except (ValueError, OSError, AttributeError) as e:
            log.warning("cpu placement %s=%r not applied: %s", CPUS_ENV, cpus_s, e)
    if nice_s:
        try:
            wanted_nice = int(nice_s)
            os.nice(wanted_nice)
            nice = wanted_nice
        except (ValueError, OSError) as e:
            log.warning("cpu placement %s=%r not applied: %s", NICE_ENV, nice_s, e)
    if cpus is None and nice == 0:
        return None
    return Placement(cpus, nice)
