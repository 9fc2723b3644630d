from __future__ import annotations

import pytest

from catalign.errors import InvalidInputError, ShapeReadError
from catalign.library.sources import (
    collect_sources,
    unit_factor,
    validate_model_id,
)


def test_folders_are_searched_recursively_and_ids_are_stems(mixed_folder):
    found = collect_sources([mixed_folder])
    assert sorted(s.model_id for s in found) == [
        "big",
        "box",
        "capsule",
        "cone",
        "cylinder",
        "points",
        "scan",
        "scan2",
        "sphere",
    ]
    assert all(s.path.is_file() and s.path.stem == s.model_id for s in found)


def test_files_and_explicit_ids(files):
    a, b = files.cloud("a.npy"), files.box("b.obj")
    found = collect_sources([a, b], ids=["chair-1", "chair_2.v3"])
    assert [(s.model_id, s.path) for s in found] == [("chair-1", a), ("chair_2.v3", b)]


def test_duplicate_ids_name_both_files(files):
    first = files.cloud("one/chair.npy")
    second = files.box("two/chair.obj")
    with pytest.raises(InvalidInputError, match="'chair'") as caught:
        collect_sources([files.root])
    assert str(first) in str(caught.value) and str(second) in str(caught.value)


def test_the_same_file_twice_is_refused(files):
    path = files.cloud("chair.npy")
    with pytest.raises(InvalidInputError, match="listed twice"):
        collect_sources([path, files.root])


@pytest.mark.parametrize("bad", ["../x", "a/b", ".hidden", "..evil", "", "x" * 129, "a b", "é"])
def test_bad_ids_are_refused(files, bad):
    path = files.cloud("fine.npy")
    with pytest.raises(InvalidInputError, match="not a valid model id"):
        collect_sources([path], ids=[bad])


def test_a_file_whose_stem_is_not_an_id_is_refused(files):
    path = files.cloud("..evil.npy")
    with pytest.raises(InvalidInputError, match="not a valid model id") as caught:
        collect_sources([path])
    assert str(path) in str(caught.value)


def test_validate_model_id_accepts_the_pattern():
    for good in ("a", "A9", "chair-01_v2.final", "0" * 128):
        assert validate_model_id(good) == good


def test_argument_errors(files):
    path = files.cloud("a.npy")
    with pytest.raises(InvalidInputError, match="2 ids given for 1 sources"):
        collect_sources([path], ids=["a", "b"])
    with pytest.raises(InvalidInputError, match="is a folder"):
        collect_sources([files.root], ids=["a"])
    with pytest.raises(InvalidInputError, match="no sources"):
        collect_sources([])
    (files.root / "notes.txt").write_text("x")
    with pytest.raises(InvalidInputError, match=r"unsupported file type .txt"):
        collect_sources([files.root / "notes.txt"])
    (files.root / "empty").mkdir()
    with pytest.raises(InvalidInputError, match="holds no supported shape files"):
        collect_sources([files.root / "empty"])
    with pytest.raises(ShapeReadError, match="no such file or folder"):
        collect_sources([files.root / "missing.obj"])


def test_units():
    assert unit_factor("m") == 1.0
    assert unit_factor("cm") == 0.01
    assert unit_factor("mm") == 0.001
    with pytest.raises(InvalidInputError, match="unknown units 'inch'"):
        unit_factor("inch")
