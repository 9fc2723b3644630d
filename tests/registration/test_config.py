"""The engine's one configuration: the measured defaults, loud refusals, no heavy imports."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from pydantic import ValidationError

from catalign.errors import ConfigError
from catalign.geometry.distance_grid import TRUNCATION_VOXELS
from catalign.options import OptionGroup
from catalign.registration.config import FLAT_NAMES, EngineConfig, parse_options

# The engine's defaults as measured (bench/tradeoff.py); a change here is a change of behaviour.
DEFAULTS = {
    "top_k": 10,
    "model_cache": 256,
    "input": {"min_points": 50, "fine_cells": 4, "pass_voxels": 32000},
    "shortlist": {
        "index_from": 5000,
        "index_candidates": 1024,
        "fit_from": 100,
        "fit_candidates": 300,
        "fit_weight": 20.0,
    },
    "orient": {
        "headings": None,
        "up_proposals": 3,
        "up_mass": 0.5,
        "up_snap_deg": None,
        "heading_proposals": 2,
        "heading_mass": 0.95,
        "snap_deg": 15.0,
        "snap_draws": 2048,
        "snap_cell_voxels": 0.8,
        "snap_tolerance_voxels": 0.4,
        "snap_share": 0.1,
        "snap_min_points": 30,
        "guessed_floor_spread": (1.0, 2.0),
    },
    "floor": {
        "max_tilt_deg": 12.0,
        "bottom_percentile": 0.5,
        "band_m": 0.05,
        "ransac_draws": 256,
        "ransac_sample": 4000,
        "ransac_tol_m": 0.02,
        "below_weight": 4.0,
        "refits": 3,
        "sigma_window_m": 0.06,
        "tol_sigmas": 2.5,
        "min_tol_m": 0.015,
        "max_tol_m": 0.05,
        "min_floor_area_m2": 0.2,
        "coarse_voxels": 3,
        "min_interior": 4,
        "max_sigma_m": 0.02,
        "max_below_share": 0.02,
        "below_slack": 20,
        "remnant_band_m": 0.05,
        "footprint_margin_m": 0.03,
    },
    "cleanup": {"link_m": 0.2, "small_share": 0.1, "max_set_aside": 0.5},
    "match": {
        "query_points": 500,
        "model_points": 1000,
        "keep_headings": 3,
        "heading_models": 10,
        "heading_draws": 300,
    },
    "ransac": {
        "factor": 2.0,
        "iterations": 5000,
        "pair_draws": 3000,
        "poses_per_view": 8,
        "up_tolerance_deg": 30.0,
    },
    "sweep": {
        "models": 10,
        "yaw_deg": 5.0,
        "span_deg": 30.0,
        "step": 2,
        "probes": 64,
        "shifts": 512,
        "poses": 2,
        "refine": 2,
    },
    "verify": {
        "probe_points": 384,
        "coverage_points": 1500,
        "coverage_cell": 0.5,
        "top": 32,
        "up_belief_power": 0.3,
        "heading_belief_power": 0.3,
    },
    "icp": {"factor": 1.0, "iterations": 30, "points": 600, "threads": None, "poses": 3},
    "decision": {
        "alternatives": 3,
        "confidence_margin": 0.2,
        "exact_fitness": 0.9,
        "sure_fitness": 0.95,
        "fit_margin": 0.02,
        "heading_fallback": 0.7,
    },
}


def test_defaults_are_the_measured_ones() -> None:
    assert EngineConfig().model_dump() == DEFAULTS


def test_every_option_and_group_is_documented() -> None:
    for name, field in EngineConfig.model_fields.items():
        assert field.description, f"EngineConfig.{name} has no docstring"
        group = field.annotation
        if isinstance(group, type) and issubclass(group, OptionGroup):
            assert group.__doc__, f"{group.__name__} has no docstring"
            for option, info in group.model_fields.items():
                assert info.description, f"engine.{name}.{option} has no docstring"


@pytest.mark.parametrize(
    "bad",
    [
        {"keep_heading": 2},  # a typo
        {"match": {"keep_heading": 2}},  # a typo within a group
        {"top_k": 0},
        {"match": {"query_points": -1}},
        {"match_points": -1},  # a flat name of earlier releases, checked as well
        {"ransac": {"factor": 0.0}},
        {"ransac": {"factor": TRUNCATION_VOXELS + 0.5}},  # past the library's distance grids
        {"decision": {"exact_fitness": 1.5}},
        {"icp": {"poses": "three"}},
        {"floor": {"max_tilt_deg": 95.0}},
        {"cleanup": {"link_m": float("inf")}},
    ],
)
def test_unknown_fields_and_bad_values_are_refused(bad: dict) -> None:
    with pytest.raises(ValidationError):
        EngineConfig.model_validate(bad)


def test_the_verification_distance_may_reach_the_end_of_the_distance_grids() -> None:
    config = EngineConfig(ransac={"factor": TRUNCATION_VOXELS})
    assert config.ransac.factor == TRUNCATION_VOXELS


def test_none_means_all_and_the_config_is_frozen() -> None:
    config = EngineConfig.model_validate({"match": {"model_points": None}, "top_k": None})
    assert (config.match.model_points, config.top_k) == (None, None)
    with pytest.raises(ValidationError):
        config.top_k = 3  # type: ignore[misc]
    with pytest.raises(ValidationError):
        config.sweep.models = 3  # type: ignore[misc]


def test_the_flat_names_of_earlier_releases_land_in_the_tree() -> None:
    flat = EngineConfig.model_validate({"sweep_models": 0, "refine": 5, "top_k": 4})
    assert (flat.sweep.models, flat.icp.poses, flat.top_k) == (0, 5, 4)
    assert flat == EngineConfig(sweep={"models": 0}, icp={"poses": 5}, top_k=4)
    # only what was named counts as set (a library's options stay its own)
    assert flat.model_dump(exclude_unset=True) == {
        "top_k": 4,
        "sweep": {"models": 0},
        "icp": {"poses": 5},
    }
    mixed = EngineConfig.model_validate({"sweep": {"yaw_deg": 10.0}, "sweep_models": 3})
    assert (mixed.sweep.yaw_deg, mixed.sweep.models) == (10.0, 3)
    assert set(FLAT_NAMES) | {"top_k", "model_cache"} >= {"match_points", "verify_top"}


def test_replaced_validates_what_it_changes() -> None:
    config = EngineConfig(top_k=4).replaced(sweep={"models": 0}, exact_fitness=0.5)
    assert (config.top_k, config.sweep.models, config.decision.exact_fitness) == (4, 0, 0.5)
    assert config.sweep.yaw_deg == EngineConfig().sweep.yaw_deg
    with pytest.raises(ConfigError, match=re.escape("sweep.models")):
        config.replaced(sweep={"models": -1})
    with pytest.raises(ConfigError, match=re.escape("unknown engine option 'sweep.model'")):
        config.replaced(sweep={"model": 1})


def test_importing_it_pulls_in_neither_torch_nor_open3d() -> None:
    code = (
        "import sys; import catalign.registration.config, catalign.api.settings; "
        "heavy = {'torch', 'open3d'} & set(sys.modules); assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_options_replace_the_named_fields_of_a_base() -> None:
    config = parse_options(["top_k=4", "match.model_points=none", " ransac.factor = 1.5 "])
    assert (config.top_k, config.match.model_points, config.ransac.factor) == (4, None, 1.5)
    assert isinstance(config.top_k, int)
    assert config.match.query_points == EngineConfig().match.query_points
    over = parse_options(["icp.poses=2", "floor.max_tilt_deg=8"], base=config)
    assert (over.top_k, over.match.model_points, over.icp.poses) == (4, None, 2)
    assert over.floor.max_tilt_deg == 8.0
    assert over.model_dump(exclude_unset=True)["match"] == {"model_points": None}
    assert parse_options(["sweep_models=0"]).sweep.models == 0  # a flat name of earlier releases
    assert parse_options([]) == EngineConfig()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (
            "topk=4",
            "unknown engine option 'topk'; the options and groups: top_k, model_cache, input",
        ),
        ("sweep.model=4", "unknown engine option 'sweep.model'; the sweep options: sweep.models"),
        ("top_k=0", "engine option top_k: Input should be greater than or equal to 1"),
        ("sweep.models=-1", "engine option sweep.models: Input should be greater than or equal"),
        ("top_k=many", "'many' is not a number"),
        ("top_k", "is not NAME=VALUE"),
        ("=4", "is not NAME=VALUE"),
    ],
)
def test_a_bad_option_is_refused_naming_it(option: str, message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        parse_options([option])
