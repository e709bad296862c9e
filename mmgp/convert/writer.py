"""Writing converted logs: one file, or a folder of parts; complete or absent, inputs untouched."""
from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import pandas as pd

from ..errors import InputError
from ..data.outputs import atomic_output_dir, atomic_write_bytes, write_table
from .base import ConvertedLog

LOG_SUFFIXES = (".parquet", ".pq", ".csv")


def log_frame(log: ConvertedLog) -> pd.DataFrame:
    """Contract columns: t, q_*, [dq_*], [ddq_*], tau_*."""
    cols = {"t": log.t}
    cols.update({f"{k}_{j}": a[:, j] for k, a in log.arrays().items() for j in range(log.n_joints)})
    return pd.DataFrame(cols)


def log_metadata(log: ConvertedLog, urdf_name: str | None) -> dict[str, str]:
    """Parquet metadata: the contract's robot / urdf / joint_names / start_time, plus source, notes and
    (absolute stamps) time_origin."""
    meta = {"source": log.source, "notes": "; ".join(log.notes)}
    if log.robot is not None:
        meta["robot"] = log.robot
    if urdf_name is not None:
        meta["urdf"] = urdf_name
    if log.joint_names is not None:
        meta["joint_names"] = json.dumps(list(log.joint_names))
    if log.start_time is not None:
        meta["start_time"] = log.start_time
    if log.metadata.get("time_origin"):
        meta["time_origin"] = json.dumps(log.metadata["time_origin"])
    return meta


def _write_one(path: Path, log: ConvertedLog) -> list[Path]:
    """The log at ``path`` and, when it names a URDF, that URDF beside it (``<stem>.urdf``)."""
    written = []
    urdf_name = None
    if log.urdf is not None and path.suffix.lower() != ".csv":
        urdf_name = f"{path.stem}.urdf"
        target = path.with_name(urdf_name)
        existed = target.exists()
        atomic_write_bytes(target, Path(log.urdf).read_bytes())
        written.append(target)
    try:
        write_table(path, log_frame(log), metadata=log_metadata(log, urdf_name))
    except BaseException:
        if written and not existed:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(written[0])
        raise
    return [path] + written


def _inside(child: Path, parent: Path) -> bool:
    child, parent = child.resolve(), parent.resolve()
    return child == parent or parent in child.parents


def write_logs(parts: list[ConvertedLog], out: str | os.PathLike, *, source: str | os.PathLike,
               part: str | None = None, force: bool = False) -> list[Path]:
    """Write ``parts`` to ``out`` and return the files written.

    ``out`` ending in .parquet/.pq/.csv takes exactly one part (``part`` picks it by name);
    any other ``out`` is a folder that receives every part as ``<name>.parquet``. Existing
    outputs are refused unless ``force``; an output inside the input ``source`` is refused.
    """
    out, source = Path(out), Path(source)
    if part is not None:
        names = [p.name for p in parts]
        if part not in names:
            raise InputError(f"--part {part}: the input holds {names}", file=source)
        parts = [p for p in parts if p.name == part]
    if _inside(out, source):
        raise InputError(f"--out {out} lies inside the input: inputs are never modified", file=source)
    if out.suffix.lower() not in LOG_SUFFIXES:
        with atomic_output_dir(out, force=force) as tmp:
            for p in parts:
                _write_one(tmp / f"{p.name}.parquet", p)
        return sorted(f for f in out.iterdir() if f.is_file())
    if len(parts) != 1:
        raise InputError(f"the input holds {len(parts)} logs ({[p.name for p in parts]}): give --part NAME, "
                         "or an --out folder for all of them", file=source)
    if out.is_dir():
        raise InputError("--out is a folder; a log file name (.parquet/.csv) or a new folder was expected", file=out)
    if out.exists() and not force:
        raise InputError("--out exists (use --force to replace it)", file=out)
    return _write_one(out, parts[0])
