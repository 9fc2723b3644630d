"""The engine's configuration: one typed, frozen tree of every option of every stage.

:class:`EngineConfig` gathers the option groups (:class:`~catalign.options.OptionGroup`), one
per stage: ``engine.input``, ``engine.shortlist``, ``engine.orient``, ``engine.floor``,
``engine.cleanup``, ``engine.match``, ``engine.ransac``, ``engine.sweep``, ``engine.verify``,
``engine.icp`` and ``engine.decision``, beside the two options every deployment sets, ``top_k`` and
``model_cache``. The clean-up stages declare their groups beside their code
(:mod:`~catalign.registration.prepare.floor`, :mod:`~catalign.registration.prepare.detached`,
:mod:`~catalign.registration.prepare.orient`) and take them whole; the others' are here, and
:mod:`~catalign.registration.assembly` turns them into the stages' keyword arguments.

It is validated once, where it enters: the service's settings (``CATALIGN_ENGINE__SWEEP__MODELS``,
``CATALIGN_ENGINE__TOP_K``), the command line's and the benchmarks' ``name=value`` options
(``sweep.models=0``), the library's manifest, a test. Each field's docstring is its
documentation (also in the JSON schema ``/info`` reports); an unknown field is refused, so a
typo fails loudly. The flat names of earlier releases (``sweep_models``) are still read, and
mapped onto the tree (:data:`FLAT_NAMES`), so that libraries configured then keep working. It
imports nothing heavy (no torch, no open3d): the API's settings embed it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from catalign.errors import ConfigError
from catalign.library.quantise import STORED_KEYPOINTS
from catalign.options import OptionGroup, one_line_descriptions
from catalign.registration.prepare.detached import CleanupOptions
from catalign.registration.prepare.floor import FloorOptions
from catalign.registration.prepare.orient import OrientOptions
from catalign.registration.prepare.validation import FINE_CELLS, MIN_VOXELS


class InputOptions(OptionGroup):
    """What a query must hold and how it is fed to the network (``engine.input``)."""

    min_points: int = Field(default=MIN_VOXELS, ge=1)
    """Occupied voxels a query needs."""
    fine_cells: int | None = Field(default=FINE_CELLS, ge=1)
    """Cells per voxel edge of the grid a dense query is down-sampled to first (None:
    never)."""
    pass_voxels: int = Field(default=32_000, ge=1)
    """Query voxels, over all headings, that one forward pass may describe (bounds its
    memory)."""


class ShortlistOptions(OptionGroup):
    """The shortlist (``engine.shortlist``, :mod:`~catalign.registration.stages.shortlist`)."""

    index_from: int | None = Field(default=5_000, ge=1)
    """Searched entries (the request's category's, or the library's) from which the shortlist
    scores only the index's nearest neighbours of the query and the unindexed entries, instead
    of every entry (None: always every entry; a library without an index is always scanned)."""
    index_candidates: int = Field(default=1_024, ge=1)
    """Neighbours the index gives per heading the query is described at, scored exactly."""
    fit_from: int | None = Field(default=100, ge=1)
    """Searched entries from which the best-scored are re-ranked by their outline fit (None:
    never): among fewer the descriptors' ``top_k`` already hold a view's own model."""
    fit_candidates: int | None = Field(default=300, ge=1)
    """The best-scored entries re-ranked by how well the view lies on their outlines before
    the ``top_k`` are kept (None: none, the scores alone rank)."""
    fit_weight: float = Field(default=20.0, ge=0)
    """Score lost per metre of a candidate's outline fit (the view's mean distance to it)."""


class MatchOptions(OptionGroup):
    """Matching the query's features to a model's (``engine.match``,
    :mod:`~catalign.registration.stages.match`)."""

    query_points: int | None = Field(default=500, ge=1)
    """Query key points that take part in matching (None: all)."""
    model_points: int | None = Field(default=STORED_KEYPOINTS, ge=1)
    """Each model's key points that take part in matching (None: all an entry keeps, which is
    this default); fewer matched points measured as accurate and a third faster
    (``bench/tradeoff.py``)."""
    keep_headings: int = Field(default=3, ge=1)
    """Headings that go through RANSAC, chosen on the ``heading_models`` best shortlisted
    models."""
    heading_models: int = Field(default=10, ge=1)
    """Best shortlisted models the headings are chosen on."""
    heading_draws: int = Field(default=300, ge=1)
    """With ``up``: pairs the two-point search draws on each of those models to rank a
    heading."""


class RansacOptions(OptionGroup):
    """The pose search from matches (``engine.ransac``,
    :mod:`~catalign.registration.stages.hypothesise`)."""

    factor: float = Field(default=2.0, gt=0, le=3.0)
    """RANSAC and verification inlier distance, in voxels; at most 3, where the library's
    distance grids (``catalign.geometry.distance_grid.TRUNCATION_VOXELS``) stop."""
    iterations: int = Field(default=5_000, ge=1)
    """Cap on draws of the three-point RANSAC (without ``up``, or with ``estimate_scale``)."""
    pair_draws: int = Field(default=3_000, ge=1)
    """Pairs the two-point search draws per candidate and heading."""
    poses_per_view: int = Field(default=8, ge=1)
    """Distinct poses the two-point search keeps per candidate and heading."""
    up_tolerance_deg: float = Field(default=30.0, gt=0, le=180)
    """How far the chair's up may tilt from the given ``up`` in the three-point search."""


