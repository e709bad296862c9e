"""The ``--map`` file: a YAML mapping that tells the readers what the input cannot say itself.

Every key is optional; a key no reader knows is refused (a typo would otherwise be ignored)::

    format: csv              # force a reader: csv, rtde, franka_csv, joint_states_csv, rosbag, dataset
    delimiter: ";"           # CSV field separator (default: guessed from the header line)
    decimal: ","             # CSV decimal mark (default ".")
    header: true             # false: the CSV has no header line; columns are 0-based indices
    columns:                 # plain CSV: which column holds what (names, or indices without header)
      t: time_ms
      q: [pos1, pos2]
      dq: [vel1, vel2]       # optional
      ddq: [acc1, acc2]      # optional
      tau: [trq1, trq2]
    units:                   # value * factor = contract unit; a unit name or a number (or a list)
      t: ms                  # s, ms, us, ns
      q: deg                 # rad, deg, m, mm
      dq: deg/s
      tau: [1.0, 1.0]
    joint_names: [a1, a2]    # names of the joints, in column order
    joints: [a1, a2]         # keep only these joints (bags: choose among the published joints)
    robot: panda             # same as --robot (the flag wins)
    topic: /joint_states     # same as --topic (the flag wins)
    stamp: header            # bags: header (default) or receive (the recorder's clock)
    tau_source: actual_current   # RTDE: actual_current_as_torque, target_moment, actual_current;
                                 # franka: tau_J (default), tau_J_d
    current_to_torque: [..]  # RTDE actual_current: joint torque per motor current, N*m/A, per joint
    dataset: {flip_tau: false}   # options of the shared-dataset converters (docs/convert.md)
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

KNOWN_KEYS = {"format", "delimiter", "decimal", "header", "columns", "units", "joint_names", "joints",
              "robot", "topic", "stamp", "tau_source", "current_to_torque", "dataset"}

UNITS = {
    "s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9,
    "rad": 1.0, "deg": math.pi / 180.0, "m": 1.0, "mm": 1e-3,
    "rad/s": 1.0, "deg/s": math.pi / 180.0, "m/s": 1.0, "mm/s": 1e-3,
    "rad/s^2": 1.0, "deg/s^2": math.pi / 180.0, "m/s^2": 1.0, "mm/s^2": 1e-3,
    "n*m": 1.0, "nm": 1.0, "n": 1.0, "mn*m": 1e-3,
}


def load_map(path: str | Path | None) -> dict[str, Any]:
    """The validated mapping of a ``--map`` YAML file ({} without one)."""
    if path is None:
        return {}
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError("map file does not exist", file=path)
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(f"map file is not valid YAML ({exc})", file=path) from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise InputError("map file must hold a mapping of keys (format, columns, units, ...)", file=path)
    unknown = sorted(str(k) for k in data if k not in KNOWN_KEYS)
    if unknown:
        raise InputError(f"unknown map key(s) {unknown}; known keys: {sorted(KNOWN_KEYS)}", file=path)
    for key in ("columns", "units", "dataset"):
        if key in data and not isinstance(data[key], dict):
            raise InputError(f"map key '{key}' must be a mapping", file=path, column=key)
    for key in ("format", "delimiter", "decimal", "robot", "topic", "stamp", "tau_source"):
        if key in data and not isinstance(data[key], str):
            raise InputError(f"map key '{key}' must be a string, found {data[key]!r}", file=path, column=key)
    if "header" in data and not isinstance(data["header"], bool):
        raise InputError("map key 'header' must be true or false", file=path, column="header")
    for key in ("joint_names", "joints"):
        if key in data and not (isinstance(data[key], list) and all(isinstance(s, str) for s in data[key])):
            raise InputError(f"map key '{key}' must be a list of joint names", file=path, column=key)
    return dict(data, _file=str(path))


def map_file(options: dict[str, Any]) -> str | None:
    """The map file the options came from (for error messages)."""
    return options.get("_file")


def unit_factor(spec: Any, kind: str, n: int, options: dict[str, Any]) -> np.ndarray:
    """Multiplier(s) turning ``kind`` values into contract units: shape () or (n,).

    ``spec`` is a unit name (see ``UNITS``), a number, or a list of n of either.
    """
    if spec is None:
        return np.asarray(1.0)
    items = spec if isinstance(spec, list) else [spec]
    if isinstance(spec, list) and len(spec) != n:
        raise InputError(f"units.{kind}: {len(spec)} entries for {n} columns", file=map_file(options),
                         column=f"units.{kind}")
    out = []
    for item in items:
        if isinstance(item, bool) or not isinstance(item, (int, float, str)):
            raise InputError(f"units.{kind}: expected a unit name or a number, found {item!r}",
                             file=map_file(options), column=f"units.{kind}")
        if isinstance(item, str):
            key = item.strip().lower().replace(" ", "").replace("·", "*")
            if key not in UNITS:
                raise InputError(f"units.{kind}: unknown unit '{item}'; known: {sorted(UNITS)} or a number",
                                 file=map_file(options), column=f"units.{kind}")
            out.append(UNITS[key])
        else:
            out.append(float(item))
    return np.asarray(out if isinstance(spec, list) else out[0], dtype=np.float64)


def float_list(options: dict[str, Any], key: str, n: int) -> np.ndarray:
    """Map key ``key`` as n floats (one per joint)."""
    value = options.get(key)
    ok = isinstance(value, list) and len(value) == n and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not ok:
        raise InputError(f"map key '{key}' must be a list of {n} numbers (one per joint), found {value!r}",
                         file=map_file(options), column=key)
    return np.asarray(value, dtype=np.float64)


def choice(options: dict[str, Any], key: str, allowed: tuple[str, ...], default: str | None = None) -> str | None:
    """Map key ``key``, which must be one of ``allowed``."""
    value = options.get(key, default)
    if value is not None and value not in allowed:
        raise InputError(f"map key '{key}' must be one of {list(allowed)}, found {value!r}",
                         file=map_file(options), column=key)
    return value
