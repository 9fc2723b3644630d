"""Render a contact sheet of procedurally generated chairs (seeds 0..23) to a PNG.

Each tile is one chair seen from a 3/4 front view, ray cast with open3d's RaycastingScene and
Lambert-shaded by the hit triangle's normal, so the sheet doubles as a visual check that every
part is closed and the frame conventions hold (chairs upright, facing the viewer).

Usage: python scripts/render_contact_sheet.py [--out docs/procedural_chairs.png] [--count 24]
       [--start 0] [--kind sofa]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import open3d as o3d
import trimesh

from catalign.data.procedural import chair_kind, generate_chair

_VIEW_DIR = np.array([0.62, 0.42, -0.9])  # from the chair towards the camera (front-right)
_LIGHT_DIR = np.array([-0.35, 0.8, -0.5])  # towards the light (front-left, above)
_TINTS = {
    "chair": (0.85, 0.72, 0.55),
    "armchair": (0.78, 0.62, 0.48),
    "office": (0.55, 0.62, 0.75),
    "stool": (0.8, 0.75, 0.6),
    "bench": (0.7, 0.78, 0.6),
    "sofa": (0.8, 0.6, 0.62),
}


def render_mesh(
    mesh: trimesh.Trimesh, size: int = 320, tint: tuple[float, float, float] = (0.8, 0.8, 0.8)
) -> np.ndarray:
    """Lambert-shaded RGB image (size, size, 3) of ``mesh`` from a 3/4 front view."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    center = mesh.bounds.mean(axis=0)
    radius = float(np.linalg.norm(mesh.extents)) * 0.5
    fov = 30.0
    dist = radius / np.sin(np.deg2rad(0.5 * fov)) * 1.02
    eye = center + dist * _VIEW_DIR / np.linalg.norm(_VIEW_DIR)
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        fov_deg=fov,
        center=center.tolist(),
        eye=eye.tolist(),
        up=[0.0, 1.0, 0.0],
        width_px=size,
        height_px=size,
    )
    ans = scene.cast_rays(rays)
    hit = np.isfinite(ans["t_hit"].numpy())
    normals = ans["primitive_normals"].numpy()
    dirs = rays.numpy()[..., 3:]
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    facing = np.where((normals * dirs).sum(-1, keepdims=True) > 0, -normals, normals)
    light = _LIGHT_DIR / np.linalg.norm(_LIGHT_DIR)
    lambert = np.clip(facing @ light, 0.0, 1.0)
    shade = 0.28 + 0.72 * lambert
    img = np.ones((size, size, 3))
    img[hit] = shade[hit, None] * np.asarray(tint)[None, :]
    # open3d's pinhole rays come out with image rows bottom-up and columns mirrored
    return img[::-1, ::-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/procedural_chairs.png"))
    parser.add_argument("--count", type=int, default=24)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--cols", type=int, default=6)
    parser.add_argument("--size", type=int, default=320)
    parser.add_argument("--kind", default=None, help="only seeds of this kind (from --start on)")
    args = parser.parse_args()

    seeds: list[int] = []
    seed = args.start
    while len(seeds) < args.count:
        if args.kind is None or chair_kind(seed) == args.kind:
            seeds.append(seed)
        seed += 1

    rows = int(np.ceil(args.count / args.cols))
    fig, axes = plt.subplots(rows, args.cols, figsize=(2.4 * args.cols, 2.55 * rows))
    for ax in np.atleast_1d(axes).ravel():
        ax.axis("off")
    for seed, ax in zip(seeds, np.atleast_1d(axes).ravel(), strict=False):
        kind = chair_kind(seed)
        mesh = generate_chair(seed)
        ax.imshow(render_mesh(mesh, args.size, _TINTS.get(kind, (0.8, 0.8, 0.8))))
        h = mesh.extents[1]
        ax.set_title(f"seed {seed}: {kind}  ({h:.2f} m)", fontsize=9)
    fig.suptitle("catalign procedural chairs (3/4 front view, +Y up, facing -Z)", fontsize=11)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