class SweepOptions(OptionGroup):
    """The upright sweep (``engine.sweep``, :mod:`~catalign.registration.stages.sweep`)."""

    models: int = Field(default=10, ge=0)
    """With an up: the best shortlisted models whose poses are also searched from their
    surfaces alone, every yaw and shift on a grid (:mod:`~catalign.registration.stages.sweep`; 0:
    none): the observed chair's own CAD may match too poorly to be posed by its matches."""
    yaw_deg: float = Field(default=5.0, gt=0, le=90)
    """Step of the sweep's yaws (degrees)."""
    span_deg: float | None = Field(default=30.0, ge=0, le=180)
    """How far either side of each described heading the sweep's yaws reach (degrees; None:
    the whole turn)."""
    step: int = Field(default=2, ge=1)
    """Step of the sweep's shifts, in cells of the distance grids (half a voxel each)."""
    probes: int = Field(default=64, ge=3)
    """Query key points the sweep reads, of the probes verification uses."""
    shifts: int = Field(default=512, ge=1)
    """Most shifts the sweep tries at one yaw (the step grows for a view small in its box)."""
    poses: int = Field(default=2, ge=1)
    """Distinct poses of each swept model that go on to verification."""
    refine: int = Field(default=2, ge=0)
    """When no refined matched pose fits exactly: the best distinct swept answers that get
    ICP; those that then fit exactly are answers, the other swept poses are dropped."""


class VerifyOptions(OptionGroup):
    """Verifying poses and weighing them by the beliefs in their orientation (``engine.verify``,
    :mod:`~catalign.registration.stages.verify`)."""

    probe_points: int = Field(default=384, ge=1)
    """Query key points used to rank headings and to verify poses."""
    coverage_points: int = Field(default=1_500, ge=1)
    """Model surface points for the coverage check (and the model's extent in the category
    fit)."""
    coverage_cell: float = Field(default=0.5, gt=0, le=2.0)
    """Edge of the query's coverage grid, in voxels: its distance transform, built once per
    request, costs with the grid's cell count, and a posed point's coverage can be missed
    only within about a cell of the inlier distance. 0.75 saves a few milliseconds and lost
    a case at a few thresholds of the evaluation's three seeds."""
    top: int = Field(default=32, ge=1)
    """Poses, best by the surface check, that get the coverage check."""
    up_belief_power: float = Field(default=0.3, ge=0)
    """Without ``up``: a pose's verification score is multiplied by the proposal's belief in
    its up (probability mass) to this power (0: verification alone chooses the up)."""
    heading_belief_power: float = Field(default=0.3, ge=0)
    """A pose's verification score is multiplied by the heading network's belief in its
    heading (the mass of the proposed heading within half a proposal's width of it, else the
    mass no proposal holds) to this power (0: verification alone chooses the heading)."""


