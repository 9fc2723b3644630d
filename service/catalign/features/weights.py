"""The shipped weights as serving reads them: the model card, the checked weights file, and
what the card says about the queries (how many headings a query is described at).

Training writes these files (:mod:`catalign.training.checkpoint`); serving only reads them, so
the reading lives here, below every layer that serves.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from safetensors.torch import load_file

from catalign.errors import ConfigError
from catalign.features.resunet import ResUNet2, build_model

WEIGHTS_FILE = "model.safetensors"
CARD_FILE = "model_card.json"
# Headings a query is tried at for each binned rotation mode of training; its yaws span one
# bin, +-180/n degrees.
YAW_BINS = {"yaw-bin": 8, "yaw-quarter": 4}


def sha256_of(path: Path) -> str:
    """The sha256 of a file, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def verified_card(directory: Path, weights_file: str, card_file: str) -> dict[str, Any]:
    """The card of the weights in ``directory``, after checking that the weights' sha256 is
    the one it records (a corrupt or replaced file is refused)."""
    card_path, weights = directory / card_file, directory / weights_file
    if not card_path.is_file() or not weights.is_file():
        raise ConfigError(f"no model in {directory}: expected {card_file} and {weights_file}")
    card = json.loads(card_path.read_text())
    actual = sha256_of(weights)
    if card.get("sha256") != actual:
        raise ConfigError(
            f"{weights} does not match its card (sha256 {actual[:12]}..., card says "
            f"{str(card.get('sha256'))[:12]}...): the weights file is corrupt or was replaced"
        )
    return card


def load_model(directory: Path) -> tuple[ResUNet2, dict[str, Any]]:
    """The shipped model in eval mode and its card; the weights' sha256 must match the card."""
    card = verified_card(directory, WEIGHTS_FILE, CARD_FILE)
    model = build_model(**card["architecture"])
    model.load_state_dict(load_file(str(directory / WEIGHTS_FILE)))
    model.eval()
    return model, card
