"""How often the proposed ups find a reconstruction's up as the cloud thins, beside the real scans.

Without ``up`` the engine searches under the orientation networks' first proposed ups only, so
a scan whose true up is not among them lies down. The real ScanNet chairs are the vertices of a
decimated mesh (378 to 1,289 points each). This asks whether thinning alone explains their
misses: on fused views of the validation chairs turned at random (the cases of ``catalign
evaluate --views fused --pose-mode turned --seed S``), the share whose first proposed up is
within ``--within`` degrees of the truth (by default the evaluation's ``up@1`` tolerance)
and whose first three proposals hold one; for the fusion as made, decimated to a share of
its triangles (``--decimate``, as ScanNet's meshes are) and thinned at random to a number of
points (``--points``). Then the real scans' proposals
(+Z is up). Writes the tables to ``--out`` (default ``bench/results/up_proposals.md``).

    .venv/bin/python bench/up_proposals.py [--seed 0] [--decimate 0.05 0.0167] [--points 600 400]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _report import load_average, publish

from catalign.data.reconstruction import Reconstruction
from catalign.data.shapes import SharedChairs, default_chairs_root
from catalign.evaluation.metrics import UP_TOLERANCE_DEG
from catalign.evaluation.protocol import TestCase, build_cases, metric_shapes
from catalign.features.orientation import OrientationProposer, find_orientation
from catalign.frames import MODEL_UP
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.threads import limit_threads

PROPOSALS = 3  # the engine's up_proposals


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(
        np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
    )


def hits(
    proposer: OrientationProposer, clouds: list[np.ndarray], ups: list[np.ndarray], within: float
) -> tuple[int, int]:
    """How many clouds have their up first, and among the first three proposals."""
    first = among = 0
    for cloud, up in zip(clouds, ups, strict=True):
        errors = [angle_deg(np.asarray(p.value), up) for p in proposer.ups(cloud, PROPOSALS)]
        first += errors[0] <= within
        among += min(errors) <= within
    return first, among


def true_ups(cases: list[TestCase]) -> list[np.ndarray]:
    return [case.pose[:3, :3] @ np.asarray(MODEL_UP, dtype=float) for case in cases]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=2, help="per validation chair")
    parser.add_argument("--decimate", type=float, nargs="*", default=[0.05, 1 / 60])
    parser.add_argument("--points", type=int, nargs="*", default=[600, 400])
    parser.add_argument("--within", type=float, default=UP_TOLERANCE_DEG, help="degrees")
    parser.add_argument("--model-dir", type=Path, default=DEFAULT_MODEL_DIR)
    parser.add_argument("--scans", type=Path, default=default_chairs_root().parent / "real_scans")
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results/up_proposals.md"
    )
    args = parser.parse_args()
    limit_threads(1, total=1)
    proposer = find_orientation(args.model_dir)
    if proposer is None:
        raise SystemExit(f"{args.model_dir} holds no orientation networks")
    chairs = SharedChairs()
    shapes = metric_shapes(chairs, chairs.ids("val"))

    rows = []  # (cloud, median points, views, first hits, hits among the first three)
    full: list[TestCase] = []
    for share in [None, *args.decimate]:
        config = Reconstruction(decimate=share)
        cases = build_cases(
            shapes, args.views, args.seed, "turned", source="fused", reconstruction=config
        )
        full = full or cases
        first, among = hits(proposer, [c.points for c in cases], true_ups(cases), args.within)
        label = "as fused" if share is None else f"decimated to {share:.3g} of its triangles"
        median = float(np.median([len(c.points) for c in cases]))
        rows.append((label, median, len(cases), first, among))
    for count in args.points:
        rng = np.random.default_rng(args.seed)
        picks = [rng.choice(len(c.points), min(count, len(c.points)), replace=False) for c in full]
        thinned = [c.points[pick] for c, pick in zip(full, picks, strict=True)]
        first, among = hits(proposer, thinned, true_ups(full), args.within)
        rows.append(("as fused, thinned at random", count, len(full), first, among))

    lines = [
        f"# Proposed ups of reconstructions (seed {args.seed}, load {load_average():.1f})",
        "",
        f"Fused views of the {len(shapes)} validation chairs, {args.views} each, turned at random; "
        f"a hit is a proposed up within {args.within:g} degrees of the truth.",
        "",
        "| cloud | median points | first proposal | among the first 3 |",
        "|---|---:|---:|---:|",
    ]
    for label, points, views, first, among in rows:
        lines.append(f"| {label} | {points:.0f} | {first} of {views} | {among} of {views} |")
    lines += [
        "",
        "| real scan | points | first proposal, degrees off +Z | best of the first 3 |",
        "|---|---:|---:|---:|",
    ]
    up = np.array([0.0, 0.0, 1.0])
    for path in sorted(args.scans.glob("*.npy")):
        cloud = np.load(path).astype(np.float64)
        errors = [angle_deg(np.asarray(p.value), up) for p in proposer.ups(cloud, PROPOSALS)]
        lines.append(f"| {path.stem} | {len(cloud)} | {errors[0]:.0f} | {min(errors):.0f} |")
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