class IcpOptions(OptionGroup):
    """Refining poses by ICP (``engine.icp``, :mod:`~catalign.registration.stages.refine`)."""

    factor: float = Field(default=1.0, gt=0)
    """ICP inlier distance, in voxels."""
    iterations: int = Field(default=30, ge=1)
    """Gauss-Newton steps of each ICP pass, at most (a pose on the wrong model, or on another
    instance, can slide for many steps without converging)."""
    points: int | None = Field(default=600, ge=3)
    """Query key points ICP aligns, a fixed subset (None: all); 600 measured as accurate as all
    of them and a quarter faster (``bench/results/tradeoff-icp.md``)."""
    threads: int | None = Field(default=None, ge=1)
    """Threads each ICP pass and fit search uses (None: the worker's thread budget, as
    torch's); on two cores two threads measured a third faster than one
    (``bench/latency.py``)."""
    poses: int = Field(default=3, ge=1)
    """Best poses that get ICP (several starts of one answer find its best fit)."""


class DecisionOptions(OptionGroup):
    """Choosing the answer (``engine.decision``, :mod:`~catalign.registration.decision.rules`)."""

    alternatives: int = Field(default=3, ge=0)
    """Other distinct answers (another model, or the same one turned more than 30 degrees)
    returned beside the winner; the best pose of each also gets ICP."""
    confidence_margin: float | None = Field(default=0.2, ge=0)
    """An alternative whose confidence beats the winner's by more than this becomes the answer
    (None: the verification score alone decides). The calibrated probability of being right
    weighs more evidence than the score the answers were ranked by. 0.2 gains nearly as much
    as the best margin on the evaluation's seeds 0 and 1 (0.1), and keeps a moved real scan's
    answer, which 0.1 flips (``docs/evaluation.md``)."""
    exact_fitness: float = Field(default=0.9, ge=0, le=1)
    """The share of the query within one ICP distance of the model above which the model is
    taken to be the observed instance itself, and its fitted pose is not recentred."""
    sure_fitness: float = Field(default=0.95, ge=0, le=1)
    """The share above which a fit is sure: below it, an exact fit may be the observed
    instance turned the wrong way (a view of the underside fits so), and the swept poses are
    refined too; an answer that fits surely beats one that fits only exactly. At
    ``exact_fitness`` or below, every exact fit is sure. 0.95 gained 2 *same* views within 10
    degrees with ``up`` and without (of 108, seeds 0 and 1), lost none (seed 3 too)."""
    fit_margin: float | None = Field(default=0.02, ge=0, le=1)
    """Among answers that fit surely (else exactly), only those within this of the closest fit
    compete on score (None: all): a near twin fits surely too, the own model more closely
    (``docs/evaluation.md``, the closest of the sure fits)."""
    heading_fallback: float = Field(default=0.7, ge=0, le=1)
    """With ``heading_mass`` (or ``up_mass``): the confidence below which an answer found at
    the confident headings (or ups) alone sends the query to a search at every proposed
    heading under every proposed up (0: never; always without a calibrator)."""


