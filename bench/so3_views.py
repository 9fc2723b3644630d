"""Where answers without ``up`` fail: the up estimate, the choice among the proposed ups, or
the view itself?

The evaluation's views without ``up`` (``catalign evaluate --pose-mode so3``: validation chairs
in any rotation; ``--pose-mode turned``: standing chairs, the whole view turned at random) are
registered by the shipped engine without ``up``, as ``catalign evaluate`` does; under each up
the engine proposed for the view, given as the caller's ``up`` (a view counts as right there
when any of them gives a right answer: what a perfect choice among the proposals would give);
and with the view's *true* up given (what a perfect up estimate would give). The rates are
split by the camera's elevation over the chair's seat plane in the chair's own frame: a camera
above the seat sees what the upright views show (5 to 50 degrees), one below it sees the seat's
underside and the legs from beneath. Prints a markdown table and writes it to
``bench/results/so3-views.md`` (``turned-views.md`` for ``--pose-mode turned``).

    .venv/bin/python bench/so3_views.py [--pose-mode so3|turned] [--seeds 0 1]
        [--settings same cross]
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
from catalign.geometry.ncc import NCCFrame
from catalign.registration.engine import Engine
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape, RegistrationResult
from catalign.threads import limit_threads
from catalign.training.calibration import right_pose

RESULTS = Path(__file__).parent / "results"
# Camera elevation bands over the chair's seat plane (degrees, chair frame).
BANDS = (
    (-90.0, -30.0, "below, under -30"),
    (-30.0, 0.0, "below, -30 to 0"),
    (0.0, 50.0, "above, 0 to 50"),
    (50.0, 90.0, "above, over 50"),
)


def band_of(case: TestCase) -> str:
    return next(name for low, high, name in BANDS if low <= case.elevation_deg <= high)


def rights(
    engine: Engine, case: TestCase, seed: int, frames: dict[str, NCCFrame]
) -> dict[str, bool]:
    """Whether ``case`` is answered right without up (``none``), under the best of the ups
    the engine proposed for it, each given as up (``proposed``), and under its true up."""

    def answer(up: np.ndarray | None) -> RegistrationResult | None:
        try:
            return engine.register(case.points, up=up, seed=seed)
        except InvalidInputError:  # too little of the chair in sight: a failure
            return None

    def hit(result: RegistrationResult | None) -> bool:
        return result is not None and right_pose(result.pose, result.model_id, case, frames)

    guessed = answer(None)
    proposed = () if guessed is None else guessed.orientations
    return {
        "none": hit(guessed),
        "proposed": any(hit(answer(o.up)) for o in proposed),
        "true": hit(answer(case.pose[:3, :3] @ MODEL_UP)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pose-mode", choices=["so3", "turned"], default="so3")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--settings", nargs="+", default=["same", "cross"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    out = args.out or RESULTS / f"{args.pose_mode}-views.md"
    limit_threads(args.threads, total=args.threads)

    extractor = LearnedExtractor()
    chairs = SharedChairs(None)
    observed = metric_shapes(chairs, chairs.ids("val"))
    libraries = {"same": observed, "cross": metric_shapes(chairs, chairs.ids("train"))}
    # right[(setting, band, how up was had)]: one flag per view
    right: dict[tuple[str, str, str], list[bool]] = {}
    for setting in args.settings:
        frames = frames_of(observed | libraries[setting])
        registrar = IndexedRegistrar(extractor, name="learned")
        registrar.prepare(
            [LibraryShape(i, s.points, s.mesh) for i, s in libraries[setting].items()]
        )
        assert registrar.engine is not None
        for seed in args.seeds:
            cases = build_cases(observed, 2, seed, args.pose_mode)
            for case in tqdm(cases, desc=f"{setting} seed {seed}"):
                hits = rights(registrar.engine, case, seed, frames)
                for band in (band_of(case), "all"):
                    for how, flag in hits.items():
                        right.setdefault((setting, band, how), []).append(flag)

    lines = [
        f"# Views without up ({args.pose_mode}): no up, the best proposed up, the true up",
        "",
        f"The evaluation's {args.pose_mode} views, seeds {' '.join(map(str, args.seeds))}; load "
        f"average {load_average():.2f}. Right: within 10 degrees and 5 cm (category-level), the "
        "evaluation's criterion. Best proposed up: right under any of the ups the engine "
        "proposed, each given as up. Bands: the camera's elevation over the chair's seat plane.",
        "",
        "| setting | camera | views | right, no up | right, best proposed up | right, true up |",
        "|---|---|---|---|---|---|",
    ]
    for setting in args.settings:
        for band in [name for _, _, name in BANDS] + ["all"]:
            flags = [right.get((setting, band, how)) for how in ("none", "proposed", "true")]
            if not flags[0]:
                continue
            rates = " | ".join(f"{100 * np.mean(f):.1f} %" for f in flags)
            lines.append(f"| {setting} | {band} | {len(flags[0])} | {rates} |")
    publish("\n".join(lines) + "\n", out)


if __name__ == "__main__":
    main()
