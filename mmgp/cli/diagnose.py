"""Commands that hold the nominal model against a log: diagnose, compare."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .common import _check_device, _fail, _robot_for, app


def _diagnose_settings(path: Optional[Path]) -> dict:
    """Settings of the YAML section ``diagnose:`` (every key a Diagnoser parameter).

    A local reader until the generic ``mmgp.config.load_settings(path, section, cls)`` is on
    main; the lead connects it there.
    """
    if path is None:
        return {}
    import yaml

    from ..diagnosis import Diagnoser

    if not path.is_file():
        raise InputError("config file does not exist", file=path)
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML ({exc})", file=path) from None
    section = doc.get("diagnose") if isinstance(doc, dict) else None
    if section is None:
        return {}
    if not isinstance(section, dict):
        raise InputError("section 'diagnose' is not a mapping of setting: value", file=path)
    known = set(Diagnoser().get_params()) - {"selector", "differentiator"}
    unknown = sorted(set(section) - known)
    if unknown:
        raise InputError(f"unknown diagnose setting(s) {unknown}; known: {sorted(known)}", file=path)
    return section


@app.command()
def diagnose(log: Path = typer.Argument(..., help="Log of the real robot."),
             out: Path = typer.Option(..., "--out", help="Output folder (created; refused if non-empty)."),
             robot: Optional[str] = typer.Option(None, "--robot", help="example-robot-data robot name."),
             urdf: Optional[Path] = typer.Option(None, "--urdf", help="URDF file of the robot."),
             config: Optional[Path] = typer.Option(None, "--config", help="YAML file; section 'diagnose:' holds "
                                                   "Diagnoser settings."),
             force: bool = typer.Option(False, "--force", help="Replace a non-empty --out.")):
    """Locate the sim-vs-real mismatch, name the missing physics, fit it, show the held-out gain."""
    from ..data.outputs import atomic_output_dir
    from ..diagnosis import Diagnoser

    try:
        diagnoser = Diagnoser(**_diagnose_settings(config))
        robot_model = _robot_for(log, robot, urdf)
        if robot_model is None:
            raise InputError("diagnosis needs a nominal model: give --robot NAME or --urdf PATH "
                             "(or name one in the log's metadata)", file=log)
        with atomic_output_dir(out, force=force) as tmp:
            diagnoser.fit(log, robot_model).report(tmp)
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
            device: str = typer.Option("cpu", "--device", help="torch device: cpu, cuda, auto."),
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
        with atomic_output_dir(out, force=force) as tmp:
            res = run_compare(lg, robot_model, max_train=max_train, gp_options={"device": device},
                              progress=lambda msg: typer.echo(msg, err=True))
            write_compare(res, tmp)
    except InputError as exc:
        _fail(exc)
    typer.echo(format_compare(res))
