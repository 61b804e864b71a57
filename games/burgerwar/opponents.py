"""Opponents for the Burger War env, re-implemented from the contest kit's descriptions.

Every opponent works in ITS OWN frame (the frame in which it starts at (0, -1.3) facing +y; the
layout is point-symmetric, so the static map is the same in every own frame). The env calls
``reset(rng)`` at each episode start and ``act(view)`` at the opponent's own rate ``hz``;
``act`` returns ``(v, w)`` in m/s and rad/s (clipped by the env), or, for ``needs_obs``
opponents (frozen policies), an action of the env's action space.

``view`` is an :class:`OpponentView`: ``x, y, yaw`` own-frame pose, ``lidar`` float32[360]
noisy ranges (None unless ``needs_lidar``), ``obs`` the observation an agent on that side would
get (None unless ``needs_obs``), ``time`` seconds; for ``needs_enemy`` opponents ``enemy`` the
enemy's true own-frame pose (x, y, yaw) and ``taken`` which of the enemy's L, R, B markers this
opponent has read.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from zenrl.games.burgerwar import geometry as geo


@dataclass
class OpponentView:
    x: float
    y: float
    yaw: float
    time: float
    lidar: np.ndarray | None = None
    obs: Any = None
    enemy: tuple[float, float, float] | None = None
    taken: tuple[bool, bool, bool] = (False, False, False)


class Opponent:
    """Base class. ``hz``: decision rate; ``needs_lidar``/``needs_obs``/``needs_enemy``: what
    ``act`` needs."""

    name = "base"
    hz = 10.0
    needs_lidar = False
    needs_obs = False
    needs_enemy = False

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def act(self, view: OpponentView):  # pragma: no cover - interface
        raise NotImplementedError


def _bearings(n: int = geo.LIDAR_BEAMS) -> np.ndarray:
    return geo.wrap(2 * np.pi * np.arange(n) / n)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _arc_min(lidar: np.ndarray, i0: int, i1: int) -> float:
    """min of beams i0 .. i1-1 (indices modulo len(lidar), i1 - i0 <= len(lidar))."""
    n = len(lidar)
    i0 %= n
    i1 = i0 + (i1 - i0 if i1 > i0 else i1 - i0 + n)
    if i1 <= n:
        return float(lidar[i0:i1].min())
    return float(min(lidar[i0:].min(), lidar[:i1 - n].min()))


def _heading_control(err: float, delta: float = 0.0, gain: float = 0.5, limit: float = 0.3) -> float:
    return min(max(gain * (err + delta), -limit), limit)


class Idle(Opponent):
    """Stands still."""

    name = "idle"
    hz = 1.0

    def act(self, view):
        return 0.0, 0.0


class RandomDrive(Opponent):
    """Uniform random (v, w) within the robot's limits, held for ``hold`` seconds."""

    name = "random"

    def __init__(self, hold: float = 1.0):
        self.hold = hold

    def reset(self, rng):
        super().reset(rng)
        self._until = -1.0
        self._cmd = (0.0, 0.0)

    def act(self, view):
        if view.time >= self._until:
            self._cmd = (float(self.rng.uniform(-geo.MAX_V, geo.MAX_V)),
                         float(self.rng.uniform(-geo.MAX_W, geo.MAX_W)))
            self._until = view.time + self.hold
        return self._cmd


class Cheese(Opponent):
    """Level 1: forward/back on its start line at ``speed``, re-reading the FriedShrimp facing it.

    Drives forward until ``forward`` m from the start, back until ``back`` m, and so on; 5 Hz.
    """

    name = "cheese"
    hz = 5.0

    def __init__(self, speed: float = 0.12, forward: float = 0.92, back: float = 0.17):
        self.speed, self.forward, self.back = speed, forward, back

    def reset(self, rng):
        super().reset(rng)
        self._dir = 1.0

    def act(self, view):
        s = view.y - geo.RED_START[1]  # progress along the start line (own frame, +y)
        if self._dir > 0 and s >= self.forward:
            self._dir = -1.0
        elif self._dir < 0 and s <= self.back:
            self._dir = 1.0
        w = float(np.clip(2.0 * geo.wrap(math.pi / 2 - view.yaw) + 1.0 * view.x * self._dir, -1.0, 1.0))
        return self._dir * self.speed, w


