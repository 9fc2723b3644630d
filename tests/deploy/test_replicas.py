"""Replicas behind a real load balancer, on one machine: HAProxy in front of three
``catalign serve`` processes that share one library folder (see ``_replicas.py``).

One writer takes library changes, two ``--read-only`` readers take registrations, and HAProxy
checks ``/health/ready`` every 250 ms. What must hold: a model added through the writer is
served by every reader from the next request on; under a flood through HAProxy with the SDK, a
reader killed with SIGKILL, or every reader restarted one after another, fails no request the
SDK sees, and HAProxy takes a replica out and back in; and while models are added, replaced and
removed, no reader fails a request or answers from a library that no writer committed.
"""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import trimesh

import catalign_client as sdk
from catalign.data.shapes import procedural_shape
from catalign.features.extractor import LearnedExtractor
from catalign.library.index import add
from catalign.library.store import read_manifest
from tests.deploy._load import UP, Load, chair_view
from tests.deploy._replicas import LIBRARY_SEEDS, Deployment, haproxy_binary

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(haproxy_binary() is None, reason="haproxy is not installed"),
]

FLOOD_CLIENTS = 16
FLOOD_S = float(os.environ.get("CATALIGN_FLOOD_SECONDS", "12"))

State = frozenset[tuple[str, str]]  # a library as (model id, source) pairs


@pytest.fixture(scope="module")
def deployment(
    model_dir: Path, procedural_library: Path, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Deployment]:
    """A writer and two single-worker readers (1 thread each) on a 3-chair library."""
    root = tmp_path_factory.mktemp("replicas")
    shutil.copytree(procedural_library, root / "library")
    with Deployment(root / "library", model_dir, root / "run", readers=2) as running:
        yield running


@pytest.fixture
def replicas(deployment: Deployment) -> Deployment:
    deployment.ensure_up()
    return deployment


def chair_file(folder: Path, seed: int, name: str) -> Path:
    """Procedural chair ``seed``'s mesh as a PLY file named ``name``."""
    mesh = procedural_shape(seed).mesh
    assert mesh is not None
    path = folder / name
    path.write_bytes(trimesh.exchange.ply.export_ply(trimesh.Trimesh(mesh.vertices, mesh.faces)))
    return path


def served(replicas: Deployment, server: str) -> int:
    """Answers with a 2xx status that HAProxy got from ``server`` (``backend/name``) so far."""
    return int(replicas.proxy.stats()[server]["hrsp_2xx"])


def test_a_model_added_through_the_writer_is_served_by_every_replica(
    replicas: Deployment, tmp_path: Path
) -> None:
    view = chair_view(7)
    urls = [r.url for r in replicas.readers] + [replicas.url] * 2
    with sdk.Client(replicas.url, timeout=60) as proxy:
        added = proxy.add_model(chair_file(tmp_path, 7, "chair seven.ply"), model_id="chair-7")
        assert added.model_id == "chair-7"
        for url in urls:  # each reader directly, then twice through HAProxy
            with sdk.Client(url, timeout=60, retries=0) as client:
                assert "chair-7" in [m.model_id for m in client.models()], url
                assert client.align(view, up=UP, seed=0).model_id == "chair-7", url
        with (
            sdk.Client(replicas.readers[0].url, retries=0) as reader,
            pytest.raises(sdk.PermissionDeniedError),
        ):
            reader.remove_model("chair-7")  # readers refuse changes; HAProxy routes them
        assert proxy.remove_model("chair-7") == LIBRARY_SEEDS
        for url in urls:
            with sdk.Client(url, timeout=60, retries=0) as client:
                assert "chair-7" not in [m.model_id for m in client.models()], url


