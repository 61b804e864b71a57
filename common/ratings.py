"""Bradley-Terry ratings on the Elo scale from pairwise match results, with 95% intervals.

The model: player i beats player j with probability ``1 / (1 + 10 ** ((R_j - R_i) / 400))``
(Elo's logistic curve; ``R = 400 / ln 10 * theta`` with Bradley-Terry strengths ``exp(theta)``).
A draw counts as half a win for each side. Ratings are the maximum a-posteriori estimate with
``virtual_draws`` draws added to every pair that played (BayesElo's prior: a perfect record
gives a large but finite gap instead of an infinite one; 0 gives the plain maximum likelihood),
found by Newton's method. Intervals are +-1.96 standard errors from the inverse of the observed
information (the Laplace approximation), for ratings measured against ``anchor`` (its rating
fixed at 0, its interval a point) or, without one, against the players' mean (ratings sum to
0). Pure numpy: ``zenrl evaluate --round-robin`` and the league's status use it.

Players without any match get NaN; players that played but are split into groups that never
met have no common scale: a :class:`ValueError` names the groups.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Iterable, Mapping, Sequence

import numpy as np

#: Elo points per unit of Bradley-Terry log-strength
ELO_PER_NAT = 400.0 / math.log(10.0)
Z95 = 1.959964


@dataclasses.dataclass(frozen=True)
class PairRecord:
    """Results of ``a`` against ``b``: ``a_wins``, ``draws``, ``b_wins``."""

    a: str
    b: str
    a_wins: int
    draws: int
    b_wins: int

    @property
    def games(self) -> int:
        return self.a_wins + self.draws + self.b_wins


@dataclasses.dataclass(frozen=True)
class Rating:
    """One player's rating (Elo scale), its 95% interval, standard error, matches played and
    score (wins + draws / 2) / matches."""

    player: str
    elo: float
    ci95: tuple[float, float]
    se: float
    games: int
    score: float


def expected_score(elo_a: float, elo_b: float) -> float:
    """The probability that a player rated ``elo_a`` beats one rated ``elo_b`` (draws as half)."""
    return 1.0 / (1.0 + 10.0 ** ((elo_b - elo_a) / 400.0))


def _components(n: int, games: np.ndarray, active: np.ndarray) -> list[list[int]]:
    seen, groups = set(), []
    for start in range(n):
        if start in seen or not active[start]:
            continue
        stack, group = [start], []
        seen.add(start)
        while stack:
            i = stack.pop()
            group.append(i)
            for j in np.flatnonzero(games[i] > 0):
                if int(j) not in seen:
                    seen.add(int(j))
                    stack.append(int(j))
        groups.append(sorted(group))
    return groups


def fit_ratings(players: Sequence[str], records: Iterable[PairRecord], anchor: str | None = None,
                virtual_draws: float = 1.0, iterations: int = 100) -> dict[str, Rating]:
    """Ratings of ``players`` (names) from ``records`` (several records of one pair add up;
    either order). ``anchor``: the player rated 0 (default: the mean is 0). Returns a
    :class:`Rating` per player, in the order of ``players``."""
    names = list(players)
    if len(set(names)) != len(names):
        raise ValueError("player names must be unique")
    index = {p: i for i, p in enumerate(names)}
    n = len(names)
    games = np.zeros((n, n))   # games[i, j]: matches between i and j
    score = np.zeros((n, n))   # score[i, j]: i's wins + draws / 2 against j
    for r in records:
        for who in (r.a, r.b):
            if who not in index:
                raise ValueError(f"record names unknown player {who!r}")
        i, j = index[r.a], index[r.b]
        if i == j:
            raise ValueError(f"a player cannot play itself ({r.a!r})")
        games[i, j] += r.games
        games[j, i] += r.games
        score[i, j] += r.a_wins + 0.5 * r.draws
        score[j, i] += r.b_wins + 0.5 * r.draws
    played = games.sum(1) > 0
    if anchor is not None and anchor not in index:
        raise ValueError(f"anchor {anchor!r} is not a player")
    groups = _components(n, games, played)
    if len(groups) > 1:
        raise ValueError("players split into groups that never met, so they have no common scale: "
                         + " | ".join(", ".join(names[i] for i in g) for g in groups))
    if anchor is not None and not played[index[anchor]]:
        raise ValueError(f"anchor {anchor!r} has played no match")
    # the prior: virtual draws in every pair that met
    met = games > 0
    g = games + virtual_draws * met
    s = score + 0.5 * virtual_draws * met
    act = np.flatnonzero(played)
    theta = np.zeros(n)
    # free parameters: every active player but the anchor (with an anchor), else all active ones
    # with the sum-zero constraint applied through the pseudo-inverse
    free = act if anchor is None else np.array([i for i in act if i != index[anchor]], int)
    info = np.zeros((n, n))
    converged = False
    for _ in range(iterations):
        d = theta[:, None] - theta[None, :]
        p = 1.0 / (1.0 + np.exp(-d))
        grad = (s - g * p).sum(1)
        w = g * p * (1.0 - p)
        info = np.diag(w.sum(1)) - w  # the observed information (negative Hessian)
        sub = info[np.ix_(free, free)]
        step = (np.linalg.pinv(sub) if anchor is None else np.linalg.inv(sub)) @ grad[free]
        step = np.clip(step, -2.0, 2.0)  # a damped first step from 0 for lopsided records
        theta[free] += step
        if anchor is None:
            theta[act] -= theta[act].mean()
        if np.max(np.abs(step)) < 1e-10:
            converged = True
            break
    if not converged or not np.all(np.isfinite(theta)):
        raise ValueError("ratings did not converge: without virtual_draws a player (or group) that won or lost "
                         "every match has no finite rating")
    cov = np.zeros((n, n))
    sub = info[np.ix_(free, free)]
    cov[np.ix_(free, free)] = np.linalg.pinv(sub) if anchor is None else np.linalg.inv(sub)
    out = {}
    for i, name in enumerate(names):
        total = games[i].sum()
        if not played[i]:
            out[name] = Rating(name, float("nan"), (float("nan"), float("nan")), float("nan"), 0, float("nan"))
            continue
        se = math.sqrt(max(cov[i, i], 0.0)) * ELO_PER_NAT
        elo = float(theta[i] * ELO_PER_NAT)
        out[name] = Rating(name, elo, (elo - Z95 * se, elo + Z95 * se), se, int(total), float(score[i].sum() / total))
    return out


def records_from_table(table: Mapping[tuple[str, str], tuple[int, int, int]]) -> list[PairRecord]:
    """``{(a, b): (a_wins, draws, b_wins)}`` -> records."""
    return [PairRecord(a, b, *map(int, v)) for (a, b), v in table.items()]
