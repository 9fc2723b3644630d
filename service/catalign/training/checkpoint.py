"""Checkpoints: a resumable training state, and the shipped weights with their model card.

The training state (weights, optimizer, step) is saved with ``torch.save`` and read back with
``weights_only=True`` (tensors and plain data only, no pickled objects). The shipped model is
``model.safetensors`` plus ``model_card.json``: architecture and training configuration as plain
data, metrics, and the sha256 of the weights file, which the library index records.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

from catalign.atomic import atomic_write_bytes
from catalign.features.resunet import ResUNet2
from catalign.features.weights import CARD_FILE, WEIGHTS_FILE, sha256_of

STATE_FILE = "state.pt"


def save_state(
    directory: Path,
    model: ResUNet2,
    optimizer: torch.optim.Optimizer,
    step: int,
    config: dict[str, Any],
) -> None:
    tmp = directory / f".{STATE_FILE}.tmp"
    directory.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "step": step,
            "model_config": model.config,
            "train_config": config,
        },
        tmp,
    )
    tmp.replace(directory / STATE_FILE)


def load_state(directory: Path) -> dict[str, Any] | None:
    path = directory / STATE_FILE
    if not path.is_file():
        return None
    return torch.load(path, weights_only=True)


def export_model(directory: Path, model: ResUNet2, card: dict[str, Any]) -> dict[str, Any]:
    """Write ``model.safetensors`` and ``model_card.json``; return the card with its sha256."""
    metadata = {"model_config": json.dumps(model.config)}
    return export_weights(directory, model, card, WEIGHTS_FILE, CARD_FILE, metadata)


def export_weights(
    directory: Path,
    model: torch.nn.Module,
    card: dict[str, Any],
    weights_file: str,
    card_file: str,
    metadata: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Write a model's weights (safetensors) and its card, which records the architecture
    (``model.config``) and the weights' sha256; return the card."""
    directory.mkdir(parents=True, exist_ok=True)
    weights = directory / weights_file
    tmp = directory / f".{weights_file}.tmp"
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(tmp), metadata=metadata)
    tmp.replace(weights)
    card = card | {
        "architecture": model.config,
        "weights": weights_file,
        "sha256": sha256_of(weights),
    }
    atomic_write_bytes(directory / card_file, json.dumps(card, indent=2).encode())
    return card
