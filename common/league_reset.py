"""Exploiter resets where no launcher restarts the processes (``league.self_reset``): a cluster
(docker compose, Kubernetes, several hosts) runs each league agent's replay, learner and actors
as services of their own, started with ``--agent <id>``.

When the league starts a new generation of an agent (``generation/<agent>`` in the league's
stats goes up), ``zenrl run`` terminates that agent's processes, deletes its directory and
starts them afresh. Without ``zenrl run``, each of the agent's processes does its own part:
:class:`GenerationWatch` follows the league's stats, stops the role loop at a higher
generation, the process deletes what belongs to the old generation (the learner its
checkpoints, the replay its durable log) and exits with :data:`EXIT_GENERATION`; the engine's
restart policy (compose ``restart: unless-stopped``, a Deployment) starts it again, fresh.

Each stateful process keeps the generation its files belong to in a marker file
(``<runs_dir>/<run_id>/league_generation.<role>``): a learner that was down while the league
moved on deletes the stale checkpoints at its next start instead of resuming them. Actors keep
no files: the first generation they hear is theirs.

Between the league's reset and each process's exit lie up to ``league.stats_interval_s`` plus a
match's worth of reports: the new replay may take a few chunks of the old generation's actors.
"""

from __future__ import annotations

import logging
import shutil
import threading
from pathlib import Path
from typing import Any, Iterable, Mapping

from zenrl.common import protocol as P
from zenrl.common.atomic_files import write_bytes_atomically
from zenrl.common.config import RunConfig
from zenrl.common.errors import ProtocolError, ZenrlError

log = logging.getLogger(__name__)

#: exit status of a process stopped by its agent's new generation (EX_TEMPFAIL: start me again)
EXIT_GENERATION = 75


class GenerationReset(ZenrlError):
    """The league started a new generation of this process's agent: exit and be started again."""


def generations(values: Mapping[str, Any]) -> dict[str, int]:
    """The agents' generations (``generation/<agent>``) among a league stats message's values:
    what ``zenrl run``'s launcher and :class:`GenerationWatch` both follow."""
    return {k.split("/", 1)[1]: v for k, v in values.items()
            if k.startswith("generation/") and type(v) is int and v >= 0}


def marker_path(cfg: RunConfig, run_id: str, role: str) -> Path:
    """Where a stateful process of a league agent keeps the generation of its files."""
    return Path(cfg.runs_dir) / run_id / f"league_generation.{role}"


class GenerationWatch:
    """Follows ``generation/<league.player>`` in the league's stats (``stats/league/league`` of
    ``league.run_id``: the league service of the default id) and sets ``stop`` once it is above
    this process's generation. ``marker``: the file that holds the generation of this process's
    files (None for a process without files). Use :meth:`for_config` (None unless
    ``league.self_reset`` applies to this process)."""

    def __init__(self, node: Any, league_run_id: str, agent: str, stop: threading.Event,
                 marker: Path | None = None) -> None:
        self.agent, self.stop, self.marker = agent, stop, marker
        self.own: int | None = _read_marker(marker)
        self.reset_to: int | None = None
        self._lock = threading.Lock()
        node.subscribe(P.Keys(league_run_id).stats("league", "league"), self._on_stats)

    @classmethod
    def for_config(cls, cfg: RunConfig, node: Any, run_id: str, role: str, stop: threading.Event,
                   stateful: bool = True) -> "GenerationWatch | None":
        lc = cfg.league
        if not (lc.self_reset and lc.run_id and lc.player):
            return None
        return cls(node, lc.run_id, lc.player, stop, marker_path(cfg, run_id, role) if stateful else None)

    def _on_stats(self, key: str, payload: bytes) -> None:
        try:
            g = generations(P.Stats.decode(payload, 1 << 20).values).get(self.agent)
        except ProtocolError:
            return
        if g is None:
            return
        with self._lock:
            if self.own is None:  # the first word: this is the generation of whatever we hold
                self.own = g
                if self.marker is not None:
                    _write_marker(self.marker, g)
                return
            if g > self.own and self.reset_to is None:
                self.reset_to = g
                log.warning("league: %s moved to generation %d (this process holds %d): stopping to start afresh",
                            self.agent, g, self.own)
                self.stop.set()

    def finish(self, stale: Iterable[Path]) -> None:
        """After the role loop has stopped and closed: if a new generation stopped it, delete
        ``stale`` (the old generation's files), record the new generation and raise
        :class:`GenerationReset`; else nothing."""
        with self._lock:
            to = self.reset_to
        if to is None:
            return
        for p in stale:
            shutil.rmtree(p, ignore_errors=True)
        if self.marker is not None:
            _write_marker(self.marker, to)
        raise GenerationReset(f"league agent {self.agent} is at generation {to}: exiting to be started afresh "
                              f"(exit status {EXIT_GENERATION})")


def _read_marker(path: Path | None) -> int | None:
    if path is None:
        return None
    try:
        g = int(path.read_text().strip())
    except (OSError, ValueError):
        return None
    return g if g >= 0 else None


def _write_marker(path: Path, g: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomically(path, f"{g}\n".encode())
