"""The fleet command: many logs as Ray tasks, one table, trends and drift flags."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..errors import InputError
from .common import (ProgressDisplay, _fail, _given, app, force_option, logs_argument, out_dir_option, quiet_option,
                     robot_option, urdf_option)


def _progress(shown: ProgressDisplay, total: int):
    # no line of its own when piped: a bad log time found before the first log stays one error line
    shown.stage("fleet: logs", total, line=False)

    def step(done: int, total: int, outcome: dict) -> None:
        what = f"error: {outcome['error']}" if outcome["error"] else f"{len(outcome['findings'])} finding(s)"
        shown.step(f"  [{done}/{total}] {outcome['log']}: {what} ({outcome['seconds']:.1f} s)", completed=done,
                   total=total)

    return step


def _report(fleet, out: Path) -> str:
    s = fleet.summary()
    lines = [f"{s['n_logs']} log(s), {s['n_failed']} failed; {s['engine']} engine, {s['workers'] or 'cluster'} "
             f"worker(s), {s['seconds']:.1f} s."]
    for d in fleet.drift_["series"]:
        if d["status"] == "drift":
            lines.append(f"DRIFT {d['robot']} {d['effect']} {d['joint'] or ''} {d['param']}: from {d['first_log']} "
                         f"({d['first_value']:.4g}, baseline {d['baseline']['lo']:.4g}..{d['baseline']['hi']:.4g}), "
                         f"{len(d['flagged_logs'])} log(s) flagged")
        elif d["status"] == "appeared":
            lines.append(f"NEW   {d['robot']} {d['effect']} {d['joint'] or ''} {d['param']}: first in {d['first_log']}")
    drift = fleet.drift_
    if drift["robots_without_baseline"]:
        lines.append(f"NO BASELINE for {', '.join(map(str, drift['robots_without_baseline']))}: fewer than "
                     f"{drift['baseline_size']} log(s), no series judged (--baseline sets the number)")
    by_mtime = sum(log["log_time_source"] == "mtime" for log in s["logs"])
    if by_mtime:
        lines.append(f"{by_mtime} log(s) without start_time in their metadata: placed in time by file mtime")
    lines.append(f"Wrote {out}/report.html, fleet.parquet, drift.json, fleet.json, trends/, logs/.")
    return "\n".join(lines)


@app.command()
def fleet(logs: List[Path] = logs_argument("Log files, or folders of logs (*.parquet, *.pq, *.csv)."),
          out: Path = out_dir_option(),
          address: Optional[str] = typer.Option(None, "--address",
                                                help="Ray cluster address (e.g. auto, ray://host:10001); "
                                                     "default: a local Ray on this machine."),
          train: bool = typer.Option(False, "--train", help="Also train a model on each log."),
          robot: Optional[str] = robot_option(),
          urdf: Optional[Path] = urdf_option(),
          workers: Optional[int] = typer.Option(None, "--workers",
                                                help="Tasks at once (default: the cores available)."),
          baseline: int = typer.Option(5, "--baseline", help="First logs per robot that define the drift baseline."),
          serial: bool = typer.Option(False, "--serial", help="Run the logs one after another here, without Ray."),
          force: bool = force_option(),
          quiet: bool = quiet_option()):
    """Diagnose (and with --train train on) every log as a Ray task; write one table (DIR/fleet.parquet),
    trend plots (DIR/trends/), drift flags (DIR/drift.json) and DIR/report.html."""
    settings = dict(robot=robot, urdf=urdf, train=train, engine="serial" if serial else "ray", address=address,
                    workers=workers, baseline=baseline)
    try:
        with ProgressDisplay(quiet) as shown:
            shown.waiting("fleet: loading the libraries")  # the imports take seconds
            runner, missing = _run(shown, logs, out, force, settings)
    except InputError as exc:
        _fail(exc)
    if missing is not None:
        typer.echo(f"error: {missing}", err=True)
        raise typer.Exit(1)
    typer.echo(_report(runner, out))


def _run(shown: ProgressDisplay, logs: List[Path], out: Path, force: bool, settings: dict):
    """The fleet run and its outputs; (the Fleet, None), or (it, the error) when Ray is missing."""
    from ..data.outputs import atomic_output_dir
    from ..fleet import Fleet, expand_logs
    from ..fleet.engine import RayMissingError

    runner = Fleet(**settings)
    try:
        with atomic_output_dir(out, force=force, inputs=_given(*logs)) as tmp:
            runner.fit(logs, progress=_progress(shown, len(expand_logs(logs))))
            shown.stage("fleet: writing the table, trends, drift flags and report", None)
            runner.write(tmp)
    except RayMissingError as exc:
        return runner, exc
    return runner, None
