"""The shipped orientation proposers (the general one, trained on chairs, and the tables' own):
each matches its card, and on the card's held-out views (of the validation shapes of its
category, rendered at the card's seed) reaches the accuracy the card states, within 5 points;
the engine orients a query answered from tables alone with the tables' own."""

from __future__ import annotations

from pathlib import Path

import pytest

from catalign.data.shapes import SharedChairs, SharedTables
from catalign.features.extractor import LearnedExtractor
from catalign.features.orientation import ORIENTATION_DIR, load_orientation
from catalign.library.loaded import load
from catalign.paths import CATEGORIES_DIR, DEFAULT_MODEL_DIR
from catalign.registration.engine import Engine
from catalign.training.orientation import (
    HELD_OUT_SEED,
    OrientationConfig,
    proposal_accuracy,
    render_views,
)

TOLERANCE = 0.05
# Each shipped proposer's folder, by the category whose shared shapes it was trained on.
SHIPPED = {
    "chair": DEFAULT_MODEL_DIR / ORIENTATION_DIR,
    "table": DEFAULT_MODEL_DIR / CATEGORIES_DIR / "table" / ORIENTATION_DIR,
}


@pytest.mark.parametrize("category", list(SHIPPED))
def test_shipped_proposals_reach_their_measured_accuracy(
    category: str, chairs_root: Path, tables_root: Path
) -> None:
    proposer = load_orientation(SHIPPED[category])
    card = proposer.card
    stated = card["held_out_accuracy"]
    training = OrientationConfig(**{k: v for k, v in card["training"].items() if k != "out"})
    assert training.category == category
    shared = SharedChairs(chairs_root) if category == "chair" else SharedTables(tables_root)
    shapes = [shared.metric(i) for i in shared.ids("val")]
    views = render_views(
        shapes,
        4,
        seed=HELD_OUT_SEED,
        view_points=training.view_points,
        so3_share=training.so3_share,
        floor_share=training.floor_share,
        progress=False,
    )
    measured = proposal_accuracy(proposer, views)
    for name in ("up_top3", "heading_top2", "up_top1", "heading_top1"):
        assert measured[name] >= stated[name] - TOLERANCE, (name, measured, stated)
    assert measured["up_top3"] >= 0.8 and measured["heading_top2"] >= 0.85


@pytest.mark.parametrize("category", list(SHIPPED))
@pytest.mark.parametrize("field", ["command", "training_data", "training_time_s", "sha256"])
def test_the_card_says_how_the_weights_were_made(category: str, field: str) -> None:
    card = load_orientation(SHIPPED[category]).card
    assert card[field]


def test_the_engine_holds_the_tables_own_proposer_beside_the_general_one() -> None:
    extractor = LearnedExtractor()
    engine = Engine(extractor, load(DEFAULT_MODEL_DIR / "library", extractor.fingerprint))
    assert list(engine.orientations) == ["table"]
    table = load_orientation(SHIPPED["table"])
    assert engine.orientations["table"].card["sha256"] == table.card["sha256"]
