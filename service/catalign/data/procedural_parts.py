"""Part builders for the procedural chair generator: backrests, arms, office bases and sofa
bodies, and the assembly of each chair family, from the closed solids of
:mod:`catalign.data.procedural_primitives` and the seats and legs of
:mod:`catalign.data.procedural_legs`, in the floor frame (y=0 is the floor).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import trimesh

from catalign.data.procedural_legs import (
    LEG_STYLES,
    SQUARE_STYLES,
    Leg,
    leg_layout,
    leg_parts,
    member,
    seat_parts,
    seat_slab_bottom,
)
from catalign.data.procedural_primitives import (
    _X,
    _Y,
    _Z,
    bar,
    box,
    curved_panel,
    frustum,
    horizontal_slab,
    recline_transform,
    rod,
    rounded_polyline,
    rounded_rect,
    superellipse,
    transformed,
    tube,
    vertical_slab,
    wheel,
)

if TYPE_CHECKING:
    from catalign.data.procedural_params import ArmParams, ChairParams, SeatParams


# --------------------------------------------------------------------------------------------
# Part assembly: one builder per chair family, all in the floor frame (y=0 is the floor, the
# seat is centred on x=z=0); procedural.build_chair concatenates and centres the result.
# --------------------------------------------------------------------------------------------


def _back_frame(params: ChairParams, layout: list[Leg]) -> tuple[list[float], float, float, bool]:
    """Upright x positions, pivot (y, z), and whether uprights are square, for a backrest."""
    seat, legs, back = params.seat, params.legs, params.back
    assert legs is not None and back is not None
    pivot_y = seat_slab_bottom(seat)
    if back.posts and legs.style in LEG_STYLES:
        rear = [t for t, _ in layout if t[2] > 0]
        xs = sorted(float(t[0]) for t in rear)
        if len(xs) > 2:
            xs = [xs[0], xs[-1]]
        return xs, pivot_y, float(rear[0][2]), legs.style in SQUARE_STYLES
    w = _post_width(params)
    if seat.shape == "round":
        x = 0.34 * seat.width
        z = 0.34 * seat.depth - 0.5 * w
    else:
        clear = max(0.012, 0.3 * seat.corner) + 0.5 * w
        x, z = 0.5 * seat.width - clear, 0.5 * seat.depth - clear
    xs = [-x, 0.0, x] if seat.width > 1.1 else [-x, x]
    return xs, pivot_y, z, legs.style in SQUARE_STYLES


def _post_width(params: ChairParams) -> float:
    legs, back = params.legs, params.back
    assert legs is not None and back is not None
    if back.posts and legs.style in LEG_STYLES:
        return legs.thickness
    return float(np.clip(1.3 * back.thickness, 0.02, 0.04))


def _backrest(params: ChairParams, layout: list[Leg]) -> list[trimesh.Trimesh]:
    seat, back = params.seat, params.back
    assert back is not None
    xs, pivot_y, pivot_z, square = _back_frame(params, layout)
    pw = _post_width(params)
    seat_top = seat.height - pivot_y
    top = seat_top + back.height
    bottom = seat_top + back.gap
    span = xs[-1] - xs[0]
    bt = back.thickness
    rail = 0.04 + 0.6 * bt
    post_top_z = [0.0] * len(xs)
    out: list[trimesh.Trimesh] = []
    if back.style == "solid":
        outline = rounded_rect(span, top - bottom, back.corner)
        out.append(vertical_slab(outline, -0.5 * bt, 0.5 * bt, center=(0.0, 0.5 * (top + bottom))))
    elif back.style == "upholstered":
        outline = superellipse(span + pw + 0.03, top - bottom + 0.02, back.corner)
        out.append(vertical_slab(outline, -0.5 * bt, 0.5 * bt, center=(0.0, 0.5 * (top + bottom))))
    elif back.style == "curved":
        radius = max(back.curvature, 0.9 * span)
        out.append(curved_panel(span + pw, bottom, top, bt, radius))
        post_top_z = [radius * (np.sqrt(1.0 - (x / radius) ** 2) - 1.0) for x in xs]
    elif back.style == "horizontal_slats":
        for i in range(back.slats):
            y = top - 0.5 * rail - i * (top - bottom - rail) / max(back.slats - 1, 1)
            out.append(bar((xs[0], y, 0.0), (xs[-1], y, 0.0), bt, rail))
    else:  # vertical_slats / spindles between a top rail and a bottom rail (or the seat)
        y_top = top - 0.5 * rail
        out.append(bar((xs[0], y_top, 0.0), (xs[-1], y_top, 0.0), bt, rail))
        y_low = seat_top - 0.005
        if back.gap > 0:
            y_low = bottom + 0.5 * rail
            out.append(bar((xs[0], y_low, 0.0), (xs[-1], y_low, 0.0), bt, rail))
        for i in range(back.slats):
            x = xs[0] + span * (i + 1) / (back.slats + 1)
            if back.style == "spindles":
                out.append(rod((x, y_low, 0.0), (x, y_top, 0.0), 0.006 + 0.2 * bt, sections=10))
            else:
                w = min(0.06, 0.55 * span / (back.slats + 1))
                out.append(bar((x, y_low, 0.0), (x, y_top, 0.0), w, 0.7 * bt, up=_Z))
    for x, dz in zip(xs, post_top_z, strict=True):
        out.append(member((x, 0.0, 0.0), (x, top, dz), pw, pw, square))
    return transformed(out, recline_transform((0.0, pivot_y, pivot_z), back.recline))


def _armrests(params: ChairParams, layout: list[Leg]) -> list[trimesh.Trimesh]:
    seat, arms, back, legs = params.seat, params.arms, params.back, params.legs
    assert arms is not None and back is not None and legs is not None
    xs, pivot_y, pivot_z, square = _back_frame(params, layout)
    y = seat.height + arms.height - 0.5 * arms.thickness
    z_back = pivot_z + (y - pivot_y) * np.tan(np.deg2rad(back.recline))
    slab_bottom = seat_slab_bottom(seat)
    z_front = -0.5 * seat.depth + arms.setback
    half_w = 0.5 * seat.width
    x_front = half_w + 0.3 * arms.width
    if arms.style == "spindles":
        x_front = half_w
    front_legs = [t for t, _ in layout if t[2] < 0]
    use_leg = arms.style == "leg" and legs.style in LEG_STYLES
    style = "post" if arms.style == "leg" and not use_leg else arms.style
    if use_leg:
        x_front = max(abs(float(t[0])) for t in front_legs)
        z_front = float(front_legs[0][2]) - 0.5 * legs.thickness - max(arms.setback, 0.0)
    out: list[trimesh.Trimesh] = []
    for s in (-1.0, 1.0):
        x_back = s * x_front if style == "panel" else s * max(s * x for x in xs)
        front = np.array([s * x_front, y, z_front])
        rear = np.array([x_back, y, z_back])
        out.append(bar(front, rear, arms.width, arms.thickness))
        low = slab_bottom
        below = y - 0.5 * arms.thickness + 0.005
        if use_leg:
            leg = max(front_legs, key=lambda t, s=s: s * t[0])
            top = (leg[0], below, leg[2])
            out.append(member(leg, top, legs.thickness, legs.thickness, square))
        elif style == "post":
            r = float(np.clip(0.5 * arms.width, 0.012, 0.025))
            z = max(z_front + r + 0.02, -0.5 * seat.depth + seat.corner + r)
            p0, p1 = (s * x_front, low, z), (s * x_front, below, z)
            out.append(member(p0, p1, 2 * r, 2 * r, square))
        elif style == "panel":
            x0, x1 = s * (half_w - 0.005), s * (half_w + 0.025)
            lo = (min(x0, x1), low - 0.02, z_front + 0.01)
            out.append(box(lo, (max(x0, x1), below, z_back)))
        else:  # spindles
            for f in (0.2, 0.5, 0.8):
                p = front + f * (rear - front)
                out.append(rod((p[0], low, p[2]), (p[0], below, p[2]), 0.009, sections=8))
    return out


def _legged(params: ChairParams) -> list[trimesh.Trimesh]:
    """Chairs, armchairs, stools and benches: a seat on legs, optional back and arms."""
    seat, legs = params.seat, params.legs
    assert legs is not None
    layout = leg_layout(seat, legs)
    battens: list[float] = []
    if seat.slats:
        battens = [float(t[0]) for t, _ in layout if t[2] < 0]
        if legs.style == "panel":
            x = 0.5 * seat.width - legs.inset
            battens = [-x, x]
    out = seat_parts(seat, battens) + leg_parts(seat, legs, layout)
    if params.back is not None:
        out += _backrest(params, layout)
    if params.arms is not None:
        out += _armrests(params, layout)
    return out


def _office(params: ChairParams) -> list[trimesh.Trimesh]:
    """Office chair: star base on casters, gas column, mechanism, seat, back on a post."""
    seat, back, office, arms = params.seat, params.back, params.office, params.arms
    assert back is not None and office is not None
    cr = office.caster_radius
    spoke_y = 2 * cr + 0.02
    hub_top = spoke_y + 0.07
    out: list[trimesh.Trimesh] = [
        frustum((0, spoke_y - 0.01, 0), (0, hub_top, 0), 0.05, 0.04, sections=16)
    ]
    for k in range(office.spokes):
        a = 2.0 * np.pi * k / office.spokes
        d = np.array([np.sin(a), 0.0, -np.cos(a)])
        end = d * office.base_radius + np.array([0.0, spoke_y, 0.0])
        out.append(bar((0.0, spoke_y + 0.03, 0.0), end + 0.012 * _Y, 0.045, 0.035))
        out.append(rod(end + 0.01 * _Y, end - (spoke_y - cr) * _Y, 0.009, sections=8))
        axis = np.array([np.cos(a), 0.0, np.sin(a)])
        hub = end * np.array([1.0, 0.0, 1.0]) + np.array([0.0, cr, 0.0]) - 0.25 * cr * d
        for side in (-1.0, 1.0):
            out.append(wheel(hub + side * 0.011 * axis, cr, 0.018, axis))
    slab_bottom = seat_slab_bottom(seat)
    mech_bottom = slab_bottom - office.mech_height
    out.append(rod((0, hub_top - 0.01, 0), (0, mech_bottom + 0.01, 0), office.column_radius, 16))
    if office.column_cover:
        y1 = hub_top + 0.45 * (mech_bottom - hub_top)
        out.append(rod((0, hub_top - 0.01, 0), (0, y1, 0), office.column_radius + 0.012, 16))
    out.append(box((-0.1, mech_bottom, -0.11), (0.1, slab_bottom + 0.005, 0.09)))
    out += seat_parts(seat)
    # backrest on an L-shaped post behind the seat
    bt = back.thickness
    pivot_y = mech_bottom + 0.5 * office.mech_height
    pivot_z = 0.5 * seat.depth + 0.03 + bt
    out.append(bar((0.0, pivot_y, 0.0), (0.0, pivot_y, pivot_z + 0.02), 0.05, 0.025))
    y0 = seat.height - pivot_y + back.gap
    y1 = seat.height - pivot_y + back.height
    zc = -(0.01 + 0.5 * bt)
    width = office.back_width * seat.width
    local: list[trimesh.Trimesh] = []
    if back.style == "curved":
        panel = curved_panel(width, y0, y1, bt, back.curvature)
        panel.apply_translation((0.0, 0.0, zc))
        local.append(panel)
    elif back.style == "mesh":  # tubular frame around a thin membrane
        outline = superellipse(width, y1 - y0, back.corner, 40)
        r = 0.014
        frame = np.column_stack([outline[:, 0], outline[:, 1] + 0.5 * (y0 + y1), np.full(40, zc)])
        local.append(tube(frame, r, _Z, closed=True))
        inner = superellipse(width - r, y1 - y0 - r, back.corner, 40)
        local.append(vertical_slab(inner, zc - 0.004, zc + 0.004, (0.0, 0.5 * (y0 + y1))))
    else:
        outline = superellipse(width, y1 - y0, back.corner)
        local.append(vertical_slab(outline, zc - 0.5 * bt, zc + 0.5 * bt, (0.0, 0.5 * (y0 + y1))))
    post_top = y0 + 0.45 * (y1 - y0)
    if office.headrest:
        post_top = y1 + 0.12
        outline = superellipse(0.6 * width, 0.12, 4.0)
        local.append(vertical_slab(outline, zc - 0.03, zc + 0.03, (0.0, y1 + 0.1)))
    local.append(bar((0.0, -0.0125, 0.0), (0.0, post_top, 0.0), 0.05, 0.02, up=_Z))
    out += transformed(local, recline_transform((0.0, pivot_y, pivot_z), back.recline))
    if arms is not None:
        out += _office_arms(seat, arms)
    return out


def _office_arms(seat: SeatParams, arms: ArmParams) -> list[trimesh.Trimesh]:
    """T-shaped arms (post and pad) or closed tubular loops beside the seat."""
    slab_bottom = seat_slab_bottom(seat)
    top = seat.height + arms.height
    out = []
    for s in (-1.0, 1.0):
        x = s * (0.5 * seat.width + 0.025)
        y = slab_bottom - 0.012
        out.append(bar((s * (0.5 * seat.width - 0.1), y, 0.0), (x, y, 0.0), 0.04, 0.02))
        if arms.style == "loop":
            r = 0.5 * arms.thickness
            z0, z1 = -0.5 * seat.depth + arms.setback + 0.05, 0.3 * seat.depth
            corners = [(x, y, z1), (x, y, z0), (x, top - r, z0), (x, top - r, z1), (x, y, z1)]
            path = rounded_polyline(corners, 0.05)[:-1]
            out.append(tube(path, r, _X, closed=True))
            continue
        up = (x, top - arms.thickness + 0.005, -0.01)
        out.append(bar((x, slab_bottom - 0.022, 0.0), up, 0.025, 0.05, up=_Z))
        pad = superellipse(arms.width + 0.02, 0.24, 4.0)
        out.append(horizontal_slab(pad, top - arms.thickness, top, center=(x, -0.02)))
    return out


def _sofa(params: ChairParams) -> list[trimesh.Trimesh]:
    """Sofa-like chair: boxy base, thick arms and back, seat and back cushions."""
    seat, back, arms, sofa = params.seat, params.back, params.arms, params.sofa
    assert back is not None and arms is not None and sofa is not None
    w, d, fh = seat.width, seat.depth, sofa.feet
    aw, bt = arms.width, back.thickness
    total_w = w + 2 * aw
    base_top = sofa.base_top
    out = [box((-0.5 * w - 0.01, fh, -0.5 * d), (0.5 * w + 0.01, base_top, 0.5 * d))]
    arm_top = seat.height + arms.height
    z0, z1 = -0.5 * d + arms.setback, 0.5 * d
    for s in (-1.0, 1.0):
        xa, xb = s * 0.5 * w, s * 0.5 * total_w
        lo, hi = min(xa, xb), max(xa, xb)
        if arms.style == "rolled":
            r = 0.6 * aw
            out.append(box((lo, fh, z0), (hi, arm_top - r, z1)))
            xm = 0.5 * (xa + xb)
            out.append(rod((xm, arm_top - r, z0 - 0.01), (xm, arm_top - r, z1), r, sections=16))
        else:
            out.append(box((lo, fh, z0), (hi, arm_top, z1)))
    # back: a lower block to the base, the upper block reclined about its foot
    out.append(box((-0.5 * total_w, fh, 0.5 * d - bt), (0.5 * total_w, base_top + 0.02, 0.5 * d)))
    pivot = (0.0, base_top, 0.5 * d - 0.5 * bt)
    top = seat.height + back.height - base_top
    local = [box((-0.5 * total_w, 0.0, -0.5 * bt), (0.5 * total_w, top, 0.5 * bt))]
    if sofa.rolled_back:
        r = 0.6 * bt
        ends = ((-0.5 * total_w, top - 0.5 * r, 0.0), (0.5 * total_w, top - 0.5 * r, 0.0))
        local.append(rod(*ends, r, sections=16))
    n = sofa.seat_cushions
    cw = (w - (n - 1) * 0.01) / n
    tc = min(0.14, 0.5 * d - bt - 0.05)
    if sofa.back_cushions and tc > 0.06:
        y0 = seat.height - base_top
        outline = superellipse(cw, top - y0 - 0.03, seat.corner)
        for i in range(n):
            x = -0.5 * w + 0.5 * cw + i * (cw + 0.01)
            z = -0.5 * bt - 0.5 * tc + 0.01
            local.append(vertical_slab(outline, z - 0.5 * tc, z + 0.5 * tc, (x, 0.5 * (top + y0))))
    out += transformed(local, recline_transform(pivot, back.recline))
    cushion_d = d - bt + 0.02
    outline = superellipse(cw, cushion_d, seat.corner)
    for i in range(n):
        x = -0.5 * w + 0.5 * cw + i * (cw + 0.01)
        centre = (x, -0.5 * d + 0.5 * cushion_d - 0.01)
        out.append(horizontal_slab(outline, base_top - 0.01, seat.height, center=centre))
    if fh > 0:
        for sx in (-1.0, 1.0):
            for sz in (-1.0, 1.0):
                p = (sx * (0.5 * total_w - 0.05), 0.0, sz * (0.5 * d - 0.05))
                out.append(frustum(p, (p[0], fh + 0.01, p[2]), 0.02, 0.028, sections=10))
    return out


def build_parts(params: ChairParams) -> list[trimesh.Trimesh]:
    """Closed part meshes for ``params`` in the floor frame."""
    if params.kind == "office":
        return _office(params)
    if params.kind == "sofa":
        return _sofa(params)
    return _legged(params)
