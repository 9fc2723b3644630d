"""Procedural chair generator: the shippable CAD library that replaces ShapeNet chairs.

ShapeNet shapes may not be redistributed, so the default CAD library is generated instead: a seed
deterministically picks a chair kind (four-legged chair, armchair, office chair, stool, bench,
sofa) and samples its part parameters, and the chair is assembled from closed primitives
(boxes, prisms, cylinders, lofted panels) so that every part is watertight and ray casting,
surface sampling and inside tests behave as on a clean CAD model. Sampling
(:func:`sample_chair_params`) is separate from building (:func:`build_chair`) so parameters can be
inspected, compared and logged. The output uses ShapeNet's canonical chair frame: +Y up, the
backrest on the +Z side (the chair faces -Z), sizes in metres, and the axis-aligned bounding-box
centre at the origin.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh

from catalign.data import procedural_parts as parts
from catalign.data.procedural_params import (
    ArmParams,
    BackParams,
    ChairParams,
    LegParams,
    OfficeParams,
    SeatParams,
    SofaParams,
)

CHAIR_KINDS: tuple[str, ...] = ("chair", "armchair", "office", "stool", "bench", "sofa")
_KIND_WEIGHTS = (0.32, 0.16, 0.16, 0.13, 0.10, 0.13)

LEG_STYLES = parts.LEG_STYLES
BACK_STYLES: tuple[str, ...] = (
    "solid",
    "curved",
    "vertical_slats",
    "spindles",
    "horizontal_slats",
    "upholstered",
)


class Sampler:
    """Thin wrapper over a numpy Generator returning plain, rounded Python values."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def u(self, lo: float, hi: float) -> float:
        return round(float(self.rng.uniform(lo, hi)), 4)

    def i(self, lo: int, hi: int) -> int:
        """Integer in [lo, hi] inclusive."""
        return int(self.rng.integers(lo, hi + 1))

    def p(self, prob: float) -> bool:
        return bool(self.rng.random() < prob)

    def pick(self, options: tuple[str, ...], weights: tuple[float, ...] | None = None) -> str:
        w = None if weights is None else np.asarray(weights, dtype=float) / sum(weights)
        return str(options[int(self.rng.choice(len(options), p=w))])


def _kind_from(s: Sampler) -> str:
    return s.pick(CHAIR_KINDS, _KIND_WEIGHTS)


def chair_kind(seed: int) -> str:
    """Kind of the chair generated for ``seed`` (the first draw of its random stream)."""
    return _kind_from(Sampler(np.random.default_rng(seed)))


def _sample_seat(s: Sampler, width: float, depth: float, height: float, arm: bool) -> SeatParams:
    shapes, weights = ("square", "rounded", "trapezoid", "round"), (0.4, 0.3, 0.2, 0.1)
    shape = s.pick(shapes[:3], weights[:3]) if arm else s.pick(shapes, weights)
    corner = {"square": s.u(0.004, 0.02), "rounded": s.u(0.04, 0.11)}.get(shape, s.u(0.01, 0.05))
    cushion = s.u(0.025, 0.06) if s.p(0.3) else 0.0
    return SeatParams(
        width=width,
        depth=depth,
        height=height,
        thickness=s.u(0.02, 0.05) if cushion else s.u(0.02, 0.07),
        shape=shape,
        corner=corner,
        flare=s.u(0.08, 0.2) if shape == "trapezoid" else 0.0,
        cushion=cushion,
        slats=0,
    )


def _sample_legs(
    s: Sampler, seat: SeatParams, count: int = 4, thick: tuple[float, float] = (0.025, 0.05)
) -> LegParams:
    style = s.pick(LEG_STYLES, (0.35, 0.25, 0.2, 0.2))
    thickness = s.u(*thick)
    corner_clear = 0.3 * seat.corner if seat.shape in ("rounded", "trapezoid") else 0.0
    stretchers = s.pick(("none", "box", "h", "x", "sides"), (0.4, 0.2, 0.2, 0.08, 0.12))
    return LegParams(
        count=count,
        style=style,
        thickness=thickness,
        taper=s.u(0.45, 0.8) if style.startswith("tapered") else 1.0,
        splay=s.u(2.0, 10.0) if s.p(0.35) else 0.0,
        inset=round(max(s.u(0.015, 0.05), corner_clear) + 0.5 * thickness, 4),
        stretchers=stretchers,
        stretcher_height=s.u(0.1, 0.25),
        apron=s.u(0.04, 0.1) if s.p(0.45) else 0.0,
    )


def _sample_back(
    s: Sampler, seat: SeatParams, height_range: tuple[float, float], posts_prob: float = 0.5
) -> BackParams:
    style = s.pick(BACK_STYLES, (0.22, 0.14, 0.18, 0.1, 0.2, 0.16))
    height = min(s.u(*height_range), 1.19 - seat.height)
    gap = s.u(0.04, 0.2) if s.p(0.5) else 0.0
    if style == "horizontal_slats":
        gap = max(gap, s.u(0.06, 0.15))
    return BackParams(
        style=style,
        height=round(height, 4),
        thickness=s.u(0.035, 0.08) if style == "upholstered" else s.u(0.015, 0.03),
        recline=s.u(0.0, 14.0),
        slats=s.i(2, 4) if style == "horizontal_slats" else s.i(3, 7),
        gap=round(min(gap, 0.4 * height), 4),
        posts=s.p(posts_prob),
        corner=s.u(3.0, 8.0) if style == "upholstered" else s.u(0.004, 0.08),
        curvature=s.u(0.35, 0.9),
    )


