"""Closed triangle-mesh primitives for the procedural chair generator.

The generator assembles chairs by concatenating simple solids, so every primitive here must be
closed and consistently wound on its own (ray casting, point sampling and inside tests all rely
on it) and cheap in triangles. Trimesh's polygon extrusion needs shapely and booleans need an
external engine, neither of which we ship, so the solids are built from one lofting routine:
consecutive rings of points joined by quads and capped with triangle fans. All coordinates are
metres in the chair frame (+Y up, the chair faces -Z).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])


def _as_point(p: ArrayLike) -> FloatArray:
    return np.asarray(p, dtype=np.float64).reshape(3)


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of 3-vectors (np.cross is slow on single vectors)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _solid(verts: FloatArray, faces: NDArray[np.int64]) -> trimesh.Trimesh:
    """Mesh from a closed triangulation, flipping the winding if its signed volume is negative."""
    tri = verts[faces]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    det = (
        a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
        - a[:, 1] * (b[:, 0] * c[:, 2] - b[:, 2] * c[:, 0])
        + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    )
    if det.sum() < 0:
        faces = faces[:, ::-1]
    return trimesh.Trimesh(vertices=verts, faces=np.ascontiguousarray(faces), process=False)


_BOX_CORNERS = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float64
)
_BOX_FACES = np.array(
    [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
        [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],
    ],
    dtype=np.int64,
)  # fmt: skip


def _box_mesh(extents: ArrayLike, rotation: FloatArray, center: FloatArray) -> trimesh.Trimesh:
    verts = (_BOX_CORNERS * np.asarray(extents, dtype=np.float64)) @ rotation.T + center
    return _solid(verts, _BOX_FACES)


def loft(rings: Sequence[ArrayLike], closed_loop: bool = False) -> trimesh.Trimesh:
    """Join rings of K points each into a closed solid.

    Ring ``i`` point ``k`` is connected to ring ``i + 1`` point ``k``. Open lofts are capped at
    both ends with a fan around the ring centroid (so the end rings must be star-shaped about
    their centroid); ``closed_loop`` connects the last ring back to the first (a torus).
    """
    arr = np.stack([np.asarray(r, dtype=np.float64) for r in rings])
    n_rings, k = arr.shape[:2]
    verts = arr.reshape(-1, 3)
    faces: list[NDArray[np.int64]] = []
    idx = np.arange(k)
    nxt = (idx + 1) % k
    n_seg = n_rings if closed_loop else n_rings - 1
    for i in range(n_seg):
        a = i * k
        b = ((i + 1) % n_rings) * k
        faces.append(np.stack([a + idx, a + nxt, b + nxt], axis=1))
        faces.append(np.stack([a + idx, b + nxt, b + idx], axis=1))
    if not closed_loop:
        c0 = len(verts)
        c1 = c0 + 1
        verts = np.vstack([verts, arr[0].mean(axis=0), arr[-1].mean(axis=0)])
        last = (n_rings - 1) * k
        faces.append(np.stack([np.full(k, c0), nxt, idx], axis=1))
        faces.append(np.stack([np.full(k, c1), last + idx, last + nxt], axis=1))
    return _solid(verts, np.vstack(faces))


def _perpendicular_frame(axis: FloatArray, ref: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit vectors (u, v) with (u, v, axis) right-handed and v as close to ``ref`` as possible."""
    v = ref - axis * float(ref @ axis)
    if np.linalg.norm(v) < 1e-6:
        alt = _Z if abs(axis @ _Z) < 0.9 else _X
        v = alt - axis * float(alt @ axis)
    v /= np.linalg.norm(v)
    u = _cross(v, axis)
    return u, v


def frustum(
    p0: ArrayLike,
    p1: ArrayLike,
    r0: float,
    r1: float | None = None,
    sections: int = 14,
    phase: float = 0.0,
) -> trimesh.Trimesh:
    """Closed (possibly tapered) prism from ``p0`` to ``p1`` with circumradii ``r0``/``r1``.

    ``sections=4`` with ``phase=pi/4`` gives a square cross-section whose sides follow the
    world X/Z axes for near-vertical members (use :func:`square_leg`).
    """
    a, b = _as_point(p0), _as_point(p1)
    axis = b - a
    axis /= np.linalg.norm(axis)
    u, v = _perpendicular_frame(axis, _Z if abs(axis @ _Y) > 0.7 else _Y)
    ang = phase + 2.0 * np.pi * np.arange(sections) / sections
    ring = np.outer(np.cos(ang), u) + np.outer(np.sin(ang), v)
    r1 = r0 if r1 is None else r1
    return loft([a + r0 * ring, b + r1 * ring])


