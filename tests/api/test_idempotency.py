"""Idempotency keys on library changes, against two real servers sharing one library folder.

A repeated ``Idempotency-Key`` with the same request gets the first answer (status and body,
marked ``Idempotent-Replayed``) and changes nothing, on the replica that made the change or on
another one; the same key with another request is a 422; a writer killed after its change and
before its record is answered from the library; the records are bounded in age and number.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np
import pytest

import catalign_client as sdk
from catalign.api.idempotency import FOLDER, Answer, Change, IdempotencyStore
from catalign.data.shapes import procedural_shape

if TYPE_CHECKING:
    from tests.api.conftest import Server

KEY = "Idempotency-Key"


@pytest.fixture(scope="module")
def library(library_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    target = tmp_path_factory.mktemp("idempotency") / "library"
    shutil.copytree(library_dir, target)
    return target


@pytest.fixture(scope="module")
def replicas(library: Path, serve: Callable) -> Iterator[tuple[Server, Server]]:
    """Two servers on the same library folder (no registrations here: no worker processes)."""
    options = {"library": library, "warmup": False, "worker_processes": False, "workers": 1}
    with serve(**options) as first, serve(**options) as second:
        yield first, second


@pytest.fixture(scope="module")
def chair_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("upload") / "visitor.npy"
    np.save(path, procedural_shape(7).points.astype(np.float32))
    return path


def ids(server: Server) -> list[str]:
    with sdk.Client(server.url, retries=0) as client:
        return [m.model_id for m in client.models()]


def test_a_repeated_key_returns_the_first_answer_and_adds_the_model_once(
    replicas: tuple[Server, Server], chair_file: Path
) -> None:
    first, second = replicas
    upload = {"file": ("visitor.npy", chair_file.read_bytes())}
    fields = {"model_id": "once"}
    headers = {KEY: "add-once-1"}
    made = httpx.post(f"{first.url}/models", files=upload, data=fields, headers=headers, timeout=60)
    assert made.status_code == 201, made.text
    assert "Idempotent-Replayed" not in made.headers
    for server in (first, second, first):  # a new multipart boundary each time
        again = httpx.post(
            f"{server.url}/models", files=upload, data=fields, headers=headers, timeout=60
        )
        assert (again.status_code, again.json()) == (201, made.json())
        assert again.headers["Idempotent-Replayed"] == "true"
    assert ids(first).count("once") == ids(second).count("once") == 1
    without_key = httpx.post(f"{second.url}/models", files=upload, data=fields, timeout=60)
    assert without_key.status_code == 409  # what the key spares a client that resends

    with sdk.Client(second.url) as client:  # the SDK: the same call twice, one model
        added = client.add_model(chair_file, model_id="once-sdk", idempotency_key="sdk-add-1")
        assert client.add_model(chair_file, model_id="once-sdk", idempotency_key="sdk-add-1") == (
            added
        )
    assert ids(first).count("once-sdk") == 1


def test_a_key_reused_with_another_request_is_refused(
    replicas: tuple[Server, Server], chair_file: Path
) -> None:
    first, second = replicas
    with sdk.Client(first.url) as client:
        client.add_model(chair_file, model_id="reused", idempotency_key="reuse-1")
    other_file = chair_file.parent / "other.npy"
    np.save(other_file, procedural_shape(8).points.astype(np.float32))
    attempts = [
        lambda c: c.add_model(chair_file, model_id="reused-2", idempotency_key="reuse-1"),
        lambda c: c.add_model(other_file, model_id="reused", idempotency_key="reuse-1"),
        lambda c: c.add_model(chair_file, model_id="reused", units="mm", idempotency_key="reuse-1"),
        lambda c: c.remove_model("reused", idempotency_key="reuse-1"),
    ]
    with sdk.Client(second.url) as client:
        for attempt in attempts:
            with pytest.raises(sdk.InvalidInputError) as caught:
                attempt(client)
            assert caught.value.status_code == 422
            assert caught.value.code == "idempotency_key_reused"
            assert "reuse-1" in caught.value.message and "POST /models" in caught.value.message
    assert "reused" in ids(first) and "reused-2" not in ids(first)


def test_delete_with_a_key_answers_the_first_200_every_time(
    replicas: tuple[Server, Server], chair_file: Path
) -> None:
    first, second = replicas
    with sdk.Client(first.url) as client:
        client.add_model(chair_file, model_id="to-remove")
    headers = {KEY: "remove-1"}
    removed = httpx.delete(f"{first.url}/models/to-remove", headers=headers, timeout=60)
    assert removed.status_code == 200, removed.text
    for server in (first, second):
        again = httpx.delete(f"{server.url}/models/to-remove", headers=headers, timeout=60)
        assert (again.status_code, again.json()) == (200, removed.json())
        assert again.headers["Idempotent-Replayed"] == "true"
    assert httpx.delete(f"{second.url}/models/to-remove", timeout=60).status_code == 404


def test_a_key_sent_to_two_replicas_at_once_makes_one_change(
    replicas: tuple[Server, Server], chair_file: Path
) -> None:
    answers: list[tuple[int, dict, bool]] = []

    def add(server: Server) -> None:
        response = httpx.post(
            f"{server.url}/models",
            files={"file": ("visitor.npy", chair_file.read_bytes())},
            data={"model_id": "raced"},
            headers={KEY: "race-1"},
            timeout=60,
        )
        replayed = "Idempotent-Replayed" in response.headers
        answers.append((response.status_code, response.json(), replayed))

    threads = [threading.Thread(target=add, args=(server,)) for server in replicas]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    (status_a, body_a, replayed_a), (status_b, body_b, replayed_b) = answers
    assert status_a == status_b == 201 and body_a == body_b
    assert sorted([replayed_a, replayed_b]) == [False, True]
    assert ids(replicas[0]).count("raced") == 1


def test_a_bad_key_is_refused(replicas: tuple[Server, Server]) -> None:
    for key in ("with space", "x" * 256):
        refused = httpx.delete(f"{replicas[0].url}/models/proc-0000", headers={KEY: key})
        assert refused.status_code == 422
        assert refused.json()["error"]["code"] == "invalid_input"
        assert KEY in refused.json()["error"]["message"]
    assert "proc-0000" in ids(replicas[0])


CRASH = """
import asyncio, os, sys
from pathlib import Path
from catalign.api.idempotency import FOLDER, Change, IdempotencyStore
from catalign.library.index import remove

