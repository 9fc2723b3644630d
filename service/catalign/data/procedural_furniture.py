"""Procedural shelves and cabinets: furniture of categories the shipped weights never saw.

The chairs' generator (:mod:`catalign.data.procedural`) covers benches and stools; this one adds
bookcases (two side panels, a top, a bottom and 3 to 5 boards, with or without a back panel,
on a plinth or not) and cabinets (a closed carcass whose front is tiled with doors and drawer
fronts: thin slabs with small gaps between them and a pull or knob each, on a plinth or legs,
from a nightstand to a wardrobe). A seed deterministically samples the parameters
(:func:`sample_shelf_params`, :func:`sample_cabinet_params`), kept apart from building
(:func:`build_shelf_parts`, :func:`build_cabinet_parts`) so they can be inspected. Every part is
a closed solid of :mod:`catalign.data.procedural_primitives`; meshes use the chairs' frame:
metres, +Y up, the back on +Z (the front, open side or doors, faces -Z, as a chair's seat
does), and the bounding-box centre at the origin.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import trimesh

from catalign.data.procedural import Sampler, assemble
from catalign.data.procedural_legs import member
from catalign.data.procedural_primitives import _Z, bar, box, frustum, rod

FURNITURE_KINDS: tuple[str, ...] = ("shelf", "cabinet")
CABINET_STYLES: tuple[str, ...] = ("nightstand", "chest", "cupboard", "sideboard", "wardrobe")
# Width, height and depth ranges (metres) of each cabinet style.
_CABINET_SIZES = {
    "nightstand": ((0.38, 0.6), (0.45, 0.7), (0.32, 0.45)),
    "chest": ((0.6, 1.0), (0.7, 1.3), (0.4, 0.55)),
    "cupboard": ((0.5, 1.0), (0.8, 0.95), (0.45, 0.62)),
    "sideboard": ((1.1, 1.8), (0.7, 0.95), (0.38, 0.52)),
    "wardrobe": ((0.8, 1.4), (1.7, 2.0), (0.5, 0.62)),
}
# A column of a cabinet's front: all drawers, one door, or a drawer above a door.
COLUMN_LAYOUTS: tuple[str, ...] = ("drawers", "door", "drawer_door")


@dataclass(frozen=True)
class ShelfParams:
    """A bookcase; ``boards`` counts the boards between the bottom and the top."""

    seed: int
    width: float  # along X
    depth: float  # along Z
    height: float
    panel: float  # thickness of sides, top, bottom and boards
    boards: int
    back: float  # back panel thickness, 0 for an open back
    plinth: float  # height of the bottom board above the floor, 0 for none
    overhang: float  # of the top over the sides (front and sides), 0 for a top between them
    setback: float  # of the boards behind the front edge
    divider: bool  # a vertical panel in the middle, between bottom and top


@dataclass(frozen=True)
class CabinetParams:
    """A cabinet: a carcass on a base, tiled at the front by ``columns`` of fronts."""

    seed: int
    style: str  # one of CABINET_STYLES
    width: float
    depth: float  # carcass and fronts together
    height: float
    base: str  # plinth | legs | none
    base_height: float
    leg_width: float
    leg_round: bool
    top: float  # top slab thickness
    overhang: float  # of the top over the front and sides
    front: float  # thickness of the door and drawer fronts
    gap: float  # between neighbouring fronts
    columns: tuple[str, ...]  # one of COLUMN_LAYOUTS per column, left to right
    drawers: int  # drawers in a column of drawers
    handle: str  # bar | knob | none


def _sample(kind: str, seed: int) -> Sampler:
    """The random stream of the ``kind`` of ``seed``: a shelf and a cabinet of one seed differ."""
    return Sampler(np.random.default_rng([FURNITURE_KINDS.index(kind), seed]))


def sample_shelf_params(seed: int) -> ShelfParams:
    """Every parameter of the bookcase of ``seed`` (deterministic)."""
    s = _sample("shelf", seed)
    height = s.u(0.9, 2.0)
    plinth = s.u(0.04, 0.1) if s.p(0.5) else 0.0
    panel = s.u(0.016, 0.028)
    inner = height - plinth - 2 * panel
    # 3 to 5 boards, at least 0.18 m apart (a 0.9 m case holds 3)
    boards = min(s.i(3, 5), int(inner / 0.18) - 1)
    width = s.u(0.4, 1.2)
    return ShelfParams(
        seed=seed,
        width=width,
        depth=s.u(0.22, 0.42),
        height=height,
        panel=panel,
        boards=boards,
        back=s.u(0.005, 0.012) if s.p(0.6) else 0.0,
        plinth=plinth,
        overhang=s.u(0.005, 0.025) if s.p(0.4) else 0.0,
        setback=s.u(0.0, 0.02),
        divider=width > 0.85 and s.p(0.5),
    )


def build_shelf_parts(p: ShelfParams) -> list[trimesh.Trimesh]:
    """Closed parts of the bookcase in the floor frame (y=0 the floor, centred on x=z=0)."""
    w, d, t = 0.5 * p.width, 0.5 * p.depth, p.panel
    side_top = p.height if p.overhang == 0 else p.height - t
    out = [box((-w, 0.0, -d), (-w + t, side_top, d)), box((w - t, 0.0, -d), (w, side_top, d))]
    if p.overhang:
        o = p.overhang
        out.append(box((-w - o, side_top, -d - o), (w + o, p.height, d)))
    else:
        out.append(box((-w + t, p.height - t, -d), (w - t, p.height, d)))
    back = d - p.back
    front = -d + p.setback
    out.append(box((-w + t, p.plinth, -d), (w - t, p.plinth + t, back)))
    if p.plinth:  # a kick board under the front edge of the bottom
        out.append(box((-w + t, 0.0, -d + 0.01), (w - t, p.plinth, -d + 0.01 + t)))
    if p.back:
        out.append(box((-w + t, p.plinth, back), (w - t, side_top - 0.002, d)))
    low, high = p.plinth + t, side_top - (t if p.overhang == 0 else 0.0)
    if p.divider:
        out.append(box((-0.5 * t, low, front), (0.5 * t, high, back)))
    pitch = (high - low) / (p.boards + 1)
    for k in range(1, p.boards + 1):
        y = low + k * pitch - 0.5 * t
        out.append(box((-w + t, y, front), (w - t, y + t, back)))
    return out


def sample_cabinet_params(seed: int) -> CabinetParams:
    """Every parameter of the cabinet of ``seed`` (deterministic)."""
    s = _sample("cabinet", seed)
    style = s.pick(CABINET_STYLES, (0.2, 0.2, 0.2, 0.2, 0.2))
    (w0, w1), (h0, h1), (d0, d1) = _CABINET_SIZES[style]
    width, height, depth = s.u(w0, w1), s.u(h0, h1), s.u(d0, d1)
    base = s.pick(("plinth", "legs", "none"), (0.45, 0.4, 0.15))
    base_height = {"plinth": s.u(0.05, 0.12), "legs": s.u(0.08, 0.25), "none": 0.0}[base]
    count = 1 if width < 0.65 else 2 if width < 1.1 else s.i(3, 4)
    if style in ("nightstand", "chest"):
        columns = ("drawers",) * count
    elif style == "cupboard":
        columns = ("drawer_door",) * count
    elif style == "sideboard":
        inner = s.pick(("drawers", "door", "drawer_door"), (0.5, 0.25, 0.25))
        columns = ("door", *(inner,) * (count - 2), "door") if count > 2 else ("door",) * count
    else:
        columns = ("door",) * count
    drawers = s.i(2, 3) if style == "nightstand" else s.i(3, 5)
    tall = style == "wardrobe"
    return CabinetParams(
        seed=seed,
        style=style,
        width=width,
        depth=depth,
        height=height,
        base=base,
        base_height=base_height,
        leg_width=s.u(0.03, 0.05),
        leg_round=s.p(0.4),
        top=s.u(0.018, 0.04),
        overhang=0.0 if tall or s.p(0.4) else s.u(0.005, 0.03),
        front=s.u(0.016, 0.022),
        gap=s.u(0.003, 0.006),
        columns=columns,
        drawers=drawers,
        handle=s.pick(("bar", "knob", "none"), (0.55, 0.3, 0.15)),
    )


def _handle(p: CabinetParams, x: float, y: float, vertical: bool) -> list[trimesh.Trimesh]:
    """A pull (a bar on two posts, along the front's long side) or a knob at (x, y)."""
    face = -0.5 * p.depth
    if p.handle == "knob":
        return [frustum((x, y, face + 0.002), (x, y, face - 0.028), 0.008, 0.015, sections=12)]
    if p.handle == "none":
        return []
    half = 0.09 if vertical else min(0.07, 0.25 * p.width)
    ends = [(x, y + sign * half) if vertical else (x + sign * half, y) for sign in (-1.0, 1.0)]
    stand = face - 0.03
    out = [rod((a, b, face + 0.002), (a, b, stand), 0.005, sections=8) for a, b in ends]
    (a0, b0), (a1, b1) = ends
    out.append(bar((a0, b0, stand), (a1, b1, stand), 0.012, 0.012, up=_Z))
    return out


def _fronts(p: CabinetParams, low: float, high: float) -> list[trimesh.Trimesh]:
    """Door and drawer fronts tiling the carcass front from ``low`` to ``high``, each with its
    handle: columns left to right, drawers of equal height."""
    z0, z1, g = -0.5 * p.depth, -0.5 * p.depth + p.front, p.gap
    pitch = p.width / len(p.columns)
    drawer_h = min(0.2, (high - low) / 4)
    out: list[trimesh.Trimesh] = []
    for c, layout in enumerate(p.columns):
        x0, x1 = -0.5 * p.width + c * pitch + g, -0.5 * p.width + (c + 1) * pitch - g
        if layout == "drawers":
            rows = [(low + k * (high - low) / p.drawers, False) for k in range(p.drawers + 1)]
        elif layout == "drawer_door":
            rows = [(low, True), (high - drawer_h, False), (high, False)]
        else:
            rows = [(low, True), (high, False)]
        for (y0, door), (y1, _) in pairwise(rows):
            out.append(box((x0, y0 + g, z0), (x1, y1 - g, z1)))
            if not door:
                out += _handle(p, 0.5 * (x0 + x1), 0.5 * (y0 + y1), vertical=False)
                continue
            # the handle near the door's opening edge: towards the middle of the cabinet, or
            # (a lone door) on the side the seed picks
            centre = 0.5 * (x0 + x1)
            side = -np.sign(centre) if abs(centre) > 1e-9 else (1.0 if p.seed % 2 else -1.0)
            x = centre + side * (0.5 * (x1 - x0) - 0.05)
            y = min(y0 + 0.55 * (y1 - y0), y1 - 0.15) if p.style != "wardrobe" else 1.0
            out += _handle(p, x, y, vertical=True)
    return out


def build_cabinet_parts(p: CabinetParams) -> list[trimesh.Trimesh]:
    """Closed parts of the cabinet in the floor frame (y=0 the floor, centred on x=z=0)."""
    w, d = 0.5 * p.width, 0.5 * p.depth
    low, high = p.base_height, p.height - p.top
    carcass_front = -d + p.front
    out = [box((-w, low, carcass_front), (w, high, d))]
    o = p.overhang
    out.append(box((-w - o, high, -d - o), (w + o, p.height, d)))
    if p.base == "plinth":
        inset = min(0.05, 0.1 * p.depth)
        lo, hi = (-w + inset, 0.0, carcass_front + inset), (w - inset, low + 0.005, d - 0.01)
        out.append(box(lo, hi))
    elif p.base == "legs":
        lw, edge = p.leg_width, 0.5 * p.leg_width + 0.01
        for x in (-w + edge, w - edge):
            for z in (carcass_front + edge, d - edge):
                top, foot = (x, low + 0.005, z), (x, 0.0, z)
                out.append(member(top, foot, lw, 0.75 * lw, square=not p.leg_round))
    return out + _fronts(p, low, high)


def generate_furniture(kind: str, seed: int) -> trimesh.Trimesh:
    """The ``kind`` (shelf or cabinet) of ``seed`` in the chairs' frame (+Y up, back on +Z,
    bounding-box centre at 0); an unknown kind raises ValueError."""
    if kind == "shelf":
        return assemble(build_shelf_parts(sample_shelf_params(seed)))
    if kind == "cabinet":
        return assemble(build_cabinet_parts(sample_cabinet_params(seed)))
    raise ValueError(f"unknown furniture kind {kind!r}; expected one of {FURNITURE_KINDS}")
