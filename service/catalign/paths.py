"""Where the repository keeps its shipped artifacts, defined once for the server and the tools.

The trained weights, their model card and the default library live in ``model_store/`` at the
repository root. Both the feature extractor (torch) and the service's settings (no torch) need
that folder, so it is defined here, in a module that imports nothing heavy.
"""

from __future__ import annotations

from pathlib import Path

# The repository's model_store/ (service/catalign/paths.py -> the repository root).
DEFAULT_MODEL_DIR = Path(__file__).resolve().parents[2] / "model_store"
# Beside the general companions of the weights (``orientation/``, ``confidence/``), a weights
# folder may hold a category's own: ``categories/<name>/orientation/`` and
# ``categories/<name>/confidence/``, used where a query is answered from that category alone.
CATEGORIES_DIR = "categories"


def category_companions(model_dir: Path) -> dict[str, list[str]]:
    """The categories with companions of their own in ``model_dir`` and which (``orientation``,
    ``confidence``), by category name: what ``/info`` reports beside the model card."""
    root = model_dir / CATEGORIES_DIR
    folders = sorted(f for f in root.iterdir() if f.is_dir()) if root.is_dir() else []
    return {f.name: sorted(p.name for p in f.iterdir() if p.is_dir()) for f in folders}
