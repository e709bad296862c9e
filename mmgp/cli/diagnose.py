"""Commands that hold the nominal model against a log: diagnose, compare."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .common import DEVICE_HELP, _check_device, _fail, _robot_for, app, command_numerics


@app.command()
def diagnose(log: Path = typer.Argument(..., help="Log of the real robot."),
             out: Path = typer.Option(..., "--out"),
             robot: Optional[str] = typer.Option(None, "--robot"),
             urdf: Optional[Path] = typer.Option(None, "--urdf"),
             device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
             force: bool = typer.Option(False, "--force")):
    """Locate the sim-vs-real mismatch, name the missing physics, fit it, show the held-out gain."""
    from ..diagnosis.pipeline import diagnose as run_diagnose
    from ..data.outputs import atomic_output_dir
    from ..data.logs import read_log
    from ..data.differentiation import complete_derivatives

    try:
        _check_device(device)
        robot_model = _robot_for(log, robot, urdf)
        if robot_model is None:
            raise InputError("diagnosis needs a nominal model: give --robot NAME or --urdf PATH "
                             "(or name one in the log's metadata)", file=log)
        lg = complete_derivatives(read_log(log, n_joints=robot_model.n_joints, joint_names=robot_model.joint_names))
        with command_numerics(device), atomic_output_dir(out, force=force) as tmp:
            res = run_diagnose(lg, robot_model)
            res.write(tmp)
    except InputError as exc:
        _fail(exc)
    report = out / "report.md"
    typer.echo(report.read_text() if report.is_file() else (out / "findings.json").read_text())


@app.command()
def compare(log: Path = typer.Argument(..., help="Log to compare models on."),
            out: Path = typer.Option(..., "--out"),
            robot: Optional[str] = typer.Option(None, "--robot"),
            urdf: Optional[Path] = typer.Option(None, "--urdf"),
            max_train: int = typer.Option(1000, "--max-train", help="Training samples per fold."),
            device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
            force: bool = typer.Option(False, "--force")):
    """Held-out (time-block) normalised MSE per joint: rigid body only, GP only, rigid body + GP."""
    from ..evaluation.compare import compare as run_compare, format_compare, write_compare
    from ..data.outputs import atomic_output_dir
    from ..data.logs import read_log
    from ..data.differentiation import complete_derivatives

    try:
        _check_device(device)
        robot_model = _robot_for(log, robot, urdf)
        lg = complete_derivatives(read_log(log, n_joints=robot_model.n_joints if robot_model else None,
                                           joint_names=robot_model.joint_names if robot_model else None))
        with command_numerics(device), atomic_output_dir(out, force=force) as tmp:
            res = run_compare(lg, robot_model, max_train=max_train,
                              progress=lambda msg: typer.echo(msg, err=True))
            write_compare(res, tmp)
    except InputError as exc:
        _fail(exc)
    typer.echo(format_compare(res))
