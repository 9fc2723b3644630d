"""The shipped orientation proposer: it matches its card, and on the card's held-out views (of
the validation chairs, rendered at the card's seed) it reaches the accuracy the card states,
within 5 points."""

from __future__ import annotations

import pytest

from catalign.data.shapes import SharedChairs, to_metric
from catalign.features.orientation import ORIENTATION_DIR, load_orientation
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.training.orientation import (
    HELD_OUT_SEED,
    OrientationConfig,
    proposal_accuracy,
    render_views,
)

TOLERANCE = 0.05


def test_shipped_proposals_reach_their_measured_accuracy(shared_chairs: SharedChairs) -> None:
    proposer = load_orientation(DEFAULT_MODEL_DIR / ORIENTATION_DIR)
    card = proposer.card
    stated = card["held_out_accuracy"]
    training = OrientationConfig(**{k: v for k, v in card["training"].items() if k != "out"})
    shapes = [to_metric(shared_chairs.load(i)) for i in shared_chairs.ids("val")]
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


@pytest.mark.parametrize("field", ["command", "training_data", "training_time_s", "sha256"])
def test_the_card_says_how_the_weights_were_made(field: str) -> None:
    card = load_orientation(DEFAULT_MODEL_DIR / ORIENTATION_DIR).card
    assert card[field]
