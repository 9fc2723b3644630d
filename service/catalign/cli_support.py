"""What every ``catalign`` command shares: errors raised on purpose become one sentence, the
``--engine FIELD=VALUE`` option, and the options naming the folders training reads.

A :class:`~catalign.errors.CatalignError` is the user's to act on, so it is printed as
``error: <message>`` with exit code 2, never as a traceback; anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, TypeVar

import typer
from pydantic import BaseModel, ValidationError

from catalign.errors import CatalignError

Config = TypeVar("Config", bound=BaseModel)

# ``--engine NAME=VALUE`` (repeatable): EngineConfig options, for the commands that take them.
EngineOptions = Annotated[
    list[str] | None,
    typer.Option(
        metavar="NAME=VALUE",
        help="An engine option of catalign.registration.config.EngineConfig, by its dotted name "
        "(e.g. top_k=5, sweep.models=0); repeat the option for several.",
    ),
]


@contextmanager
def exit_on_error() -> Iterator[None]:
    """Run the block; on a CatalignError print its message and exit with code 2."""
    try:
        yield
    except CatalignError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(code=2) from None


def options_to(config: Callable[..., Config], **options: object) -> Config:
    """``config(**options)``; when a value is refused, print which option and why (``error:
    --up-frame: ...``) and exit with code 2."""
    try:
        return config(**options)
    except ValidationError as error:
        first = error.errors()[0]
        message = first["msg"].removeprefix("Value error, ")
        if first["loc"]:  # one option's value; else a rule across options
            message = "--" + str(first["loc"][0]).replace("_", "-") + ": " + message
        typer.echo(f"error: {message}", err=True)
        raise typer.Exit(code=2) from None


# The options naming a user's CAD folder of one category and the shared shapes' folders, as
# the training commands take them.
CategoryFolder = Annotated[
    Path | None, typer.Option(help="Your own canonically aligned CAD files (+Y up) of --category.")
]
FolderUnits = Annotated[str, typer.Option(help="Units of the --data files: m, cm or mm.")]
ChairsFolder = Annotated[
    Path | None, typer.Option(help="Shared chairs folder (default: ../shared/data/chairs).")
]
TablesFolder = Annotated[
    Path | None, typer.Option(help="Shared tables folder (default: ../shared/data/tables).")
]
