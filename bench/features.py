"""Benchmark of FCGF feature extraction on CPU: a synthetic 20k-point chair (seat, back and four
legs sampled on box surfaces, about 0.9 m tall), voxelised at 2.5 and 3 cm, run through
ResUNetBN2C and ResUNetSmall with ``extract_features`` (voxelisation, kernel maps, forward pass
and centroids, i.e. everything a caller pays per cloud). Prints a markdown table and writes it to
``bench/results/features.md``. Wall-clock times are only meaningful on an otherwise idle machine,
so the table also gives CPU time per run and the load average.

    .venv/bin/python bench/features.py [--runs 20] [--threads 2 1]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from _report import load_average, publish

from catalign.features.resunet import build_model, extract_features

BOXES = [
    ((-0.225, -0.225, 0.42), (0.225, 0.225, 0.47)),  # seat
    ((-0.225, 0.18, 0.47), (0.225, 0.225, 0.90)),  # back
] + [
    ((sx * 0.2 - 0.02, sy * 0.2 - 0.02, 0.0), (sx * 0.2 + 0.02, sy * 0.2 + 0.02, 0.42))
    for sx in (-1, 1)
    for sy in (-1, 1)
]  # legs


def chair_cloud(n_points: int = 20_000, seed: int = 0) -> np.ndarray:
    """Points sampled uniformly by area on the faces of the chair's boxes."""
    rng = np.random.default_rng(seed)
    faces = []
    for lo, hi in BOXES:
        lo_a, size = np.asarray(lo), np.asarray(hi) - np.asarray(lo)
        for axis in range(3):
            u, v = (a for a in range(3) if a != axis)
            for side in (0.0, 1.0):
                faces.append((lo_a, size, axis, u, v, side, size[u] * size[v]))
    areas = np.array([f[-1] for f in faces])
    counts = rng.multinomial(n_points, areas / areas.sum())
    parts = []
    for (lo_a, size, axis, u, v, side, _), count in zip(faces, counts, strict=True):
        pts = np.empty((count, 3))
        pts[:, u] = lo_a[u] + rng.random(count) * size[u]
        pts[:, v] = lo_a[v] + rng.random(count) * size[v]
        pts[:, axis] = lo_a[axis] + side * size[axis]
        parts.append(pts)
    return np.concatenate(parts).astype(np.float32)


def time_extraction(
    model: torch.nn.Module, points: np.ndarray, voxel_size: float, warmup: int, runs: int
) -> dict[str, float]:
    for _ in range(warmup):
        extract_features(model, points, voxel_size)
    wall, cpu = [], []
    for _ in range(runs):
        w0, c0 = time.perf_counter(), time.process_time()
        _, feats = extract_features(model, points, voxel_size)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return {
        "voxels": int(feats.shape[0]),
        "min_ms": float(np.min(wall) * 1e3),
        "median_ms": float(np.median(wall) * 1e3),
        "p95_ms": float(np.percentile(wall, 95) * 1e3),
        "cpu_ms": float(np.median(cpu) * 1e3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[2, 1])
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results/features.md")
    args = parser.parse_args()

    torch.manual_seed(0)
    points = chair_cloud(args.points)
    load_before = load_average()
    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for name in ("ResUNetBN2C", "ResUNetSmall"):
            model = build_model(name).eval()
            n_params = sum(p.numel() for p in model.parameters())
            for voxel_size in (0.025, 0.03):
                stats = time_extraction(model, points, voxel_size, args.warmup, args.runs)
                rows.append(
                    f"| {name} | {voxel_size * 100:.1f} cm | {threads} | {stats['voxels']}"
                    f" | {n_params / 1e6:.2f} M | {stats['median_ms']:.1f} | {stats['p95_ms']:.1f}"
                    f" | {stats['min_ms']:.1f} | {stats['cpu_ms']:.1f} |"
                )
    load_after = load_average()

    lines = [
        "# FCGF feature extraction on CPU",
        "",
        f"{args.points} points on a synthetic 0.9 m chair; `extract_features` end to end "
        f"(voxelise, kernel maps, forward, centroids); {args.warmup} warm-up + {args.runs} timed "
        f"runs; torch {torch.__version__}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs; 1-min load average {load_before:.2f} before, "
        f"{load_after:.2f} after (wall times inflate when other processes compete for cores; "
        "min ms approximates an idle machine; CPU ms is the median process CPU time, summed over "
        "threads, spin-waiting OpenMP threads included).",
        "",
        "| model | voxel | threads | voxels | params | median ms | p95 ms | min ms | CPU ms |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    table = "\n".join(lines) + "\n"
    publish(table, args.out)


if __name__ == "__main__":
    main()
