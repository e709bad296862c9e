"""``mmgp config``: the settings files shipped with the package (a start for ``--config``)."""
from __future__ import annotations

import typer

from ..errors import InputError
from .common import _fail, app
from .helptext import App

config_app = App(no_args_is_help=True, help="The settings files shipped with mmgp (for --config).")
app.add_typer(config_app, name="config")


@config_app.command("list")
def list_configs():
    """Name and path of each shipped settings file."""
    from ..resources import config_files

    for name, path in config_files().items():
        typer.echo(f"{name:<16}{path}")


@config_app.command("show")
def show_config(name: str = typer.Argument("default", help="Shipped settings file (see 'mmgp config list').")):
    """Print a shipped settings file, e.g. 'mmgp config show default > my.yaml', then --config my.yaml."""
    from ..resources import config_file

    try:
        path = config_file(name)
    except InputError as exc:
        _fail(exc)
    typer.echo(path.read_text(), nl=False)
