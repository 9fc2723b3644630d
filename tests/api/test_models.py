"""Library changes through the API: added and removed models are served at once and persist."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np
import pytest
import trimesh

from catalign.api import service as service_module
from catalign.api.service import RegistrationService
from catalign.data.shapes import procedural_shape
from catalign.library.index import remove

if TYPE_CHECKING:
    from tests.api.conftest import View


def _ply_of_chair(seed: int) -> bytes:
    mesh = procedural_shape(seed).mesh
    assert mesh is not None
    return trimesh.exchange.ply.export_ply(trimesh.Trimesh(mesh.vertices, mesh.faces))


def test_added_and_removed_models_are_served_and_persist(
    serve: Callable, library_copy: Path, views: Callable[..., View]
) -> None:
    upload = {"file": ("chair seven.ply", _ply_of_chair(7))}
    with (
        serve(library=library_copy, warmup=False) as server,
        httpx.Client(base_url=server.url, timeout=120) as http,
    ):
        catalogue = (library_copy / "catalogue.sqlite").read_bytes()
        for fields in ({"model_id": ".hidden"}, {"units": "furlongs"}):
            refused = http.post("/models", files=upload, data=fields)
            assert refused.status_code == 422, fields
            assert refused.json()["error"]["code"] == "invalid_input"
        assert (library_copy / "catalogue.sqlite").read_bytes() == catalogue

        added = http.post("/models", files=upload, data={"model_id": "chair-7"})
        assert added.status_code == 201, added.text
        model = added.json()
        assert model["model_id"] == "chair-7" and model["units"] == "m"
        assert model["source"] == "upload:chair seven.ply"  # not the temporary file
        extent = np.ptp(procedural_shape(7).mesh.vertices, axis=0)
        np.testing.assert_allclose(model["size"], extent, atol=1e-5)

        again = http.post("/models", files=upload, data={"model_id": "chair-7"})
        assert again.status_code == 409
        assert again.json()["error"]["code"] == "model_exists"

        traversal = http.delete("/models/..%2Fproc-0002")
        assert traversal.status_code == 422
        assert traversal.json()["error"]["code"] == "invalid_input"

        removed = http.delete("/models/proc-0002")
        assert removed.status_code == 200
        assert removed.json() == {"removed": "proc-0002", "count": 3}

        listed = http.get("/models").json()
        assert listed["count"] == 3
        assert [m["model_id"] for m in listed["models"]] == [
            "chair-7",
            "proc-0000",
            "proc-0001",
        ]

        # the engine registers against the new library
        cloud = views(seed=7, step=4).points
        answer = http.post("/register", json={"points": cloud.tolist(), "up": [0, 0, 1]})
        assert answer.status_code == 200, answer.text
        tried = {c["model_id"] for c in answer.json()["candidates"]}
        assert tried == {"chair-7", "proc-0000", "proc-0001"}

    with (
        serve(library=library_copy, warmup=False) as server,
        httpx.Client(base_url=server.url, timeout=30) as http,
    ):
        ids = [m["model_id"] for m in http.get("/models").json()["models"]]
        assert ids == ["chair-7", "proc-0000", "proc-0001"]
        assert http.get("/models/chair-7").json()["num_points"] > 0
        assert http.get("/models/proc-0002").status_code == 404


def test_changes_by_another_process_are_served_without_a_restart(
    serve: Callable, library_copy: Path, model_dir: Path, tmp_path: Path
) -> None:
    source = tmp_path / "chair-9.ply"
    source.write_bytes(_ply_of_chair(9))
    with (
        serve(library=library_copy, warmup=False) as server,
        httpx.Client(base_url=server.url, timeout=120) as http,
    ):
        assert "chair-9" not in {m["model_id"] for m in http.get("/models").json()["models"]}
        cli = Path(sys.executable).with_name("catalign")  # the console script beside python
        command = [str(cli), "library", "add", str(library_copy)]
        subprocess.run([*command, str(source), "--model-dir", str(model_dir)], check=True)
        listed = http.get("/models").json()
        assert "chair-9" in {m["model_id"] for m in listed["models"]} and listed["count"] == 4
        assert http.get("/models/chair-9").status_code == 200


def test_a_change_on_disk_is_loaded_once(
    serve: Callable, library_copy: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first request after another process changed the library loads it; later ones do not
    (each load reads every entry, under the lock that serialises library changes)."""
    loads: list[Path] = []
    reload = RegistrationService._reload

    def counted(self: RegistrationService, extractor: object) -> object:
        loads.append(self.settings.library)
        return reload(self, extractor)  # type: ignore[arg-type]

    monkeypatch.setattr(RegistrationService, "_reload", counted)
    with (
        serve(library=library_copy, warmup=False) as server,
        httpx.Client(base_url=server.url, timeout=60) as http,
    ):
        remove(library_copy, ["proc-0002"])  # as `catalign library remove` would
        for _ in range(3):
            assert http.get("/models").json()["count"] == 2
    assert loads == [library_copy]


def test_every_library_change_hands_freed_memory_back(
    serve: Callable, library_copy: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A change through the API and one made on disk by another process each end with
    ``malloc_trim``: the old library's engine is freed, and glibc would keep its pages (the
    server's resident memory would creep up with library versions)."""
    trims: list[int] = []
    monkeypatch.setattr(service_module, "release_free_memory", lambda: trims.append(1) or True)
    with (
        serve(library=library_copy, warmup=False, workers=1, worker_processes=False) as server,
        httpx.Client(base_url=server.url, timeout=60) as http,
    ):
        assert http.delete("/models/proc-0002").status_code == 200
        assert len(trims) == 1
        remove(library_copy, ["proc-0001"])  # as `catalign library remove` would
        assert http.get("/models").json()["count"] == 1
        assert len(trims) == 2


def test_a_models_points_come_as_float32_thinned_to_the_limit(
    serve: Callable, library_dir: Path
) -> None:
    with (
        serve(library=library_dir, warmup=False) as server,
        httpx.Client(base_url=server.url, timeout=60) as http,
    ):
        model = http.get("/models/proc-0001").json()
        answer = http.get("/models/proc-0001/points", params={"max_points": 1000})
        assert answer.status_code == 200
        assert answer.headers["content-type"] == "application/octet-stream"
        points = np.frombuffer(answer.content, dtype="<f4").reshape(-1, 3)
        assert len(points) == int(answer.headers["x-point-count"]) and 900 < len(points) <= 1000
        assert np.all(points >= np.asarray(model["bbox_min"]) - 1e-5)
        assert np.all(points <= np.asarray(model["bbox_max"]) + 1e-5)
        default = http.get("/models/proc-0001/points")
        assert int(default.headers["x-point-count"]) == 5000
        assert http.get("/models/no-such/points").status_code == 404
        assert http.get("/models/proc-0001/points", params={"max_points": 0}).status_code == 422
