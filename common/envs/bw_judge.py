"""The Burger War judge as pure logic (no simulation).

Rules (contest judge server + rule book):

* a field marker belongs to whoever read it last and can be retaken any number of times;
* a robot marker (left/right 3 points, back 5 points) read by the enemy stays the enemy's; a
  robot cannot read its own markers;
* scores are recounted as the sum of the points of the markers each player owns;
* called game: as soon as ``|score_r - score_b| >= call_diff`` (10) the state becomes "stop";
* the match lasts ``match_time`` (180 s); if tied then, sudden death lasts up to
  ``sudden_death_time`` (60 s) more and ends at the first score change; still tied at the end =
  draw (state "end", winner "draw").

If both players read the same field marker in the same judge tick the reads cancel (the
ownership does not change): this keeps the rules point-symmetric.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

import numpy as np

from zenrl.common.envs.bw_geometry import N_FIELD, TARGET_NAMES, TARGET_POINTS

NEUTRAL, RED, BLUE = 0, 1, 2
_PLAYER_CHAR = {NEUTRAL: "n", RED: "r", BLUE: "b"}
_CHARS = ("n", "r", "b")
_POINTS = [int(p) for p in TARGET_POINTS]


class Judge:
    """Ownership, scores and match state.

    Attributes: ``owners`` int8[18] (0 neutral, 1 red, 2 blue) in ``TARGET_NAMES`` order,
    ``scores`` (red, blue), ``state`` "running" | "stop" | "end", ``time`` seconds,
    ``sudden_death`` bool.
    """

    def __init__(self, match_time: float = 180.0, sudden_death_time: float = 60.0,
                 call_diff: int = 10, players: tuple[str, str] = ("red", "blue")):
        self.match_time = float(match_time)
        self.sudden_death_time = float(sudden_death_time)
        self.call_diff = int(call_diff)
        self.players = players
        self.reset()

    def reset(self) -> None:
        self.owners = np.zeros(len(TARGET_NAMES), dtype=np.int8)
        self.scores = (0, 0)
        self.state = "running"
        self.time = 0.0
        self.sudden_death = False
        self._sd_scores: tuple[int, int] | None = None

    # ------------------------------------------------------------------ reads
    def read(self, red_reads: Iterable[int] = (), blue_reads: Iterable[int] = ()) -> list[dict]:
        """Apply one tick of reads (target indices) by red and blue; returns capture events.

        Each event: ``{"name", "player": "r"|"b", "previous": "n"|"r"|"b", "point", "time"}``.
        Reads after the match is over, of a robot's own markers, of already-owned markers, and of
        robot markers already taken are ignored.
        """
        if self.state != "running":
            return []
        r, b = set(int(i) for i in red_reads), set(int(i) for i in blue_reads)
        both = {i for i in r & b if i < N_FIELD}
        events = []
        for player, reads in ((RED, r), (BLUE, b)):
            for i in sorted(reads - both):
                if not self._can_take(player, i):
                    continue
                prev = int(self.owners[i])
                self.owners[i] = player
                events.append({"name": TARGET_NAMES[i], "player": _PLAYER_CHAR[player],
                               "previous": _PLAYER_CHAR[prev], "point": int(TARGET_POINTS[i]),
                               "time": self.time})
        if events:
            self._recount()
        return events

    def _can_take(self, player: int, i: int) -> bool:
        owner = int(self.owners[i])
        if owner == player:
            return False
        if i < N_FIELD:
            return True
        robot = RED if i < N_FIELD + 3 else BLUE
        return robot != player and owner == NEUTRAL

    def _recount(self) -> None:
        pts = TARGET_POINTS
        self.scores = (int(pts[self.owners == RED].sum()), int(pts[self.owners == BLUE].sum()))
        self._check_scores()

    def _check_scores(self) -> None:
        if self.state != "running":
            return
        sr, sb = self.scores
        if abs(sr - sb) >= self.call_diff:
            self.state = "stop"
        elif self.sudden_death and self.scores != self._sd_scores:
            self.state = "end"

    # ------------------------------------------------------------------ clock
    def set_time(self, t: float) -> None:
        """Advance the clock to ``t`` seconds and apply the time rules."""
        self.time = float(t)
        if self.state != "running":
            return
        eps = 1e-9
        if not self.sudden_death and self.time >= self.match_time - eps:
            if self.scores[0] != self.scores[1]:
                self.state = "end"
            else:
                self.sudden_death = True
                self._sd_scores = self.scores
        if self.sudden_death and self.time >= self.match_time + self.sudden_death_time - eps:
            self.state = "end"

    # ------------------------------------------------------------------ outputs
    @property
    def done(self) -> bool:
        return self.state != "running"

    @property
    def winner(self) -> str | None:
        """"r", "b", "draw", or None while running."""
        if self.state == "running":
            return None
        sr, sb = self.scores
        return "r" if sr > sb else "b" if sb > sr else "draw"

    def war_state(self) -> dict:
        """The judge's ``GET /warState`` JSON object."""
        return {
            "players": {"r": self.players[0], "b": self.players[1]},
            "ready": {"r": True, "b": True},
            "scores": {"r": int(self.scores[0]), "b": int(self.scores[1])},
            "state": self.state,
            "targets": [{"name": n, "player": _CHARS[o], "point": p}
                        for n, o, p in zip(TARGET_NAMES, self.owners.tolist(), _POINTS)],
            "time": float(self.time),
        }


def match_outcome(info: Mapping[str, Any]) -> tuple[str, int, int] | None:
    """(outcome, my score, enemy score) from the ``info`` of a match's last step, or None for
    an info without a match (not this env). ``outcome`` is "win", "draw" or "loss" as the
    contest counts it: a win only when my score is higher; at equal scores the judge's winner
    decides (a draw when there is none, e.g. a match cut off by ``max_steps``)."""
    if "war_state" not in info or "side" not in info:
        return None
    me = "r" if info["side"] == "red" else "b"
    other = "b" if me == "r" else "r"
    scores = info["war_state"]["scores"]
    mine, theirs = int(scores[me]), int(scores[other])
    if mine != theirs:
        return ("win" if mine > theirs else "loss"), mine, theirs
    winner = info.get("winner")
    return ("draw" if winner in (None, "draw") else ("win" if winner == me else "loss")), mine, theirs
