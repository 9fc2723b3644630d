"""The engine's configuration: one typed, frozen model of every knob of every stage.

:class:`EngineConfig` is validated once, where it enters (the service's settings, a benchmark's
command line, a test), and the engine turns it into plain keyword arguments of its stages, so
no configuration object travels below :class:`~catalign.registration.engine.Engine`. It imports
nothing heavy (no torch, no open3d): the API's settings embed it, and ``/info`` reports it.
:func:`from_config` builds a stage whose options are named as the configuration's fields.
Each field's docstring is its documentation (also in the JSON schema); an unknown field is
refused, so a typo in ``CATALIGN_ENGINE__<FIELD>`` or a benchmark's ``name=value`` fails loudly.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from catalign.errors import ConfigError
from catalign.registration.prepare.validation import FINE_CELLS, MIN_VOXELS

Stage = TypeVar("Stage")


def _one_line_descriptions(schema: dict[str, Any]) -> None:
    """Docstrings wrap at the source's line length; the JSON schema (``/info``,
    ``openapi.yaml``) gets each as one line."""
    for part in [schema, *schema.get("properties", {}).values()]:
        if "description" in part:
            part["description"] = " ".join(part["description"].split())


class EngineConfig(BaseModel):
    """Every option of the query engine; the defaults are the measured ones
    (``bench/tradeoff.py`` compares alternatives on the evaluation's cases)."""

    model_config = ConfigDict(
        extra="forbid",
        frozen=True,
        use_attribute_docstrings=True,
        json_schema_extra=_one_line_descriptions,
    )

    headings: int | None = Field(default=None, ge=1)
    """Headings the query is described at (None: the extractor's, 8 for ``yaw-bin`` models,
    else 1)."""
    top_k: int | None = Field(default=10, ge=1)
    """Default shortlist size: library models registered per query (None: every entry)."""
    ransac_factor: float = Field(default=2.0, gt=0, le=3.0)
    """RANSAC and verification inlier distance, in voxels; at most 3, where the library's
    distance grids (``catalign.geometry.distance_grid.TRUNCATION_VOXELS``) stop."""
    icp_factor: float = Field(default=1.0, gt=0)
    """ICP inlier distance, in voxels."""
    icp_iterations: int = Field(default=30, ge=1)
    """Gauss-Newton steps of each ICP pass, at most (a pose on the wrong model, or on another
    instance, can slide for many steps without converging)."""
    icp_points: int | None = Field(default=600, ge=3)
    """Query key points ICP aligns, a fixed subset (None: all); 600 measured as accurate as all
    of them and a quarter faster (``bench/results/tradeoff-icp.md``)."""
    up_tolerance_deg: float = Field(default=30.0, gt=0, le=180)
    """How far the chair's up may tilt from the given ``up`` in the three-point search."""
    up_snap_deg: float | None = Field(default=None, gt=0, le=30)
    """With ``up`` given, snap it to the largest plane within this many degrees of it (a seat,
    the floor), as proposed ups are: for an up known to a few degrees only (an imprecise IMU).
    Off by default: a seat may slope a few degrees, and snapping an exact up to it costs about
    4 of 108 *same* views within 10 degrees; an up 5 or 10 degrees off gains 4 and 17 of them
    (docs/evaluation.md, "An imprecise up")."""
    min_points: int = Field(default=MIN_VOXELS, ge=1)
    """Occupied voxels a query needs."""
    up_proposals: int = Field(default=3, ge=1)
    """Without ``up``: proposed up directions the gravity-aware search runs under (the best
    verified pose wins)."""
    up_mass: float | None = Field(default=0.5, gt=0, le=1)
    """Without ``up``: a further proposed up is searched at first only while the ones before
    it hold less than this probability mass (None: always ``up_proposals``; a floor found under
    the cloud holds it all): a confident up network then costs one up's search instead of
    three; when the answer's confidence is below ``heading_fallback``, the query is searched
    again under every proposed up."""
    up_belief_power: float = Field(default=0.3, ge=0)
    """Without ``up``: a pose's verification score is multiplied by the proposal's belief in
    its up (probability mass) to this power (0: verification alone chooses the up)."""
    heading_belief_power: float = Field(default=0.3, ge=0)
    """A pose's verification score is multiplied by the heading network's belief in its
    heading (the mass of the proposed heading within half a proposal's width of it, else the
    mass no proposal holds) to this power (0: verification alone chooses the heading)."""
    heading_proposals: int | None = Field(default=2, ge=1)
    """Proposed headings the query is described at, under each up (None: every heading of
    the extractor)."""
    heading_mass: float | None = Field(default=0.95, gt=0, le=1)
    """A further heading proposal is described at first only while the ones before it hold
    less than this probability mass (None: always ``heading_proposals``): a confident heading
    network then costs one heading's features, matching and verification instead of two; when
    the answer's confidence is below ``heading_fallback``, the query is searched again at every
    proposed heading. About 0.85x the time on the evaluation's *same* views and 0.97x on
    *cross* ones, which fall back more often (``docs/benchmarks.md``)."""
    heading_fallback: float = Field(default=0.7, ge=0, le=1)
    """With ``heading_mass`` (or ``up_mass``): the confidence below which an answer found at
    the confident headings (or ups) alone sends the query to a search at every proposed
    heading under every proposed up (0: never; always without a calibrator)."""
    keep_headings: int = Field(default=3, ge=1)
    """Headings that go through RANSAC, chosen on the ``heading_models`` best shortlisted
    models."""
    heading_models: int = Field(default=10, ge=1)
    """Best shortlisted models the headings are chosen on."""
    heading_draws: int = Field(default=300, ge=1)
    """With ``up``: pairs the two-point search draws on each of those models to rank a
    heading."""
    ransac_iterations: int = Field(default=5_000, ge=1)
    """Cap on draws of the three-point RANSAC (without ``up``, or with ``estimate_scale``)."""
    pair_draws: int = Field(default=3_000, ge=1)
    """Pairs the two-point search draws per candidate and heading."""
    poses_per_view: int = Field(default=8, ge=1)
    """Distinct poses the two-point search keeps per candidate and heading."""
    probe_points: int = Field(default=384, ge=1)
    """Query key points used to rank headings and to verify poses."""
    coverage_points: int = Field(default=1_500, ge=1)
    """Model surface points for the coverage check (and the model's extent in the category
    fit)."""
    match_points: int | None = Field(default=500, ge=1)
    """Query key points that take part in matching (None: all)."""
    model_points: int | None = Field(default=1_000, ge=1)
    """Each model's key points that take part in matching (None: all); fewer matched points
    measured as accurate and a third faster (``bench/tradeoff.py``)."""
    coverage_cell: float = Field(default=0.5, gt=0, le=2.0)
    """Edge of the query's coverage grid, in voxels: its distance transform, built once per
    request, costs with the grid's cell count, and a posed point's coverage can be missed
    only within about a cell of the inlier distance. 0.75 saves a few milliseconds and lost
    a case at a few thresholds of the evaluation's three seeds."""
    verify_top: int = Field(default=32, ge=1)
    """Poses, best by the surface check, that get the coverage check."""
    sweep_models: int = Field(default=10, ge=0)
    """With an up: the best shortlisted models whose poses are also searched from their
    surfaces alone, every yaw and shift on a grid (:mod:`~catalign.registration.stages.sweep`; 0:
    none): the observed chair's own CAD may match too poorly to be posed by its matches."""
    sweep_yaw_deg: float = Field(default=5.0, gt=0, le=90)
    """Step of the sweep's yaws (degrees)."""
    sweep_span_deg: float | None = Field(default=30.0, ge=0, le=180)
    """How far either side of each described heading the sweep's yaws reach (degrees; None:
    the whole turn)."""
    sweep_step: int = Field(default=2, ge=1)
    """Step of the sweep's shifts, in cells of the library's distance grids (half a voxel
    each)."""
    sweep_probes: int = Field(default=64, ge=3)
    """Query key points the sweep reads, of the probes verification uses."""
    sweep_shifts: int = Field(default=512, ge=1)
    """Most shifts the sweep tries at one yaw (the step grows for a view small in its model's
    box)."""
    sweep_poses: int = Field(default=2, ge=1)
    """Distinct poses of each swept model that go on to verification."""
    sweep_refine: int = Field(default=2, ge=0)
    """When no refined matched pose fits exactly: the best distinct swept answers that get
    ICP; those that then fit exactly are answers, the other swept poses are dropped."""
    refine: int = Field(default=3, ge=1)
    """Best poses that get ICP (several starts of one answer find its best fit)."""
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
    fine_cells: int | None = Field(default=FINE_CELLS, ge=1)
    """Cells per voxel edge of the grid a dense query is down-sampled to first (None:
    never)."""
    pass_voxels: int = Field(default=32_000, ge=1)
    """Query voxels, over all headings, that one forward pass may describe (bounds its
    memory)."""
    model_cache: int | None = Field(default=256, ge=1)
    """Models whose pieces each stage keeps once computed (matching subset, surface check, ICP
    surface: about 1.1 MB a model), the least recently used dropped first (None: every model
    asked about; bounds a worker's memory on a large library)."""


def parse_options(options: Iterable[str], base: EngineConfig | None = None) -> EngineConfig:
    """``base`` (the defaults when None) with the fields named in ``name=value`` options
    replaced (``none`` for None, numbers as numbers): what the CLI's ``--engine`` and
    ``bench/tradeoff.py`` take. The fields counted as set are ``base``'s and the options'. An
    unknown field or a bad value raises :class:`ConfigError` saying which."""
    fields: dict[str, Any] = {}
    for option in options:
        name, equals, value = (part.strip() for part in option.partition("="))
        if not name or not equals or not value:
            raise ConfigError(f"engine option {option!r} is not NAME=VALUE (e.g. top_k=5)")
        if value.lower() == "none":
            fields[name] = None
            continue
        try:
            number = float(value)
        except ValueError:
            raise ConfigError(f"engine option {option!r}: {value!r} is not a number") from None
        fields[name] = int(number) if number.is_integer() else number
    return _validated((base or EngineConfig()).model_dump(exclude_unset=True) | fields)


def served_config(service: EngineConfig, library: Mapping[str, Any]) -> EngineConfig:
    """The options a server runs a library with: the library's own (its manifest's
    ``engine``), overridden by the fields the service sets (``CATALIGN_ENGINE__*``, then
    ``--engine``); the defaults for the rest. A bad library option raises
    :class:`ConfigError` saying which."""
    return _validated(dict(library) | service.model_dump(exclude_unset=True))


def _validated(fields: dict[str, Any]) -> EngineConfig:
    """``fields`` as a configuration (the others at their defaults, and not counted as set);
    :class:`ConfigError` naming the first unknown field or bad value."""
    try:
        return EngineConfig.model_validate(fields)
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(map(str, first["loc"])) or "engine"
        if first["type"] == "extra_forbidden":
            known = ", ".join(EngineConfig.model_fields)
            raise ConfigError(f"unknown engine option {where!r}; the options: {known}") from None
        raise ConfigError(f"engine option {where}: {first['msg']}") from None


def from_config(
    stage: Callable[..., Stage], config: EngineConfig, /, *args: Any, **given: Any
) -> Stage:
    """``stage(*args, **given)``, each of its other keyword-only options taken from the
    ``config`` field of the same name. A stage names its options as the configuration does;
    what it needs beyond them (the library, distances in metres) the caller gives. An option
    that is neither given nor a field fails loudly (AttributeError)."""
    options = inspect.signature(stage).parameters.values()
    taken = {
        option.name: getattr(config, option.name)
        for option in options
        if option.kind is option.KEYWORD_ONLY and option.name not in given
    }
    return stage(*args, **given, **taken)
