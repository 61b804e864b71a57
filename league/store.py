"""The league's state on disk, in ``<league dir>`` (``runs/<run>/league/`` by default):

* ``state.json``: :meth:`~zenrl.league.core.League.to_state` (players, the payoff table with
  raw and decayed counts, results since each snapshot or reset, generations);
* ``snapshots/<player id>.msgpack``: each frozen snapshot's weights as one
  :class:`~zenrl.common.protocol.PlayerWeights` message (msgpack, arrays as raw buffers: no
  pickle, checked like any message when read back).

Every file is written to a temporary name, fsynced, moved into place with ``os.replace`` and
the directory fsynced, so a crash leaves the old file or the new one, never a torn one. A
snapshot's file is written before the state that names it; a state naming a snapshot whose
file is missing or unreadable drops that snapshot (logged).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from zenrl.common import protocol as P
from zenrl.common.config import LeagueConfig
from zenrl.common.atomic_files import remove_stale_temp_files, write_bytes_atomically
from zenrl.common.errors import ProtocolError
from zenrl.league.core import SNAPSHOT, League, LearnerWeights

log = logging.getLogger(__name__)

STATE_FILE = "state.json"
SNAPSHOT_DIR = "snapshots"


def encode_weights(pid: str, w: LearnerWeights, max_bytes: int) -> bytes:
    return P.PlayerWeights(status="ok", player=pid, version=w.version, updates=w.updates, arch=w.arch,
                           params=w.params).encode(max_bytes)


def decode_weights(payload: bytes, max_bytes: int) -> tuple[str, LearnerWeights]:
    m = P.PlayerWeights.decode(payload, max_bytes)
    if m.status != "ok" or m.params is None:
        raise ProtocolError("status", f"stored weights of {m.player} are {m.status!r}", "field")
    return m.player, LearnerWeights(m.version, m.updates, m.arch, dict(m.params))


class LeagueStore:
    """Reads and writes one league's directory (see the module docstring)."""

    def __init__(self, directory: str | os.PathLike[str], max_bytes: int) -> None:
        self.dir = Path(directory)
        self.max_bytes = max_bytes
        self._written: set[str] = set()

    def snapshot_path(self, pid: str) -> Path:
        return self.dir / SNAPSHOT_DIR / f"{P.check_name('player', pid)}.msgpack"

    def save(self, league: League, now: float | None = None) -> None:
        """Every snapshot's weights not yet on disk, then the state; files of snapshots that
        left the league are deleted after the state no longer names them."""
        for pid, p in league.players.items():
            if p.kind == SNAPSHOT and pid not in self._written and pid in league.weights:
                write_bytes_atomically(self.snapshot_path(pid), encode_weights(pid, league.weights[pid], self.max_bytes))
                self._written.add(pid)
        write_bytes_atomically(self.dir / STATE_FILE, json.dumps(league.to_state(now)).encode())
        keep = {f"{pid}.msgpack" for pid, p in league.players.items() if p.kind == SNAPSHOT}
        snap_dir = self.dir / SNAPSHOT_DIR
        if snap_dir.is_dir():
            for f in snap_dir.iterdir():
                if f.suffix == ".msgpack" and f.name not in keep:
                    f.unlink(missing_ok=True)
                    self._written.discard(f.stem)

    def load(self, cfg: LeagueConfig, now: float, frozen: list[str] | tuple[str, ...] = ()) -> League | None:
        """The league saved here, or None when there is no state yet. An unreadable state
        file is an error (:class:`ValueError`): a league must not silently start over."""
        for d in (self.dir, self.dir / SNAPSHOT_DIR):  # writes killed before their rename
            remove_stale_temp_files(d)
        path = self.dir / STATE_FILE
        if not path.exists():
            return None
        try:
            state: dict[str, Any] = json.loads(path.read_text())
        except ValueError as e:
            raise ValueError(f"league state {path} is unreadable: {e}") from None
        weights: dict[str, LearnerWeights] = {}
        for d in state.get("players", []):
            if d.get("kind") != SNAPSHOT:
                continue
            pid = str(d.get("id"))
            try:
                got, w = decode_weights(self.snapshot_path(pid).read_bytes(), self.max_bytes)
                if got != pid:
                    raise ProtocolError("player", f"file holds {got!r}", "field")
            except (OSError, ProtocolError) as e:
                log.error("league snapshot %s dropped: its weights cannot be read (%s)", pid, e)
                continue
            weights[pid] = w
            self._written.add(pid)
        return League.from_state(cfg, state, weights, now, frozen)
