"""The ``mmgp`` command line: parses options, calls the library, reports. Nothing else.

Every bad input ends in one line ``error: <file, column, row: what was expected>`` on stderr and
exit status 2; outputs are written into a temporary folder that replaces ``--out`` only when
complete. Each module of this package adds its commands to the one ``app``.
"""
from __future__ import annotations

import typer

from .. import __version__
# imported for their side effect, in the order `mmgp --help` lists the commands
from . import train, compensator, diagnose, convert, annotate, fleet, settings  # noqa: F401,I001
from .common import app


@app.command()
def version():
    """Print the version."""
    typer.echo(__version__)


def main() -> None:  # pragma: no cover - console entry point
    app()
