"""Fuzzing the mesh readers behind the header checks: OBJ, STL (binary and ASCII), OFF and GLB.

Inputs are valid files of a 42-vertex sphere (trimesh's own STL and GLB writers, OBJ with
absolute and negative indices, OFF with the counts on their own line or on the OFF line) put
through the mutators of ``_kit.py``; GLB also has its JSON chunk edited and the container rebuilt
with true lengths, so the edits reach the accessor checks. Property: finite (N, 3) points within
the limit and faces that index existing vertices, or the project's own error; never another
exception, a hang or a huge allocation.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.fuzz._kit import TARGETS, glb_seeds, obj_seeds, off_seeds, run_target, stl_seeds

FUZZ = settings(max_examples=500, deadline=None, derandomize=True, database=None)
SEEDS = {"obj": obj_seeds, "stl": stl_seeds, "off": off_seeds, "glb": glb_seeds}


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-mesh")


@pytest.mark.parametrize("name", sorted(SEEDS))
def test_every_seed_reads_as_points(name: str, folder: Path) -> None:
    for seed in SEEDS[name]():
        assert run_target(TARGETS[name], seed, folder) >= 42


@pytest.mark.parametrize("name", sorted(SEEDS))
@FUZZ
@given(rng=st.randoms(use_true_random=False))
def test_reads_points_or_refuses(name: str, rng: random.Random, folder: Path) -> None:
    run_target(TARGETS[name], TARGETS[name].generate(rng), folder)