# The flat option names of earlier releases, and where each now lives in the tree.
FLAT_NAMES: dict[str, tuple[str, str]] = {
    "headings": ("orient", "headings"),
    "up_proposals": ("orient", "up_proposals"),
    "up_mass": ("orient", "up_mass"),
    "up_snap_deg": ("orient", "up_snap_deg"),
    "heading_proposals": ("orient", "heading_proposals"),
    "heading_mass": ("orient", "heading_mass"),
    "min_points": ("input", "min_points"),
    "fine_cells": ("input", "fine_cells"),
    "pass_voxels": ("input", "pass_voxels"),
    "match_points": ("match", "query_points"),
    "model_points": ("match", "model_points"),
    "keep_headings": ("match", "keep_headings"),
    "heading_models": ("match", "heading_models"),
    "heading_draws": ("match", "heading_draws"),
    "ransac_factor": ("ransac", "factor"),
    "ransac_iterations": ("ransac", "iterations"),
    "pair_draws": ("ransac", "pair_draws"),
    "poses_per_view": ("ransac", "poses_per_view"),
    "up_tolerance_deg": ("ransac", "up_tolerance_deg"),
    "sweep_models": ("sweep", "models"),
    "sweep_yaw_deg": ("sweep", "yaw_deg"),
    "sweep_span_deg": ("sweep", "span_deg"),
    "sweep_step": ("sweep", "step"),
    "sweep_probes": ("sweep", "probes"),
    "sweep_shifts": ("sweep", "shifts"),
    "sweep_poses": ("sweep", "poses"),
    "sweep_refine": ("sweep", "refine"),
    "probe_points": ("verify", "probe_points"),
    "coverage_points": ("verify", "coverage_points"),
    "coverage_cell": ("verify", "coverage_cell"),
    "verify_top": ("verify", "top"),
    "up_belief_power": ("verify", "up_belief_power"),
    "heading_belief_power": ("verify", "heading_belief_power"),
    "icp_factor": ("icp", "factor"),
    "icp_iterations": ("icp", "iterations"),
    "icp_points": ("icp", "points"),
    "refine": ("icp", "poses"),
    "alternatives": ("decision", "alternatives"),
    "confidence_margin": ("decision", "confidence_margin"),
    "exact_fitness": ("decision", "exact_fitness"),
    "sure_fitness": ("decision", "sure_fitness"),
    "heading_fallback": ("decision", "heading_fallback"),
}


class EngineConfig(BaseModel):
    """Every option of the query engine, as a tree of groups; the defaults are the measured
    ones (``bench/tradeoff.py`` compares alternatives on the evaluation's cases)."""

    model_config = ConfigDict(
        extra="forbid",
        frozen=True,
        use_attribute_docstrings=True,
        json_schema_extra=one_line_descriptions,
    )

    top_k: int | None = Field(default=10, ge=1)
    """Default shortlist size: library models registered per query (None: every entry)."""
    model_cache: int | None = Field(default=256, ge=1)
    """Models whose pieces each stage keeps once computed (matching subset, surface check, ICP
    surface: about 1.1 MB a model), the least recently used dropped first (None: every model
    asked about; bounds a worker's memory on a large library)."""
    input: InputOptions = InputOptions()
    """What a query must hold and how it is fed to the network."""
    shortlist: ShortlistOptions = ShortlistOptions()
    """Which entries the shortlist scores."""
    orient: OrientOptions = OrientOptions()
    """Which ways up and which headings the query is searched at."""
    floor: FloorOptions = FloorOptions()
    """Finding the floor under the object, set aside before the features."""
    cleanup: CleanupOptions = CleanupOptions()
    """Finding small clusters detached from the object, set aside before the features."""
    match: MatchOptions = MatchOptions()
    """Matching features."""
    ransac: RansacOptions = RansacOptions()
    """The pose search from matches."""
    sweep: SweepOptions = SweepOptions()
    """The upright sweep."""
    verify: VerifyOptions = VerifyOptions()
    """Verification."""
    icp: IcpOptions = IcpOptions()
    """Refinement."""
    decision: DecisionOptions = DecisionOptions()
    """The choice of the answer."""

    def replaced(self, **options: Any) -> EngineConfig:
        """A copy with ``options`` changed and validated (unlike ``model_copy``): groups as
        mappings of their changed fields (``sweep={"models": 0}``) or flat names of earlier
        releases (``sweep_models=0``)."""
        return _validated(merged(self.model_dump(exclude_unset=True), options))

    @model_validator(mode="before")
    @classmethod
    def _tree_from_flat_names(cls, data: Any) -> Any:
        """Options under their flat names of earlier releases, moved to their place in the
        tree (a group given as a model is kept, its set fields only)."""
        if not isinstance(data, Mapping) or not FLAT_NAMES.keys() & data.keys():
            return data
        tree = dict(data)
        for name in FLAT_NAMES.keys() & data.keys():
            group, field = FLAT_NAMES[name]
            given = tree.get(group, {})
            if isinstance(given, BaseModel):
                given = given.model_dump(exclude_unset=True)
            tree[group] = {**given, field: tree.pop(name)}
        return tree


