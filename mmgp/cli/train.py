"""Commands that learn from logs and use what was learned: train, predict, evaluate, demo.

Each one parses its options, calls :class:`mmgp.MultimodalGP` and prints; training settings
come from the ``train:`` section of ``--config`` with the flags on top.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from ..errors import InputError
from .common import (DEVICE_HELP, ProgressDisplay, SweepProgress, _fail, _given, _model_files, app, read_logs,
                     command_numerics, config_option, device_option, echo_warnings, force_option, logs_argument,
                     out_dir_option, quiet_option, seed_option, setting_option, sweep_limit, thinning_line)


def _modes(value: Optional[str]):
    if value is None or value == "auto":
        return value
    try:
        return int(value)
    except ValueError:
        raise InputError(f"--modes: expected a positive integer or 'auto', got {value!r}") from None


def _robot_option(robot: Optional[str], urdf: Optional[Path]):
    if robot is not None and urdf is not None:
        raise InputError("give either --robot or --urdf, not both")
    return robot if robot is not None else urdf


def _write_training_outputs(out: Path, model, evaluation: dict | None = None, title: str = "mmgp train") -> None:
    """labels.parquet, report.json, model.npz + model.json, the two plots and report.html
    (with the classification figures of ``evaluation`` when given)."""
    import numpy as np

    from ..data.outputs import atomic_write_text, write_table
    from ..evaluation.plots import plot_labels, plot_trace
    from ..evaluation.reports import write_training_report

    labels = model.labels_
    write_table(out / "labels.parquet", labels)
    atomic_write_text(out / "report.json", json.dumps(model.report_, indent=2))
    model.save(out)
    t = np.concatenate([lg.t for lg in model.logs_])
    tau = np.concatenate([lg.tau for lg in model.logs_])
    plot_labels(out / "labels.png", t, tau, labels["mode"].to_numpy(), labels["p_disturbed"].to_numpy(),
                model.joint_names_)
    plot_trace(out / "likelihood_trace.png", model.report_["likelihood_trace"])
    write_training_report(out, model.report_, evaluation, title=title)


def _summary(model) -> str:
    rep = model.report_
    spec = model.robot_spec_ or {}
    return (f"{rep['n_samples']} samples, robot {spec.get('robot') or spec.get('urdf')}, {rep['n_modes']} mode(s), {rep['disturbance']['n_disturbed']} flagged "
            f"disturbed; {rep['n_sweeps']} sweeps ({'converged' if rep['converged'] else 'sweep limit'}), "
            f"{rep['timings']['total_s']:.1f} s.{_flags_note(rep)}{_shortened(rep)}{_selection(rep)}{_dissipation(rep)}")


def _flags_note(rep: dict) -> str:
    """Why the flagged count differs from the last sweep's "disturbed": the flags are the final
    labels (averaged sweeps, short pushes dropped, the scan's added; none when abstaining)."""
    trace = rep.get("likelihood_trace") or []
    dist = rep["disturbance"]
    kept = rep.get("labels_from_sweep")
    if kept is not None:
        best, last = trace[kept], trace[-1]
        cycle = (f" The sweeps did not converge (the last held {last['n_disturbed']} samples in the disturbance "
                 f"state, log marginal {last['log_marginal']:.1f}); the labels are sweep {kept}'s, whose log "
                 f"marginal {best['log_marginal']:.1f} is the highest since the last hyperparameter refit.")
        trace = trace[:kept + 1]
    else:
        cycle = ""
    if not trace or trace[-1]["n_disturbed"] == dist["n_disturbed"]:
        return cycle
    if dist.get("abstained"):
        return cycle + (f" The sweeps held {trace[-1]['n_disturbed']} samples in the disturbance state, but it did not "
                        "raise the evidence by more than its price (a log without pushes), so none is flagged.")
    which, labels = ("kept", "its labels") if kept is not None else ("last", "the averaged labels of the last sweeps")
    return cycle + (f" The {which} sweep held {trace[-1]['n_disturbed']} in the disturbance state; the flags are "
                    f"{labels}, without pushes shorter than min_push_s, plus the sustained-offset scan's "
                    f"({dist.get('n_by_scan', 0)}).")


def _dissipation(rep: dict) -> str:
    """Which start the evidence kept, and what the friction check found where it refitted
    (mmgp.labelling.dissipation)."""
    d = rep.get("dissipation") or {}
    fits = d.get("fits") or []
    if len(fits) < 2:
        return ""
    kept = fits[d["chosen"]]
    starts = [f for f in fits if f.get("start") != "swapped labels"]
    refits = len(fits) - len(starts)
    out = ""
    if len(starts) > 1:
        out += (" The EM ran from both starts (" + ", ".join(f"{f['start']} {f['log_marginal']:.1f}" for f in starts)
                + " log marginal);")
    if refits:
        first = fits[0]
        depth = f" (p {first['p_value']:.2g} for a dissipative model)" if "p_value" in first else ""
        out += (f" Friction: the first fit's injected energy on {100 * first['worst']:.0f}% of the sliding samples"
                f"{depth}; refitted {refits} time(s) from labels swapped there;")
    state = "dissipates" if d["physical"] else f"still injects energy on {100 * kept['worst']:.0f}% of sliding samples"
    gap = d["runner_up_gap"]
    runner_up = (f"the runner-up {gap:.1f} lower" if gap >= 0 else
                 f"a fit whose friction injects energy {-gap:.1f} higher, not kept")
    return (out + f" kept fit {d['chosen'] + 1} ({kept.get('start', 'first')}), whose friction {state} "
            f"(log marginal {kept['log_marginal']:.1f}, {runner_up}).")


def _selection(rep: dict) -> str:
    """Why --modes auto stopped where it did (the last K tried, if it was not kept)."""
    sel = rep.get("mode_selection")
    if not sel:
        return ""
    chosen, tried = int(sel["chosen"]), max(int(k) for k in sel["scores"])
    if tried == chosen:
        return f" --modes auto: {chosen} mode(s), the most tried."
    scores = {int(k): v for k, v in sel["scores"].items()}
    runs = {int(k): v for k, v in sel.get("longest_run_s", {}).items()}
    if scores[tried] <= scores[chosen]:
        why = f"scored lower ({scores[tried]:.1f} vs {scores[chosen]:.1f})"
    else:
        why = (f"one of its modes lasted at most {min(runs[tried]):.2g} s in one stretch "
               f"(< min_mode_s {sel.get('min_mode_s')} s)")
    abandoned = {int(k): v for k, v in (sel.get("abandoned") or {}).items()}
    if abandoned.get(tried):
        why += f"; stopped early, one of its modes held nowhere for {sel.get('min_mode_s')} s in one stretch"
    return f" --modes auto: {chosen} mode(s); {tried} rejected: {why}."


def _shortened(rep: dict) -> str:
    short = rep.get("windows_shortened_s") or {}
    if not short:
        return ""
    parts = ", ".join(f"{k} {v:.3g} s" for k, v in short.items())
    return f" The log is short: time windows shortened to {parts}."


@app.command()
def train(logs: List[Path] = logs_argument(),
          out: Path = out_dir_option(),
          config: Optional[Path] = config_option("train", " ('mmgp config show default' prints every setting "
                                                          "at its default)"),
          modes: Optional[str] = setting_option("train", "n_modes", "--modes",
                                                help="Number of dynamic modes, or 'auto'."),
          disturbance: Optional[bool] = setting_option("train", "disturbance", "--disturbance/--no-disturbance",
                                                       help="Disturbance mode."),
          robot: Optional[str] = setting_option("train", "robot", "--robot", help="example-robot-data robot name; "
                                                "default: the one the log's metadata names."),
          urdf: Optional[Path] = typer.Option(None, "--urdf", help="URDF file of the robot."),
          device: Optional[str] = device_option("train"),
          seed: Optional[int] = seed_option(section="train"),
          force: bool = force_option(),
          quiet: bool = quiet_option()):
    """Learn modes, disturbances and per-mode GPs from logs; write labels, report, model, plots, report.html."""
    read = read_logs(logs)
    try:
        with ProgressDisplay(quiet) as shown:
            shown.waiting("train: loading the libraries")  # the imports take seconds
            from ..config import load_settings
            from ..data.outputs import atomic_output_dir
            from ..estimator import MultimodalGP

            settings = load_settings(config, "train", MultimodalGP, n_modes=_modes(modes), disturbance=disturbance,
                                     robot=_robot_option(robot, urdf), device=device, seed=seed)
            with command_numerics(device), atomic_output_dir(out, force=force, inputs=_given(*logs, config)) as tmp:
                model = MultimodalGP(**settings, progress=SweepProgress(shown, sweep_limit(settings)))
                shown.stage(f"train: {len(logs)} log(s)", None)
                model.fit(read)
                _step_thinning(shown, model.report_.get("thinning"))
                shown.stage("train: writing the model, labels, plots and report", None)
                _write_training_outputs(tmp, model)
    except InputError as exc:
        _fail(exc)
    typer.echo(f"{_summary(model)} Wrote {out}/labels.parquet, report.json, model, plots, report.html.")
    if model.report_.get("heldout"):
        from ..evaluation.heldout import format_heldout

        typer.echo(format_heldout(model.report_["heldout"]))
    echo_warnings(model.report_.get("warnings"))


def _step_thinning(shown: ProgressDisplay, thinning: dict | None) -> None:
    """The line saying how many samples rate_hz left (docs/training.md, Thinning and subsampling)."""
    if thinning:
        line = thinning_line(thinning["n_used"], thinning["n_read"], f"rate_hz {thinning['rate_hz']:g}")
        if line:
            shown.step(line)


def _check_model_device(model, model_dir: Path) -> None:
    """A model trained on a device this machine lacks is refused with the way out."""
    from ..gp.linalg import resolve_device

    try:
        resolve_device(model.device)
    except ValueError:
        raise InputError(f"the model was trained with device {model.device!r}, which this machine lacks: "
                         "give --device cpu", file=model_dir) from None


@app.command()
def predict(model_dir: Path = typer.Argument(..., help="Folder written by 'mmgp train'."),
            log: Path = typer.Argument(..., help="Log to predict (q, and dq/ddq or estimated)."),
            out: Path = typer.Option(..., "--out", help="Output Parquet file."),
            mode: int = typer.Option(0, "--mode", help="Mode to predict with (0 = nominal)."),
            device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP.replace("cpu (default)", "cpu") + " Default: the model's."),
            force: bool = force_option()):
    """Predicted torque and its standard deviation per joint for a log."""
    import pandas as pd

    from ..data.differentiation import SavitzkyGolay, complete_derivatives
    from ..data.logs import read_log
    from ..data.outputs import check_output, write_table
    from ..estimator import MultimodalGP

    try:
        model = MultimodalGP.load(model_dir)
        if device is not None:
            model.set_params(device=device)
        else:
            _check_model_device(model, model_dir)
        check_output(out, force=force, inputs=_model_files(model_dir) + [log])
        if not 0 <= mode < model.n_modes_:
            raise InputError(f"--mode must be in 0..{model.n_modes_ - 1}")
        lg = complete_derivatives(read_log(log, n_joints=len(model.joint_names_)),
                                  SavitzkyGolay(window_s=model.diff_window_s, cv=True))
        with command_numerics(device):
            mean, std = model.predict(lg.q, lg.dq, lg.ddq, mode=mode)
        cols = {"t": lg.t}
        for j in range(len(model.joint_names_)):
            cols[f"tau_hat_{j}"] = mean[:, j]
            cols[f"tau_std_{j}"] = std[:, j]
        write_table(out, pd.DataFrame(cols), force=force, inputs=_model_files(model_dir) + [log])
    except InputError as exc:
        _fail(exc)
    typer.echo(f"wrote {out} ({len(lg.t)} samples, mode {mode})")


