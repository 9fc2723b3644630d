"""The engine's one configuration: the measured defaults, loud refusals, no heavy imports."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from pydantic import ValidationError

from catalign.errors import ConfigError
from catalign.geometry.distance_grid import TRUNCATION_VOXELS
from catalign.registration.config import EngineConfig, from_config, parse_options

# The engine's defaults as measured (bench/tradeoff.py); a change here is a change of behaviour.
DEFAULTS = {
    "headings": None,
    "top_k": 10,
    "ransac_factor": 2.0,
    "icp_factor": 1.0,
    "icp_iterations": 30,
    "icp_points": 600,
    "up_tolerance_deg": 30.0,
    "up_snap_deg": None,
    "min_points": 50,
    "up_proposals": 3,
    "up_mass": 0.5,
    "up_belief_power": 0.3,
    "heading_belief_power": 0.3,
    "heading_proposals": 2,
    "heading_mass": 0.95,
    "heading_fallback": 0.7,
    "keep_headings": 3,
    "heading_models": 10,
    "heading_draws": 300,
    "ransac_iterations": 5_000,
    "pair_draws": 3_000,
    "poses_per_view": 8,
    "probe_points": 384,
    "coverage_points": 1_500,
    "match_points": 500,
    "model_points": 1_000,
    "coverage_cell": 0.5,
    "verify_top": 32,
    "sweep_models": 10,
    "sweep_yaw_deg": 5.0,
    "sweep_span_deg": 30.0,
    "sweep_step": 2,
    "sweep_probes": 64,
    "sweep_shifts": 512,
    "sweep_poses": 2,
    "sweep_refine": 2,
    "refine": 3,
    "alternatives": 3,
    "confidence_margin": 0.2,
    "exact_fitness": 0.9,
    "sure_fitness": 0.95,
    "fine_cells": 4,
    "pass_voxels": 32_000,
    "model_cache": 256,
}


def test_defaults_are_the_measured_ones() -> None:
    assert EngineConfig().model_dump() == DEFAULTS


def test_every_field_is_documented() -> None:
    for name, field in EngineConfig.model_fields.items():
        assert field.description, f"EngineConfig.{name} has no docstring"


@pytest.mark.parametrize(
    "bad",
    [
        {"keep_heading": 2},  # a typo
        {"top_k": 0},
        {"match_points": -1},
        {"ransac_factor": 0.0},
        {"ransac_factor": TRUNCATION_VOXELS + 0.5},  # past the library's distance grids
        {"exact_fitness": 1.5},
        {"refine": "three"},
    ],
)
def test_unknown_fields_and_bad_values_are_refused(bad: dict) -> None:
    with pytest.raises(ValidationError):
        EngineConfig.model_validate(bad)


def test_the_verification_distance_may_reach_the_end_of_the_distance_grids() -> None:
    assert EngineConfig(ransac_factor=TRUNCATION_VOXELS).ransac_factor == TRUNCATION_VOXELS


def test_none_means_all_and_the_config_is_frozen() -> None:
    config = EngineConfig.model_validate({"model_points": None, "top_k": None})
    assert (config.model_points, config.top_k) == (None, None)
    with pytest.raises(ValidationError):
        config.top_k = 3  # type: ignore[misc]


def test_importing_it_pulls_in_neither_torch_nor_open3d() -> None:
    code = (
        "import sys; import catalign.registration.config, catalign.api.settings; "
        "heavy = {'torch', 'open3d'} & set(sys.modules); assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_from_config_fills_a_stages_options_by_name() -> None:
    def stage(library: str, *, distance: float, top_k: int | None, refine: int) -> tuple:
        return library, distance, top_k, refine

    config = EngineConfig(top_k=4)
    assert from_config(stage, config, "lib", distance=0.05) == ("lib", 0.05, 4, 3)
    assert from_config(stage, config, "lib", distance=0.05, refine=1) == ("lib", 0.05, 4, 1)

    def unknown(*, distance: float, surprise: int) -> None: ...

    with pytest.raises(AttributeError, match="surprise"):
        from_config(unknown, config, distance=0.05)


def test_options_replace_the_named_fields_of_a_base() -> None:
    config = parse_options(["top_k=4", "model_points=none", " ransac_factor = 1.5 "])
    assert (config.top_k, config.model_points, config.ransac_factor) == (4, None, 1.5)
    assert isinstance(config.top_k, int)
    assert config.match_points == EngineConfig().match_points
    over = parse_options(["refine=2"], base=config)
    assert (over.top_k, over.model_points, over.refine) == (4, None, 2)
    assert parse_options([]) == EngineConfig()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ("topk=4", "unknown engine option 'topk'; the options: headings, top_k"),
        ("top_k=0", "engine option top_k: Input should be greater than or equal to 1"),
        ("top_k=many", "'many' is not a number"),
        ("top_k", "is not NAME=VALUE"),
        ("=4", "is not NAME=VALUE"),
    ],
)
def test_a_bad_option_is_refused_naming_it(option: str, message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        parse_options([option])
