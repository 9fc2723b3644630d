"""What ``GET /info`` answers: the weights, the library and the engine options a server runs
with, and the versions of what it runs on."""

from __future__ import annotations

import platform
from typing import TYPE_CHECKING

import numpy as np

import catalign
from catalign.api.schemas import InfoResponse, LibraryInfo, Versions
from catalign.api.settings import ServiceSettings
from catalign.paths import category_companions
from catalign.registration.config import served_config

if TYPE_CHECKING:
    from catalign.features.extractor import LearnedExtractor
    from catalign.library.loaded import Library


def service_info(
    settings: ServiceSettings, extractor: LearnedExtractor, library: Library
) -> InfoResponse:
    """The answer of ``GET /info`` for a server of ``settings`` serving ``library``."""
    import open3d
    import torch

    manifest = library.manifest
    config = served_config(settings.engine, manifest.engine)
    headings = config.orient.headings or extractor.headings
    return InfoResponse(
        version=catalign.__version__,
        model_card=extractor.card,
        categories=category_companions(extractor.model_dir),
        library=LibraryInfo(
            path=str(settings.library),
            format_version=manifest.format_version,
            models=len(library),
            fingerprint=manifest.fingerprint,
            updated=manifest.updated,
            indexed=0 if library.index is None else library.index.indexed,
            unindexed=len(library) if library.index is None else library.index.unindexed,
            engine=manifest.engine,
        ),
        voxel_size=extractor.voxel_size,
        headings=headings,
        engine=config.model_copy(
            update={"orient": config.orient.model_copy(update={"headings": headings})}
        ),
        versions=Versions(
            python=platform.python_version(),
            torch=str(torch.__version__),
            open3d=str(open3d.__version__),
            numpy=np.__version__,
        ),
    )
