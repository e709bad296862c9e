"""Commands that hold the nominal model against a log: diagnose, compare."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .common import (DEVICE_HELP, ProgressDisplay, _check_device, _fail, _given, _robot_for, app, command_numerics,
                     config_option, echo_warnings, force_option, out_dir_option, parameter_default, quiet_option, read_logs,
                     robot_option, setting_option, thinning_line, urdf_option)


@app.command()
def diagnose(log: Path = typer.Argument(..., help="Log of the real robot."),
             out: Path = out_dir_option(),
             robot: Optional[str] = robot_option(),
             urdf: Optional[Path] = urdf_option(),
             config: Optional[Path] = config_option("diagnose", " (Diagnoser settings)"),
             device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
             force: bool = force_option(),
             quiet: bool = quiet_option()):
    """Locate the sim-vs-real mismatch, name the missing physics, fit it, show the held-out gain."""
    read = read_logs([log])[0]
    try:
        with ProgressDisplay(quiet) as shown:
            shown.waiting("diagnose: loading the libraries and the robot")  # the imports take seconds
            from ..data.logs import for_robot
            from ..data.outputs import atomic_output_dir
            from ..config import load_settings
            from ..diagnosis import Diagnoser
            from ..diagnosis.pipeline import STAGES

            _check_device(device)
            diagnoser = Diagnoser(**load_settings(config, "diagnose", Diagnoser))
            robot_model = _robot_for(read, robot, urdf)
            if robot_model is None:
                raise InputError("diagnosis needs a nominal model: give --robot NAME or --urdf PATH "
                                 "(or name one in the log's metadata)", file=log)
            read = for_robot(read, n_joints=robot_model.n_joints, joint_names=robot_model.joint_names)
            with command_numerics(device), atomic_output_dir(out, force=force, inputs=_given(log, urdf, config)) as tmp:
                # the diagnosis's stages and the report's writing: the count follows the library's reports
                shown.stage("diagnose", len(STAGES) + 1, follow="diagnosis")
                diagnoser.fit(read, robot_model)
                shown.step(f"diagnose: writing the report [{len(STAGES) + 1}/{len(STAGES) + 1}]",
                           completed=len(STAGES))
                diagnoser.report(tmp)
                shown.step(completed=len(STAGES) + 1)
                info = diagnoser.result_.info
                line = thinning_line(info["n_samples"], info["n_samples_in_log"],
                                     f"max_samples {diagnoser.max_samples}")
                if line:
                    shown.step(line)
    except InputError as exc:
        _fail(exc)
    typer.echo(diagnoser.result_.report_markdown())     # report.md without its plot links
    echo_warnings(diagnoser.result_.warnings)


@app.command()
def compare(log: Path = typer.Argument(..., help="Log to compare models on."),
            out: Path = out_dir_option(),
            robot: Optional[str] = robot_option(),
            urdf: Optional[Path] = urdf_option(),
            config: Optional[Path] = config_option("compare", " (compare's settings)"),
            max_train: Optional[int] = setting_option("compare", "max_train", "--max-train", min=2,
                                                      help="Training samples per fold."),
            device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
            force: bool = force_option(),
            quiet: bool = quiet_option()):
    """Held-out (time-block) normalised MSE per joint: rigid body only, GP only, rigid body + GP."""
    read = read_logs([log])[0]
    from ..config import load_settings
    from ..evaluation.compare import compare as run_compare, format_compare, write_compare
    from ..data.outputs import atomic_output_dir
    from ..data.logs import for_robot
    from ..data.differentiation import complete_derivatives

    try:
        _check_device(device)
        settings = load_settings(config, "compare", run_compare, max_train=max_train)
        robot_model = _robot_for(read, robot, urdf)
        lg = complete_derivatives(for_robot(read, n_joints=robot_model.n_joints if robot_model else None,
                                            joint_names=robot_model.joint_names if robot_model else None))
        with (command_numerics(device), atomic_output_dir(out, force=force, inputs=_given(log, urdf, config)) as tmp,
              ProgressDisplay(quiet) as shown):
            shown.stage("compare: folds", settings.get("n_folds", parameter_default(run_compare, "n_folds")))
            res = run_compare(lg, robot_model, **settings, progress=lambda msg: shown.step(msg, advance=1))
            write_compare(res, tmp)
    except InputError as exc:
        _fail(exc)
    typer.echo(format_compare(res))
    echo_warnings(res["warnings"])
