"""Burger War arena geometry, analytic 2D lidar and geometric marker reading.

Everything here is pure numpy and works in the *world* frame (metres, radians, z up):
red starts at (0, -1.3) facing +y, blue at (0, +1.3) facing -y. The field is the square
``|x| + |y| <= ARENA_HALF_DIAG`` (a 2.4 m square rotated 45 deg).

Shapes used below: ``S`` = number of 2D segments, ``B`` = number of lidar beams (360),
``M`` = number of markers tested.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

# --------------------------------------------------------------------------------------
# Game geometry (facts from the contest kit; see docs/burgerwar.md)
# --------------------------------------------------------------------------------------
ARENA_HALF_DIAG = 1.697  # inside of the field: |x| + |y| <= this
WALL_THICKNESS = 0.3
WALL_HEIGHT = 0.25
BOX_HEIGHT = 0.2

#: (cx, cy, half_x, half_y) of the five axis-aligned boxes: centre box, then the 4 corners.
BOXES = np.array(
    [
        [0.0, 0.0, 0.175, 0.175],
        [0.53, 0.53, 0.10, 0.075],
        [0.53, -0.53, 0.10, 0.075],
        [-0.53, 0.53, 0.10, 0.075],
        [-0.53, -0.53, 0.10, 0.075],
    ],
    dtype=np.float64,
)
PITFALLS = np.array([[0.53, 0.0], [-0.53, 0.0]])  # 0.2 m discs, 10 mm high: not obstacles
PITFALL_RADIUS = 0.1

RED_START = (0.0, -1.3, math.pi / 2)
BLUE_START = (0.0, 1.3, -math.pi / 2)

# Robot (TurtleBot3 burger), base frame: x forward, y left.
MAX_V = 0.22
MAX_W = 2.84
FOOTPRINT_CX = -0.032
FOOTPRINT_HALF = (0.089, 0.058)  # 0.178 x 0.116 m
ROBOT_MASS = 2.6
LIDAR_X = -0.032
LIDAR_Z = 0.1786
HOUSING_X = -0.017
HOUSING_R = 0.055
LIDAR_BEAMS = 360
LIDAR_MIN = 0.12
LIDAR_MAX = 3.5
CAMERA_X = 0.055
CAMERA_Z = 0.11
CAMERA_HFOV = 0.864
MIN_READ_DIST = 0.1

# Targets in the judge's order: 12 field markers (1 pt), then red's and blue's robot markers.
FIELD_MARKERS = [
    # name, x, y, normal angle
    ("FriedShrimp_N", 0.0, 0.176, math.pi / 2),
    ("FriedShrimp_S", 0.0, -0.176, -math.pi / 2),
    ("FriedShrimp_E", 0.176, 0.0, 0.0),
    ("FriedShrimp_W", -0.176, 0.0, math.pi),
    ("Omelette_N", 0.53, 0.615, math.pi / 2),
    ("Omelette_S", 0.53, 0.445, -math.pi / 2),
    ("OctopusWiener_N", 0.53, -0.445, math.pi / 2),
    ("OctopusWiener_S", 0.53, -0.615, -math.pi / 2),
    ("Tomato_N", -0.53, 0.615, math.pi / 2),
    ("Tomato_S", -0.53, 0.445, -math.pi / 2),
    ("Pudding_N", -0.53, -0.445, math.pi / 2),
    ("Pudding_S", -0.53, -0.615, -math.pi / 2),
]
N_FIELD = len(FIELD_MARKERS)
#: robot markers in base frame: suffix, x, y, normal angle (relative to the robot's yaw), points
ROBOT_MARKERS = [("L", -0.032, 0.09, math.pi / 2, 3), ("R", -0.032, -0.09, -math.pi / 2, 3),
                 ("B", -0.122, 0.0, math.pi, 5)]
TARGET_NAMES = [m[0] for m in FIELD_MARKERS] + [f"RE_{m[0]}" for m in ROBOT_MARKERS] + [
    f"BL_{m[0]}" for m in ROBOT_MARKERS]
TARGET_POINTS = np.array([1] * N_FIELD + [m[4] for m in ROBOT_MARKERS] * 2, dtype=np.int64)
N_TARGETS = len(TARGET_NAMES)  # 18
RED_MARKERS = np.arange(N_FIELD, N_FIELD + 3)
BLUE_MARKERS = np.arange(N_FIELD + 3, N_FIELD + 6)

FIELD_POS = np.array([[m[1], m[2]] for m in FIELD_MARKERS])  # (12, 2)
FIELD_NORMAL = np.array([[math.cos(m[3]), math.sin(m[3])] for m in FIELD_MARKERS])  # (12, 2)
ROBOT_MARKER_LOCAL = np.array([[m[1], m[2]] for m in ROBOT_MARKERS])  # (3, 2)
ROBOT_MARKER_NANGLE = np.array([m[3] for m in ROBOT_MARKERS])  # (3,)


def _mirror_field_perm() -> np.ndarray:
    """perm[i] = index of the field marker at the 180-deg rotated position of marker i."""
    perm = np.empty(N_FIELD, dtype=np.int64)
    for i in range(N_FIELD):
        d = np.abs(FIELD_POS + FIELD_POS[i]).sum(axis=1)
        perm[i] = int(np.argmin(d))
    return perm


FIELD_MIRROR = _mirror_field_perm()


def _box_segments(boxes: np.ndarray) -> np.ndarray:
    """(N, 4) boxes -> (4N, 4) segments (x0, y0, x1, y1)."""
    segs = []
    for cx, cy, hx, hy in boxes:
        c = [(cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)]
        for k in range(4):
            segs.append((*c[k], *c[(k + 1) % 4]))
    return np.array(segs, dtype=np.float64)


WALL_VERTS = np.array([[ARENA_HALF_DIAG, 0.0], [0.0, ARENA_HALF_DIAG], [-ARENA_HALF_DIAG, 0.0],
                       [0.0, -ARENA_HALF_DIAG]])
WALL_SEGMENTS = np.array([[*WALL_VERTS[k], *WALL_VERTS[(k + 1) % 4]] for k in range(4)])
BOX_SEGMENTS = _box_segments(BOXES)  # (20, 4)
STATIC_SEGMENTS = np.concatenate([WALL_SEGMENTS, BOX_SEGMENTS])  # (24, 4)


# --------------------------------------------------------------------------------------
# Small pose helpers
# --------------------------------------------------------------------------------------
def wrap(a):
    """Wrap angle(s) to (-pi, pi]."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def to_frame(x: float, y: float, yaw: float, side: int) -> tuple[float, float, float]:
    """World pose -> pose in ``side``'s own frame (side 0 red: identity; 1 blue: rotate 180 deg)."""
    if side == 0:
        return x, y, yaw
    return -x, -y, yaw + math.pi