def _sample_arms(s: Sampler, styles: tuple[str, ...], weights: tuple[float, ...]) -> ArmParams:
    return ArmParams(
        style=s.pick(styles, weights),
        height=s.u(0.17, 0.27),
        width=s.u(0.035, 0.08),
        thickness=s.u(0.02, 0.045),
        setback=s.u(-0.03, 0.08),
    )


def _sample_chair(s: Sampler, seed: int, kind: str) -> ChairParams:
    arm = kind == "armchair"
    width = s.u(0.45, 0.62) if arm else s.u(0.38, 0.52)
    seat = _sample_seat(s, width, s.u(0.38, 0.52), s.u(0.40, 0.50), arm)
    legs = _sample_legs(s, seat)
    if s.p(0.12):  # tubular sled base: one bent runner per side
        legs = replace(
            legs,
            count=2,
            style="sled",
            thickness=s.u(0.018, 0.03),
            splay=0.0,
            stretchers="none",
            apron=0.0,
        )
    tall = s.p(0.2)
    low = not tall and s.p(0.15)
    rng_h = (0.55, 0.72) if tall else (0.2, 0.3) if low else (0.3, 0.52)
    arms = None
    if arm:
        rng_h = (max(rng_h[0], 0.32), max(rng_h[1], 0.4))
        arms = _sample_arms(s, ("leg", "post", "panel", "spindles"), (0.3, 0.35, 0.2, 0.15))
    back = _sample_back(s, seat, rng_h)
    if arms is not None and back.height < arms.height + 0.1:
        back = replace(back, height=round(arms.height + 0.12, 4))
    return ChairParams(seed, kind, seat, legs=legs, back=back, arms=arms)


def _sample_office(s: Sampler, seed: int) -> ChairParams:
    seat = SeatParams(
        width=s.u(0.45, 0.55),
        depth=s.u(0.42, 0.52),
        height=s.u(0.42, 0.52),
        thickness=s.u(0.015, 0.03),
        shape="soft",
        corner=s.u(2.5, 6.0),
        flare=0.0,
        cushion=s.u(0.04, 0.09),
        slats=0,
    )
    headrest = s.p(0.25)
    top = 1.17 - seat.height - (0.16 if headrest else 0.0)
    style = s.pick(("curved", "upholstered", "mesh"), (0.35, 0.35, 0.3))
    back = BackParams(
        style=style,
        height=round(min(s.u(0.42, 0.72), top), 4),
        thickness=s.u(0.012, 0.02) if style == "mesh" else s.u(0.03, 0.07),
        recline=s.u(2.0, 14.0),
        slats=0,
        gap=s.u(0.05, 0.15),
        posts=False,
        corner=s.u(2.2, 7.0),
        curvature=s.u(0.35, 0.8),
    )
    arms = _sample_arms(s, ("t", "loop"), (0.65, 0.35)) if s.p(0.6) else None
    office = OfficeParams(
        spokes=5 if s.p(0.85) else s.i(4, 6),
        base_radius=s.u(0.25, 0.34),
        back_width=s.u(0.72, 1.0),
        caster_radius=s.u(0.022, 0.035),
        column_radius=s.u(0.018, 0.03),
        column_cover=s.p(0.5),
        mech_height=s.u(0.035, 0.07),
        headrest=headrest,
    )
    return ChairParams(seed, "office", seat, back=back, arms=arms, office=office)


def _sample_stool(s: Sampler, seed: int) -> ChairParams:
    round_seat = s.p(0.65)
    size = s.u(0.28, 0.40)
    height = s.u(0.45, 0.56) if s.p(0.5) else s.u(0.6, 0.78)
    seat = SeatParams(
        width=size,
        depth=size,
        height=height,
        thickness=s.u(0.02, 0.045),
        shape="round" if round_seat else s.pick(("square", "rounded"), (0.5, 0.5)),
        corner=s.u(0.01, 0.06),
        flare=0.0,
        cushion=s.u(0.03, 0.06) if s.p(0.25) else 0.0,
        slats=0,
    )
    pedestal = s.p(0.2)
    count = 1 if pedestal else (s.i(3, 4) if round_seat else 4)
    legs = _sample_legs(s, seat, count, thick=(0.022, 0.04))
    footrest = height > 0.6 or s.p(0.5)
    stretchers = s.pick(("ring", "box", "h", "x"), (0.5, 0.25, 0.15, 0.1)) if footrest else "none"
    legs = replace(
        legs,
        style="pedestal" if pedestal else legs.style,
        splay=s.u(4.0, 12.0) if s.p(0.7) else 0.0,
        stretchers=stretchers,
        stretcher_height=round(height * s.u(0.3, 0.5), 4),
        apron=legs.apron if not round_seat else 0.0,
    )
    return ChairParams(seed, "stool", seat, legs=legs)


