"""What one fleet task does with one log: read it, diagnose it (optionally train on it), report.

Everything here runs inside a Ray worker (or in this process for the serial engine) and returns
plain data (dicts, lists, bytes), so that results travel back from any node of a cluster and
the driver alone writes the output folder.
"""
from __future__ import annotations

import os
import tempfile
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path

from ..data.times import EXAMPLE, START_TIME_KEY, parse_start_time
from ..errors import InputError
from ..threads import limit_threads
from ..progress import report

#: the metadata key fleets before contract 1.2 read (ISO 8601, a time without zone taken as UTC,
#: or Unix seconds); still read after ``start_time`` so that logs written for them keep their times
LEGACY_TIME_KEY = "log_time"


def _parse_legacy_time(raw: str, path: Path) -> float:
    text = raw.strip()
    try:
        return float(text)
    except ValueError:
        pass
    try:
        stamp = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"metadata '{LEGACY_TIME_KEY}' is {raw!r}: expected an ISO 8601 time "
                         f"(e.g. {EXAMPLE}) or Unix seconds; new logs name it '{START_TIME_KEY}'",
                         file=path) from None
    if stamp.tzinfo is None:  # a time without zone is read as UTC, the same on every node
        stamp = stamp.replace(tzinfo=timezone.utc)
    return stamp.timestamp()


def _parquet_keys(path: Path) -> dict[str, str]:
    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
    except Exception:  # an unreadable file is reported by its task (read_log), not here
        return {}
    return {k.decode(errors="replace"): v.decode(errors="replace") for k, v in meta.items()}


def log_time(path: str | os.PathLike) -> tuple[float, str]:
    """When a log was recorded, in Unix seconds, and where that came from.

    Rule: the Parquet metadata ``start_time`` (CONTRACT 1.2: ISO 8601 with its offset), else the
    legacy key ``log_time``, else the file's modification time (``mtime``: CSV logs have no
    metadata; copying a file changes it). Returns ``(seconds, "start_time" | "log_time" |
    "mtime")``, or ``(nan, "missing")`` for a file that is not there. A malformed time is an
    InputError naming the file and the key: a wrong time would misplace the log in every trend."""
    path = Path(path)
    if path.suffix.lower() in (".parquet", ".pq") and path.is_file():
        meta = _parquet_keys(path)
        if START_TIME_KEY in meta:
            return parse_start_time(meta[START_TIME_KEY], path).timestamp(), START_TIME_KEY
        if LEGACY_TIME_KEY in meta:
            return _parse_legacy_time(meta[LEGACY_TIME_KEY], path), LEGACY_TIME_KEY
    return _mtime(path)


def _mtime(path: Path) -> tuple[float, str]:
    try:
        return path.stat().st_mtime, "mtime"
    except OSError:
        return float("nan"), "missing"


def robot_label(robot, robot_name: str | None) -> str:
    """The fleet table's ``robot``: the name given or in the log's metadata, else the URDF's stem."""
    if robot_name:
        return robot_name
    if getattr(robot, "name", None):
        return robot.name
    return Path(robot.urdf_path).stem if getattr(robot, "urdf_path", None) else "unknown"


def diagnose_log(log, robot, settings: dict | None):
    """Findings (contract section 2) and the whole result as a dict, for one read log (its
    derivatives are estimated by the Diagnoser's own differentiator, as ``mmgp diagnose`` does).

    The one place the fleet calls the diagnosis."""
    from ..diagnosis import Diagnoser

    diagnoser = Diagnoser(**(settings or {})).fit(log, robot)
    return diagnoser.findings_, diagnoser.result_.to_dict()


def train_log(log, robot, settings: dict | None) -> dict:
    """Train on one log (a RobotLog read against ``robot``, or a path); returns the training
    report and the saved model's files as bytes.

    The one place the fleet calls the training."""
    from ..data.outputs import jsonable, write_table
    from ..estimator import MultimodalGP

    model = MultimodalGP(robot=robot, **(settings or {})).fit(log)
    with tempfile.TemporaryDirectory(prefix="mmgp-fleet-") as tmp:
        folder = Path(tmp)
        model.save(folder)
        write_table(folder / "labels.parquet", model.labels_)
        files = {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}
    return {"report": jsonable(model.report_), "files": files}


def _process(path: Path, job: dict, out: dict) -> None:
    from ..data.logs import for_robot, read_log
    from ..physics.robot import load_robot

    if out["log_time_source"] is None:  # a job from the Fleet carries the time its driver read
        out["log_time"], out["log_time_source"] = log_time(path)
    log = read_log(path)  # once: the robot is found in it, the diagnosis and the training use it
    robot = load_robot(robot=job.get("robot"), urdf=job.get("urdf"), log_path=log)
    if robot is None:
        raise InputError("diagnosis needs a nominal model: give --robot NAME or --urdf PATH "
                         "(or name one in the log's metadata)", file=path)
    out["robot"] = robot_label(robot, job.get("robot"))
    report(f"{out['log']}: diagnosis")
    log = for_robot(log, n_joints=robot.n_joints, joint_names=robot.joint_names)
    out["findings"], out["diagnosis"] = diagnose_log(log, robot, job.get("diagnosis_settings"))
    if job.get("train"):
        report(f"{out['log']}: training")
        out["training"] = train_log(log, robot, job.get("train_settings"))


def blank_outcome(job: dict, error: str | None = None) -> dict:
    """The outcome of a job before it runs (or of one whose task never returned: ``error``)."""
    out = {"log": str(job.get("name", job["path"])), "robot": job.get("robot"),
           "log_time": job.get("log_time", float("nan")), "log_time_source": job.get("log_time_source"),
           "findings": None, "diagnosis": None, "training": None, "error": error, "seconds": 0.0}
    if error is not None and out["log_time_source"] is None:
        out["log_time"], out["log_time_source"] = _mtime(Path(job["path"]))
    return out


def process_log(job: dict) -> dict:
    """One fleet task. ``job``: ``path`` (str, absolute), ``name`` (the log as the user gave it),
    the fleet's ``robot``, ``urdf``, ``train``, ``diagnosis_settings``, ``train_settings``. Never
    raises: a log that fails is returned with ``error`` (the message; an unexpected failure also
    carries its traceback in ``traceback``)."""
    path = Path(job["path"])
    out = blank_outcome(job)
    t0 = time.perf_counter()
    try:
        with limit_threads(1):   # one task per core: N tasks x N BLAS threads would run N^2
            _process(path, job, out)
    except InputError as exc:
        out["error"] = str(exc)
    except Exception as exc:  # one log's numerical failure must not end a fleet of hundreds
        out["error"] = f"{type(exc).__name__}: {exc}"
        out["traceback"] = traceback.format_exc()
    out["seconds"] = time.perf_counter() - t0
    if out["log_time_source"] is None:  # failed before or while reading the time: order by mtime
        out["log_time"], out["log_time_source"] = _mtime(path)
    return out
