"""How faithful a reconstruction of a point-only shape is: top-1 on fused views of the shared
chairs that have a CAD mesh, reconstructed once from the mesh and once from the alpha mesh of
the shape's surface points alone (what :func:`catalign.data.reconstruction.reconstruct` does for
the many shared shapes that have no mesh). The library is every validation chair, ``up`` given.

Usage: .venv/bin/python bench/fused_proxy.py [--views 4] [--seeds 0 1]
Writes bench/results/fused_proxy.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from _report import publish

from catalign.data.shapes import Shape, SharedChairs
from catalign.data.views import WORLD_UP
from catalign.evaluation.protocol import build_cases, metric_shapes, run_cases
from catalign.registration.methods import build_registrar


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = parser.parse_args()
    chairs = SharedChairs()
    library = metric_shapes(chairs, chairs.ids("val"))
    meshed = {i: s for i, s in library.items() if s.mesh is not None}
    registrar = build_registrar("learned", None, WORLD_UP, None)
    rows = ["| surface fused | seed | views | top-1 |", "|---|---|---|---|"]
    sources = {
        "CAD mesh": meshed,
        "alpha mesh of the points": {i: Shape(i, s.points) for i, s in meshed.items()},
    }
    for name, shapes in sources.items():
        for seed in args.seeds:
            cases = build_cases(shapes, args.views, seed, source="fused")
            outcomes = run_cases(registrar, library, cases, seed, label=f"{name}, seed {seed}")
            top1 = sum(
                o.result is not None and o.result.model_id == o.case.shape_id for o in outcomes
            )
            rows.append(f"| {name} | {seed} | {len(outcomes)} | {top1} |")
    publish("\n".join(rows) + "\n", Path("bench/results/fused_proxy.md"))


if __name__ == "__main__":
    main()