def rod(p0: ArrayLike, p1: ArrayLike, radius: float, sections: int = 14) -> trimesh.Trimesh:
    """Round cylinder between two points."""
    return frustum(p0, p1, radius, radius, sections=sections)


def square_leg(
    p0: ArrayLike, p1: ArrayLike, width0: float, width1: float | None = None
) -> trimesh.Trimesh:
    """Square-section member between two points, side ``width0`` at ``p0`` and ``width1`` at p1."""
    width1 = width0 if width1 is None else width1
    s = np.sqrt(0.5)
    return frustum(p0, p1, width0 * s, width1 * s, sections=4, phase=np.pi / 4)


def bar(
    p0: ArrayLike, p1: ArrayLike, width: float, height: float, up: ArrayLike = _Y
) -> trimesh.Trimesh:
    """Box-section bar from ``p0`` to ``p1``; ``height`` is measured along ``up``."""
    a, b = _as_point(p0), _as_point(p1)
    axis = b - a
    length = float(np.linalg.norm(axis))
    axis /= length
    u, v = _perpendicular_frame(axis, _as_point(up))
    return _box_mesh((width, height, length), np.column_stack([u, v, axis]), 0.5 * (a + b))


def box(lo: ArrayLike, hi: ArrayLike) -> trimesh.Trimesh:
    """Axis-aligned box spanning the corners ``lo`` and ``hi``."""
    lo_, hi_ = _as_point(lo), _as_point(hi)
    return _box_mesh(np.abs(hi_ - lo_), np.eye(3), 0.5 * (lo_ + hi_))


def rounded_rect(width: float, depth: float, radius: float, per_corner: int = 6) -> FloatArray:
    """Counter-clockwise outline (N, 2) of a rectangle centred on the origin, rounded corners."""
    radius = float(np.clip(radius, 1e-4, 0.5 * min(width, depth) - 1e-4))
    hx, hy = 0.5 * width - radius, 0.5 * depth - radius
    pts = []
    for cx, cy, start in ((hx, hy, 0.0), (-hx, hy, 90.0), (-hx, -hy, 180.0), (hx, -hy, 270.0)):
        t = np.deg2rad(start + np.linspace(0.0, 90.0, per_corner))
        pts.append(np.stack([cx + radius * np.cos(t), cy + radius * np.sin(t)], axis=1))
    return np.vstack(pts)


def superellipse(width: float, depth: float, exponent: float, n: int = 48) -> FloatArray:
    """Counter-clockwise outline of ``|2x/w|^p + |2y/d|^p = 1`` (p=2 ellipse, large p boxy)."""
    t = 2.0 * np.pi * np.arange(n) / n
    c, s = np.cos(t), np.sin(t)
    e = 2.0 / exponent
    x = 0.5 * width * np.sign(c) * np.abs(c) ** e
    y = 0.5 * depth * np.sign(s) * np.abs(s) ** e
    return np.stack([x, y], axis=1)


def flare(outline: FloatArray, depth: float, amount: float) -> FloatArray:
    """Widen an outline linearly towards -y (the front of a seat in plan view) by ``amount``."""
    out = outline.copy()
    out[:, 0] *= 1.0 + amount * (0.5 - outline[:, 1] / depth)
    return out


def horizontal_slab(
    outline_xz: FloatArray, y0: float, y1: float, center: ArrayLike = (0.0, 0.0)
) -> trimesh.Trimesh:
    """Extrude a plan-view outline (x, z) vertically between heights ``y0`` and ``y1``."""
    cx, cz = center  # type: ignore[misc]
    x, z = outline_xz[:, 0] + cx, outline_xz[:, 1] + cz
    return loft([np.stack([x, np.full_like(x, h), z], axis=1) for h in (y0, y1)])


def vertical_slab(
    outline_xy: FloatArray, z0: float, z1: float, center: ArrayLike = (0.0, 0.0)
) -> trimesh.Trimesh:
    """Extrude an elevation outline (x, y) along Z between ``z0`` and ``z1``."""
    cx, cy = center  # type: ignore[misc]
    x, y = outline_xy[:, 0] + cx, outline_xy[:, 1] + cy
    return loft([np.stack([x, y, np.full_like(x, d)], axis=1) for d in (z0, z1)])


def curved_panel(
    width: float, y0: float, y1: float, thickness: float, radius: float, steps: int = 12
) -> trimesh.Trimesh:
    """Slice of a vertical cylindrical shell: a backrest whose sides wrap forward (towards -Z).

    The middle of the mid-surface sits at z=0; the shell axis is at z=-radius.
    """
    half = 0.5 * width / radius
    rings = []
    for phi in np.linspace(-half, half, steps + 1):
        s, c = np.sin(phi), np.cos(phi)
        corners = []
        for r, h in (
            (radius - 0.5 * thickness, y0),
            (radius + 0.5 * thickness, y0),
            (radius + 0.5 * thickness, y1),
            (radius - 0.5 * thickness, y1),
        ):
            corners.append((r * s, h, r * c - radius))
        rings.append(np.array(corners))
    return loft(rings)


