"""Geometry of the Push-T tee: its two rectangles, the goal pose, and the goal coverage without shapely.

gym-pusht 0.1.8 measures coverage as the shapely intersection area of the block's tee with the goal's
tee, divided by the goal's area: about 145 us a step. Both tees are unions of two rectangles that share
only an edge, so the intersection area is the sum of four convex rectangle-rectangle intersections.
Expressed in the goal's frame the goal rectangles are axis-aligned boxes, and each intersection is the
block rectangle clipped by four half-planes (Sutherland-Hodgman). Same area as shapely to ~1e-12.
"""

from __future__ import annotations

import math

__all__ = ["GOAL_POSE", "TEE_AREA", "TEE_RECTS", "coverage", "tee_polygons"]

GOAL_POSE = (256.0, 256.0, math.pi / 4)
"""The goal pose of the tee's body origin: x, y (pixels) and angle (radians), as gym-pusht 0.1.8."""

_SCALE = 30.0
_LENGTH = 4.0
TEE_RECTS: tuple[tuple[tuple[float, float], ...], ...] = (
    # The bar, then the stem, in body coordinates, with gym-pusht's vertex order.
    (
        (-_LENGTH * _SCALE / 2, _SCALE),
        (_LENGTH * _SCALE / 2, _SCALE),
        (_LENGTH * _SCALE / 2, 0.0),
        (-_LENGTH * _SCALE / 2, 0.0),
    ),
    (
        (-_SCALE / 2, _SCALE),
        (-_SCALE / 2, _LENGTH * _SCALE),
        (_SCALE / 2, _LENGTH * _SCALE),
        (_SCALE / 2, _SCALE),
    ),
)
"""The tee's two rectangles (bar, stem) as vertex lists in the body's frame."""

TEE_AREA = _LENGTH * _SCALE * _SCALE + _SCALE * (_LENGTH - 1) * _SCALE
"""Area of the tee: 6300 px^2."""

# The goal's rectangles in the goal's own frame, as axis-aligned boxes (x0, x1, y0, y1).
_GOAL_BOXES = tuple(
    (min(v[0] for v in rect), max(v[0] for v in rect), min(v[1] for v in rect), max(v[1] for v in rect)) for rect in TEE_RECTS
)
_GOAL_COS = math.cos(GOAL_POSE[2])
_GOAL_SIN = math.sin(GOAL_POSE[2])


def coverage(x: float, y: float, angle: float) -> float:
    """Fraction of the goal tee covered by a tee whose body origin is at (x, y) with this angle."""
    # The block's pose in the goal's frame: rotate the offset by -goal_angle.
    dx = x - GOAL_POSE[0]
    dy = y - GOAL_POSE[1]
    tx = _GOAL_COS * dx + _GOAL_SIN * dy
    ty = _GOAL_COS * dy - _GOAL_SIN * dx
    rel = angle - GOAL_POSE[2]
    c = math.cos(rel)
    s = math.sin(rel)
    area = 0.0
    for rect in TEE_RECTS:
        poly = [(c * vx - s * vy + tx, s * vx + c * vy + ty) for vx, vy in rect]
        xs = [p[0] for p in poly]
        ys = [p[1] for p in poly]
        px0, px1, py0, py1 = min(xs), max(xs), min(ys), max(ys)
        for bx0, bx1, by0, by1 in _GOAL_BOXES:
            if px1 <= bx0 or px0 >= bx1 or py1 <= by0 or py0 >= by1:
                continue
            clipped = poly
            # Clip only by the box sides the polygon crosses; a side it lies inside changes nothing.
            if px0 < bx0:
                clipped = _clip(clipped, 0, bx0, 1.0)
            if px1 > bx1:
                clipped = _clip(clipped, 0, bx1, -1.0)
            if py0 < by0:
                clipped = _clip(clipped, 1, by0, 1.0)
            if py1 > by1:
                clipped = _clip(clipped, 1, by1, -1.0)
            area += _area(clipped)
    return area / TEE_AREA


def tee_polygons(x: float, y: float, angle: float) -> list[list[tuple[float, float]]]:
    """World vertices of the tee's two rectangles for a body origin at (x, y) with this angle."""
    c = math.cos(angle)
    s = math.sin(angle)
    return [[(c * vx - s * vy + x, s * vx + c * vy + y) for vx, vy in rect] for rect in TEE_RECTS]


def _clip(poly: list[tuple[float, float]], axis: int, bound: float, sign: float) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: the part of a convex polygon where sign * (p[axis] - bound) >= 0."""
    out: list[tuple[float, float]] = []
    if not poly:
        return out
    prev = poly[-1]
    d_prev = sign * (prev[axis] - bound)
    for cur in poly:
        d_cur = sign * (cur[axis] - bound)
        if (d_cur >= 0.0) != (d_prev >= 0.0):
            t = d_prev / (d_prev - d_cur)
            crossing = (prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1]))
            if axis == 0:
                crossing = (bound, crossing[1])  # exactly on the side, as the exact clip would be
            else:
                crossing = (crossing[0], bound)
            out.append(crossing)
        if d_cur >= 0.0:
            out.append(cur)
        prev, d_prev = cur, d_cur
    return out


def _area(poly: list[tuple[float, float]]) -> float:
    """Unsigned shoelace area of a simple polygon."""
    n = len(poly)
    if n < 3:
        return 0.0
    total = 0.0
    x_prev, y_prev = poly[-1]
    for x_cur, y_cur in poly:
        total += x_prev * y_cur - x_cur * y_prev
        x_prev, y_prev = x_cur, y_cur
    return abs(total) * 0.5
