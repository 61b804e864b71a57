"""Top-down numpy renderer for the Burger War env (no matplotlib, no pybullet camera).

``TopDownRenderer(size).draw(poses, owners, scores, time, state)`` returns uint8[size, size, 3]:
arena, boxes, pitfalls, field markers coloured by owner (white neutral, red, blue), both robots
(red / blue footprints, a yellow dot at the front), their markers, and the scores and clock as
text in a built-in 3x5 bitmap font.
"""

from __future__ import annotations

import math

import numpy as np

from zenrl.games.burgerwar import geometry as geo

# 3x5 bitmap glyphs ('#' = ink), rows top to bottom.
_GLYPHS = {
    "0": ["###", "#.#", "#.#", "#.#", "###"], "1": [".#.", "##.", ".#.", ".#.", "###"],
    "2": ["###", "..#", "###", "#..", "###"], "3": ["###", "..#", "###", "..#", "###"],
    "4": ["#.#", "#.#", "###", "..#", "..#"], "5": ["###", "#..", "###", "..#", "###"],
    "6": ["###", "#..", "###", "#.#", "###"], "7": ["###", "..#", "..#", ".#.", ".#."],
    "8": ["###", "#.#", "###", "#.#", "###"], "9": ["###", "#.#", "###", "..#", "###"],
    ":": ["...", ".#.", "...", ".#.", "..."], ".": ["...", "...", "...", "...", ".#."],
    "-": ["...", "...", "###", "...", "..."], " ": ["...", "...", "...", "...", "..."],
    "R": ["##.", "#.#", "##.", "#.#", "#.#"], "B": ["##.", "#.#", "##.", "#.#", "##."],
    "T": ["###", ".#.", ".#.", ".#.", ".#."], "D": ["##.", "#.#", "#.#", "#.#", "##."],
    "W": ["#.#", "#.#", "#.#", "###", "#.#"], "I": ["###", ".#.", ".#.", ".#.", "###"],
    "N": ["#.#", "###", "###", "#.#", "#.#"], "E": ["###", "#..", "##.", "#..", "###"],
    "S": ["###", "#..", "###", "..#", "###"], "O": ["###", "#.#", "#.#", "#.#", "###"],
    "P": ["###", "#.#", "###", "#..", "#.."], "A": ["###", "#.#", "###", "#.#", "#.#"],
}
FONT = {k: np.array([[c == "#" for c in row] for row in v], dtype=bool) for k, v in _GLYPHS.items()}

RED = (220, 30, 30)
BLUE = (30, 70, 230)
OWNER_COLOURS = np.array([[250, 250, 250], [255, 90, 90], [90, 140, 255]], dtype=np.uint8)


def draw_text(img: np.ndarray, text: str, row: int, col: int, scale: int = 1,
              colour=(255, 255, 255)) -> None:
    """Draw ``text`` (characters of FONT; others become spaces) with its top-left at (row, col)."""
    for ch in text.upper():
        g = FONT.get(ch, FONT[" "])
        if scale > 1:
            g = np.kron(g, np.ones((scale, scale), dtype=bool))
        h, w = g.shape
        r0, c0 = max(row, 0), max(col, 0)
        r1, c1 = min(row + h, img.shape[0]), min(col + w, img.shape[1])
        if r1 > r0 and c1 > c0:
            sub = g[r0 - row:r1 - row, c0 - col:c1 - col]
            img[r0:r1, c0:c1][sub] = colour
        col += w + scale