# ---------------------------------------------------------------------------------------------
# Teriyaki / clubhouse: heading lookup in a coarse grid over the own map frame
# ---------------------------------------------------------------------------------------------
#: The tour the teriyaki grid is built from (own frame): approach each FriedShrimp face
#: head-on, then swing out counter-clockwise to the next one.
TERIYAKI_LOOP = np.array([
    [0.0, -1.15], [0.0, -0.45], [0.55, -0.28], [1.1, 0.0], [0.45, 0.0], [0.28, 0.55],
    [0.0, 1.1], [0.0, 0.45], [-0.55, 0.28], [-1.1, 0.0], [-0.45, 0.0], [-0.28, -0.55],
])


@functools.lru_cache(maxsize=8)
def teriyaki_grid(n: int = 8, lookahead: float = 0.35) -> np.ndarray:
    """float64[n, n] heading table over the own map frame [-1.7, 1.7]^2 (row = y, col = x).

    Each cell's heading points from the cell centre to a point ``lookahead`` m further along
    :data:`TERIYAKI_LOOP` than the loop point nearest to the cell centre.
    """
    loop = TERIYAKI_LOOP
    seg_a, seg_b = loop, np.roll(loop, -1, axis=0)
    seg_len = np.linalg.norm(seg_b - seg_a, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]
    edges = np.linspace(-geo.ARENA_HALF_DIAG, geo.ARENA_HALF_DIAG, n + 1)
    centres = (edges[:-1] + edges[1:]) / 2
    grid = np.zeros((n, n))
    for iy, cy in enumerate(centres):
        for ix, cx in enumerate(centres):
            p = np.array([cx, cy])
            d = seg_b - seg_a
            t = np.clip(((p - seg_a) * d).sum(1) / (seg_len ** 2), 0, 1)
            proj = seg_a + t[:, None] * d
            k = int(np.argmin(np.linalg.norm(proj - p, axis=1)))
            s = (cum[k] + t[k] * seg_len[k] + lookahead) % total
            j = int(np.searchsorted(cum, s, side="right") - 1)
            q = seg_a[j] + (s - cum[j]) / seg_len[j] * d[j]
            grid[iy, ix] = math.atan2(q[1] - cy, q[0] - cx)
    return grid


class Teriyaki(Opponent):
    """Level 2: heading from an ``grid_n`` x ``grid_n`` lookup over the own map frame.

    ``w = clip(0.5 * (dtheta + delta), +-0.3)``, ``delta`` = -+pi/4 (-+pi/8) when lidar beams within
    30 deg left/right of the wanted heading are closer than 0.2 m (0.3 m);
    ``v = 0.07``, or ``-0.035`` when a beam within +-15 deg of forward is closer than 0.2 m. 10 Hz.
    """

    name = "teriyaki"
    hz = 10.0
    needs_lidar = True

    def __init__(self, grid_n: int = 8, speed: float = 0.07):
        self.grid = teriyaki_grid(grid_n)
        self._grid = self.grid.tolist()
        self.grid_n = grid_n
        self.speed = speed
        self.bear = _bearings()

    def _cell_heading(self, x: float, y: float) -> float:
        n, h = self.grid_n, geo.ARENA_HALF_DIAG
        ix = min(max(int((x + h) / (2 * h) * n), 0), n - 1)
        iy = min(max(int((y + h) / (2 * h) * n), 0), n - 1)
        return self._grid[iy][ix]

    def tour_command(self, view) -> tuple[float, float]:
        want = _wrap(self._cell_heading(view.x, view.y) - view.yaw)
        lidar = view.lidar
        n = len(lidar)
        i0 = int(round(want / (2 * math.pi) * n)) % n
        left = _arc_min(lidar, i0, i0 + 30)  # beams i0 .. i0+29
        right = _arc_min(lidar, i0 - 30, i0)  # beams i0-30 .. i0-1
        delta = 0.0
        if left < 0.2:
            delta -= math.pi / 4
        elif left < 0.3:
            delta -= math.pi / 8
        if right < 0.2:
            delta += math.pi / 4
        elif right < 0.3:
            delta += math.pi / 8
        w = _heading_control(float(want), delta)
        v = -self.speed / 2 if _arc_min(lidar, -15, 16) < 0.2 else self.speed
        return v, w

    def act(self, view):
        return self.tour_command(view)


