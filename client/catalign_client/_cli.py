"""``catalign-client``: align a point file or list the library from a shell, printing JSON.

Operators and scripts on a robot need to poke the service without writing Python; the CLI is a
thin layer over :class:`Client` that reads ``.npy``, ``.xyz`` and ``.ply`` locally (sent as
compact float32), uploads any other file for the server to parse, prints answers as JSON on
stdout, and turns every failure into one line on stderr and exit status 1; an answer below
``--min-confidence`` is printed all the same, with ``not accepted: <reason>`` on stderr.
``align --png out.png`` also fetches the chosen model's points and draws them over the cloud
(needs matplotlib, the ``plot`` extra); options this installation or this file cannot serve
(``--png`` without matplotlib, or with a file only the server can read) are refused before
anything is sent, with exit status 2. ``--url`` and ``--api-key`` default to
``$CATALIGN_URL`` and ``$CATALIGN_API_KEY``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._client import Client
from ._exceptions import CatalignError
from ._files import LOCAL_SUFFIXES, UnsupportedFileError, read_points
from ._models import AlignResult
from ._plot import INSTALL_HINT, require_matplotlib
from ._version import __version__

ClientFactory = Callable[[str, str | None], Client]
"""Builds the client from ``(url, api_key)``; tests pass one backed by a mock transport."""


class UsageError(Exception):
    """Options this installation or this input cannot serve; nothing was sent (exit status 2)."""


def main(argv: Sequence[str] | None = None, *, client_factory: ClientFactory | None = None) -> int:
    """Run the CLI; returns the exit status (0 on success, 1 on an error, 2 on a usage error)."""
    args = _parser().parse_args(argv)
    if not args.url:
        print("catalign-client: error: no server URL (--url or $CATALIGN_URL)", file=sys.stderr)
        return 1
    factory = client_factory or _default_client
    try:
        if getattr(args, "png", None):
            _check_plotting()
        with factory(args.url, args.api_key) as client:
            print(json.dumps(args.run(client, args), indent=2))
    except UsageError as error:
        print(f"catalign-client: error: {error}", file=sys.stderr)
        return 2
    except (CatalignError, OSError, ValueError) as error:
        message = " ".join(str(error).split()) or type(error).__name__
        print(f"catalign-client: error: {message}", file=sys.stderr)
        return 1
    return 0


def _check_plotting() -> None:
    try:
        require_matplotlib()
    except ImportError as exc:
        raise UsageError(f"--png needs matplotlib, which is not installed: {INSTALL_HINT}") from exc


def _default_client(url: str, api_key: str | None) -> Client:
    return Client(url, api_key=api_key)


def _align(client: Client, args: argparse.Namespace) -> dict[str, Any]:
    path = Path(args.file)
    options: dict[str, Any] = {
        "top_k": args.top_k,
        "up": args.up,
        "estimate_scale": args.estimate_scale,
        "seed": args.seed,
        "category": args.category,
        "min_confidence": args.min_confidence,
    }
    points = _local_points(path)
    if points is None:
        if args.png:
            raise UsageError(
                f"--png draws the points read here, and {path.name} is not a file this client "
                f"reads ({', '.join(LOCAL_SUFFIXES)}); convert it, or drop --png"
            )
        return _answer(client.align_file(path, **options))
    result = client.align(points, encoding=args.encoding, **options)
    if args.png:
        model = client.model_points(result.model_id)
        result.plot(points, model, args.png, title=path.name)
    return _answer(result)


def _answer(result: AlignResult) -> dict[str, Any]:
    """The result as JSON-ready data; an answer below ``--min-confidence`` also says so on
    stderr (stdout stays the answer, exit status 0: the server did answer)."""
    if not result.accepted:
        print(f"catalign-client: not accepted: {result.reason}", file=sys.stderr)
    return result.to_dict()


def _local_points(path: Path) -> np.ndarray | None:
    """The file's points read here, or ``None`` when the server must parse it."""
    if path.suffix.lower() not in LOCAL_SUFFIXES:
        return None
    try:
        return read_points(path)
    except UnsupportedFileError:
        return None  # a variant this reader does not parse: let the server try


def _models(client: Client, args: argparse.Namespace) -> dict[str, Any]:
    models = client.models(category=args.category)
    return {"count": len(models), "models": [model.to_dict() for model in models]}


def _parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--url", default=os.environ.get("CATALIGN_URL"), help="server root URL ($CATALIGN_URL)"
    )
    common.add_argument(
        "--api-key", default=os.environ.get("CATALIGN_API_KEY"), help="($CATALIGN_API_KEY)"
    )

    parser = argparse.ArgumentParser(
        prog="catalign-client", description="Client of the catalign registration service."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)

    align = commands.add_parser(
        "align", parents=[common], help="register a point cloud file, print the result as JSON"
    )
    align.add_argument("file", help=".npy, .xyz or .ply (read here); other formats are uploaded")
    align.add_argument("--top-k", type=int, help="how many shortlisted models to register")
    align.add_argument("--up", help="the cloud's up direction, e.g. 0,0,1")
    align.add_argument("--seed", type=int, help="seed for a reproducible answer")
    align.add_argument("--estimate-scale", action="store_true", help="also fit a uniform scale")
    align.add_argument(
        "--category", help="search only this category's models (e.g. table); default: every model"
    )
    align.add_argument(
        "--min-confidence",
        type=float,
        metavar="P",
        help="probability from 0 to 1 the answer needs to be accepted; below it the answer is "
        "still printed, with accepted false, and 'not accepted: <reason>' goes to stderr",
    )
    align.add_argument("--encoding", choices=("binary", "json"), default="binary")
    align.add_argument(
        "--png",
        metavar="PATH",
        help="also draw the cloud and the posed model to this PNG (needs catalign-client[plot])",
    )
    align.set_defaults(run=_align)

    models = commands.add_parser("models", parents=[common], help="list the library as JSON")
    models.add_argument("--category", help="only this category's models (e.g. table)")
    models.set_defaults(run=_models)
    return parser


if __name__ == "__main__":
    sys.exit(main())
