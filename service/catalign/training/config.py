"""Typed configurations of the training commands (features, orientation networks, calibrator),
stored as plain JSON beside every run; the command line takes its defaults from them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, Field, model_validator

from catalign.data.views import PoseMode
from catalign.library.sources import CATEGORY_PATTERN
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.decision.confidence import CALIBRATION_DIR

# The calibration's views are drawn from their own seed, apart from the evaluation's 0 and 1.
CALIBRATION_SEED = 2_000


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
    categories: tuple[Annotated[str, Field(pattern=f"^{CATEGORY_PATTERN.pattern}$")], ...] = Field(
        ("chair",),
        min_length=1,
        description="categories trained on (the shared chair and table, or those of data); "
        "NCC positives pair shapes of one category",
    )
    data: Path | None = Field(
        None,
        description="a folder of the user's own canonically aligned CAD files, trained on "
        "instead of the shared shapes (one category, or one sub-folder per category)",
    )
    units: Literal["m", "cm", "mm"] = Field("m", description="units of the files in data")
    out: Path = Path("runs/default")
    init_from: Path | None = Field(
        None, description="start from the weights of another run (e.g. a shared stage 1)"
    )

    @property
    def total_steps(self) -> int:
        return self.stage1_steps + self.stage2_steps


class OrientationConfig(BaseModel):
    """Everything an orientation training run depends on (``catalign train-orientation``)."""

    steps: int = Field(3_000, ge=1)
    batch_size: int = Field(64, ge=1)
    learning_rate: float = Field(2e-3, gt=0)
    width: int = Field(16, ge=1, description="channels of the first conv block")
    up_width: int | None = Field(
        None, ge=1, description="the up network's width, when not width (heading's stays)"
    )
    up_frame: Literal["view", "principal"] = Field(
        "view", description="the frame the up network sees a view in"
    )
    category: str = Field(
        "chair",
        pattern=f"^{CATEGORY_PATTERN.pattern}$",
        description="the category trained on: shared chairs or tables, or data's",
    )
    data: Path | None = Field(
        None, description="a user's CAD folder of that category instead of the shared shapes"
    )
    units: str = Field("m", description="units of the data files")
    views_per_shape: int = Field(48, ge=1)
    procedural: int = Field(
        60, ge=0, description="procedural chairs added to the shared ones (chairs only)"
    )
    view_points: int = Field(2_048, ge=16, description="points kept per cached view")
    min_points: int = Field(300, ge=16, description="fewest points a training sample keeps")
    so3_share: float = Field(0.5, ge=0, le=1, description="views rendered in any rotation")
    floor_share: float = Field(0.25, ge=0, le=1, description="upright views with floor kept")
    fused_share: float = Field(
        0.0,
        ge=0,
        le=1,
        description="views that are reconstructions fused along a camera trajectory",
    )
    tilt_deg: float = Field(10.0, ge=0, description="error of the up the heading net is given")
    label_sigma_deg: float = Field(10.0, gt=0)
    seed: int = 0
    threads: int = Field(2, ge=1)
    out: Path = Path("runs/orientation")
    init_from: Path | None = Field(None, description="start from another run's weights")
    networks: Literal["both", "up", "heading"] = Field(
        "both", description="the networks this run trains; the other keeps init_from's weights"
    )

    @model_validator(mode="after")
    def _a_kept_network_comes_from_somewhere(self) -> OrientationConfig:
        if self.networks != "both" and self.init_from is None:
            raise ValueError(
                f"networks={self.networks} trains one network: the other needs init_from"
            )
        return self

    def command(self) -> str:
        """The ``catalign train-orientation`` command line that runs this configuration."""
        return (
            f"catalign train-orientation --out {self.out} --steps {self.steps} "
            f"--batch-size {self.batch_size} --views-per-shape {self.views_per_shape} "
            f"--procedural {self.procedural} --seed {self.seed} --threads {self.threads}"
            + ("" if self.init_from is None else f" --init-from {self.init_from}")
            + _unless_default(self, "learning_rate", f" --learning-rate {self.learning_rate:g}")
            + _unless_default(self, "up_frame", f" --up-frame {self.up_frame}")
            + _unless_default(self, "networks", f" --networks {self.networks}")
            + _unless_default(self, "fused_share", f" --fused-share {self.fused_share:g}")
            + _unless_default(self, "so3_share", f" --so3-share {self.so3_share:g}")
            + ("" if self.up_width is None else f" --up-width {self.up_width}")
            + _unless_default(self, "category", f" --category {self.category}")
            + ("" if self.data is None else f" --data {self.data} --units {self.units}")
        )


class RetrievalConfig(BaseModel):
    """Everything a retrieval training run depends on (``catalign train-retrieval``)."""

    steps: int = Field(1_500, ge=1)
    batch_size: int = Field(48, ge=2, description="views a step, each of its own model")
    negatives: int = Field(
        96, ge=0, description="other models each step's views are scored against"
    )
    hard_negatives: int = Field(
        4,
        ge=0,
        description="models each view is most often mistaken for, added to its step's negatives",
    )
    mining_every: int = Field(
        100, ge=1, description="steps between two descriptions of every model, for mining"
    )
    init_from: Path | None = Field(
        None, description="retrieval encoders to start from (a folder with their card)"
    )
    temperature: float = Field(0.07, gt=0)
    learning_rate: float = Field(1e-3, gt=0)
    dims: int = Field(256, ge=8, description="the descriptor's length")
    views_per_shape: int = Field(8, ge=1, description="views of each shared training shape")
    procedural: int = Field(1_000, ge=0, description="procedural chairs among the models")
    procedural_views: int = Field(2, ge=1, description="views of each procedural chair")
    procedural_first_seed: int = Field(1_000, ge=0)
    heading_error_deg: float = Field(
        8.0, ge=0, description="error of the heading a training view is described at"
    )
    view_points: int = Field(512, ge=16, description="points a training view keeps at most")
    model_points: int = Field(768, ge=16, description="points a training model keeps at most")
    min_view_share: float = Field(
        0.5, gt=0, le=1, description="least share of its points a training view keeps"
    )
    min_view_points: int = Field(32, ge=1)
    penalty_weight: float = Field(
        0.5, ge=0, description="share of the size and height penalties the shortlist takes off"
    )
    seed: int = 100
    threads: int = Field(2, ge=1)
    out: Path = Path("runs/retrieval")

    def command(self) -> str:
        """The ``catalign train-retrieval`` command line that runs this configuration."""
        start = "" if self.init_from is None else f" --init-from {self.init_from}"
        return (
            f"catalign train-retrieval --out {self.out} --steps {self.steps} "
            f"--procedural {self.procedural} --learning-rate {self.learning_rate:g} "
            f"--hard-negatives {self.hard_negatives} "
            f"--seed {self.seed} --threads {self.threads}{start}"
        )


def _unless_default(config: BaseModel, field: str, option: str) -> str:
    """``option`` when ``config``'s ``field`` differs from its default, else nothing."""
    default = type(config).model_fields[field].default
    return "" if getattr(config, field) == default else option


@dataclass(frozen=True)
class CalibrationConfig:
    """What ``catalign calibrate`` fits on; ``command()`` is the line that reproduces it."""

    out: Path = DEFAULT_MODEL_DIR / CALIBRATION_DIR
    views: int = 2
    # Reconstructions per chair and mode beside the single views: what a mapping robot sends.
    fused_views: int = 0
    seed: int = CALIBRATION_SEED
    pose_modes: tuple[PoseMode, ...] = ("upright", "so3")
    max_shapes: int | None = None
    # The category whose training split is registered: the shared chairs or tables, or the
    # shapes of a user's CAD folder (``data``, in ``units``).
    category: str = "chair"
    data: Path | None = None
    units: str = "m"

    def command(self) -> str:
        modes = " ".join(f"--pose-mode {m}" for m in self.pose_modes)
        return (
            f"catalign calibrate --out {self.out} --views {self.views}"
            + (f" --fused-views {self.fused_views}" if self.fused_views else "")
            + f" --seed {self.seed} {modes}"
            + ("" if self.max_shapes is None else f" --max-shapes {self.max_shapes}")
            + ("" if self.category == "chair" else f" --category {self.category}")
            + ("" if self.data is None else f" --data {self.data} --units {self.units}")
        )
