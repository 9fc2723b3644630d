"""The parameters of a procedural chair, sampled by :mod:`catalign.data.procedural` and built by
:mod:`catalign.data.procedural_parts`: plain frozen records, so that they can be inspected,
compared and logged apart from the meshes."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SeatParams:
    """Seat board; ``height`` is the top of the sitting surface (cushion included)."""

    width: float  # along X
    depth: float  # along Z
    height: float
    thickness: float  # board thickness, below the cushion
    shape: str  # square | rounded | trapezoid | round | soft
    corner: float  # corner radius (square/rounded/trapezoid) or superellipse exponent (soft)
    flare: float  # extra relative width at the front (trapezoid)
    cushion: float  # cushion thickness on top of the board, 0 for none
    slats: int  # 0 for a solid board, else an odd number of slats running along X


@dataclass(frozen=True)
class LegParams:
    """Legs under the seat and the rails joining them."""

    count: int  # 3, 4 or 6 legs; 1 = pedestal; 2 = panel ends or sled runners
    style: str  # one of LEG_STYLES, or "pedestal" / "panel" / "sled"
    thickness: float  # width (or diameter) at the top
    taper: float  # bottom/top width ratio
    splay: float  # outward tilt in degrees
    inset: float  # distance of the leg axis from the seat edge
    stretchers: str  # none | box | h | x | sides | ring
    stretcher_height: float  # above the floor
    apron: float  # height of the rails right under the seat, 0 for none


@dataclass(frozen=True)
class BackParams:
    """Backrest, built upright at the rear of the seat then reclined about the X axis."""

    style: str  # one of BACK_STYLES, or "mesh" (office chairs)
    height: float  # top of the back above the seat surface (before recline)
    thickness: float
    recline: float  # degrees, top towards +Z
    slats: int  # slats / spindles / rails
    gap: float  # opening between seat surface and the panel
    posts: bool  # rear legs continue upwards as the back uprights
    corner: float  # corner radius or superellipse exponent of the panel
    curvature: float  # radius of curved panels


@dataclass(frozen=True)
class ArmParams:
    """Armrests: ``height`` of the rest's top above the seat surface."""

    style: str  # leg | post | panel | spindles | t, loop (office) | box, rolled (sofa)
    height: float
    width: float
    thickness: float
    setback: float  # distance of the front end behind the seat front (negative: overhang)


@dataclass(frozen=True)
class OfficeParams:
    """Office chair base and mounting."""

    spokes: int
    base_radius: float
    back_width: float  # backrest width relative to the seat width
    caster_radius: float
    column_radius: float
    column_cover: bool
    mech_height: float
    headrest: bool


@dataclass(frozen=True)
class SofaParams:
    """Upholstered body of a sofa-like chair."""

    feet: float  # feet height, 0 when the base skirt reaches the floor
    seat_cushions: int
    back_cushions: bool
    rolled_back: bool  # a bolster along the top of the back
    base_top: float  # top of the boxy base under the seat cushions


@dataclass(frozen=True)
class ChairParams:
    """Every sampled parameter of one chair; equal parameters build identical meshes."""

    seed: int
    kind: str
    seat: SeatParams
    legs: LegParams | None = None
    back: BackParams | None = None
    arms: ArmParams | None = None
    office: OfficeParams | None = None
    sofa: SofaParams | None = None
