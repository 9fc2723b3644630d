"""Pictures of an alignment: the observation and the posed model in three orthographic views.

A number such as ``fitness 0.91`` does not tell an operator whether the chair was found upside
down or half a metre off; a picture does, at a glance. Three orthographic projections (top, front
and side around the request's up direction, or x-y, x-z and y-z without one) show every axis of
the pose without a 3D viewer. matplotlib is an optional extra (``catalign-client[plot]``) and is
imported only here, only when a picture is asked for, so the SDK itself stays httpx and numpy.
Figures are built with matplotlib's object API on an Agg canvas: no pyplot state, no display
needed, nothing kept alive after the caller drops the figure.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from ._points import PointsLike, as_points

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ._models import AlignResult

INSTALL_HINT = 'pip install "catalign-client[plot]"'
_OBSERVED_COLOUR = "tab:blue"
_MODEL_COLOUR = "tab:orange"
_MAX_DRAWN = 20_000  # points per cloud and view; more only slows drawing down
_DPI = 120


class ViewAxis(NamedTuple):
    """One screen axis of a view: the direction it shows, and its label."""

    vector: np.ndarray
    label: str


class View(NamedTuple):
    """One orthographic view: its title and the two directions across and up the screen."""

    name: str
    horizontal: ViewAxis
    vertical: ViewAxis


def require_matplotlib() -> tuple[Any, Any]:
    """``(Figure, FigureCanvasAgg)``, or an ImportError that says how to install matplotlib."""
    try:
        import matplotlib  # noqa: F401  (first: a blocked or missing package fails here)
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise ImportError(f"plotting needs matplotlib: {INSTALL_HINT}") from exc
    return Figure, FigureCanvasAgg


def plot_alignment(
    result: AlignResult,
    observed: PointsLike,
    model_points: PointsLike,
    path: str | Path | None = None,
    *,
    title: str | None = None,
) -> Figure:
    """See :meth:`AlignResult.plot`."""
    figure_class, canvas_class = require_matplotlib()
    cloud = as_points(observed)
    posed = as_points(model_points) @ result.pose[:3, :3].T + result.pose[:3, 3]

    figure = figure_class(figsize=(13, 4.8), layout="constrained")
    canvas_class(figure)  # Agg: renders to files and notebooks without a display
    for ax, view in zip(figure.subplots(1, 3), views(result.up), strict=True):
        for points, colour, label, size in (
            (posed, _MODEL_COLOUR, f"{result.model_id} (posed, {len(posed)} points)", 1.5),
            (cloud, _OBSERVED_COLOUR, f"observed ({len(cloud)} points)", 2.5),
        ):
            shown = _thin(points)
            ax.scatter(
                shown @ view.horizontal.vector,
                shown @ view.vertical.vector,
                s=size,
                c=colour,
                alpha=0.6,
                linewidths=0,
                label=label,
                rasterized=True,
            )
        ax.set_title(view.name)
        ax.set_xlabel(view.horizontal.label)
        ax.set_ylabel(view.vertical.label)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    figure.legend(
        *figure.axes[0].get_legend_handles_labels(),
        loc="outside lower center",
        ncols=2,
        markerscale=5,
        frameon=False,
    )
    heading = (
        f"{result.model_id}: fitness {result.fitness:.3f}, inlier RMSE {result.inlier_rmse:.4f}"
    )
    figure.suptitle(f"{title}\n{heading}" if title else heading)
    if path is not None:
        figure.savefig(Path(path), dpi=_DPI)
    return figure


def views(up: Sequence[float] | None = None) -> list[View]:
    """Top, front and side around ``up``; x-y, x-z and y-z without it.

    The horizontal axes are the coordinate axis least aligned with ``up``, made perpendicular to
    it, and ``up x`` that one, so that the top view looks down on a right-handed frame.
    """
    eye = np.eye(3)
    if up is None:
        x, y, z = (ViewAxis(eye[i], "xyz"[i]) for i in range(3))
        return [View("x-y", x, y), View("x-z", x, z), View("y-z", y, z)]
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    first = eye[int(np.argmin(np.abs(u)))]
    first = first - (first @ u) * u
    first /= np.linalg.norm(first)
    second = np.cross(u, first)
    a, b, vertical = (ViewAxis(v, _label(v)) for v in (first, second, u))
    return [View("top", a, b), View("front", a, vertical), View("side", b, vertical)]


def _label(vector: np.ndarray) -> str:
    """``"x"``, ``"-y"`` for a coordinate axis, else the direction's components."""
    for index, name in enumerate("xyz"):
        if abs(abs(vector[index]) - 1.0) < 1e-9:
            return name if vector[index] > 0 else f"-{name}"
    return "(" + ", ".join(f"{v:.2f}" for v in vector) + ")"


def _thin(points: np.ndarray) -> np.ndarray:
    """At most ``_MAX_DRAWN`` points, evenly strided."""
    return points[:: -(-len(points) // _MAX_DRAWN)]