def test_a_killed_reader_fails_no_request_and_haproxy_takes_it_out_and_back(
    replicas: Deployment,
) -> None:
    victim = replicas.readers[0]
    server = f"readers/{victim.name}"
    with Load(replicas.url, chair_view(1), FLOOD_CLIENTS, FLOOD_S + 60) as flood:
        time.sleep(3.0)
        assert served(replicas, server) > 0
        victim.stop(signal.SIGKILL)
        down_s = replicas.proxy.wait_status(server, "DOWN", timeout=10)
        victim.start()
        victim.wait_ready()
        up_s = replicas.proxy.wait_status(server, "UP", timeout=10)
        back_in = served(replicas, server)
        flood.stop(at_least_s=max(FLOOD_S, time.monotonic() - flood.started + 3.0))
    assert not flood.failures, flood.failures[:5]
    assert flood.ok > FLOOD_CLIENTS
    assert down_s < 5.0 and up_s < 5.0, (down_s, up_s)  # checks every 250 ms, 2 to change
    assert served(replicas, server) > back_in  # it takes requests again


def test_a_rolling_restart_of_the_readers_fails_no_request(replicas: Deployment) -> None:
    with Load(replicas.url, chair_view(2), FLOOD_CLIENTS, FLOOD_S + 90) as flood:
        time.sleep(2.0)
        for reader in replicas.readers:  # SIGTERM, wait for the exit, start, HAProxy sees UP
            replicas.restart(reader, signal.SIGTERM)
            back_in = served(replicas, f"readers/{reader.name}")
        flood.stop(at_least_s=time.monotonic() - flood.started + 2.0)
    assert not flood.failures, flood.failures[:5]
    assert served(replicas, f"readers/{replicas.readers[-1].name}") > back_in


def test_readers_never_fail_nor_serve_a_library_no_writer_committed(
    replicas: Deployment, extractor: LearnedExtractor, tmp_path: Path
) -> None:
    """The writer adds a model, another process replaces it (``catalign library add --replace``)
    and the writer removes it, in a loop, then adds it once more, while every reader is asked
    for its models and registers views without retries: every answer is 200 and lists a library
    that was committed, and from the next request on every reader serves the last one."""
    library = replicas.readers[0].library
    first, second = chair_file(tmp_path, 7, "v1.ply"), chair_file(tmp_path, 8, "v2.ply")

    def state() -> State:
        return frozenset((i, r.source) for i, r in read_manifest(library).entries.items())

    committed = [state()]
    seen: list[State] = []
    candidates: list[set[str]] = []
    failures: list[str] = []
    stop = threading.Event()

    def ask(url: str, points: np.ndarray | None) -> None:
        """List the models (``points`` None) or register ``points``, until ``stop``."""
        with sdk.Client(url, timeout=60, retries=0) as client:
            while not stop.is_set():
                try:
                    if points is None:
                        seen.append(frozenset((m.model_id, m.source) for m in client.models()))
                    else:
                        result = client.align(points, up=UP, seed=0)
                        candidates.append({c.model_id for c in result.candidates})
                except sdk.CatalignError as error:
                    failures.append(f"{url}: {error!r}")

    threads = [
        threading.Thread(target=ask, args=(r.url, points))
        for r in replicas.readers
        for points in (None, chair_view(7, step=4))
    ]
    for thread in threads:
        thread.start()
    deadline = time.monotonic() + 60
    try:
        with sdk.Client(replicas.url, timeout=60) as writer:
            for _ in range(4):
                writer.add_model(first, model_id="swap")
                committed.append(state())
                add(library, [second], extractor, ids=["swap"], replace=True, progress=False)
                committed.append(state())
                writer.remove_model("swap")
                committed.append(state())
                if time.monotonic() > deadline:
                    break
            writer.add_model(first, model_id="swap")
            committed.append(state())
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=90)

    assert not failures, failures[:5]
    assert len(set(committed)) == 3  # base, base + swap v1, base + swap v2
    assert set(seen) <= set(committed), set(seen) - set(committed)
    ids = [{i for i, _ in s} for s in committed]
    assert all(any(c <= s for s in ids) for c in candidates)
    for replica in replicas.readers:  # no reload failed and left a reader on an old library
        assert "cannot be loaded" not in replica.log.read_text(errors="replace")
        with sdk.Client(replica.url, retries=0) as client:
            assert {(m.model_id, m.source) for m in client.models()} == committed[-1]
    with sdk.Client(replicas.url, timeout=60) as writer:
        writer.remove_model("swap")