def detect_enemy(view, bear: np.ndarray, rmin: float = 0.1, rmax: float = 0.7,
                 clearance: float = 0.1, min_points: int = 5):
    """Lidar enemy detector: points ``rmin..rmax`` m away, farther than ``clearance`` from any wall
    or box. Returns (median bearing, median range) when more than ``min_points`` such points are
    found, else None."""
    r = view.lidar
    sel = (r >= rmin) & (r <= rmax)
    if sel.sum() <= min_points:
        return None
    c, s = math.cos(view.yaw), math.sin(view.yaw)
    ox, oy = view.x + geo.LIDAR_X * c, view.y + geo.LIDAR_X * s
    ang = view.yaw + bear[sel]
    px, py = ox + r[sel] * np.cos(ang), oy + r[sel] * np.sin(ang)
    far = geo.point_static_clearance(px, py) > clearance
    if far.sum() <= min_points:
        return None
    b = bear[sel][far]
    # median of a bearing cluster: measure around the circular mean to avoid the +-pi seam
    mean = math.atan2(np.sin(b).mean(), np.cos(b).mean())
    return float(geo.wrap(mean + np.median(geo.wrap(b - mean)))), float(np.median(r[sel][far]))


class Clubhouse(Teriyaki):
    """Level 3: teriyaki plus the lidar enemy detector; when the enemy is seen, turn to its median
    bearing and drive +0.07 m/s if it is farther than 0.36 m, else -0.07."""

    name = "clubhouse"

    def act(self, view):
        seen = detect_enemy(view, self.bear)
        if seen is None:
            return self.tour_command(view)
        bearing, dist = seen
        return (self.speed if dist > 0.36 else -self.speed), _heading_control(bearing)


# ---------------------------------------------------------------------------------------------
# Waypoint bot: tour of shooting poses with a face-the-enemy override
# ---------------------------------------------------------------------------------------------
NAV_CELL = 0.05
NAV_CLEARANCE = 0.14

#: default tour (field-marker indices, own frame): my side first, counter-clockwise.
WAYPOINT_TOUR = ("FriedShrimp_S", "OctopusWiener_S", "OctopusWiener_N", "FriedShrimp_E",
                 "Omelette_S", "Omelette_N", "FriedShrimp_N", "Tomato_N", "Tomato_S",
                 "FriedShrimp_W", "Pudding_N", "Pudding_S")


@functools.lru_cache(maxsize=1024)
def nav_field(gx: float, gy: float) -> np.ndarray:
    """float64[N, N] path distance (m) to goal (gx, gy) over a NAV_CELL grid of [-1.7, 1.7]^2,
    through cells at least NAV_CLEARANCE from walls and boxes (inf where unreachable)."""
    h = geo.ARENA_HALF_DIAG
    n = int(round(2 * h / NAV_CELL))
    c = -h + NAV_CELL * (np.arange(n) + 0.5)
    X, Y = np.meshgrid(c, c)
    free = geo.point_static_clearance(X.ravel(), Y.ravel()).reshape(n, n) >= NAV_CLEARANCE
    ix, iy = _cell(gx, n), _cell(gy, n)
    free[iy, ix] = True
    D = np.full((n, n), np.inf)
    D[iy, ix] = 0.0
    shifts = [(dy, dx, NAV_CELL * math.hypot(dx, dy)) for dy in (-1, 0, 1) for dx in (-1, 0, 1)
              if dx or dy]
    while True:
        P = np.pad(D, 1, constant_values=np.inf)
        new = D.copy()
        for dy, dx, cost in shifts:
            new = np.minimum(new, P[1 + dy:1 + dy + n, 1 + dx:1 + dx + n] + cost)
        new[~free] = np.inf
        if np.array_equal(new, D):
            return D
        D = new