from_frame = to_frame  # the 180-degree rotation is its own inverse


def _footprint_local(margin: float) -> np.ndarray:
    hx, hy = FOOTPRINT_HALF[0] + margin, FOOTPRINT_HALF[1] + margin
    return np.array([[FOOTPRINT_CX - hx, -hy], [FOOTPRINT_CX + hx, -hy],
                     [FOOTPRINT_CX + hx, hy], [FOOTPRINT_CX - hx, hy]])


_FOOTPRINT_LOCAL = _footprint_local(0.0)


def footprint_corners(x: float, y: float, yaw: float, margin: float = 0.0) -> np.ndarray:
    """Corners (4, 2) of a robot footprint (counter-clockwise), optionally grown by ``margin``."""
    local = _FOOTPRINT_LOCAL if margin == 0.0 else _footprint_local(margin)
    c, s = math.cos(yaw), math.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + (x, y)


def polygon_segments(corners: np.ndarray) -> np.ndarray:
    """Closed polygon (K, 2) -> (K, 4) segments."""
    return np.concatenate([corners, np.roll(corners, -1, axis=0)], axis=1)


ROBOT_MARKER_LOCAL_N = np.stack([np.cos(ROBOT_MARKER_NANGLE), np.sin(ROBOT_MARKER_NANGLE)], 1)


