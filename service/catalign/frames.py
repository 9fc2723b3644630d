"""The canonical frame that library models share, defined once for every stage that needs it.

Library shapes of a category share one canonical orientation (ShapeNet's: +Y up), which is what
makes category-level poses and NCC positives meaningful. Registration levels queries onto it,
verification finds where a chair's back leans across it, and training turns shapes about it;
each imports it from here (the viewer's ``viewer.js`` repeats it in JavaScript). The module
imports nothing but numpy, so that no stage pulls in another's dependencies to learn it.
"""

from __future__ import annotations

import numpy as np

# The models' up axis (read-only, so that no caller can change it for every other).
MODEL_UP = np.array([0.0, 1.0, 0.0])
MODEL_UP.flags.writeable = False