def option_names() -> list[str]:
    """Every option's dotted name (``sweep.models``), in the tree's order."""
    names = []
    for name, info in EngineConfig.model_fields.items():
        group = info.annotation
        if isinstance(group, type) and issubclass(group, OptionGroup):
            names += [f"{name}.{field}" for field in group.model_fields]
        else:
            names.append(name)
    return names


def parse_options(options: Iterable[str], base: EngineConfig | None = None) -> EngineConfig:
    """``base`` (the defaults when None) with the options named in ``name=value`` replaced
    (``sweep.models=0``; a flat name of earlier releases works too; ``none`` for None, numbers
    as numbers): what the CLI's ``--engine`` and ``bench/tradeoff.py`` take. The fields counted
    as set are ``base``'s and the options'. An unknown option or a bad value raises
    :class:`ConfigError` saying which."""
    fields: dict[str, Any] = {}
    for option in options:
        name, equals, value = (part.strip() for part in option.partition("="))
        if not name or not equals or not value:
            raise ConfigError(f"engine option {option!r} is not NAME=VALUE (e.g. sweep.models=0)")
        parsed: Any = None
        if value.lower() != "none":
            try:
                number = float(value)
            except ValueError:
                raise ConfigError(f"engine option {option!r}: {value!r} is not a number") from None
            parsed = int(number) if number.is_integer() else number
        fields = merged(fields, _nested(name.split("."), parsed))
    return _validated(merged((base or EngineConfig()).model_dump(exclude_unset=True), fields))


def served_config(service: EngineConfig, library: Mapping[str, Any]) -> EngineConfig:
    """The options a server runs a library with: the library's own (its manifest's
    ``engine``), overridden by the fields the service sets (``CATALIGN_ENGINE__*``, then
    ``--engine``); the defaults for the rest. A bad library option raises
    :class:`ConfigError` saying which."""
    own = _validated(dict(library)).model_dump(exclude_unset=True)
    return _validated(merged(own, service.model_dump(exclude_unset=True)))


def stored_options(current: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """A library's options (its manifest's ``engine``) with ``changes`` applied, as the tree
    of the fields set: flat names of earlier releases moved into it, groups merged field by
    field, everything validated (:class:`ConfigError` saying what is wrong)."""
    own = _validated(dict(current)).model_dump(exclude_unset=True)
    return _validated(merged(own, changes)).model_dump(exclude_unset=True)


def merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over``'s values, group by group (a nested mapping is merged, not
    replaced)."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merged(out[key], value)
        else:
            out[key] = value
    return out


def _nested(path: list[str], value: Any) -> dict[str, Any]:
    """``{"a": {"b": value}}`` for the path ``["a", "b"]``."""
    return {path[0]: value} if len(path) == 1 else {path[0]: _nested(path[1:], value)}


def _validated(fields: Mapping[str, Any]) -> EngineConfig:
    """``fields`` as a configuration (the others at their defaults, and not counted as set);
    :class:`ConfigError` naming the first unknown option or bad value."""
    try:
        return EngineConfig.model_validate(fields)
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(map(str, first["loc"])) or "engine"
        if first["type"] == "extra_forbidden":
            group = f"{first['loc'][0]}." if len(first["loc"]) > 1 else ""
            known = [name for name in option_names() if name.startswith(group)]
            if not group:
                known = [name for name in EngineConfig.model_fields]
            listed = ", ".join(known)
            what = f"the {group[:-1]} options" if group else "the options and groups"
            raise ConfigError(f"unknown engine option {where!r}; {what}: {listed}") from None
        raise ConfigError(f"engine option {where}: {first['msg']}") from None
