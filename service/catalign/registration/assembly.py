"""The stages of the engine, built from the configuration tree.

Each builder reads one stage's options from its group of
:class:`~catalign.registration.config.EngineConfig` (the sweep's from ``config.sweep``...) and
hands them to the stage as plain keyword arguments, so the stages stay free of configuration
objects and can be built alone in tests. :func:`assemble` builds them all for the
:class:`~catalign.registration.engine.Engine`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from catalign.features.extractor import FeatureExtractor
from catalign.library.loaded import Library
from catalign.registration.config import EngineConfig
from catalign.registration.decision.confidence import Calibrator
from catalign.registration.decision.finish import Finisher
from catalign.registration.decision.rules import Rules
from catalign.registration.stages.category_fit import CategoryFitter
from catalign.registration.stages.hypothesise import Hypothesiser
from catalign.registration.stages.match import Matcher
from catalign.registration.stages.refine import Refiner
from catalign.registration.stages.searcher import Searcher
from catalign.registration.stages.sweep import Sweeper
from catalign.registration.stages.verify import Verifier


@dataclass(frozen=True)
class Stages:
    """Every stage an engine runs, built once."""

    verifier: Verifier
    searcher: Searcher
    refiner: Refiner
    rules: Rules
    finisher: Finisher


def assemble(
    config: EngineConfig,
    library: Library,
    extractor: FeatureExtractor,
    *,
    calibrator: Calibrator | None,
    calibrators: Mapping[str, Calibrator] | None = None,
) -> Stages:
    """The stages for ``library`` and the ``extractor``'s features (its voxel, its retrieval
    encoders): RANSAC and verification inlier distances are ``config.ransac.factor`` voxels,
    ICP's ``config.icp.factor``; ``calibrators`` read the answers of their category's models in
    place of ``calibrator``."""
    voxel = extractor.voxel_size
    distance = config.ransac.factor * voxel
    icp_distance = config.icp.factor * voxel
    verifier = build_verifier(config, library, distance=distance, voxel=voxel)
    refiner = build_refiner(config, library, distance=icp_distance)
    searcher = Searcher(
        library=library,
        matcher=build_matcher(config, library, distance=distance),
        hypothesiser=build_hypothesiser(config, distance=distance),
        sweeper=build_sweeper(config, library, distance=distance),
        verifier=verifier,
        heading_models=config.match.heading_models,
        up_belief_power=config.verify.up_belief_power,
        heading_belief_power=config.verify.heading_belief_power,
        retrieval=extractor.retrieval,
        index_from=config.shortlist.index_from,
        index_candidates=config.shortlist.index_candidates,
        fit_from=config.shortlist.fit_from,
        fit_candidates=config.shortlist.fit_candidates,
        fit_weight=config.shortlist.fit_weight,
    )
    fitter = CategoryFitter(library, refiner, extent_points=config.verify.coverage_points)
    finisher = Finisher(
        library,
        refiner,
        fitter,
        icp_distance=icp_distance,
        exact_fitness=config.decision.exact_fitness,
        calibrator=calibrator,
        calibrators=dict(calibrators or {}),
    )
    return Stages(verifier, searcher, refiner, build_rules(config), finisher)


def build_verifier(
    config: EngineConfig, library: Library, *, distance: float, voxel: float
) -> Verifier:
    options = config.verify
    return Verifier(
        library,
        distance=distance,
        coverage_points=options.coverage_points,
        verify_top=options.top,
        cell=options.coverage_cell * voxel,
        model_cache=config.model_cache,
    )


def build_matcher(config: EngineConfig, library: Library, *, distance: float) -> Matcher:
    options = config.match
    return Matcher(
        library,
        distance=distance,
        keep_headings=options.keep_headings,
        heading_draws=options.heading_draws,
        match_points=options.query_points,
        model_points=options.model_points,
        model_cache=config.model_cache,
    )


def build_hypothesiser(config: EngineConfig, *, distance: float) -> Hypothesiser:
    options = config.ransac
    return Hypothesiser(
        distance=distance,
        pair_draws=options.pair_draws,
        poses_per_view=options.poses_per_view,
        ransac_iterations=options.iterations,
        up_tolerance_deg=options.up_tolerance_deg,
    )


def build_sweeper(config: EngineConfig, library: Library, *, distance: float) -> Sweeper:
    options = config.sweep
    return Sweeper(
        library,
        distance=distance,
        sweep_models=options.models,
        sweep_yaw_deg=options.yaw_deg,
        sweep_span_deg=options.span_deg,
        sweep_step=options.step,
        sweep_probes=options.probes,
        sweep_shifts=options.shifts,
        sweep_poses=options.poses,
    )


def build_refiner(config: EngineConfig, library: Library, *, distance: float) -> Refiner:
    return Refiner(
        library,
        distance=distance,
        icp_iterations=config.icp.iterations,
        icp_points=config.icp.points,
        threads=config.icp.threads,
        model_cache=config.model_cache,
    )


def build_rules(config: EngineConfig) -> Rules:
    decision = config.decision
    return Rules(
        refine=config.icp.poses,
        alternatives=decision.alternatives,
        sweep_refine=config.sweep.refine,
        exact_fitness=decision.exact_fitness,
        sure_fitness=decision.sure_fitness,
        confidence_margin=decision.confidence_margin,
        fit_margin=decision.fit_margin,
    )
