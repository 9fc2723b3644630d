"""Losses: zero when features already satisfy the margins, positive and decreasing otherwise."""

from __future__ import annotations

import pytest
import torch

from catalign.training.loss import NEG_MARGIN, contrastive_loss, hardest_contrastive_loss

LOSSES = [contrastive_loss, hardest_contrastive_loss]


def _setup(separated: bool):
    """Eight points on a line in the aligned frame; positives pair i with i."""
    aligned = torch.arange(8, dtype=torch.float32)[:, None] * torch.tensor([[1.0, 0, 0]])
    positives = torch.stack([torch.arange(8), torch.arange(8)], dim=1)
    if separated:
        features = torch.eye(8)  # distinct points sqrt(2) > NEG_MARGIN apart, matches identical
    else:
        features = torch.nn.functional.normalize(torch.ones(8, 8), dim=1)  # all the same
    return features, features.clone(), positives, aligned, aligned.clone()


@pytest.mark.parametrize("loss_fn", LOSSES)
def test_loss_vanishes_when_margins_hold(loss_fn) -> None:
    fa, fb, positives, xa, xb = _setup(separated=True)
    assert torch.sqrt(torch.tensor(2.0)) > NEG_MARGIN
    terms = loss_fn(fa, fb, positives, xa, xb, 0.5, torch.Generator().manual_seed(0))
    assert float(terms.loss) == pytest.approx(0.0, abs=1e-6)
    assert terms.pos_distance == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("loss_fn", LOSSES)
def test_collapsed_features_are_punished(loss_fn) -> None:
    fa, fb, positives, xa, xb = _setup(separated=False)
    terms = loss_fn(fa, fb, positives, xa, xb, 0.5, torch.Generator().manual_seed(0))
    assert float(terms.loss) == pytest.approx(NEG_MARGIN**2, rel=1e-4)
    assert terms.neg_distance == pytest.approx(0.0, abs=1e-5)


def test_negatives_near_the_anchor_are_never_used() -> None:
    fa, fb, positives, xa, xb = _setup(separated=False)
    # every pair is within the radius: no negative remains, only the (zero) positive term
    terms = hardest_contrastive_loss(fa, fb, positives, xa, xb, 100.0, torch.Generator())
    assert float(terms.loss) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("loss_fn", LOSSES)
def test_gradient_descent_lowers_the_loss(loss_fn) -> None:
    torch.manual_seed(0)
    raw = torch.randn(16, 8, requires_grad=True)
    aligned = torch.randn(16, 3) * 5
    positives = torch.stack([torch.arange(16), torch.arange(16)], dim=1)
    optimizer = torch.optim.SGD([raw], lr=0.5)

    def loss() -> torch.Tensor:
        f = torch.nn.functional.normalize(raw, dim=1)
        noisy = torch.nn.functional.normalize(raw + 0.3, dim=1)
        return loss_fn(
            f, noisy, positives, aligned, aligned, 0.5, torch.Generator().manual_seed(1)
        ).loss

    first = float(loss().detach())
    for _ in range(200):
        optimizer.zero_grad()
        value = loss()
        value.backward()
        optimizer.step()
    assert float(loss().detach()) < 0.5 * first