def _cell(v: float, n: int) -> int:
    return int(np.clip((v + geo.ARENA_HALF_DIAG) / NAV_CELL, 0, n - 1))


class Waypoint(Opponent):
    """Levels 4-11 style: visits shooting poses ``standoff`` m in front of each field marker
    (order :data:`WAYPOINT_TOUR`), following a precomputed grid path field, turns to face the
    marker and dwells ``dwell`` s; when the lidar detector sees the enemy (within ``see_range``)
    it turns to face it for up to ``face_time`` s (then ignores it for ``face_cooldown`` s).
    A target not reached within ``target_timeout`` s is skipped. 10 Hz."""

    name = "waypoint"
    hz = 10.0
    needs_lidar = True

    def __init__(self, standoff: float = 0.3, dwell: float = 0.6, see_range: float = 1.0,
                 face_time: float = 3.0, face_cooldown: float = 6.0, target_timeout: float = 25.0,
                 tour: tuple[str, ...] = WAYPOINT_TOUR):
        names = [m[0] for m in geo.FIELD_MARKERS]
        self.goals = []
        for name in tour:
            i = names.index(name)
            p, nrm = geo.FIELD_POS[i], geo.FIELD_NORMAL[i]
            g = p + standoff * nrm
            self.goals.append((float(g[0]), float(g[1]), math.atan2(-nrm[1], -nrm[0])))
        self.dwell, self.see_range = dwell, see_range
        self.face_time, self.face_cooldown = face_time, face_cooldown
        self.target_timeout = target_timeout
        self.bear = _bearings()
        ang = np.linspace(-np.pi, np.pi, 16, endpoint=False)
        self.probe = 0.12 * np.stack([np.cos(ang), np.sin(ang)], 1)

    def reset(self, rng):
        super().reset(rng)
        self.k = 0
        self._since = 0.0
        self._dwell_until = None
        self._face_until = -1.0
        self._ignore_until = -1.0

    def _next(self, t):
        self.k = (self.k + 1) % len(self.goals)
        self._since = t
        self._dwell_until = None

    def act(self, view):
        t = view.time
        if t >= self._ignore_until:
            seen = detect_enemy(view, self.bear, rmax=self.see_range)
            if seen is not None:
                if self._face_until < 0:
                    self._face_until = t + self.face_time
                if t < self._face_until:
                    return 0.0, float(np.clip(2.0 * seen[0], -1.5, 1.5))
                self._ignore_until = t + self.face_cooldown
            self._face_until = -1.0
        gx, gy, gyaw = self.goals[self.k]
        if t - self._since > self.target_timeout:
            self._next(t)
            gx, gy, gyaw = self.goals[self.k]
        dist = math.hypot(gx - view.x, gy - view.y)
        if dist < 0.06 or self._dwell_until is not None:
            err = float(geo.wrap(gyaw - view.yaw))
            if abs(err) < 0.08 and self._dwell_until is None:
                self._dwell_until = t + self.dwell
            if self._dwell_until is not None and t >= self._dwell_until:
                self._next(t)
            return 0.0, float(np.clip(2.0 * err, -1.5, 1.5))
        return self._drive(view, self._path_heading(view, gx, gy, dist), dist)

    def _path_heading(self, view, gx: float, gy: float, dist: float, snap: bool = False) -> float:
        """The heading (rad, own frame) down the grid path field to (gx, gy), ``dist`` m away
        (with ``snap``, the field of the goal rounded to 0.1 m): straight at the goal within
        0.25 m, or where the field has no finite cell around."""
        if dist < 0.25:
            return math.atan2(gy - view.y, gx - view.x)
        D = nav_field(round(gx, 1), round(gy, 1)) if snap else nav_field(gx, gy)
        n = D.shape[0]
        pts = np.array([view.x, view.y]) + self.probe
        ix = np.clip(((pts[:, 0] + geo.ARENA_HALF_DIAG) / NAV_CELL).astype(int), 0, n - 1)
        iy = np.clip(((pts[:, 1] + geo.ARENA_HALF_DIAG) / NAV_CELL).astype(int), 0, n - 1)
        d = D[iy, ix]
        if not np.isfinite(d).any():
            return math.atan2(gy - view.y, gx - view.x)
        j = int(np.argmin(d))
        return math.atan2(self.probe[j, 1], self.probe[j, 0])

    def _drive(self, view, want: float, dist: float) -> tuple[float, float]:
        """(v, w) turning onto heading ``want``, slowing for the turn and the last ``dist`` m,
        backing off a wall closer than 0.16 m ahead."""
        err = float(geo.wrap(want - view.yaw))
        w = float(np.clip(2.0 * err, -1.5, 1.5))
        v = 0.2 * max(0.0, math.cos(err)) ** 3 * min(1.0, dist / 0.15 + 0.3)
        if view.lidar is not None and view.lidar[np.abs(self.bear) <= math.radians(20)].min() < 0.16:
            v = min(v, 0.0) - 0.05
        return v, w


