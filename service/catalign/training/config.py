"""Typed training configuration, stored as plain JSON beside every checkpoint."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field


class TrainConfig(BaseModel):
    """Everything a training run depends on; ``catalign train`` flags map onto these fields.

    The curriculum ``ncc`` is the paper's: ``stage1_steps`` of same-instance pairs, then
    ``stage2_steps`` in which a pair is cross-instance with probability ``1 - same_share``.
    ``same-only`` keeps same-instance pairs throughout (the paper's "FCGF baseline" ablation).
    """

    model: str = "ResUNetBN2C"
    conv1_kernel_size: int = Field(5, ge=1)
    voxel_size: float = Field(0.025, gt=0)
    loss: Literal["contrastive", "hardest"] = "hardest"
    curriculum: Literal["ncc", "same-only"] = "ncc"
    stage1_steps: int = Field(600, ge=0)
    stage2_steps: int = Field(900, ge=0)
    same_share: float = Field(0.3, ge=0, le=1)
    batch_size: int = Field(2, ge=1)
    learning_rate: float = Field(1e-3, gt=0)
    tau_ncc: float = Field(0.04, gt=0)
    rotation: Literal["upright", "yaw-bin", "yaw-quarter", "so3"] = "upright"
    procedural: int = Field(0, ge=0, description="procedural chairs added to the training shapes")
    view_so3_share: float = Field(
        0.0, ge=0, le=1, description="views of the chair in any rotation (seen from below, aside)"
    )
    seed: int = 0
    validate_every: int = Field(100, ge=1)
    checkpoint_every: int = Field(50, ge=1)
    validation_pairs: int = Field(16, ge=1)
    threads: int = Field(2, ge=1)
    out: Path = Path("runs/default")
    init_from: Path | None = Field(
        None, description="start from the weights of another run (e.g. a shared stage 1)"
    )

    @property
    def total_steps(self) -> int:
        return self.stage1_steps + self.stage2_steps
