"""Command-line front door: ``catalign evaluate|...``."""

from __future__ import annotations

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False, help=__doc__)


@app.callback()
def main() -> None:
    """catalign: align partial point clouds of chairs to a CAD library."""
