"""Plain CSV with a column mapping (``--map`` keys ``columns``, ``units``, ``delimiter``, ...)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .base import ConvertedLog
from .mapping import map_file, unit_factor
from .tables import numeric_block, read_table

TEXT_SUFFIXES = (".csv", ".txt", ".tsv", ".dat")


def recognises(path: Path, options: dict[str, Any]) -> bool:
    return path.is_file() and "columns" in options


def _column_list(spec: Any, kind: str, options: dict[str, Any]) -> list:
    items = spec if isinstance(spec, list) else [spec]
    if not items or not all(isinstance(c, (str, int)) and not isinstance(c, bool) for c in items):
        raise InputError(f"columns.{kind}: expected a column name (or index), or a list of them, found {spec!r}",
                         file=map_file(options), column=f"columns.{kind}")
    return items


def mapped_columns(options: dict[str, Any]) -> dict[str, list]:
    """The ``columns`` map checked: t, q and tau present, every joint list of the same length."""
    cols = options.get("columns", {})
    unknown = sorted(str(k) for k in cols if k not in ("t", "q", "dq", "ddq", "tau"))
    if unknown:
        raise InputError(f"columns: unknown key(s) {unknown}; expected t, q, dq, ddq, tau",
                         file=map_file(options), column="columns")
    for kind in ("t", "q", "tau"):
        if kind not in cols:
            raise InputError(f"columns.{kind} is required", file=map_file(options), column=f"columns.{kind}")
    out = {kind: _column_list(spec, kind, options) for kind, spec in cols.items()}
    if len(out["t"]) != 1:
        raise InputError("columns.t must name one column", file=map_file(options), column="columns.t")
    n = len(out["q"])
    for kind in ("dq", "ddq", "tau"):
        if kind in out and len(out[kind]) != n:
            raise InputError(f"columns.{kind} lists {len(out[kind])} columns but columns.q lists {n}",
                             file=map_file(options), column=f"columns.{kind}")
    unit_keys = sorted(str(k) for k in options.get("units", {}) if k not in out)
    if unit_keys:
        raise InputError(f"units given for {unit_keys}, which columns does not map",
                         file=map_file(options), column="units")
    return out


def read(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    """One log from a CSV whose columns the map names; units scaled to the contract's."""
    cols = mapped_columns(options)
    df = read_table(path, options)
    units = options.get("units", {})
    n = len(cols["q"])
    arrays = {}
    for kind, names in cols.items():
        factor = unit_factor(units.get(kind), kind, len(names), options)
        block = numeric_block(df, names, path) * factor
        arrays[kind] = block[:, 0] if kind == "t" else block
    names = options.get("joint_names")
    if names is not None and len(names) != n:
        raise InputError(f"joint_names lists {len(names)} joints but columns.q lists {n}",
                         file=map_file(options), column="joint_names")
    scaled = [k for k in cols if k in units]
    notes = [f"columns as mapped in {Path(map_file(options)).name}"]
    if scaled:
        notes.append("scaled to contract units: " + ", ".join(f"{k} ({units[k]})" for k in scaled))
    return [ConvertedLog.of(name=path.stem, t=np.asarray(arrays["t"]), q=arrays["q"], tau=arrays["tau"],
                         dq=arrays.get("dq"), ddq=arrays.get("ddq"), joint_names=names,
                         source=f"{path.name}: columns {cols}", notes=notes)]
