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
