"""Idempotency keys: a library change sent again with the same ``Idempotency-Key`` gets the first
answer and is not made twice.

A client that lost the answer to ``POST /models`` or ``DELETE /models/{id}`` (a dropped
connection, a 502 from a proxy whose replica died) cannot tell whether the change was made; with
a key it may send the request again. The first request with a key makes the change and records
its answer (status and body); a later one with the same key and the same request gets that
answer back, with ``Idempotent-Replayed: true``, and changes nothing. "The same request" is what
the change depends on (:attr:`Change.asked`: the method, the path, the form's fields and the
upload's checksum), not the bytes: a multipart boundary differs each time a body is sent. The
same key with another request is refused (422 ``idempotency_key_reused``). A change that fails is
not recorded, so sending it again runs it again.

The records live beside the library, in its ``.idempotency`` folder (which the library's own
clean-up never touches): one JSON file per key, named by the key's sha256 and written atomically
(:mod:`catalign.atomic`), so every replica serving the folder reads the same records and a crash
leaves a file old or new, never half written. The folder's ``.lock`` (``flock``) is held from
the look-up to the record, so a key that reaches two replicas at once is handled once: the
second waits and answers from the record. Before its change, the first marks the key *pending*
with what was asked; a writer killed between its change and its record leaves that mark, and
the next request with the key asks the library whether the change is there
(:attr:`Change.committed`: the model with the upload's checksum present, the removed model
absent): if so it answers from the library, otherwise it makes the change.

Records are kept :data:`KEEP_S` (24 h), at most :data:`MAX_KEYS` (10,000); older and surplus
ones are removed whenever a new answer is recorded.
"""

from __future__ import annotations

import asyncio
import fcntl
import hashlib
import json
import logging
import os
import re
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi.responses import JSONResponse

from catalign.api.errors import IdempotencyKeyReusedError
from catalign.atomic import atomic_write_bytes, fsync_directory
from catalign.errors import InvalidInputError

logger = logging.getLogger(__name__)

KEY_HEADER = "Idempotency-Key"
REPLAYED_HEADER = "Idempotent-Replayed"
KEY_PATTERN = re.compile(r"[\x21-\x7e]{1,255}")  # visible ASCII, no spaces: a UUID fits
FOLDER = ".idempotency"
LOCK_NAME = ".lock"
KEEP_S = 24 * 3600.0
MAX_KEYS = 10_000
_POLL_S = 0.05  # how often a request waits for the lock another request holds
_TEMPORARY_KEEP_S = 3600.0  # a writer killed mid-write leaves a temporary file this long


@dataclass(frozen=True)
class Answer:
    """An answer as recorded: HTTP status and JSON body."""

    status: int
    body: dict[str, Any]


@dataclass(frozen=True)
class Change:
    """A library change made at most once per key.

    ``asked``: what the answer depends on, which a repeat must match. ``run``: makes the change
    and returns its answer. ``committed``: after a writer died between its change and its
    record, the answer read from the library when the change is there, else None.
    """

    asked: Mapping[str, str]
    run: Callable[[], Awaitable[Answer]]
    committed: Callable[[], Awaitable[Answer | None]]


def checked_key(key: str) -> str:
    """``key`` if it is 1 to 255 visible ASCII characters, else 422."""
    if not KEY_PATTERN.fullmatch(key):
        raise InvalidInputError(
            f"the {KEY_HEADER} header must be 1 to 255 visible ASCII characters without spaces "
            "(a UUID, say)"
        )
    return key


