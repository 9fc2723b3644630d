"""Where answers without ``up`` fail: the up estimate, or the view itself?

The evaluation's ``so3`` views (validation chairs in any rotation, ``catalign evaluate
--pose-mode so3``) are registered twice by the shipped engine: without ``up``, as
``catalign evaluate`` does, and with each view's *true* up given (what a perfect up estimate
would give). The rates are split by the camera's elevation over the chair's seat plane in the
chair's own frame: a camera above the seat sees what the upright views show (5 to 50 degrees),
one below it sees the seat's underside and the legs from beneath. Prints a markdown table and
writes it to ``bench/results/so3-views.md``.

    .venv/bin/python bench/so3_views.py [--seeds 0 1] [--settings same cross]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _report import load_average, publish
from tqdm import tqdm

from catalign.data.shapes import SharedChairs
from catalign.errors import InvalidInputError
from catalign.evaluation.protocol import TestCase, build_cases, frames_of, metric_shapes
from catalign.features.extractor import LearnedExtractor
from catalign.frames import MODEL_UP
from catalign.registration.base import LibraryShape
from catalign.registration.indexed import IndexedRegistrar
from catalign.threads import limit_threads
from catalign.training.calibration import right_pose

RESULTS = Path(__file__).parent / "results" / "so3-views.md"
# Camera elevation bands over the chair's seat plane (degrees, chair frame).
BANDS = (
    (-90.0, -30.0, "below, under -30"),
    (-30.0, 0.0, "below, -30 to 0"),
    (0.0, 50.0, "above, 0 to 50"),
    (50.0, 90.0, "above, over 50"),
)


def band_of(case: TestCase) -> str:
    return next(name for low, high, name in BANDS if low <= case.elevation_deg <= high)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--settings", nargs="+", default=["same", "cross"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)

    extractor = LearnedExtractor()
    chairs = SharedChairs(None)
    observed = metric_shapes(chairs, chairs.ids("val"))
    libraries = {"same": observed, "cross": metric_shapes(chairs, chairs.ids("train"))}
    # right[(setting, band, up given)]: one flag per view
    right: dict[tuple[str, str, bool], list[bool]] = {}
    for setting in args.settings:
        frames = frames_of(observed | libraries[setting])
        registrar = IndexedRegistrar(extractor, name="learned")
        registrar.prepare([LibraryShape(i, s.points) for i, s in libraries[setting].items()])
        assert registrar.engine is not None
        for seed in args.seeds:
            cases = build_cases(observed, 2, seed, "so3")
            for case in tqdm(cases, desc=f"{setting} seed {seed}"):
                for given in (False, True):
                    up = case.pose[:3, :3] @ MODEL_UP if given else None
                    try:
                        result = registrar.engine.register(case.points, up=up, seed=seed)
                        hit = right_pose(result.pose, result.model_id, case, frames)
                    except InvalidInputError:  # too little of the chair in sight: a failure
                        hit = False
                    for band in (band_of(case), "all"):
                        right.setdefault((setting, band, given), []).append(hit)

    lines = [
        "# Views in any rotation: without up and with the true up",
        "",
        f"The evaluation's so3 views, seeds {' '.join(map(str, args.seeds))}; load average "
        f"{load_average():.2f}. Right: within 10 degrees and 5 cm (category-level), the "
        "evaluation's criterion. Bands: the camera's elevation over the chair's seat plane.",
        "",
        "| setting | camera | views | right, no up | right, true up given |",
        "|---|---|---|---|---|",
    ]
    for setting in args.settings:
        for band in [name for _, _, name in BANDS] + ["all"]:
            guessed, given = right.get((setting, band, False)), right.get((setting, band, True))
            if not guessed:
                continue
            lines.append(
                f"| {setting} | {band} | {len(guessed)} | {100 * np.mean(guessed):.1f} % | "
                f"{100 * np.mean(given):.1f} % |"
            )
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
