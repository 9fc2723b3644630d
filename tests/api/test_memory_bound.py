"""The server answers the heaviest requests within its limits under a 2 GB address-space cap.

``catalign serve`` runs as a subprocess whose address space (``RLIMIT_AS``: every mapping, not
only what is resident) is capped at :data:`ADDRESS_SPACE`. It is then sent, one after the other,
the requests within the limits that cost the most memory: the largest JSON body of points the
point limit allows, half a million random points in a 2 m cube, a dense chair standing on a
floor that fills nearly the whole voxel budget, and files whose headers claim billions of
points. Each must be answered (200 or a 4xx), and the server must still be alive afterwards: a
reader or a stage that allocated without bound would fail its allocation here (and, without the
cap, would have the process killed by the kernel).
"""

from __future__ import annotations

import io
import json
import resource
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np
import pytest

from catalign.data.shapes import procedural_shape
from catalign.geometry.sampling import sample_surface, voxel_downsample
from catalign.registration.prepare.validation import MAX_VOXELS

if TYPE_CHECKING:
    from tests.api.conftest import ServerProcess

pytestmark = pytest.mark.slow

ADDRESS_SPACE = 2 << 30
MAX_POINTS = 500_000  # the server's default limit
BINARY = {"content-type": "application/octet-stream"}


@pytest.fixture(scope="module")
def url(
    serve_process: Callable[..., AbstractContextManager[ServerProcess]], library_dir: Path
) -> Iterator[str]:
    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))

    # Memory is under test here, not time: a generous deadline.
    with serve_process(library_dir, env={"CATALIGN_DEADLINE_S": "120"}, preexec_fn=cap) as server:
        yield server.url
        assert server.process.poll() is None, "the server died"


def dense_chair_on_a_floor() -> np.ndarray:
    """A densely scanned chair on a floor disc that together fill about 90 % of the voxels a
    query may have, as 500,000 points: the most the engine can be asked to describe."""
    shape = procedural_shape(4)
    rng = np.random.default_rng(0)
    # Both sides of every part, all round: more voxels than any view; scaled to leave room.
    chair = sample_surface(0.7 * shape.mesh.vertices, shape.mesh.faces, 200_000, rng)
    chair = chair[:, [0, 2, 1]]  # +Y up -> +Z up
    floor_cells = 0.9 * MAX_VOXELS - len(voxel_downsample(chair, 0.025)[0])
    radius = np.sqrt(floor_cells * 0.025**2 / np.pi)
    r, angle = radius * np.sqrt(rng.random(300_000)), rng.uniform(0, 2 * np.pi, 300_000)
    floor = np.c_[r * np.cos(angle), r * np.sin(angle), np.full(300_000, chair[:, 2].min())]
    cloud = np.r_[chair, floor]
    assert 0.8 * MAX_VOXELS < len(voxel_downsample(cloud, 0.025)[0]) <= MAX_VOXELS
    return cloud


def test_the_heaviest_requests_are_answered_under_the_cap(url: str) -> None:
    rng = np.random.default_rng(1)
    with httpx.Client(base_url=url, timeout=300) as client:
        rows = rng.uniform(-0.5, 0.5, size=(MAX_POINTS, 3)).round(6).tolist()
        largest_json = client.post(
            "/register",
            content=json.dumps({"points": rows}),
            headers={"content-type": "application/json"},
        )
        assert largest_json.status_code == 422, largest_json.text  # a volume, not a chair

        cube = rng.uniform(0.0, 2.0, size=(MAX_POINTS, 3)).astype("<f4")
        volume = client.post("/register", content=cube.tobytes(), headers=BINARY)
        assert volume.status_code == 422, volume.text

        cloud = dense_chair_on_a_floor().astype("<f4")
        largest = client.post(
            "/register", content=cloud.tobytes(), params={"up": "0,0,1"}, headers=BINARY
        )
        assert largest.status_code == 200, largest.text

        for name, body in _lying_files().items():
            answer = client.post("/register", files={"file": (name, body)})
            assert answer.status_code == 422, (name, answer.text)
        assert client.get("/health/live").status_code == 200


def _lying_files() -> dict[str, bytes]:
    pcd = b"VERSION .7\nFIELDS x y z\nPOINTS 1000000000\nDATA ascii\n1 2 3\n"
    ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3000000000\n"
    ply += b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 12
    npy = io.BytesIO()
    header = {"descr": "<f4", "fortran_order": False, "shape": (9_999_999_999, 3)}
    np.lib.format.write_array_header_1_0(npy, header)
    npy.write(b"\0" * 48)
    return {"evil.pcd": pcd, "evil.ply": ply, "evil.npy": npy.getvalue()}