class IdempotencyStore:
    """The key records of one library, in ``folder`` (created on first use)."""

    def __init__(self, folder: Path, *, keep_s: float = KEEP_S, max_keys: int = MAX_KEYS) -> None:
        self.folder = folder
        self.keep_s = keep_s
        self.max_keys = max_keys

    async def respond(self, key: str, change: Change) -> JSONResponse:
        """The answer to ``change`` sent with ``key``: made now, or the first one replayed."""
        answer, replayed = await self.answer(key, change)
        headers = {REPLAYED_HEADER: "true"} if replayed else None
        return JSONResponse(answer.body, answer.status, headers=headers)

    async def answer(self, key: str, change: Change) -> tuple[Answer, bool]:
        """The answer to ``change`` sent with ``key``, and whether it is a replay. Shielded: a
        caller that goes away leaves the change and its record to finish."""
        return await asyncio.shield(self._answer(key, change))

    async def _answer(self, key: str, change: Change) -> tuple[Answer, bool]:
        path = self.folder / f"{hashlib.sha256(key.encode()).hexdigest()}.json"
        asked = dict(change.asked)
        async with self._locked():
            record = await asyncio.to_thread(self._read, path)
            if record is not None:
                if record["asked"] != asked:
                    raise IdempotencyKeyReusedError(
                        f"the {KEY_HEADER} {key!r} was sent first with another request "
                        f"({_describe(record['asked'])}); send a new key with each change"
                    )
                if record["answer"] is not None:
                    return Answer(**record["answer"]), True
                answer = await change.committed()
                if answer is not None:
                    logger.info("key %r: its writer stopped after the change; answered", key)
                    await asyncio.to_thread(self._write, path, key, asked, answer)
                    return answer, True
            await asyncio.to_thread(self._write, path, key, asked, None)
            try:
                answer = await change.run()
            except BaseException:
                path.unlink(missing_ok=True)  # not made (or unknown): a repeat runs it again
                raise
            await asyncio.to_thread(self._write, path, key, asked, answer)
            await asyncio.to_thread(self._prune)
        return answer, False

    @asynccontextmanager
    async def _locked(self) -> AsyncIterator[None]:
        """Hold the folder's ``flock`` (other processes and requests of this one alike),
        polled so that waiting never blocks the event loop."""
        await asyncio.to_thread(self.folder.mkdir, parents=True, exist_ok=True)
        fd = os.open(self.folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    await asyncio.sleep(_POLL_S)
            yield
        finally:
            os.close(fd)  # closing the descriptor releases the lock

    def _read(self, path: Path) -> dict[str, Any] | None:
        """The record at ``path``; None when there is none, it expired or cannot be read."""
        try:
            record = json.loads(path.read_bytes())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as error:
            logger.warning("ignoring the unreadable key record %s: %s", path, error)
            return None
        if time.time() - float(record.get("created", 0)) > self.keep_s:
            return None
        return record

    def _write(self, path: Path, key: str, asked: dict[str, str], answer: Answer | None) -> None:
        record = {
            "key": key,
            "asked": asked,
            "answer": None if answer is None else {"status": answer.status, "body": answer.body},
            "created": time.time(),
        }
        atomic_write_bytes(path, json.dumps(record, sort_keys=True).encode())

    def _prune(self) -> None:
        """Remove records older than ``keep_s``, beyond the newest ``max_keys``, and temporary
        files that a killed writer left."""
        now = time.time()
        records: list[tuple[float, str]] = []
        stale: list[str] = []
        with os.scandir(self.folder) as entries:
            for entry in entries:
                try:
                    age = now - entry.stat().st_mtime
                except FileNotFoundError:
                    continue
                if entry.name.endswith(".json") and not entry.name.startswith("."):
                    records.append((age, entry.path))
                elif entry.name.endswith(".tmp") and age > _TEMPORARY_KEEP_S:
                    stale.append(entry.path)
        records.sort()  # newest first
        for n, (age, name) in enumerate(records):
            if n >= self.max_keys or age > self.keep_s:
                stale.append(name)
        for name in stale:
            Path(name).unlink(missing_ok=True)
        if stale:
            fsync_directory(self.folder)
            logger.info("removed %d expired key record(s) from %s", len(stale), self.folder)


def _describe(asked: Mapping[str, str]) -> str:
    """``POST /models`` and its fields, for the message that refuses a reused key."""
    fields = ", ".join(f"{k}={v!r}" for k, v in asked.items() if k not in ("method", "path"))
    head = f"{asked.get('method', '?')} {asked.get('path', '?')}"
    return f"{head}: {fields}" if fields else head
