"""Commands that learn from logs and use what was learned: train, predict, evaluate, demo."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from ..errors import InputError
from .common import _fail, _check_device, _progress_printer, _robot_for, app


def _write_training_outputs(out: Path, result) -> None:
    from ..data.outputs import write_table
    from ..models.trained import labels_frame
    from ..evaluation.plots import plot_labels, plot_trace

    import numpy as np

    labels = labels_frame(result)
    write_table(out / "labels.parquet", labels)
    (out / "report.json").write_text(json.dumps(result.report, indent=2))
    result.model.save(out)
    t = np.concatenate([lg.t for lg in result.logs])
    tau = np.concatenate([lg.tau for lg in result.logs])
    plot_labels(out / "labels.png", t, tau, labels["mode"].to_numpy(), labels["p_disturbed"].to_numpy(),
                result.model.joint_names_)
    plot_trace(out / "likelihood_trace.png", result.report["likelihood_trace"])


@app.command()
def train(logs: List[Path] = typer.Argument(..., help="One or more logs (Parquet or CSV)."),
          out: Path = typer.Option(..., "--out", help="Output folder (created; refused if non-empty)."),
          config: Optional[Path] = typer.Option(None, "--config", help="YAML settings (see configs/default.yaml)."),
          modes: Optional[str] = typer.Option(None, "--modes", help="Number of dynamic modes, or 'auto'."),
          disturbance: Optional[bool] = typer.Option(None, "--disturbance/--no-disturbance",
                                                     help="Disturbance mode (default on)."),
          robot: Optional[str] = typer.Option(None, "--robot", help="example-robot-data robot name."),
          urdf: Optional[Path] = typer.Option(None, "--urdf", help="URDF file of the robot."),
          device: Optional[str] = typer.Option(None, "--device", help="torch device: cpu, cuda, auto."),
          seed: Optional[int] = typer.Option(None, "--seed"),
          force: bool = typer.Option(False, "--force", help="Replace a non-empty --out."),
          quiet: bool = typer.Option(False, "--quiet", help="No per-sweep progress.")):
    """Learn modes, disturbances and per-mode GPs from logs; write labels, report, model, plots."""
    from ..config import load_config
    from ..data.outputs import atomic_output_dir
    from ..models.trained import train as run_train

    try:
        _check_device(device)
        cfg = load_config(config, modes=modes, disturbance=disturbance, device=device, seed=seed)
        robot_model = _robot_for(logs[0], robot, urdf)
        with atomic_output_dir(out, force=force) as tmp:
            typer.echo(f"training on {len(logs)} log(s): modes={cfg.modes}, disturbance={cfg.disturbance}, "
                       f"robot={getattr(robot_model, 'name', None) or getattr(robot_model, 'urdf_path', None)}", err=True)
            result = run_train(logs, cfg, robot=robot_model, progress=_progress_printer(quiet))
            _write_training_outputs(tmp, result)
    except InputError as exc:
        _fail(exc)
    rep = result.report
    typer.echo(f"{rep['n_samples']} samples, {rep['n_modes']} mode(s), {rep['disturbance']['n_disturbed']} flagged "
               f"disturbed; {rep['n_sweeps']} sweeps ({'converged' if rep['converged'] else 'sweep limit'}), "
               f"{rep['timings']['total_s']:.1f} s. Wrote {out}/labels.parquet, report.json, model, plots.")


@app.command()
def predict(model_dir: Path = typer.Argument(..., help="Folder written by 'mmgp train'."),
            log: Path = typer.Argument(..., help="Log to predict (q, and dq/ddq or estimated)."),
            out: Path = typer.Option(..., "--out", help="Output Parquet file."),
            mode: int = typer.Option(0, "--mode", help="Mode to predict with (0 = nominal)."),
            force: bool = typer.Option(False, "--force")):
    """Predicted torque and its standard deviation per joint for a log."""
    import pandas as pd

    from ..data.logs import read_log
    from ..data.outputs import write_table
    from ..models.trained import TrainedModel
    from ..data.differentiation import SavitzkyGolay, complete_derivatives

    try:
        model = TrainedModel.load(model_dir)
        if out.exists() and not force:
            raise InputError("output exists (use --force to replace it)", file=out)
        lg = complete_derivatives(read_log(log, n_joints=model.n_joints),
                                  SavitzkyGolay(window_s=model.config.diff_window_s, cv=True))
        if not 0 <= mode < model.n_modes:
            raise InputError(f"--mode must be in 0..{model.n_modes - 1}")
        mean, std = model.predict(lg.q, lg.dq, lg.ddq, mode=mode)
        cols = {"t": lg.t}
        for j in range(model.n_joints):
            cols[f"tau_hat_{j}"] = mean[:, j]
            cols[f"tau_std_{j}"] = std[:, j]
        write_table(out, pd.DataFrame(cols))
    except InputError as exc:
        _fail(exc)
    typer.echo(f"wrote {out} ({len(lg.t)} samples, mode {mode})")


@app.command()
def evaluate(model_dir: Path = typer.Argument(..., help="Folder written by 'mmgp train'."),
             truth: Path = typer.Option(..., "--truth", help="Ground-truth labels (t, disturbed and/or mode).")):
    """Classification figures against ground truth; writes DIR/evaluation.json."""
    import pandas as pd

    from ..evaluation.metrics import classification_figures, format_figures
    from ..data.outputs import atomic_write_bytes
    from ..data.logs import read_labels

    try:
        lab_path = model_dir / "labels.parquet"
        if not lab_path.is_file():
            raise InputError("labels.parquet missing (run 'mmgp train' first)", file=model_dir)
        pred = pd.read_parquet(lab_path)
        if "log" in pred.columns:
            raise InputError("evaluation of a model trained on several logs needs one truth file per log; "
                             "train on the log alone to evaluate it", file=lab_path)
        tr = read_labels(truth, t=pred["t"].to_numpy())
        fig = classification_figures(pred, tr)
        atomic_write_bytes(model_dir / "evaluation.json", json.dumps(fig, indent=2).encode())
    except InputError as exc:
        _fail(exc)
    typer.echo(format_figures(fig))


@app.command()
def demo(out: Path = typer.Option(Path("mmgp-demo"), "--out", help="Output folder."),
         force: bool = typer.Option(False, "--force")):
    """Train and evaluate on the shipped 1-DOF replica of the source experiment (MuJoCo,
    0.73 kg load, Bowden-cable-like friction, pushes, 20 Hz) and print our figures beside the source's."""
    from ..config import load_config
    from ..evaluation.metrics import classification_figures, format_figures
    from ..data.outputs import atomic_output_dir, atomic_write_bytes
    from ..data.logs import read_labels
    from ..models.trained import labels_frame, train as run_train
    from ..resources import demo_files

    marker = ".mmgp-demo"
    if out.exists() and (out / marker).exists():
        force = True  # the demo may replace its own previous output
    try:
        with atomic_output_dir(out, force=force) as tmp:
            log, lab = demo_files()
            typer.echo(f"demo: training on {log}", err=True)
            result = run_train([log], load_config(), progress=_progress_printer(False))
            _write_training_outputs(tmp, result)
            pred = labels_frame(result)
            fig = classification_figures(pred, read_labels(lab, t=pred["t"].to_numpy()))
            atomic_write_bytes(tmp / "evaluation.json", json.dumps(fig, indent=2).encode())
            (tmp / marker).write_text("written by mmgp demo\n")
    except InputError as exc:
        _fail(exc)
    typer.echo("")
    typer.echo("1-DOF replica of the source experiment (Haninger 2016, ch. 5): disturbance classification")
    typer.echo(format_figures(fig, with_source=True))
    typer.echo(f"\ntrained in {result.report['timings']['total_s']:.1f} s; outputs in {out}/ "
               "(labels.parquet, report.json, evaluation.json, labels.png, likelihood_trace.png)")
