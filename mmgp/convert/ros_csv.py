"""CSV exports of ROS topics: ``rostopic echo -p`` (``%time``, ``field.header.stamp``,
``field.q0`` ...) and PlotJuggler-style names (``__time``, ``/topic/q[0]``).

Two message types: ``franka_msgs/FrankaState`` (see :mod:`.franka` for the torque choice) and
``sensor_msgs/JointState`` (``field.name0``.., ``field.position0``.., see :mod:`.joint_states`).

Time: the header stamp (integer ns in ``rostopic`` output) unless the map says
``stamp: receive``, then the recording time (``%time``, ns, or ``__time``, s); a FrankaState
export without either uses its ``time`` field (robot clock, s). ``t`` starts at 0. A header
stamp or recording time (Unix time) of the first sample becomes the log's ``start_time`` (UTC);
the robot clock gives none.
"""
from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..data.times import wall_clock_iso
from ..errors import InputError
from .base import ConvertedLog
from .franka import FRANKA_FIELDS, franka_log, franka_source
from .joint_states import JointStateMessage, assemble
from .mapping import choice
from .tables import header_names, indexed_columns, numeric_block, read_table

# (regex on the column name, seconds per unit, what it is); searched in this order. Stamps and
# recording times are Unix time (a wall clock, when in range); the robot's clock is not.
STAMP_COLUMNS = [(r"(?:^|[./])header[./]stamp$", 1e-9, "header stamp")]
RECEIVE_COLUMNS = [(r"^%time$", 1e-9, "recording time"), (r"^__time$", 1.0, "recording time")]
ROBOT_TIME_COLUMNS = [(r"(?:^|[./])time$", 1.0, "robot time")]
WALL_CLOCKS = ("header stamp", "recording time")


def field_pattern(field: str) -> str:
    """Regex of a flattened array element column: ``field.q3``, ``/x/q[3]``, ``q_3`` -> index."""
    return rf"(?:^|[./]){re.escape(field)}(?:_|\[)?(\d+)\]?$"


def _has(names: list[str], field: str) -> bool:
    rx = re.compile(field_pattern(field))
    return any(rx.search(nm) for nm in names)


def recognises_franka(path: Path, options: dict[str, Any]) -> bool:
    names = header_names(path) if path.is_file() else []
    return _has(names, "tau_J") and _has(names, "q")


def recognises_joint_states(path: Path, options: dict[str, Any]) -> bool:
    names = header_names(path) if path.is_file() else []
    return all(_has(names, f) for f in ("name", "position", "effort"))


def _time(df: pd.DataFrame, path: Path, options: dict[str, Any],
          robot_time: bool) -> tuple[np.ndarray, str, int | None]:
    """(t in s from 0, note, Unix ns of t = 0 or None for the robot's clock) from the first time
    column the rule in the module doc finds."""
    stamp = choice(options, "stamp", ("header", "receive"), "header")
    order = (RECEIVE_COLUMNS + STAMP_COLUMNS) if stamp == "receive" else (STAMP_COLUMNS + RECEIVE_COLUMNS)
    order = order + (ROBOT_TIME_COLUMNS if robot_time else [])
    for pattern, unit, what in order:
        col = next((c for c in df.columns if re.search(pattern, str(c))), None)
        if col is None:
            continue
        raw = pd.to_numeric(df[col], errors="coerce")
        if raw.isna().any():
            row = int(np.flatnonzero(raw.isna().to_numpy())[0])
            raise InputError("expected a time", file=path, column=str(col), row=row)
        # integer ns stamps are subtracted as integers: as float64 s they would lose the ns digits
        v = raw.to_numpy()
        origin = v.min()
        origin_ns = (int(origin) if unit == 1e-9 else int(round(float(origin) * 1e9))) if what in WALL_CLOCKS else None
        return (v - origin).astype(np.float64) * unit, f"t = {what} ('{col}') - {origin}", origin_ns
    raise InputError("no time column: expected field.header.stamp, %time or __time"
                     + (" or time" if robot_time else ""), file=path)


def read_franka(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    """One log from a CSV export of FrankaState messages."""
    df = read_table(path, options)
    names = [str(c) for c in df.columns]
    fields = {}
    for field in FRANKA_FIELDS:
        cols = indexed_columns(names, field_pattern(field), path, field)
        if cols:
            fields[field] = numeric_block(df, cols, path)
    t, note, origin_ns = _time(df, path, options, robot_time=True)
    start = None if origin_ns is None else wall_clock_iso(ns=origin_ns)
    return [franka_log(path.stem, t, fields, options, franka_source(path, "CSV export"), [note], path, start)]


def read_joint_states(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    """One log from a ``rostopic echo -p`` CSV of JointState messages."""
    df = read_table(path, options)
    names = [str(c) for c in df.columns]
    cols = {f: indexed_columns(names, field_pattern(f), path, f) for f in ("name", "position", "velocity", "effort")}
    t, note, origin_ns = _time(df, path, options, robot_time=False)
    stamps = np.round(t * 1e9).astype(np.int64)
    joint_names = df[cols["name"]].astype(str).to_numpy()
    blocks = {f: numeric_block(df, cols[f], path) if cols[f] else np.zeros((len(df), 0))
              for f in ("position", "velocity", "effort")}
    messages = [JointStateMessage(int(stamps[k]), tuple(joint_names[k]), blocks["position"][k],
                                  blocks["velocity"][k], blocks["effort"][k]) for k in range(len(df))]
    log = assemble(messages, options, options.get("robot"), path, path.stem,
                   f"sensor_msgs/JointState CSV export {path.name}", origin_ns=origin_ns)
    return [replace(log, notes=(note,) + log.notes[1:])]
