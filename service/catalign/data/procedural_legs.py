"""Seat and leg builders for the procedural chair generator: seats, leg layouts, stretchers,
aprons, pedestals, panel ends and sleds, each assembled from the closed solids of
:mod:`catalign.data.procedural_primitives` in the floor frame (y=0 is the floor).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from catalign.data.procedural_primitives import (
    _X,
    FloatArray,
    bar,
    box,
    flare,
    frustum,
    horizontal_slab,
    rod,
    rounded_polyline,
    rounded_rect,
    square_leg,
    superellipse,
    torus,
    tube,
)

if TYPE_CHECKING:
    from catalign.data.procedural_params import LegParams, SeatParams

LEG_STYLES: tuple[str, ...] = ("square", "round", "tapered_square", "tapered_round")

SQUARE_STYLES = ("square", "tapered_square")
Leg = tuple[FloatArray, FloatArray]  # (top, bottom) of a leg axis


def member(p0: ArrayLike, p1: ArrayLike, w0: float, w1: float, square: bool) -> trimesh.Trimesh:
    if square:
        return square_leg(p0, p1, w0, w1)
    return frustum(p0, p1, 0.5 * w0, 0.5 * w1, sections=14)


def seat_slab_bottom(seat: SeatParams) -> float:
    return seat.height - seat.cushion - seat.thickness


def seat_outline(seat: SeatParams) -> FloatArray:
    """Plan-view (x, z) outline of the seat board."""
    if seat.shape == "round":
        return superellipse(seat.width, seat.depth, 2.0, 40)
    if seat.shape == "soft":
        return superellipse(seat.width, seat.depth, seat.corner, 48)
    out = rounded_rect(seat.width, seat.depth, seat.corner)
    if seat.shape == "trapezoid":
        out = flare(out, seat.depth, seat.flare)
    return out


def seat_parts(seat: SeatParams, battens_x: Sequence[float] = ()) -> list[trimesh.Trimesh]:
    top = seat.height - seat.cushion
    bottom = top - seat.thickness
    outline = seat_outline(seat)
    out: list[trimesh.Trimesh] = []
    if seat.slats:
        gap = 0.012
        depth = (seat.depth - (seat.slats - 1) * gap) / seat.slats
        for i in range(seat.slats):
            z = -0.5 * seat.depth + i * (depth + gap)
            out.append(box((-0.5 * seat.width, bottom, z), (0.5 * seat.width, top, z + depth)))
        for x in battens_x:
            lo = (x - 0.02, bottom - 0.03, -0.5 * seat.depth + 0.01)
            out.append(box(lo, (x + 0.02, bottom + 0.005, 0.5 * seat.depth - 0.01)))
    else:
        out.append(horizontal_slab(outline, bottom, top))
    if seat.cushion > 0:
        scale = np.array([1.0 - 0.03 / seat.width, 1.0 - 0.03 / seat.depth])
        out.append(horizontal_slab(outline * scale, top - 0.005, seat.height))
    return out


def leg_layout(seat: SeatParams, legs: LegParams) -> list[Leg]:
    """Leg axes, ordered around the seat: front-left, (front-middle,) front-right, back..."""
    top_y = seat_slab_bottom(seat) + 0.01
    spread = top_y * np.tan(np.deg2rad(legs.splay))
    tops: list[tuple[float, float]] = []
    dirs: list[tuple[float, float]] = []
    if seat.shape == "round" or legs.count == 3:
        angles = (240.0, 120.0, 0.0) if legs.count == 3 else (225.0, 135.0, 45.0, 315.0)
        rx, rz = 0.5 * seat.width - legs.inset, 0.5 * seat.depth - legs.inset
        for a in np.deg2rad(angles):
            tops.append((rx * np.sin(a), rz * np.cos(a)))
            dirs.append((np.sin(a), np.cos(a)))
    else:
        xs, zs = 0.5 * seat.width - legs.inset, 0.5 * seat.depth - legs.inset
        front = 1.0 + seat.flare * (0.5 + zs / seat.depth)
        cols = (-1.0, 0.0, 1.0) if legs.count == 6 else (-1.0, 1.0)
        for c in cols:
            tops.append((c * xs * front, -zs))
            dirs.append((c, -1.0))
        for c in reversed(cols):
            tops.append((c * xs, zs))
            dirs.append((c, 1.0))
    out = []
    for (x, z), (dx, dz) in zip(tops, dirs, strict=True):
        top = np.array([x, top_y, z])
        bottom = np.array([x + dx * spread, 0.0, z + dz * spread])
        # lift the foot so the lowest corner of the tilted end face rests on the floor
        axis = (top - bottom) / np.linalg.norm(top - bottom)
        sin_tilt = float(np.sqrt(max(0.0, 1.0 - axis[1] ** 2)))
        bottom[1] = 0.5 * np.sqrt(2.0) * legs.thickness * legs.taper * sin_tilt
        out.append((top, bottom))
    return out


def _at_height(leg: Leg, y: float) -> FloatArray:
    top, bottom = leg
    return top + (bottom - top) * (top[1] - y) / (top[1] - bottom[1])


def _stretchers(layout: list[Leg], legs: LegParams) -> list[trimesh.Trimesh]:
    h = legs.stretcher_height
    n = len(layout)
    pts = [_at_height(leg, h) for leg in layout]
    frac = (layout[0][0][1] - h) / layout[0][0][1]
    width = max(0.012, 0.45 * legs.thickness * (1.0 + (legs.taper - 1.0) * frac))
    square = legs.style in SQUARE_STYLES
    kind = legs.stretchers
    if kind == "ring":
        radius = float(np.mean([np.hypot(p[0], p[2]) for p in pts]))
        return [torus((0.0, h, 0.0), radius, max(0.009, 0.5 * width))]
    if kind in ("sides", "h", "x") and n == 3:
        kind = "box"
    if kind == "x" and n != 4:
        kind = "box"
    pairs: list[tuple[FloatArray, FloatArray]] = []
    if kind == "box":
        pairs = [(pts[i], pts[(i + 1) % n]) for i in range(n)]
    elif kind in ("sides", "h"):
        pairs = [(pts[i], pts[n - 1 - i]) for i in range(n // 2)]
        if kind == "h":
            mids = [0.5 * (a + b) for a, b in pairs]
            pairs.append((mids[0], mids[-1]))
    elif kind == "x":
        pairs = [(pts[0], pts[2]), (pts[1], pts[3])]
    return [
        bar(a, b, width, width) if square else rod(a, b, 0.5 * width, sections=10) for a, b in pairs
    ]


def _aprons(layout: list[Leg], seat: SeatParams, legs: LegParams) -> list[trimesh.Trimesh]:
    y = seat_slab_bottom(seat) - 0.5 * legs.apron + 0.005
    pts = [np.array([t[0], y, t[2]]) for t, _ in layout]
    n = len(pts)
    return [bar(pts[i], pts[(i + 1) % n], 0.018, legs.apron) for i in range(n)]


def _pedestal(seat: SeatParams, legs: LegParams) -> list[trimesh.Trimesh]:
    top_y = seat_slab_bottom(seat) + 0.01
    col = max(0.022, 0.6 * legs.thickness)
    base_r = 0.42 * min(seat.width, seat.depth) + 0.04
    out = [
        frustum((0, 0, 0), (0, 0.025, 0), base_r, base_r * 0.92, sections=32),
        frustum((0, 0.02, 0), (0, 0.07, 0), 2.2 * col, col, sections=16),
        rod((0, 0.02, 0), (0, top_y, 0), col, sections=16),
        frustum((0, top_y - 0.06, 0), (0, top_y, 0), col, 2.5 * col, sections=16),
    ]
    if legs.stretchers != "none":
        h = legs.stretcher_height
        ring_r = 0.5 * min(seat.width, seat.depth) - 0.02
        out.append(torus((0, h, 0), ring_r, 0.01))
        for a in np.deg2rad((0.0, 120.0, 240.0)):
            end = (ring_r * np.sin(a), h, ring_r * np.cos(a))
            out.append(rod((0, h, 0), end, 0.008, sections=8))
    return out


def _panel_ends(seat: SeatParams, legs: LegParams) -> list[trimesh.Trimesh]:
    top_y = seat_slab_bottom(seat) + 0.01
    x = 0.5 * seat.width - legs.inset
    t = 0.5 * legs.thickness
    z = 0.5 * seat.depth - 0.03
    out = [box((s * x - t, 0.0, -z), (s * x + t, top_y, z)) for s in (-1.0, 1.0)]
    if legs.stretchers != "none":
        h = legs.stretcher_height
        out.append(bar((-x, h, 0.0), (x, h, 0.0), 0.03, 0.06))
    return out


def _sled(seat: SeatParams, legs: LegParams, layout: list[Leg]) -> list[trimesh.Trimesh]:
    r = 0.5 * legs.thickness
    top_y = layout[0][0][1]
    z_front, z_back = float(layout[0][0][2]), float(layout[-1][0][2])
    out = []
    for s in (-1.0, 1.0):
        x = s * abs(float(layout[-1][0][0]))
        path = [(x, top_y, z_back), (x, r, z_back + 0.04), (x, r, z_front - 0.04)]
        path.append((x, top_y, z_front))
        out.append(tube(rounded_polyline(path, 0.07), r, _X))
    return out


def leg_parts(seat: SeatParams, legs: LegParams, layout: list[Leg]) -> list[trimesh.Trimesh]:
    if legs.style == "pedestal":
        return _pedestal(seat, legs)
    if legs.style == "panel":
        return _panel_ends(seat, legs)
    if legs.style == "sled":
        return _sled(seat, legs, layout)
    square = legs.style in SQUARE_STYLES
    out = [member(t, b, legs.thickness, legs.thickness * legs.taper, square) for t, b in layout]
    if legs.stretchers != "none":
        out += _stretchers(layout, legs)
    if legs.apron > 0:
        out += _aprons(layout, seat, legs)
    return out
