"""Seed a shard's library on its writer's first start: the entries of the image's library that
belong to the shard, nothing else.

A shard named for a category gets that category's entries, and entries added to it without a
category become that category; the shard ``default`` gets every entry whose category has no
shard of its own. A volume that already holds a library is left alone (one of an older format
is converted in place). Entries are written first (temporary name,
fsync, rename), the catalogue last, by the library's own commit; then the shard's shortlist
index is written over its entries.

Environment: ``SHARD`` (this shard's name, from the pod's ``catalign/shard`` label), ``SHARDS``
(the categories that have a shard of their own, separated by spaces), ``CATALIGN_LIBRARY`` (the
shard's library) and ``SEED_FROM`` (the image's library).
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

from catalign.atomic import atomic_write_bytes
from catalign.library.legacy import migrate
from catalign.library.shortlist_index import write_index
from catalign.library.store import (
    begin_write,
    commit,
    has_manifest,
    read_manifest,
    utc_now,
    writer_lock,
)

DEFAULT_SHARD = "default"


def main() -> int:
    target = Path(os.environ["CATALIGN_LIBRARY"])
    source = Path(os.environ.get("SEED_FROM", "/app/model_store/library"))
    shard = os.environ["SHARD"]
    own = set(os.environ["SHARDS"].split())
    if shard != DEFAULT_SHARD and shard not in own:
        print(
            f"shard {shard!r} is neither {DEFAULT_SHARD!r} nor in SHARDS ({' '.join(sorted(own))})"
        )
        return 2
    if has_manifest(target):
        migrate(target)  # one of an older format converted; one of this format left as it is
        print(f"library present in {target}; not seeding")
        return 0
    image = read_manifest(source)
    if shard == DEFAULT_SHARD:
        entries = {i: r for i, r in image.entries.items() if r.category not in own}
        category = image.category
    else:
        entries = {i: r for i, r in image.entries.items() if r.category == shard}
        category = shard
    with writer_lock(target):
        begin_write(target)
        for record in entries.values():
            atomic_write_bytes(
                target / record.file, (source / record.file).read_bytes(), sync_directory=False
            )
        now = utc_now()
        manifest = dataclasses.replace(
            image, entries=entries, category=category, created=now, updated=now
        )
        commit(target, manifest)
        write_index(target, entries)
    kept = f"{len(entries)} of the image's {len(image.entries)} models"
    print(f"seeded {target} with {kept} for shard {shard}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