@app.command()
def evaluate(model_dir: Path = typer.Argument(..., help="Folder written by 'mmgp train'."),
             truth: Path = typer.Option(..., "--truth", help="Ground-truth labels (t, disturbed and/or mode).")):
    """Classification figures against ground truth; writes DIR/evaluation.json, adds them to DIR/report.html."""
    import pandas as pd

    from ..data.outputs import atomic_write_bytes
    from ..evaluation.metrics import format_figures
    from ..evaluation.reports import write_training_report

    try:
        lab_path = model_dir / "labels.parquet"
        if not lab_path.is_file():
            raise InputError("labels.parquet missing (run 'mmgp train' first)", file=model_dir)
        pred = pd.read_parquet(lab_path)
        if "log" in pred.columns:
            raise InputError("evaluation of a model trained on several logs needs one truth file per log; "
                             "train on the log alone to evaluate it", file=lab_path)
        fig = _figures(pred, truth)
        atomic_write_bytes(model_dir / "evaluation.json", json.dumps(fig, indent=2).encode(), inputs=[truth])
        if (model_dir / "report.json").is_file():  # the page now shows the figures too
            write_training_report(model_dir, json.loads((model_dir / "report.json").read_text()), fig)
    except InputError as exc:
        _fail(exc)
    typer.echo(format_figures(fig))


