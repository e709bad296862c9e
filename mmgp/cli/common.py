"""What every command shares: the typer app, the one-line error with exit status 2, robots, progress."""
from __future__ import annotations

import contextlib
import signal
import threading
from pathlib import Path
from typing import Iterator, Optional

import typer

from ..errors import InputError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Multimodal GP inverse dynamics from messy robot logs.")


EXIT_BAD_INPUT = 2


def _fail(exc: Exception) -> None:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


DEVICE_HELP = "torch device of the GPs: cpu (default), cuda, cuda:N or auto (cuda when there is one)."


def _check_device(device: Optional[str]) -> None:
    from ..gp.linalg import resolve_device

    if device is None:
        return
    try:
        resolve_device(device)
    except (ValueError, RuntimeError) as exc:
        raise InputError(f"--device {device}: {exc}") from None


def _stop_on_sigterm(signum, frame):
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def command_numerics(device: Optional[str] = None) -> Iterator[None]:
    """What every command computes under: the one thread policy (:mod:`mmgp.threads`: one thread,
    large factorisations on idle cores), ``device`` as the default device of every GP built
    inside (:func:`mmgp.gp.linalg.default_device`), and SIGTERM (``timeout``, schedulers) turned
    into an ordinary exit, so an interrupted command removes its unfinished output folder."""
    from ..gp.linalg import default_device
    from ..threads import limit_threads

    _check_device(device)
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _stop_on_sigterm) if in_main else None
    try:
        with default_device(device), limit_threads(1):
            yield
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


def _robot_for(log_path, robot: Optional[str], urdf: Optional[Path], n_joints: Optional[int] = None):
    from ..physics.robot import load_robot

    return load_robot(robot=robot, urdf=urdf, log_path=log_path, n_joints=n_joints)


def _progress_printer(quiet: bool):
    if quiet:
        return None

    def show(rec):
        typer.echo(f"  sweep {rec.sweep:3d}  log p(Y,s) {rec.log_joint:12.2f}  changed {rec.changed:6.1%}  "
                   f"disturbed {rec.n_disturbed:5d}  modes {rec.mode_sizes}  ({rec.seconds:.2f} s)", err=True)

    return show