class TopDownRenderer:
    """World (x right, y up) -> image (col, row) with ``size`` pixels over ``2 * extent`` m."""

    def __init__(self, size: int = 256, extent: float = 1.8):
        self.size = int(size)
        self.extent = extent
        self.scale = self.size / (2 * extent)
        c = (np.arange(self.size) + 0.5) / self.scale - extent
        self._xs = c  # world x of each column
        self._ys = -c  # world y of each row
        self._bg = self._background()

    def to_px(self, x: float, y: float) -> tuple[int, int]:
        """World point -> (row, col) pixel indices."""
        return (int((self.extent - y) * self.scale), int((x + self.extent) * self.scale))

    def _fill_poly(self, img, poly: np.ndarray, colour) -> None:
        """Fill a convex counter-clockwise polygon (K, 2) in world coordinates."""
        x0, x1 = poly[:, 0].min(), poly[:, 0].max()
        y0, y1 = poly[:, 1].min(), poly[:, 1].max()
        cols = np.flatnonzero((self._xs >= x0) & (self._xs <= x1))
        rows = np.flatnonzero((self._ys >= y0) & (self._ys <= y1))
        if cols.size == 0 or rows.size == 0:
            return
        X, Y = np.meshgrid(self._xs[cols], self._ys[rows])
        inside = np.ones(X.shape, dtype=bool)
        nxt = np.roll(poly, -1, axis=0)
        for (ax, ay), (bx, by) in zip(poly, nxt):
            inside &= (bx - ax) * (Y - ay) - (by - ay) * (X - ax) >= 0
        block = img[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        block[inside] = colour

    def _fill_circle(self, img, cx, cy, r, colour) -> None:
        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        self._fill_poly(img, np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], 1), colour)

    def _square(self, img, x, y, half, colour) -> None:
        sq = np.array([[x - half, y - half], [x + half, y - half], [x + half, y + half],
                       [x - half, y + half]])
        self._fill_poly(img, sq, colour)

    def _background(self) -> np.ndarray:
        img = np.zeros((self.size, self.size, 3), dtype=np.uint8)
        img[:] = (45, 45, 50)
        h = geo.ARENA_HALF_DIAG
        t = geo.WALL_THICKNESS * math.sqrt(2)
        self._fill_poly(img, np.array([[h + t, 0], [0, h + t], [-h - t, 0], [0, -h - t]]), (90, 70, 50))
        self._fill_poly(img, geo.WALL_VERTS, (205, 200, 185))
        for cx, cy in geo.PITFALLS:
            self._fill_circle(img, cx, cy, geo.PITFALL_RADIUS, (175, 170, 155))
        for i in range(len(geo.BOXES)):
            self._fill_poly(img, geo.box_corners(i), (100, 100, 105))
        return img

    def draw(self, poses, owners: np.ndarray, scores, time: float, state: str = "running",
             sudden_death: bool = False) -> np.ndarray:
        """poses: ((x, y, yaw) red, (x, y, yaw) blue) in world frame; owners int[18] (0 n, 1 r,
        2 b); scores (red, blue). Returns uint8[size, size, 3]."""
        img = self._bg.copy()
        mh = 0.03
        for i in range(geo.N_FIELD):
            p, n = geo.FIELD_POS[i], geo.FIELD_NORMAL[i]
            self._square(img, p[0] + n[0] * mh, p[1] + n[1] * mh, mh, OWNER_COLOURS[owners[i]])
        for k, (pose, colour) in enumerate(zip(poses, (RED, BLUE))):
            x, y, yaw = pose
            self._fill_poly(img, geo.footprint_corners(x, y, yaw), colour)
            cx, cy, _ = geo.housing_circle(x, y, yaw)
            self._fill_circle(img, cx, cy, 0.035, tuple(int(c * 0.6) for c in colour))
            self._fill_circle(img, x + 0.045 * math.cos(yaw), y + 0.045 * math.sin(yaw), 0.012,
                              (255, 230, 0))
            pos, nrm = geo.robot_markers_world(x, y, yaw)
            for j in range(3):
                o = owners[geo.N_FIELD + 3 * k + j]
                self._square(img, pos[j, 0] - nrm[j, 0] * 0.012, pos[j, 1] - nrm[j, 1] * 0.012,
                             0.013, OWNER_COLOURS[o])
        s = max(1, self.size // 128)
        draw_text(img, f"R {scores[0]}", 2 * s, 2 * s, s, (255, 110, 110))
        blue = f"B {scores[1]}"
        draw_text(img, blue, 2 * s, self.size - (4 * len(blue) + 1) * s, s, (130, 160, 255))
        clock = f"{int(time) // 60}:{time % 60:04.1f}"
        draw_text(img, ("SD " if sudden_death else "") + clock, self.size - 7 * s, 2 * s, s)
        if state != "running":
            draw_text(img, state.upper(), self.size - 7 * s, self.size - (4 * len(state) + 1) * s, s,
                      (255, 230, 0))
        return img