def robot_markers_world(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """World positions (3, 2) and unit normals (3, 2) of a robot's L, R, B markers."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot_t = np.array([[c, s], [-s, c]])  # R^T
    return ROBOT_MARKER_LOCAL @ rot_t + (x, y), ROBOT_MARKER_LOCAL_N @ rot_t


# --------------------------------------------------------------------------------------
# Analytic lidar
# --------------------------------------------------------------------------------------
class Lidar:
    """Vectorised 2D lidar for the arena: diamond walls, axis-aligned boxes, one circle per scan.

    ``scan(x, y, yaw, circle)`` returns float64[B] true ranges (no noise, no clipping) from a
    sensor at base-frame x ``LIDAR_X``; beam ``i`` points at ``yaw + 2*pi*i/B`` (index 0
    forward, counter-clockwise). ``circle`` is ``(cx, cy, r)`` or None. ``scan_many(poses,
    circles)`` does R scans at once: poses (R, 3), circles (R, 3) -> float64[R, B].
    Walls: exit distance through the convex field; boxes: slab test.
    """

    def __init__(self, beams: int = LIDAR_BEAMS, boxes: np.ndarray = BOXES):
        ang = 2 * np.pi * np.arange(beams) / beams
        self.ca, self.sa = np.cos(ang), np.sin(ang)
        self.beams = beams
        f = np.float32  # float32: ~1e-6 m rounding, half the time of float64
        self.bcx, self.bcy = boxes[:, 0, None, None].astype(f), boxes[:, 1, None, None].astype(f)
        self.bhx, self.bhy = boxes[:, 2, None, None].astype(f), boxes[:, 3, None, None].astype(f)
        self.field_half = ARENA_HALF_DIAG / math.sqrt(2)  # the field is a square in (u, v)

    def scan(self, x: float, y: float, yaw: float, circle=None) -> np.ndarray:
        circles = None if circle is None else np.array([circle], dtype=np.float64)
        return self.scan_many(np.array([[x, y, yaw]], dtype=np.float64), circles)[0]

    def scan_many(self, poses: np.ndarray, circles: np.ndarray | None = None) -> np.ndarray:
        """poses (R, 3), circles (R, 3) or None -> float32[R, B] ranges (inf: no hit)."""
        f = np.float32
        poses = np.asarray(poses, dtype=np.float64)
        cyaw, syaw = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])  # (R, 1)
        ox = poses[:, 0:1] + LIDAR_X * cyaw  # (R, 1) float64
        oy = poses[:, 1:2] + LIDAR_X * syaw
        dx = (self.ca * cyaw - self.sa * syaw).astype(f)  # (R, B)
        dy = (self.sa * cyaw + self.ca * syaw).astype(f)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # walls: the field is the square |u|, |v| <= field_half in the 45-deg rotated frame
            # (u, v) = ((x + y), (y - x)) / sqrt(2); exit distance = min over the two slabs;
            # fmin: a beam parallel to one slab gives nan there and the other slab decides.
            k = 1.0 / math.sqrt(2)
            h = self.field_half
            iu = 1.0 / ((dx + dy) * f(k))
            iv = 1.0 / ((dy - dx) * f(k))
            r = np.fmin(np.abs(iu) * f(h) - iu * ((ox + oy) * k).astype(f),
                        np.abs(iv) * f(h) - iv * ((oy - ox) * k).astype(f))
            # boxes: slab test around each box centre, layout (NB, R, B)
            tiny = f(1e-12)  # axis-parallel beams: keep the slab arithmetic finite
            dx[np.abs(dx) < tiny] = tiny
            dy[np.abs(dy) < tiny] = tiny
            ix, iy = 1.0 / dx, 1.0 / dy
            txc = (self.bcx - ox.astype(f)) * ix  # (NB, R, B)
            tyc = (self.bcy - oy.astype(f)) * iy
            txh = self.bhx * np.abs(ix)
            tyh = self.bhy * np.abs(iy)
            tnear = np.maximum(txc - txh, tyc - tyh)
            np.add(txc, txh, out=txc)
            np.add(tyc, tyh, out=tyc)
            tfar = np.minimum(txc, tyc, out=txc)
            # the sensor is never inside a box: a hit needs tfar >= tnear and tfar > 0
            np.maximum(tnear, 0, out=tnear)
            tnear[tfar < tnear] = np.inf
            np.minimum(r, tnear.min(axis=0), out=r)
            if circles is not None:
                # the sensor is never inside the other robot's housing (footprints do not overlap)
                wx = ox - circles[:, 0:1]  # (R, 1)
                wy = oy - circles[:, 1:2]
                c = (wx * wx + wy * wy - circles[:, 2:3] ** 2).astype(f)
                b = dx * wx.astype(f)
                b += dy * wy.astype(f)
                sq = np.sqrt(b * b - c)  # nan where missed
                np.add(b, sq, out=sq)  # b + sqrt: -t
                sq[~(sq < 0)] = -np.inf  # behind or missed (nan)
                np.minimum(r, np.negative(sq, out=sq), out=r)
        return r


def housing_circle(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """The lidar-housing circle (cx, cy, r) of a robot at world pose (x, y, yaw)."""
    return (x + HOUSING_X * math.cos(yaw), y + HOUSING_X * math.sin(yaw), HOUSING_R)


def detect_circle(ranges: np.ndarray, pose: Sequence[float], circle: Sequence[float],
                  tol: float = 0.05) -> np.ndarray:
    """What a detector on robot ``pose``'s own scan makes of ``circle`` (the other robot's
    housing): float32[3] (seen, x, y), x forward and y left of the robot's base, in metres.

    ``ranges``: the robot's raw scan, float[B] (noisy, unclipped; beam i at yaw + 2*pi*i/B).
    The other robot counts as seen when at least one beam that points at the circle reads the
    circle's own range there (within ``tol``) and inside the sensor's range, so it is not
    hidden by a wall, a box, or distance. Its position is taken from the scan as a detector on
    the real robot would: the nearest such beam's reading plus the circle's radius, along that
    beam; (0, 0, 0) when not seen. The true circle only picks the beams to look at (a detector
    that finds the robot-sized bump in the scan); whether it is seen, and where, is the scan's.
    """
    x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    ox, oy = x + LIDAR_X * math.cos(yaw), y + LIDAR_X * math.sin(yaw)
    cx, cy, r = float(circle[0]), float(circle[1]), float(circle[2])
    d = math.hypot(cx - ox, cy - oy)
    out = np.zeros(3, np.float32)
    if d <= r or d - r > LIDAR_MAX:
        return out
    beams = len(ranges)
    step = 2 * math.pi / beams
    bearing = math.atan2(cy - oy, cx - ox) - yaw
    half = math.asin(r / d)
    lo, hi = math.ceil((bearing - half) / step), math.floor((bearing + half) / step)
    if hi < lo:  # the circle falls between two beams
        return out
    idx = np.arange(lo, hi + 1)
    delta = idx * step - bearing  # each beam's angle off the centre's bearing
    expect = d * np.cos(delta) - np.sqrt(np.maximum(r * r - (d * np.sin(delta)) ** 2, 0.0))
    got = np.asarray(ranges, dtype=np.float64)[idx % beams]
    hit = (np.abs(got - expect) <= tol) & (got >= LIDAR_MIN) & (got <= LIDAR_MAX)
    if not hit.any():
        return out
    j = int(np.argmin(np.where(hit, np.abs(delta), np.inf)))
    ang = float(idx[j]) * step
    dist = float(got[j]) + r
    out[:] = (1.0, LIDAR_X + dist * math.cos(ang), dist * math.sin(ang))
    return out


# --------------------------------------------------------------------------------------
# Line of sight and marker reading
# --------------------------------------------------------------------------------------
def segments_cross(a: np.ndarray, b: np.ndarray, segs: np.ndarray) -> np.ndarray:
    """bool[M]: does segment a[m] -> b[m] properly cross any of ``segs`` (S, 4)?

    a, b: (M, 2). Touching at the very end points (within 1e-9 of the parameter range) does
    not count, so a marker lying on an obstacle face is not blocked by that face.
    """
    rx, ry = (b - a)[:, 0:1], (b - a)[:, 1:2]  # (M, 1)
    ex, ey = segs[None, :, 2] - segs[None, :, 0], segs[None, :, 3] - segs[None, :, 1]  # (1, S)
    wx, wy = segs[None, :, 0] - a[:, 0:1], segs[None, :, 1] - a[:, 1:2]  # (M, S)
    denom = rx * ey - ry * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * ey - wy * ex) / denom
        u = (wx * ry - wy * rx) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (t < 1 - 1e-9) & (u >= 0) & (u <= 1)
    return hit.any(axis=1)


def readable(cam_x: float, cam_y: float, yaw: float, pos: np.ndarray, normal: np.ndarray,
             blockers, read_range: float, cos_read_angle: float,
             half_fov: float = CAMERA_HFOV / 2) -> np.ndarray:
    """bool[M]: which markers (pos, normal: (M, 2)) a camera at (cam_x, cam_y, yaw) reads.

    Conditions: 2D distance in [MIN_READ_DIST, read_range]; bearing within +-half_fov of the
    camera axis; angle between the marker normal and the marker->camera direction below
    ``acos(cos_read_angle)``; the 2D line of sight crosses none of ``blockers`` (S, 4) (or a
    callable returning them, called only when some marker passes the other tests).
    """
    vx, vy = pos[:, 0] - cam_x, pos[:, 1] - cam_y
    d2 = vx * vx + vy * vy
    ok = (d2 >= MIN_READ_DIST ** 2) & (d2 <= read_range * read_range)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return ok
    vx, vy = vx[idx], vy[idx]
    dist = np.sqrt(d2[idx])
    bearing = (np.arctan2(vy, vx) - yaw + np.pi) % (2 * np.pi) - np.pi
    good = (np.abs(bearing) <= half_fov) & (
        -(vx * normal[idx, 0] + vy * normal[idx, 1]) > cos_read_angle * dist)
    ok[idx] = good
    idx = idx[good]
    if idx.size == 0:
        return ok
    if callable(blockers):
        blockers = blockers()
    cam = np.broadcast_to(np.array([cam_x, cam_y]), (idx.size, 2))
    ok[idx] = ~segments_cross(cam, pos[idx], blockers)
    return ok


# --------------------------------------------------------------------------------------
# Containment checks (used by tests and the scripted bots)
# --------------------------------------------------------------------------------------
def point_static_clearance(px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Distance (N,) of points to the nearest wall or box (negative inside boxes/outside field)."""
    px, py = np.atleast_1d(px).astype(float), np.atleast_1d(py).astype(float)
    wall = (ARENA_HALF_DIAG - (np.abs(px) + np.abs(py))) / math.sqrt(2)
    d = wall
    for cx, cy, hx, hy in BOXES:
        qx, qy = np.abs(px - cx) - hx, np.abs(py - cy) - hy
        out = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0))
        inside = np.minimum(np.maximum(qx, qy), 0)
        d = np.minimum(d, out + inside)
    return d