def _sample_bench(s: Sampler, seed: int) -> ChairParams:
    width = s.u(0.8, 1.4)
    seat = SeatParams(
        width=width,
        depth=s.u(0.3, 0.46),
        height=s.u(0.43, 0.48),
        thickness=s.u(0.03, 0.06),
        shape=s.pick(("square", "rounded"), (0.6, 0.4)),
        corner=s.u(0.005, 0.05),
        flare=0.0,
        cushion=0.0,
        slats=s.i(1, 3) * 2 + 1 if s.p(0.4) else 0,
    )
    panel = s.p(0.3)
    legs = _sample_legs(s, seat, 6 if width > 1.1 else 4)
    legs = replace(
        legs,
        count=2 if panel else legs.count,
        style="panel" if panel else legs.style,
        inset=round(legs.inset + (s.u(0.03, 0.12) if panel else 0.0), 4),
        stretchers=s.pick(("none", "box", "h"), (0.4, 0.3, 0.3)),
    )
    back = None
    arms = None
    if s.p(0.45):
        back = _sample_back(s, seat, (0.28, 0.5), posts_prob=0.0 if panel else 0.7)
        if back.style in ("curved", "upholstered"):
            back = replace(back, style="horizontal_slats", slats=3, gap=max(back.gap, 0.08))
        if s.p(0.35):
            arms = _sample_arms(s, ("post", "panel", "spindles"), (0.5, 0.3, 0.2))
    return ChairParams(seed, "bench", seat, legs=legs, back=back, arms=arms)


def _sample_sofa(s: Sampler, seed: int) -> ChairParams:
    arm_w = s.u(0.08, 0.22)
    n_seats = int(s.pick(("1", "2", "3"), (0.6, 0.3, 0.1)))
    per_seat = s.u(0.48, 0.62) if n_seats == 1 else s.u(0.42, 0.55)
    height = s.u(0.40, 0.47)
    cushion = s.u(0.08, 0.16)
    seat = SeatParams(
        width=round(min(n_seats * per_seat, 1.42 - 2 * arm_w), 4),
        depth=s.u(0.7, 0.95),
        height=height,
        thickness=0.0,
        shape="soft",
        corner=s.u(5.0, 10.0),
        flare=0.0,
        cushion=cushion,
        slats=0,
    )
    back = BackParams(
        style="upholstered",
        height=s.u(0.28, 0.5),
        thickness=s.u(0.12, 0.25),
        recline=s.u(0.0, 10.0),
        slats=0,
        gap=0.0,
        posts=False,
        corner=s.u(4.0, 9.0),
        curvature=0.0,
    )
    arms = ArmParams(
        style=s.pick(("box", "rolled"), (0.6, 0.4)),
        height=round(min(s.u(0.12, 0.27), back.height - 0.05), 4),
        width=arm_w,
        thickness=0.0,
        setback=s.u(-0.01, 0.06),
    )
    sofa = SofaParams(
        feet=s.u(0.03, 0.12) if s.p(0.6) else 0.0,
        seat_cushions=n_seats,
        back_cushions=s.p(0.5),
        rolled_back=s.p(0.3),
        base_top=round(height - cushion, 4),
    )
    return ChairParams(seed, "sofa", seat, back=back, arms=arms, sofa=sofa)


def sample_chair_params(seed: int) -> ChairParams:
    """Sample every parameter of the chair for ``seed`` (deterministic)."""
    s = Sampler(np.random.default_rng(seed))
    kind = _kind_from(s)
    if kind in ("chair", "armchair"):
        return _sample_chair(s, seed, kind)
    if kind == "office":
        return _sample_office(s, seed)
    if kind == "stool":
        return _sample_stool(s, seed)
    if kind == "bench":
        return _sample_bench(s, seed)
    return _sample_sofa(s, seed)


def build_chair_parts(params: ChairParams) -> list[trimesh.Trimesh]:
    """Closed part meshes of a chair standing on the floor (y=0), seat centred on x=z=0."""
    return parts.build_parts(params)


def build_chair(params: ChairParams, center: bool = True) -> trimesh.Trimesh:
    """Concatenate the parts into one mesh; ``center`` moves the bounding-box centre to 0."""
    return assemble(build_chair_parts(params), center)


def assemble(part_list: list[trimesh.Trimesh], center: bool = True) -> trimesh.Trimesh:
    """One mesh of closed parts (each stays closed: no vertex is merged); ``center`` moves the
    bounding-box centre to 0."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in part_list[:-1]])
    verts = np.vstack([p.vertices for p in part_list])
    faces = np.vstack([p.faces + o for p, o in zip(part_list, offsets, strict=True)])
    if center:
        verts = verts - 0.5 * (verts.min(axis=0) + verts.max(axis=0))
    return trimesh.Trimesh(vertices=verts, faces=faces, process=False)


def generate_chair(seed: int) -> trimesh.Trimesh:
    """Chair mesh for ``seed`` in the canonical frame (+Y up, back towards +Z, centred)."""
    return build_chair(sample_chair_params(seed))
