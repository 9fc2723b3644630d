"""Render a contact sheet of what catalign is asked to register: for a few shared chairs and
tables, one depth camera's view beside a reconstruction fused from a camera trajectory
(:mod:`catalign.data.reconstruction`), both cut out as the evaluation's views are.

Each tile draws the points from the same 3/4 view above the object, coloured by height; the
object's own points are grey-blue, what the loose cut kept of the floor, a neighbour or a wall
is orange.

Usage: python scripts/render_views_sheet.py [--out docs/fused_views.png] [--count 4] [--seed 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from catalign.data.camera import random_camera
from catalign.data.reconstruction import Reconstruction, reconstruct
from catalign.data.shapes import shared_shapes
from catalign.data.views import Floor, random_object_pose, render_view
from catalign.geometry.se3 import transform


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/fused_views.png"))
    parser.add_argument("--count", type=int, default=4, help="objects per category")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    rows = []
    for category in ("chair", "table"):
        shapes = shared_shapes(category)
        for shape_id in shapes.ids("val")[: args.count]:
            shape = shapes.metric(shape_id)
            rng = np.random.default_rng([args.seed, len(rows)])
            pose = random_object_pose(rng, "upright", height=shape.height / 2)
            camera = random_camera(pose[:3, 3], rng)
            single = render_view(shape, pose, camera, rng, floor=Floor())
            fused = reconstruct(shape, pose, rng, Reconstruction(floor_kept=1.0)).points
            rows.append((f"{category} {shape_id[:8]}", pose, single, fused))

    figure, axes = plt.subplots(len(rows), 2, figsize=(6.4, 3.0 * len(rows)))
    for (name, pose, single, fused), pair in zip(rows, axes, strict=True):
        for points, axis, title in ((single, pair[0], "one depth view"), (fused, pair[1], "fused")):
            _draw(axis, points, pose, f"{name}: {title} ({len(points):,} points)")
    figure.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out, dpi=70)
    print(f"wrote {args.out}")


def _draw(axis: plt.Axes, points: np.ndarray, pose: np.ndarray, title: str) -> None:
    """Points in the object's frame (+Y up), projected orthographically from front-right,
    above; the nearest drawn last."""
    local = transform(points, np.linalg.inv(pose))
    on_object = local[:, 1] > local[:, 1].min() + 0.03
    view = np.array([0.62, 0.5, 0.9])
    view /= np.linalg.norm(view)
    right = np.cross([0.0, 1.0, 0.0], view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)
    order = np.argsort(local @ view)
    x, y = local[order] @ right, local[order] @ up
    colours = np.where(on_object[order, None], [[0.35, 0.45, 0.7]], [[0.95, 0.55, 0.2]])
    axis.scatter(x, y, s=0.3, c=colours, linewidths=0)
    axis.set_title(title, fontsize=7)
    axis.set_aspect("equal")
    axis.axis("off")


if __name__ == "__main__":
    main()