def _figures(pred, truth_path: Path) -> dict:
    from ..data.logs import read_labels
    from ..evaluation.metrics import classification_figures

    return classification_figures(pred, read_labels(truth_path, t=pred["t"].to_numpy()))


@app.command()
def demo(out: Path = typer.Option(Path("mmgp-demo"), "--out", help="Output folder."),
         force: bool = force_option(),
         quiet: bool = quiet_option()):
    """Train and evaluate on the shipped 1-DOF replica of the source experiment (MuJoCo,
    0.73 kg load, Bowden-cable-like friction, pushes, 20 Hz) and print our figures beside the source's."""
    from ..data.outputs import atomic_output_dir, atomic_write_bytes, atomic_write_text
    from ..estimator import MultimodalGP
    from ..evaluation.metrics import format_figures
    from ..resources import demo_files

    marker = ".mmgp-demo"
    if out.exists() and (out / marker).exists():
        force = True  # the demo may replace its own previous output
    try:
        with atomic_output_dir(out, force=force) as tmp, ProgressDisplay(quiet) as shown:
            log, lab = demo_files()
            shown.step(f"demo: training on {log}")
            model = MultimodalGP(progress=SweepProgress(shown, sweep_limit({}))).fit(log)
            fig = _figures(model.labels_, lab)
            _write_training_outputs(tmp, model, fig, title="mmgp demo: 1-DOF replica of the source experiment")
            atomic_write_bytes(tmp / "evaluation.json", json.dumps(fig, indent=2).encode())
            atomic_write_text(tmp / marker, "written by mmgp demo\n")
    except InputError as exc:
        _fail(exc)
    typer.echo("")
    typer.echo("1-DOF replica of the source experiment (Haninger 2016, ch. 5): disturbance classification")
    typer.echo(format_figures(fig, with_source=True))
    typer.echo(f"\ntrained in {model.report_['timings']['total_s']:.1f} s; outputs in {out}/ "
               "(report.html, labels.parquet, report.json, evaluation.json, labels.png, likelihood_trace.png)")
