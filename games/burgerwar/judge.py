"""The Burger War judge as pure logic (no simulation).

Rules, as the contest's judge server (``judge/judgeServer.py`` of the contest kit) applies them;
docs/burgerwar.md ("Judge and info") summarises them:

* a field marker belongs to whoever read it last and can be retaken any number of times;
* a robot marker (left/right 3 points, back 5 points) read by the enemy stays the enemy's; a
  robot cannot read its own markers;
* scores are recounted as the sum of the points of the markers each player owns;
* the server handles one read request at a time: two reads of one marker in the same tick are
  two requests, and the later one wins (it retakes the marker from the earlier reader);
* called game: as soon as ``|score_r - score_b| >= call_diff`` (10) after a request, the match
  is over and later requests are refused;
* the match lasts ``match_time`` (180 s); after that it ends as soon as the scores differ
  (sudden death), at the latest at ``match_time + sudden_death_time`` (240 s): still tied then
  = draw. A simultaneous score in sudden death therefore cannot end it as a draw: the first
  request served makes the scores differ and ends the match, the later one is refused.
* every finished match reports ``state: "stop"``; "end" is the judge server's state *before* a
  match starts and is never reported here (the simulated match starts at ``reset``).
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

import numpy as np

from zenrl.games.burgerwar.geometry import N_FIELD, TARGET_NAMES, TARGET_POINTS

NEUTRAL, RED, BLUE = 0, 1, 2
_PLAYER_CHAR = {NEUTRAL: "n", RED: "r", BLUE: "b"}
_CHARS = ("n", "r", "b")
_POINTS = [int(p) for p in TARGET_POINTS]
#: the judge server's states: before the match, during it, after it
PRE_MATCH, RUNNING, STOP = "end", "running", "stop"
#: orders in which :meth:`Judge.read` serves the two players' requests of one tick
ORDERS = ("rb", "br")


class Judge:
    """Ownership, scores and match state.

    Attributes: ``owners`` int8[18] (0 neutral, 1 red, 2 blue) in ``TARGET_NAMES`` order,
    ``scores`` (red, blue), ``state`` "running" | "stop", ``time`` seconds,
    ``sudden_death`` bool (past ``match_time`` with the scores tied).
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
        self.state = RUNNING
        self.time = 0.0
        self.sudden_death = False

    # ------------------------------------------------------------------ reads
    def read(self, red_reads: Iterable[int] = (), blue_reads: Iterable[int] = (),
             order: str = "rb") -> list[dict]:
        """Serve one tick of read requests (target indices) by red and blue; returns the
        capture events in the order they happened.

        ``order`` says whose requests the server handles first this tick: "rb" (red's, then
        blue's) or "br". It matters only when both read the same field marker (the later
        request wins) or when a request ends the match (the requests after it are refused).

        Each event: ``{"name", "player": "r"|"b", "previous": "n"|"r"|"b", "point", "time"}``.
        Requests after the match is over, of a robot's own markers, of markers the reader
        already owns, and of robot markers already taken change nothing and make no event.
        """
        if order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
        if self.state != RUNNING:
            return []
        reads = {RED: red_reads, BLUE: blue_reads}
        events = []
        for player in ((RED, BLUE) if order == "rb" else (BLUE, RED)):
            for i in dict.fromkeys(int(i) for i in reads[player]):  # unique, in request order
                if self.state != RUNNING:
                    return events
                if not self._can_take(player, i):
                    continue
                prev = int(self.owners[i])
                self.owners[i] = player
                events.append({"name": TARGET_NAMES[i], "player": _PLAYER_CHAR[player],
                               "previous": _PLAYER_CHAR[prev], "point": int(TARGET_POINTS[i]),
                               "time": self.time})
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
        if self.state != RUNNING:
            return
        sr, sb = self.scores
        if abs(sr - sb) >= self.call_diff or (self.sudden_death and sr != sb):
            self.state = STOP

    # ------------------------------------------------------------------ clock
    def set_time(self, t: float) -> None:
        """Advance the clock to ``t`` seconds and apply the time rules."""
        self.time = float(t)
        if self.state != RUNNING:
            return
        eps = 1e-9
        if self.time >= self.match_time - eps:
            if self.scores[0] != self.scores[1]:
                self.state = STOP
                return
            self.sudden_death = True
        if self.time >= self.match_time + self.sudden_death_time - eps:
            self.state = STOP

    # ------------------------------------------------------------------ outputs
    @property
    def done(self) -> bool:
        return self.state != RUNNING

    @property
    def winner(self) -> str | None:
        """"r", "b", "draw", or None while running."""
        if self.state == RUNNING:
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


def robot_marker_points(info: Mapping[str, Any]) -> tuple[int, int] | None:
    """(my points, enemy points) from robot markers (L, R, B: read from the other robot, they
    stay read) in the ``info`` of a match step, or None for an info without a match. A match's
    score is these plus the field markers held at the end: how a match was won, e.g. by
    reading an enemy that left its back open while it contested a field marker."""
    if "war_state" not in info or "side" not in info:
        return None
    me = "r" if info["side"] == "red" else "b"
    mine = theirs = 0
    for t in info["war_state"]["targets"]:
        if t["name"].startswith(("RE_", "BL_")) and t["player"] != "n":
            if t["player"] == me:
                mine += int(t["point"])
            else:
                theirs += int(t["point"])
    return mine, theirs
