"""Regenerate the protobuf and gRPC modules from the ``.proto`` files next to this module.

The generated ``*_pb2.py``, ``*_pb2.pyi`` and ``*_pb2_grpc.py`` files are committed, so that a
server needs only grpcio and protobuf, not grpcio-tools. Run ``python -m catalign.api.codegen``
after changing a ``.proto``; ``--check`` exits 1 when the committed files differ from what
grpcio-tools generates (a test runs the same comparison).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
from pathlib import Path

from catalign.errors import ConfigError

logger = logging.getLogger(__name__)

API_DIR = Path(__file__).resolve().parent
SOURCE_ROOT = API_DIR.parents[1]  # the folder that holds the catalign package
PROTOS = ("catalign.proto", "health.proto")
GENERATED_SUFFIXES = ("_pb2.py", "_pb2.pyi", "_pb2_grpc.py")


def generate(out_root: Path) -> dict[str, bytes]:
    """Run protoc on :data:`PROTOS` into ``out_root``; return each generated file's bytes."""
    from grpc_tools import protoc

    package = API_DIR.relative_to(SOURCE_ROOT).as_posix()
    args = [
        "grpc_tools.protoc",
        f"-I{SOURCE_ROOT}",
        f"--python_out={out_root}",
        f"--pyi_out={out_root}",
        f"--grpc_python_out={out_root}",
        *(f"{package}/{name}" for name in PROTOS),
    ]
    if protoc.main(args) != 0:
        raise ConfigError(f"protoc failed on {', '.join(PROTOS)} (see its message above)")
    return {path.name: path.read_bytes() for path in _generated(out_root / package)}


def committed() -> dict[str, bytes]:
    """The generated files as committed next to this module."""
    return {path.name: path.read_bytes() for path in _generated(API_DIR)}


def differences() -> list[str]:
    """Names of generated files that are missing, stale or unexpected in :data:`API_DIR`."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp))
    current = committed()
    return sorted(n for n in fresh.keys() | current.keys() if fresh.get(n) != current.get(n))


def main(argv: list[str] | None = None) -> int:
    """Write the generated files (or only compare them with ``--check``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the files are stale")
    check = parser.parse_args(argv).check
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if check:
        stale = differences()
        for name in stale:
            logger.error("%s differs from what grpcio-tools generates", name)
        return 1 if stale else 0
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp))
        for name in fresh:
            shutil.copyfile(Path(tmp) / API_DIR.relative_to(SOURCE_ROOT) / name, API_DIR / name)
            logger.info("wrote %s", API_DIR / name)
    return 0


def _generated(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.endswith(GENERATED_SUFFIXES))


if __name__ == "__main__":
    sys.exit(main())
