"""Universal Robots RTDE recordings (CSV).

Column names are those UR's RTDE client writes: the output field name, with ``_<j>`` appended
for each element of a 6-vector (``timestamp``, ``actual_q_0`` .. ``actual_q_5``, ...); UR's
``record.py`` separates fields with spaces, ur_rtde's file recording with commas (both read).

* ``t`` = ``timestamp`` (s since the controller started), ``q`` = ``actual_q_*`` (rad),
  ``dq`` = ``actual_qd_*`` (rad/s). ``target_*`` fields are the controller's plan, not the robot.
* ``tau`` (map key ``tau_source`` chooses; otherwise the first that applies):
  1. ``actual_current_as_torque_*``: measured motor currents expressed as joint torque, N*m
     (RTDE output of PolyScope 5.23 / 10.11 and later);
  2. ``actual_current_*`` (A) times the map's ``current_to_torque`` (N*m/A per joint: motor
     torque constant times gear ratio; UR publishes no such constants, so the user supplies them);
  3. ``target_moment_*``: the torque the controller's own model computes for the target motion,
     N*m. Not a measurement: it lacks friction and payload errors the controller does not model,
     which is what mmgp is meant to learn; noted in the log's metadata.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import InputError
from .base import ConvertedLog
from .mapping import choice, float_list
from .tables import header_names, indexed_columns, numeric_block, read_table

UR_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
             "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
TAU_SOURCES = ("actual_current_as_torque", "actual_current", "target_moment")


def recognises(path: Path, options: dict[str, Any]) -> bool:
    names = header_names(path) if path.is_file() else []
    return "timestamp" in names and "actual_q_0" in names


def _fields(names: list[str], field: str, path: Path) -> list[str]:
    return indexed_columns(names, rf"^{field}_(\d+)$", path, field)


def _torque_source(names: list[str], path: Path, options: dict[str, Any]) -> tuple[str, list[str]]:
    """(source field, its columns): the map's ``tau_source``, else the rule in the module doc."""
    avail = {src: _fields(names, src, path) for src in TAU_SOURCES}
    src = choice(options, "tau_source", TAU_SOURCES)
    if src is None:
        if avail["actual_current_as_torque"]:
            src = "actual_current_as_torque"
        elif avail["actual_current"] and "current_to_torque" in options:
            src = "actual_current"
        elif avail["target_moment"]:
            src = "target_moment"
        elif avail["actual_current"]:
            raise InputError("only motor currents (actual_current_*) are logged: give the joint torque per "
                             "ampere of each joint as map key 'current_to_torque' (N*m/A)", file=path)
        else:
            raise InputError("no joint torque columns: expected actual_current_as_torque_0.., "
                             "actual_current_0.. (with map key current_to_torque) or target_moment_0..",
                             file=path, column="actual_current_as_torque_0")
    if not avail[src]:
        raise InputError(f"tau_source {src}: the file has no {src}_0.. columns", file=path, column=f"{src}_0")
    return src, avail[src]


def read(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    """One log from an RTDE CSV (see the module doc for which field becomes what)."""
    df = read_table(path, options)
    names = list(df.columns)
    q_cols = _fields(names, "actual_q", path)
    n = len(q_cols)
    src, tau_cols = _torque_source(names, path, options)
    dq_cols = _fields(names, "actual_qd", path)
    for what, cols in (("actual_qd", dq_cols), (src, tau_cols)):
        if cols and len(cols) != n:
            raise InputError(f"{len(cols)} {what} columns for {n} actual_q columns", file=path)
    tau = numeric_block(df, tau_cols, path)
    notes = [f"tau from {src}"]
    if src == "actual_current":
        tau = tau * float_list(options, "current_to_torque", n)
        notes[0] += " (A) times current_to_torque from the map (N*m/A)"
    elif src == "target_moment":
        notes.append("target_moment is the controller's model torque for the planned motion, not a "
                     "measurement: friction and payload errors it does not model are absent")
    names_j = options.get("joint_names") or (UR_JOINTS if n == 6 else None)
    return [ConvertedLog.of(name=path.stem, t=numeric_block(df, ["timestamp"], path)[:, 0],
                         q=numeric_block(df, q_cols, path), tau=tau,
                         dq=numeric_block(df, dq_cols, path) if dq_cols else None,
                         joint_names=list(names_j) if names_j else None,
                         source=f"UR RTDE recording {path.name}", notes=notes)]