class Raider(Waypoint):
    """A hunter of robot markers: knows where the enemy is (its true pose, as a contestant's
    robot with a good enemy detector would) and goes for the enemy's L, R and B markers (3, 3 and
    5 points, which stay read) before anything else: it drives along the grid path field to the
    reachable shooting spot ``standoff`` m off the nearest marker it has not read yet, turning to
    the marker once it is close enough to read it. With all three read it tours the field
    markers as :class:`Waypoint` (without the face-the-enemy override). A learner that never met
    it tends to leave its back open while it contests a field marker. 10 Hz."""

    name = "raider"
    needs_enemy = True

    def __init__(self, standoff: float = 0.35, read_within: float = 0.6, **kw):
        super().__init__(see_range=0.0, **kw)
        self.standoff, self.read_within = standoff, read_within
        ang = np.array([0.0, 0.45, -0.45, 0.8, -0.8])
        #: (angle off the normal, distance) of the candidate spots, the preferred first
        self._cands = [(a, d) for d in (standoff, 0.7 * standoff) for a in ang]

    def _offsets(self, n: np.ndarray) -> np.ndarray:
        """float[K, 2]: candidate spot offsets from a marker with unit normal ``n``."""
        out = np.empty((len(self._cands), 2))
        for i, (a, d) in enumerate(self._cands):
            c, s = math.cos(a), math.sin(a)
            out[i] = d * (c * n[0] - s * n[1]), d * (s * n[0] + c * n[1])
        return out

    def reset(self, rng):
        super().reset(rng)
        self._still = (0.0, 0.0, 0.0, 0.0)  # (x, y, yaw, since): where it last moved
        self._back_until = -1.0

    def act(self, view):
        if view.enemy is None or all(view.taken):
            return super().act(view)
        # wedged against the enemy or a wall (no move, no turn for 2 s): back off for a second
        t = view.time
        x0, y0, yaw0, since = self._still
        if math.hypot(view.x - x0, view.y - y0) > 0.03 or abs(geo.wrap(view.yaw - yaw0)) > 0.1:
            self._still = (view.x, view.y, view.yaw, t)
        elif t - since > 2.0:
            self._back_until, self._still = t + 1.0, (view.x, view.y, view.yaw, t)
        if t < self._back_until:
            return -0.1, 0.8
        return self._hunt(view)

    def _hunt(self, view):
        pos, nrm = geo.robot_markers_world(*view.enemy)
        c, s = math.cos(view.yaw), math.sin(view.yaw)
        cx, cy = view.x + geo.CAMERA_X * c, view.y + geo.CAMERA_X * s
        best = None
        for j in range(3):
            if view.taken[j]:
                continue
            vx, vy = cx - pos[j, 0], cy - pos[j, 1]
            d = math.hypot(vx, vy)
            if 0.15 < d < self.read_within and vx * nrm[j, 0] + vy * nrm[j, 1] > 0.6 * d:
                # in front of the marker and close: turn the camera onto it
                err = float(geo.wrap(math.atan2(-vy, -vx) - view.yaw))
                return (0.05 if d > 0.3 else 0.0) * max(0.0, math.cos(err)), float(np.clip(2.0 * err, -1.5, 1.5))
            # shooting spots in the marker's read cone: straight out, or up to 46 degrees off
            # its normal, nearer where a wall or a box is in the way
            spots = pos[j] + self._offsets(nrm[j])
            free = geo.point_static_clearance(spots[:, 0], spots[:, 1]) >= NAV_CLEARANCE
            if not free.any():
                continue  # against a wall or a box: not reachable now
            spots = spots[free]
            dists = np.hypot(spots[:, 0] - view.x, spots[:, 1] - view.y)
            i = int(np.argmin(dists))
            if best is None or dists[i] < best[0]:
                best = (float(dists[i]), float(spots[i, 0]), float(spots[i, 1]), pos[j])
        if best is None:  # every unread marker faces an obstacle: wait for the enemy to move, near it
            ex, ey = view.enemy[0], view.enemy[1]
            best = (math.hypot(ex - view.x, ey - view.y), ex, ey, None)
        dist, gx, gy, mark = best
        if dist < 0.08 and mark is not None:  # on the spot: face the marker
            err = float(geo.wrap(math.atan2(mark[1] - view.y, mark[0] - view.x) - view.yaw))
            return 0.0, float(np.clip(2.0 * err, -1.5, 1.5))
        # the goal moves with the enemy: its path field is that of the goal snapped to a 0.1 m
        # grid, so that fields are reused
        want = self._path_heading(view, gx, gy, dist, snap=True)
        # the path field does not know the enemy's body: go round it, not through it
        rx, ry = view.x - view.enemy[0], view.y - view.enemy[1]
        r = math.hypot(rx, ry)
        if r < 0.45:
            push = 0.5 * (0.45 - r) / 0.45 / max(r, 0.05)
            hx, hy = math.cos(want) + push * rx / max(r, 0.05), math.sin(want) + push * ry / max(r, 0.05)
            # and slide along it, on the side of the goal
            side = 1.0 if rx * (gy - view.y) - ry * (gx - view.x) > 0 else -1.0
            hx, hy = hx - side * 0.6 * ry / max(r, 0.05), hy + side * 0.6 * rx / max(r, 0.05)
            want = math.atan2(hy, hx)
        return self._drive(view, want, dist)