def torus(
    center: ArrayLike, major: float, minor: float, n_major: int = 28, n_minor: int = 8
) -> trimesh.Trimesh:
    """Horizontal ring (axis +Y) centred at ``center``: a stool footrest."""
    c = _as_point(center)
    t = 2.0 * np.pi * np.arange(n_minor) / n_minor
    rings = []
    for phi in 2.0 * np.pi * np.arange(n_major) / n_major:
        radial = np.array([np.cos(phi), 0.0, np.sin(phi)])
        rings.append(
            c + np.outer(major + minor * np.cos(t), radial) + np.outer(minor * np.sin(t), _Y)
        )
    return loft(rings, closed_loop=True)


def wheel(center: ArrayLike, radius: float, width: float, axis: ArrayLike) -> trimesh.Trimesh:
    """Short cylinder (a caster wheel) centred at ``center`` spinning about ``axis``."""
    c, a = _as_point(center), _as_point(axis)
    a = a / np.linalg.norm(a)
    return rod(c - 0.5 * width * a, c + 0.5 * width * a, radius, sections=12)


def sphere(center: ArrayLike, radius: float) -> trimesh.Trimesh:
    """Low-poly sphere (80 faces)."""
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=radius)
    mesh.apply_translation(_as_point(center))
    return mesh


def rounded_polyline(points: ArrayLike, radius: float, per_corner: int = 5) -> FloatArray:
    """Replace the interior corners of a polyline (M, D) by circular arcs of ``radius``."""
    pts = np.asarray(points, dtype=np.float64)
    out = [pts[0]]
    for a, p, b in zip(pts[:-2], pts[1:-1], pts[2:], strict=True):
        d1, d2 = a - p, b - p
        d1, d2 = d1 / np.linalg.norm(d1), d2 / np.linalg.norm(d2)
        theta = np.arccos(np.clip(d1 @ d2, -1.0, 1.0))
        if theta > np.pi - 1e-3:
            out.append(p)
            continue
        room = 0.45 * min(np.linalg.norm(a - p), np.linalg.norm(b - p))
        t = min(radius / np.tan(0.5 * theta), room)
        r = t * np.tan(0.5 * theta)
        bis = d1 + d2
        centre = p + bis / np.linalg.norm(bis) * r / np.sin(0.5 * theta)
        s0, s1 = p + d1 * t - centre, p + d2 * t - centre
        for f in np.linspace(0.0, 1.0, per_corner):
            v = (1.0 - f) * s0 + f * s1
            out.append(centre + r * v / np.linalg.norm(v))
    out.append(pts[-1])
    return np.array(out)


def tube(
    path: ArrayLike, radius: float, normal: ArrayLike, closed: bool = False, sections: int = 8
) -> trimesh.Trimesh:
    """Round tube along a planar 3D path whose plane has the given ``normal``.

    Open tubes are capped; closed ones (``closed=True``) join the last point to the first.
    """
    pts = np.asarray(path, dtype=np.float64)
    nrm = _as_point(normal)
    nrm = nrm / np.linalg.norm(nrm)
    ang = 2.0 * np.pi * np.arange(sections) / sections
    rings = []
    n = len(pts)
    for i in range(n):
        nxt, prv = ((i + 1) % n, i - 1) if closed else (min(i + 1, n - 1), max(i - 1, 0))
        t = pts[nxt] - pts[prv]
        t = t / np.linalg.norm(t)
        u = _cross(nrm, t)
        rings.append(pts[i] + radius * (np.outer(np.cos(ang), u) + np.outer(np.sin(ang), nrm)))
    return loft(rings, closed_loop=closed)


def transformed(parts: Sequence[trimesh.Trimesh], matrix: FloatArray) -> list[trimesh.Trimesh]:
    """Copies of ``parts`` with a rigid transform applied."""
    rot, shift = matrix[:3, :3], matrix[:3, 3]
    return [
        trimesh.Trimesh(vertices=p.vertices @ rot.T + shift, faces=p.faces, process=False)
        for p in parts
    ]


def recline_transform(pivot: ArrayLike, degrees: float) -> FloatArray:
    """Translate the local origin to ``pivot`` and tilt local +Y towards +Z by ``degrees``."""
    rot = trimesh.transformations.rotation_matrix(np.deg2rad(degrees), _X)
    rot[:3, 3] = _as_point(pivot)
    return rot
