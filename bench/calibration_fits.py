"""Other fits of the answers' confidence, scored on the validation answers.

The shipped calibrator (``catalign calibrate``) is fitted on every answer
(winners and alternatives) of views of the 61 training chairs. This script registers the
validation views once (upright, ``up`` given, seeds 0 and 1, *same* and *cross*, as ``catalign
evaluate`` does), keeps each winner's evidence, and scores on it the calibrators fitted on:

* the shipped calibrator's samples (``--samples``: the ``samples.npz`` that the command in
  the calibrator's card writes beside it; the shipped one is not in the repository), which
  must give the figures of ``bench/results/calibration-upright.md`` again;
* views of the procedural chairs, which the features never saw (same and cross plans among
  themselves, both pose modes), alone and added to the training chairs';
* the winners of the training chairs alone.

A fit chosen on these few validation answers would fit them, so the last table scores the
training-chair fits in 5 folds of held-out chairs instead. Prints the tables and writes them
to ``bench/results/calibration-fits.md``.

    .venv/bin/python bench/calibration_fits.py [--samples runs/confidence8/samples.npz]
        [--procedural 60]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _report import publish
from tqdm import tqdm

from catalign.data.shapes import ProceduralChairs, SharedChairs
from catalign.data.views import WORLD_UP
from catalign.evaluation.protocol import build_cases, frames_of, metric_shapes
from catalign.features.extractor import LearnedExtractor
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.decision.confidence import find_calibrator
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape
from catalign.threads import limit_threads
from catalign.training.calibration import (
    CalibrationConfig,
    Samples,
    calibration_quality,
    collect,
    fit,
    right_pose,
)

RESULTS = Path(__file__).parent / "results" / "calibration-fits.md"
SHIPPED_SAMPLES = Path("runs/confidence8/samples.npz")
FOLDS = 5


def validation_answers(extractor: LearnedExtractor) -> Samples:
    """The winners of the evaluation's upright views (seeds 0 and 1), labelled."""
    chairs = SharedChairs(None)
    observed = metric_shapes(chairs, chairs.ids("val"))
    libraries = {"same": observed, "cross": metric_shapes(chairs, chairs.ids("train"))}
    answers = Samples()
    for setting, library in libraries.items():
        frames = frames_of(observed | library)
        registrar = IndexedRegistrar(extractor, name="learned")
        registrar.prepare([LibraryShape(i, s.points, s.mesh) for i, s in sorted(library.items())])
        assert registrar.engine is not None
        for seed in (0, 1):
            cases = build_cases(observed, 2, seed, "upright")
            for case in tqdm(cases, desc=f"validation {setting} seed {seed}"):
                result = registrar.engine.register(case.points, up=WORLD_UP, seed=seed)
                right = right_pose(result.pose, result.model_id, case, frames)
                answers.add(result.evidence, right, f"upright/{setting}/winner", case.shape_id)
    return answers


def subset(samples: Samples, keep: np.ndarray) -> Samples:
    rows = [i for i in range(len(samples.right)) if keep[i]]
    return Samples(
        rows=[samples.rows[i] for i in rows],
        right=[samples.right[i] for i in rows],
        kinds=[samples.kinds[i] for i in rows],
        chairs=[samples.chairs[i] for i in rows],
    )


def joined(*parts: Samples) -> Samples:
    return Samples(
        rows=[r for p in parts for r in p.rows],
        right=[r for p in parts for r in p.right],
        kinds=[k for p in parts for k in p.kinds],
        chairs=[c for p in parts for c in p.chairs],
    )


def winners(samples: Samples) -> np.ndarray:
    return np.array([k.endswith("winner") for k in samples.kinds])


def scored(probabilities: np.ndarray, right: np.ndarray) -> str:
    """ECE and AUROC as table cells."""
    quality = calibration_quality(probabilities, right)
    return f"{quality['ece']:.3f} | {quality['auroc']:.3f}"


def held_out(samples: Samples, keep: np.ndarray) -> np.ndarray:
    """Each answer's confidence from a fit on the ``keep`` answers of the other folds' chairs."""
    chairs = sorted(set(samples.chairs))
    fold = np.array([chairs.index(c) % FOLDS for c in samples.chairs])
    matrix, probabilities = samples.matrix(), np.zeros(len(samples.right))
    for k in range(FOLDS):
        calibrator = fit(subset(samples, keep & (fold != k)))
        probabilities[fold == k] = calibrator.probabilities(matrix[fold == k])
    return probabilities


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=Path, default=SHIPPED_SAMPLES)
    parser.add_argument("--procedural", type=int, default=60)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if not args.samples.is_file():
        calibrator = find_calibrator(DEFAULT_MODEL_DIR)
        command = calibrator.card.get("command", "catalign calibrate") if calibrator else ""
        parser.error(f"no calibration samples at {args.samples}: run `{command}` (it writes them)")
    limit_threads(args.threads, total=args.threads)

    extractor = LearnedExtractor()
    shipped = Samples.load(args.samples)
    answers = validation_answers(extractor)
    procedural = {s.shape_id: s for s in ProceduralChairs(args.procedural)}
    unseen = collect(CalibrationConfig(views=2), procedural, extractor)
    fits = {
        "training chairs, every answer (shipped)": shipped,
        f"{args.procedural} procedural chairs": unseen,
        "training + procedural chairs": joined(shipped, unseen),
        "training chairs, winners only": subset(shipped, winners(shipped)),
    }
    right = np.array(answers.right, dtype=bool)
    same = np.array(["/same/" in k for k in answers.kinds])
    lines = [
        "# Fits of the confidence on the validation answers",
        "",
        "Upright views of the validation chairs, `up` given, seeds 0 and 1: ECE (10 bins) | "
        "AUROC of each fit's confidence of the winners.",
        "",
        "| fitted on | answers | *same* ECE | *same* AUROC | *cross* ECE | *cross* AUROC |",
        "|---|---|---|---|---|---|",
    ]
    for name, samples in fits.items():
        p = fit(samples).probabilities(answers.matrix())
        lines.append(
            f"| {name} | {len(samples.right)} | {scored(p[same], right[same])} | "
            f"{scored(p[~same], right[~same])} |"
        )
    lines += [
        "",
        f"Held out in {FOLDS} folds of the training chairs (each fold's answers from a fit on "
        "the others'), winners by pose mode and setting, then the alternatives: ECE / AUROC.",
        "",
        "| fitted on | upright *same* | upright *cross* | so3 *same* | so3 *cross* | "
        "alternatives |",
        "|---|---|---|---|---|---|",
    ]
    truth, won = np.array(shipped.right, dtype=bool), winners(shipped)
    for name, keep in (("every answer", np.ones_like(won)), ("winners only", won)):
        p = held_out(shipped, keep)
        cells = []
        for group in ("upright/same", "upright/cross", "so3/same", "so3/cross"):
            mask = won & np.array([k.startswith(group) for k in shipped.kinds])
            cells.append(scored(p[mask], truth[mask]).replace(" | ", " / "))
        cells.append(scored(p[~won], truth[~won]).replace(" | ", " / "))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