class PolicyOpponent(Opponent):
    """A frozen policy: ``fn(obs) -> action`` with ``obs`` in its own frame like the agent's."""

    name = "policy"
    needs_obs = True

    def __init__(self, fn: Callable[[Any], Any], hz: float = 10.0):
        if not callable(fn):
            raise TypeError("opponent_policy must be a callable obs -> action")
        self.fn, self.hz = fn, hz

    def act(self, view):
        return self.fn(view.obs)


SCRIPTED = {"idle": Idle, "random": RandomDrive, "cheese": Cheese, "teriyaki": Teriyaki,
            "clubhouse": Clubhouse, "waypoint": Waypoint, "raider": Raider}
OPPONENT_NAMES = tuple(SCRIPTED) + ("policy",)


def make_opponent(name: str, policy: Callable | None = None, policy_hz: float = 10.0) -> Opponent:
    """Build an opponent by name (one of :data:`OPPONENT_NAMES`)."""
    if name == "policy":
        if policy is None:
            raise ValueError("opponent 'policy' needs the opponent_policy option (a callable)")
        return PolicyOpponent(policy, policy_hz)
    if name not in SCRIPTED:
        raise ValueError(f"unknown opponent {name!r}; known: {OPPONENT_NAMES}")
    return SCRIPTED[name]()