def polygons_overlap(a: np.ndarray, b: np.ndarray, tol: float = 0.0) -> bool:
    """Separating-axis test for two convex polygons (K, 2); ``tol`` allows that much overlap."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], 1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        pa, pb = a @ normals.T, b @ normals.T
        if np.any((pa.max(0) - tol < pb.min(0)) | (pb.max(0) - tol < pa.min(0))):
            return False
    return True


def box_corners(i: int) -> np.ndarray:
    cx, cy, hx, hy = BOXES[i]
    return np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]])


# --------------------------------------------------------------------------------------
# Fast scalar path for the env's hot loop (same model as ``readable``)
# --------------------------------------------------------------------------------------
def _seg_hits_box(ax: float, ay: float, bx: float, by: float, xmin: float, xmax: float,
                  ymin: float, ymax: float) -> bool:
    """Does segment a->b pass through the inside of an axis-aligned box (end points excluded)?"""
    t0, t1 = 1e-9, 1.0 - 1e-9
    dx, dy = bx - ax, by - ay
    for o, d, lo, hi in ((ax, dx, xmin, xmax), (ay, dy, ymin, ymax)):
        if d == 0.0:
            if o <= lo or o >= hi:
                return False
            continue
        ta, tb = (lo - o) / d, (hi - o) / d
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
        if t0 >= t1:
            return False
    return True


class MarkerReader:
    """Scalar (pure Python) version of :func:`readable` for one robot's camera against the 12
    field markers and the enemy's 3 markers, with boxes and the enemy's footprint blocking.

    ``reads(me, enemy, enemy_targets)``: me/enemy world poses (x, y, yaw), enemy_targets the
    3 target indices of the enemy's L, R, B markers -> list of target indices read. Faster
    than the vectorised path for these few markers; the two agree (tested).
    """

    def __init__(self, read_range: float, cos_read_angle: float, half_fov: float = CAMERA_HFOV / 2):
        self.rr2 = read_range * read_range
        self.min2 = MIN_READ_DIST * MIN_READ_DIST
        self.cos_read = cos_read_angle
        self.cos_fov = math.cos(half_fov)
        self.field = [(i, float(FIELD_POS[i, 0]), float(FIELD_POS[i, 1]), float(FIELD_NORMAL[i, 0]),
                       float(FIELD_NORMAL[i, 1])) for i in range(N_FIELD)]
        self.local = [(float(ROBOT_MARKER_LOCAL[j, 0]), float(ROBOT_MARKER_LOCAL[j, 1]),
                       float(ROBOT_MARKER_LOCAL_N[j, 0]), float(ROBOT_MARKER_LOCAL_N[j, 1]))
                      for j in range(3)]
        self.boxes = [(cx - hx, cx + hx, cy - hy, cy + hy) for cx, cy, hx, hy in BOXES.tolist()]

    def reads(self, me, enemy, enemy_targets) -> list[int]:
        x, y, yaw = me
        ex, ey, eyaw = enemy
        c, s = math.cos(yaw), math.sin(yaw)
        cx, cy = x + CAMERA_X * c, y + CAMERA_X * s
        ce, se = math.cos(eyaw), math.sin(eyaw)
        cands = list(self.field)
        for j, (lx, ly, lnx, lny) in enumerate(self.local):
            cands.append((int(enemy_targets[j]), ex + ce * lx - se * ly, ey + se * lx + ce * ly,
                          ce * lnx - se * lny, se * lnx + ce * lny))
        out = []
        for idx, mx, my, nx, ny in cands:
            vx, vy = mx - cx, my - cy
            d2 = vx * vx + vy * vy
            if d2 < self.min2 or d2 > self.rr2:
                continue
            d = math.sqrt(d2)
            if vx * c + vy * s < self.cos_fov * d:  # outside the field of view
                continue
            if -(vx * nx + vy * ny) <= self.cos_read * d:  # too oblique / from behind
                continue
            if self._blocked(cx, cy, mx, my, ex, ey, ce, se):
                continue
            out.append(idx)
        return out

    def _blocked(self, ax, ay, bx, by, ex, ey, ce, se) -> bool:
        for box in self.boxes:
            if _seg_hits_box(ax, ay, bx, by, *box):
                return True
        # enemy footprint: go to its frame (centred on the footprint)
        def local(px, py):
            rx, ry = px - ex, py - ey
            return ce * rx + se * ry - FOOTPRINT_CX, -se * rx + ce * ry

        lax, lay = local(ax, ay)
        lbx, lby = local(bx, by)
        hx, hy = FOOTPRINT_HALF
        return _seg_hits_box(lax, lay, lbx, lby, -hx, hx, -hy, hy)


#: the guard's rule (``zenrl export --guard``; docs/burgerwar.md, "The guard"), also the defaults of
#: the env's ``facing`` reward (``face_radius``, ``face_angle``): the other
#: robot seen within this many metres (a reader needs its camera within 0.8 m of a marker) ...
GUARD_RADIUS_M = 1.2
#: ... and more than this many degrees off the heading. A side marker is read from at most 60
#: degrees off its normal, so from 30 degrees off our heading or more. Released below this angle,
#: the policy may turn by up to 16 degrees in one decision (1.4 rad/s at 5 Hz) before the guard
#: looks again: the angle must leave that margin (at 30 an exploiter read the sides the guard
#: had just released; docs/burgerwar.md)
GUARD_ANGLE_DEG = 15.0
