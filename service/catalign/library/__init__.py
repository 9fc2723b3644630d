"""The CAD library index: shapes described once, stored crash-safely, loaded for registration.

Build a library from mesh and point-cloud files (or procedural chairs), extend or prune it, and
load it with checksum and extractor checks; :func:`shortlist` then picks the entries worth
registering a query against. Coordinates are stored in metres: a library built with
``units="mm"`` holds ``source * 0.001``, and poses map those coordinates into the observation.

    build(["cad/"], "lib", extractor, units="mm")
    library = load("lib", extractor.fingerprint)
    ids = shortlist(library, global_descriptor(features), np.ptp(points, axis=0), k=5)
"""

from catalign.library.entry import SURFACE_POINTS, LibraryEntry
from catalign.library.index import add, build, build_procedural, info, list_models, remove
from catalign.library.loaded import Library, load
from catalign.library.retrieval import global_descriptor, retrieval_scores, shortlist
from catalign.library.sources import MODEL_ID_PATTERN, UNIT_FACTORS, validate_model_id
from catalign.library.store import FORMAT_VERSION, EntryRecord, Manifest

__all__ = [
    "FORMAT_VERSION",
    "MODEL_ID_PATTERN",
    "SURFACE_POINTS",
    "UNIT_FACTORS",
    "EntryRecord",
    "Library",
    "LibraryEntry",
    "Manifest",
    "add",
    "build",
    "build_procedural",
    "global_descriptor",
    "info",
    "list_models",
    "load",
    "remove",
    "retrieval_scores",
    "shortlist",
    "validate_model_id",
]
