"""``mmgp convert``: real robot formats (bags, RTDE, franka_ros, mapped CSV, shared datasets) in."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .common import _fail, app


def _summary(path: Path, log) -> list[str]:
    kinds = "/".join(k for k in ("q", "dq", "ddq", "tau") if getattr(log, k) is not None)
    lines = [f"wrote {path}: {log.n_samples} rows, {log.n_joints} joints, {kinds}, "
             f"t {log.t[0]:.3f} .. {log.t[-1]:.3f} s, robot {log.robot or '-'}"
             + (f", URDF {path.stem}.urdf" if log.urdf is not None and path.suffix.lower() != ".csv" else "")]
    if path.suffix.lower() == ".csv" and (log.robot or log.joint_names):
        lines.append("  note: a CSV log holds no metadata: robot and joint names are not stored (use .parquet)")
    lines += [f"  note: {n}" for n in log.notes]
    return lines


@app.command()
def convert(input: Path = typer.Argument(..., help="Bag (.bag, ROS 2 folder, .db3, .mcap), CSV, or dataset folder."),
            out: Path = typer.Option(..., "--out", help="Log file (.parquet or .csv), or a folder for all parts."),
            robot: Optional[str] = typer.Option(None, "--robot", help="example-robot-data robot: orders and "
                                                "names the joints as its model does."),
            map_file: Optional[Path] = typer.Option(None, "--map", help="YAML map: columns, units, topic, "
                                                    "torque source, ... (see docs/convert.md)."),
            topic: Optional[str] = typer.Option(None, "--topic", help="Bag topic to read (when there are several)."),
            part: Optional[str] = typer.Option(None, "--part", help="Of an input holding several logs, the one "
                                               "to write to a single --out file."),
            force: bool = typer.Option(False, "--force", help="Replace an existing --out.")):
    """Turn a robot recording into a contract log: t, q, tau (dq, ddq when recorded) and metadata."""
    from ..convert import read_input, write_logs

    start = time.perf_counter()
    try:
        parts = read_input(input, robot=robot, map_path=map_file, topic=topic)
        written = write_logs(parts, out, source=input, part=part, force=force)
    except InputError as exc:
        _fail(exc)
    chosen = [p for p in parts if part is None or p.name == part]
    by_name = {p.name: p for p in chosen}
    for path in (w for w in written if w.suffix.lower() != ".urdf"):
        typer.echo("\n".join(_summary(path, by_name[path.stem] if len(chosen) > 1 else chosen[0])))
    typer.echo(f"{sum(p.suffix != '.urdf' for p in written)} log(s) in {time.perf_counter() - start:.1f} s")
