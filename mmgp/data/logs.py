"""Reading and validating robot logs and label files (CONTRACT section 1).

A log is a table with ``t``, ``q_0..q_{n-1}``, ``tau_0..tau_{n-1}`` and optionally ``dq_*`` and
``ddq_*``. Everything that can be wrong with one is reported as a single :class:`InputError` that
names the file, the column and the row, so the command line can print it and exit non-zero.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from ..errors import InputError
from .outputs import write_table

MIN_SAMPLES = 10


@dataclass(frozen=True)
class RobotLog:
    """Checked arrays of one log.

    Shapes: ``t`` (T,), ``q``/``dq``/``ddq``/``tau`` (T, n_joints). ``dq``/``ddq`` are None when
    the file lacks them (``mmgp.data.differentiation.complete_derivatives`` fills them in).
    Units: s, rad (m), rad/s, rad/s^2, N*m (N).
    """

    path: str
    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    dq: np.ndarray | None = None
    ddq: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)
    dq_estimated: bool = False
    ddq_estimated: bool = False

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def n_samples(self) -> int:
        return self.t.shape[0]

    @property
    def joint_names(self) -> list[str] | None:
        names = self.metadata.get("joint_names")
        return list(names) if names is not None else None

    def replace(self, **changes) -> "RobotLog":
        return replace(self, **changes)

    def subset(self, idx: np.ndarray) -> "RobotLog":
        """Rows ``idx`` of every array (e.g. a time block)."""
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return replace(self, t=self.t[idx], q=self.q[idx], tau=self.tau[idx],
                       dq=pick(self.dq), ddq=pick(self.ddq))


_COL = re.compile(r"^(q|dq|ddq|tau)_(\d+)$")


def _read_table(path: Path) -> tuple[pd.DataFrame, dict]:
    if not path.exists():
        raise InputError("file does not exist", file=path)
    if not path.is_file():
        raise InputError("not a regular file", file=path)
    suffix = path.suffix.lower()
    try:
        if suffix in (".parquet", ".pq"):
            import pyarrow.parquet as pq

            table = pq.read_table(path)
            raw_meta = table.schema.metadata or {}
            meta = {}
            for k, v in raw_meta.items():
                key = k.decode(errors="replace")
                if key in ("robot", "urdf", "joint_names"):
                    meta[key] = v.decode(errors="replace")
            df = table.to_pandas()
        elif suffix in (".csv", ".txt"):
            df = pd.read_csv(path)
            meta = {}
        else:
            raise InputError(f"unsupported file type '{suffix}': expected .parquet or .csv", file=path)
    except InputError:
        raise
    except Exception as exc:  # pyarrow/pandas raise many types for unreadable files
        raise InputError(f"unreadable file ({type(exc).__name__}: {exc})", file=path) from None
    if "joint_names" in meta:
        try:
            names = json.loads(meta["joint_names"])
            if not (isinstance(names, list) and all(isinstance(s, str) for s in names)):
                raise ValueError
        except ValueError:
            raise InputError("metadata 'joint_names' is not a JSON list of strings", file=path) from None
        meta["joint_names"] = names
    return df, meta


def _numeric_column(df: pd.DataFrame, col: str, path: Path) -> np.ndarray:
    try:
        arr = pd.to_numeric(df[col], errors="raise").to_numpy(dtype=np.float64)
    except (ValueError, TypeError):
        bad = pd.to_numeric(df[col], errors="coerce").isna() & df[col].notna()
        row = int(np.flatnonzero(bad.to_numpy())[0]) if bad.any() else None
        raise InputError("expected a number", file=path, column=col, row=row) from None
    finite = np.isfinite(arr)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise InputError(f"expected a finite number, found {arr[row]}", file=path, column=col, row=row)
    return arr


def read_log(path: str | os.PathLike, *, n_joints: int | None = None,
             joint_names: Sequence[str] | None = None, min_samples: int = MIN_SAMPLES) -> RobotLog:
    """Read and check one log (Parquet or CSV) per CONTRACT section 1.

    ``n_joints``/``joint_names`` come from the robot model when one is used; a log whose joint
    count disagrees is refused. Rows are reported 0-based, as data rows (header excluded).
    """
    path = Path(path)
    df, meta = _read_table(path)
    cols = list(df.columns)
    if "t" not in cols:
        near = [c for c in cols if c.strip().lower() in ("t", "time", "timestamp", "time_s")]
        hint = f" (found '{near[0]}'; rename it to 't')" if near else ""
        raise InputError(f"required column 't' is missing{hint}", file=path, column="t")
    groups: dict[str, dict[int, str]] = {"q": {}, "dq": {}, "ddq": {}, "tau": {}}
    for c in cols:
        m = _COL.match(str(c))
        if m:
            groups[m.group(1)][int(m.group(2))] = c
    unknown = [c for c in cols if c != "t" and not _COL.match(str(c))]
    if not groups["q"]:
        extra = f"; unrecognised columns: {unknown[:5]}" if unknown else ""
        raise InputError(f"no joint position columns 'q_0'..'q_(n-1)' found{extra}", file=path, column="q_0")
    n = max(groups["q"]) + 1
    for j in range(n):
        if j not in groups["q"]:
            raise InputError(f"joint positions must be q_0..q_{n-1} without gaps", file=path, column=f"q_{j}")
    for kind in ("tau",):
        for j in range(n):
            if j not in groups[kind]:
                raise InputError(f"required column is missing (log has {n} joints from q_*)",
                                 file=path, column=f"{kind}_{j}")
    for kind in ("q", "dq", "ddq", "tau"):
        extra = sorted(k for k in groups[kind] if k >= n)
        if extra:
            raise InputError(f"column beyond the {n} joints given by q_0..q_{n-1}", file=path,
                             column=f"{kind}_{extra[0]}")
    for kind in ("dq", "ddq"):
        present = sorted(groups[kind])
        if present and len(present) != n:
            missing = next(j for j in range(n) if j not in groups[kind])
            raise InputError(f"'{kind}' columns must be given for all {n} joints or none",
                             file=path, column=f"{kind}_{missing}")
    names = list(joint_names) if joint_names is not None else meta.get("joint_names")
    if meta.get("joint_names") is not None and len(meta["joint_names"]) != n:
        raise InputError(f"metadata joint_names lists {len(meta['joint_names'])} joints but the log has {n}",
                         file=path, column="q_0")
    if n_joints is not None and n != n_joints:
        raise InputError(f"log has {n} joints (q_0..q_{n-1}) but the robot model has {n_joints}",
                         file=path, column=f"q_{min(n, n_joints)}" if n < n_joints else f"q_{n_joints}")
    T = len(df)
    if T < min_samples:
        raise InputError(f"too few samples: {T} rows, at least {min_samples} needed", file=path, row=T)
    t = _numeric_column(df, "t", path)
    dt = np.diff(t)
    if (dt <= 0).any():
        row = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise InputError(f"'t' must be strictly increasing: t[{row}]={t[row]} after t[{row-1}]={t[row-1]}",
                         file=path, column="t", row=row)
    arrays = {}
    for kind in ("q", "dq", "ddq", "tau"):
        if groups[kind]:
            arrays[kind] = np.stack([_numeric_column(df, f"{kind}_{j}", path) for j in range(n)], axis=1)
        else:
            arrays[kind] = None
    if names is not None:
        meta = dict(meta, joint_names=list(names))
    return RobotLog(path=str(path), t=t, q=arrays["q"], tau=arrays["tau"], dq=arrays["dq"],
                    ddq=arrays["ddq"], metadata=meta)


def read_labels(path: str | os.PathLike, *, t: np.ndarray | None = None, atol: float = 1e-6) -> pd.DataFrame:
    """Read a ground-truth labels file: ``t`` and any of ``disturbed`` (0/1/-1), ``mode`` (int).

    When ``t`` (training times) is given, labels are matched to it by time; every training time
    must have a label within ``atol`` seconds.
    """
    path = Path(path)
    df, _ = _read_table(path)
    if "t" not in df.columns:
        raise InputError("required column 't' is missing", file=path, column="t")
    if not ({"disturbed", "mode"} & set(df.columns)):
        raise InputError("labels need a 'disturbed' or a 'mode' column", file=path, column="disturbed")
    out = pd.DataFrame({"t": _numeric_column(df, "t", path)})
    if "disturbed" in df.columns:
        d = _numeric_column(df, "disturbed", path)
        bad = ~np.isin(d, (-1, 0, 1))
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise InputError(f"expected 0, 1 or -1, found {d[row]}", file=path, column="disturbed", row=row)
        out["disturbed"] = d.astype(int)
    if "mode" in df.columns:
        m = _numeric_column(df, "mode", path)
        bad = m != np.round(m)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise InputError(f"expected an integer, found {m[row]}", file=path, column="mode", row=row)
        out["mode"] = m.astype(int)
    if t is not None:
        t = np.asarray(t, dtype=np.float64)
        order = np.argsort(out["t"].to_numpy())
        lt = out["t"].to_numpy()[order]
        pos = np.clip(np.searchsorted(lt, t), 1, len(lt) - 1) if len(lt) > 1 else np.zeros(len(t), int)
        cand = np.stack([pos - 1, pos], 1) if len(lt) > 1 else pos[:, None]
        best = cand[np.arange(len(t)), np.argmin(np.abs(lt[cand] - t[:, None]), axis=1)]
        miss = np.abs(lt[best] - t) > atol
        if miss.any():
            i = int(np.flatnonzero(miss)[0])
            raise InputError(f"no label for training time t={t[i]:.6f} (nearest {lt[best[i]]:.6f})",
                             file=path, column="t")
        out = out.iloc[order[best]].reset_index(drop=True)
    return out


def write_log(path: str | os.PathLike, t: np.ndarray, q: np.ndarray, tau: np.ndarray, *,
              dq: np.ndarray | None = None, ddq: np.ndarray | None = None,
              robot: str | None = None, urdf: str | None = None,
              joint_names: Sequence[str] | None = None) -> Path:
    """Write a contract log (Parquet with file metadata, or CSV without) atomically."""
    path = Path(path)
    cols = {"t": np.asarray(t, dtype=np.float64)}
    n = np.asarray(q).shape[1]
    for kind, arr in (("q", q), ("dq", dq), ("ddq", ddq), ("tau", tau)):
        if arr is None:
            continue
        arr = np.asarray(arr, dtype=np.float64)
        for j in range(n):
            cols[f"{kind}_{j}"] = arr[:, j]
    df = pd.DataFrame(cols)
    meta = {}
    if robot is not None:
        meta["robot"] = robot
    if urdf is not None:
        meta["urdf"] = str(urdf)
    if joint_names is not None:
        meta["joint_names"] = json.dumps(list(joint_names))
    write_table(path, df, metadata=meta)
    return path


