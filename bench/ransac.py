"""Benchmark of correspondence RANSAC: :func:`catalign.registration.stages.ransac.ransac` (numpy,
vectorised) against Open3D's ``registration_ransac_based_on_correspondence`` as
``alignment.ransac_icp`` calls it (edge-length 0.9 and distance checkers, 100,000 iterations,
confidence 0.999), on the same synthetic correspondences: model points in a 0.5 x 0.9 x 0.5 m box,
a random pose, 3 mm noise, and outliers uniform in the observation's bounding box. Both run in
the same process, one after the other for each seed, so their ratio is meaningful even on a busy
machine; absolute times are not. Prints a markdown table and writes it to
``bench/results/ransac.md``.

    .venv/bin/python bench/ransac.py [--runs 20]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
from _report import load_average, publish

from catalign.geometry.se3 import make_pose, random_rotation, rotation_error_deg, transform
from catalign.registration import alignment
from catalign.registration.baseline.open3d_recipe import point_cloud
from catalign.registration.stages.ransac import ransac

INLIER_DISTANCE = 0.03


def correspondences(
    n: int, outlier_ratio: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pose = make_pose(random_rotation(rng), rng.uniform(-1.0, 1.0, size=3))
    src = (rng.random((n, 3)) - 0.5) * np.array([0.5, 0.9, 0.5])
    dst = transform(src, pose) + rng.normal(scale=0.003, size=(n, 3))
    outliers = rng.permutation(n)[: round(outlier_ratio * n)]
    dst[outliers] = rng.uniform(dst.min(axis=0), dst.max(axis=0), size=(len(outliers), 3))
    return src, dst, pose


def open3d_ransac(src: np.ndarray, dst: np.ndarray, seed: int) -> np.ndarray:
    pairs = np.repeat(np.arange(len(src))[:, None], 2, axis=1)
    return alignment.open3d_ransac(point_cloud(src), point_cloud(dst), pairs, INLIER_DISTANCE, seed)


def numpy_ransac(src: np.ndarray, dst: np.ndarray, seed: int) -> np.ndarray:
    return ransac(src, dst, INLIER_DISTANCE, seed=seed).transform


def time_both(
    n: int, outlier_ratio: float, runs: int, warmup: int
) -> dict[str, tuple[float, float]]:
    """Median ms and worst rotation error (degrees) of each solver, interleaved per seed."""
    src, dst, pose = correspondences(n, outlier_ratio, seed=n)
    solvers: dict[str, Callable[[np.ndarray, np.ndarray, int], np.ndarray]] = {
        "numpy": numpy_ransac,
        "open3d": open3d_ransac,
    }
    for seed in range(warmup):
        for solve in solvers.values():
            solve(src, dst, seed)
    times: dict[str, list[float]] = {name: [] for name in solvers}
    errors: dict[str, list[float]] = {name: [] for name in solvers}
    for seed in range(runs):
        for name, solve in solvers.items():
            started = time.perf_counter()
            found = solve(src, dst, seed)
            times[name].append(time.perf_counter() - started)
            errors[name].append(rotation_error_deg(found[:3, :3], pose[:3, :3]))
    return {name: (float(np.median(times[name]) * 1e3), max(errors[name])) for name in solvers}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results/ransac.md")
    args = parser.parse_args()

    load_before = load_average()
    rows = []
    for n in (500, 2000):
        for outlier_ratio in (0.5, 0.9):
            stats = time_both(n, outlier_ratio, args.runs, args.warmup)
            (ours, our_err), (theirs, their_err) = stats["numpy"], stats["open3d"]
            rows.append(
                f"| {n} | {outlier_ratio:.0%} | {ours:.1f} | {theirs:.1f} | {theirs / ours:.1f}"
                f" | {our_err:.2f} | {their_err:.2f} |"
            )
    load_after = load_average()
    threads = {k: os.environ.get(k, "unset") for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}

    lines = [
        "# Correspondence RANSAC: numpy (catalign) vs Open3D",
        "",
        f"Median wall time over {args.runs} seeds ({args.warmup} warm-up), both solvers "
        f"interleaved in one process; inlier distance {INLIER_DISTANCE * 100:g} cm, confidence "
        f"0.999, 3 mm noise. Open3D {o3d.__version__}, numpy {np.__version__}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"{', '.join(f'{k}={v}' for k, v in threads.items())}; 1-min load average "
        f"{load_before:.2f} before, {load_after:.2f} after (compare the ratio, not absolute "
        "times, on a busy machine). Worst rotation error over the seeds, in degrees; Open3D "
        "returns its best hypothesis' estimate, ours is refitted on all its inliers.",
        "",
        "| matches | outliers | numpy ms | Open3D ms | Open3D / numpy | numpy max RRE° "
        "| Open3D max RRE° |",
        "|---|---|---|---|---|---|---|",
        *rows,
    ]
    table = "\n".join(lines) + "\n"
    publish(table, args.out)


if __name__ == "__main__":
    main()