library, model_id, key = Path(sys.argv[1]), sys.argv[2], sys.argv[3]

async def run():
    remove(library, [model_id])
    os._exit(9)  # killed after its change, before recording the answer

async def committed():
    raise AssertionError("no record yet")

asked = {"method": "DELETE", "path": f"/models/{model_id}"}  # as the route asks it
asyncio.run(IdempotencyStore(library / FOLDER).answer(key, Change(asked, run, committed)))
"""


def test_a_writer_killed_after_its_change_is_answered_from_the_library(
    replicas: tuple[Server, Server], library: Path
) -> None:
    """A process that removed a model under a key and died before recording the answer leaves
    the key pending; the same request then answers 200 from the library instead of a 404."""
    first, second = replicas
    before = len(ids(first))
    crashed = subprocess.run(
        [sys.executable, "-c", CRASH, str(library), "proc-0001", "crash-1"],
        env=os.environ | {"PYTHONPATH": os.pathsep.join(sys.path)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert crashed.returncode == 9, crashed.stderr
    (pending,) = [
        json.loads(p.read_text())
        for p in (library / FOLDER).glob("*.json")
        if json.loads(p.read_text())["key"] == "crash-1"
    ]
    assert pending["answer"] is None
    with sdk.Client(second.url) as client:
        assert client.remove_model("proc-0001", idempotency_key="crash-1") == before - 1
        assert client.remove_model("proc-0001", idempotency_key="crash-1") == before - 1
        with pytest.raises(sdk.NotFoundError):
            client.remove_model("proc-0001")


def test_records_are_kept_a_bounded_time_and_number(tmp_path: Path) -> None:
    store = IdempotencyStore(tmp_path / FOLDER, keep_s=3600, max_keys=3)
    made: list[str] = []

    def change(name: str) -> Change:
        async def run() -> Answer:
            made.append(name)
            return Answer(201, {"model_id": name})

        async def committed() -> Answer | None:
            return None

        return Change({"method": "POST", "path": "/models", "model_id": name}, run, committed)

    async def send(key: str, name: str) -> tuple[Answer, bool]:
        return await store.answer(key, change(name))

    for n in range(5):
        assert asyncio.run(send(f"k{n}", f"m{n}")) == (Answer(201, {"model_id": f"m{n}"}), False)
        time.sleep(0.01)  # distinct file times
    assert len(list(store.folder.glob("*.json"))) == 3  # the newest three
    assert asyncio.run(send("k4", "m4"))[1] is True
    assert asyncio.run(send("k0", "m0"))[1] is False  # forgotten: made again
    expiring = IdempotencyStore(tmp_path / FOLDER, keep_s=0.0)
    assert asyncio.run(expiring.answer("k4", change("m4")))[1] is False  # expired: made again
    assert made == ["m0", "m1", "m2", "m3", "m4", "m0", "m4"]
