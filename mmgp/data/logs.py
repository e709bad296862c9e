"""Reading and validating robot logs and label files (CONTRACT section 1).

A log is a table with ``t``, ``q_0..q_{n-1}``, ``tau_0..tau_{n-1}`` and optionally ``dq_*`` and
``ddq_*``. Everything that can be wrong with one is reported as a single :class:`InputError` that
names the file, the column and the row, so the command line can print it and exit non-zero.
"""
from __future__ import annotations

import csv
import io
import json
import os
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from ..errors import InputError, describe, one_line
from .headers import (_BLANK_LINES, _LINE_BREAK, _check_file, _csv_bytes, _csv_header, _csv_separator,
                      _log_columns, _missing_t, _parquet_metadata, _refuse_duplicates, open_parquet,
                      read_table_header)
from .outputs import write_table
from .times import START_TIME_KEY, format_start_time, parse_start_time

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


# A log may pause (an e-stop, a break, recording resumed the next morning), but a step in 't'
# longer than a day is not a pause inside one recording: it is a clock change (epoch seconds
# after a controller restart: ~1.7e9 s) or several recordings glued together, which belong in
# separate log files (every command that trains takes several logs).
MAX_TIME_STEP_S = 86_400.0

_DECIMAL_COMMA = re.compile(rb"\d,\d")
_FIELDS = re.compile(r"Expected (\d+) fields in line (\d+), saw (\d+)")


# ---------------------------------------------------------------------------------------------
# Tables: one reader for CSV and Parquet files, shared by logs and labels
# ---------------------------------------------------------------------------------------------

def _read_parquet(path: Path, check_columns) -> tuple[pd.DataFrame, dict]:
    with open_parquet(path) as pf:
        schema = pf.schema_arrow
        _refuse_duplicates(list(schema.names), path)
        check_columns(list(schema.names), path)
        try:
            df = pf.read().to_pandas()
        except Exception as exc:
            raise InputError(f"unreadable Parquet file ({describe(exc)})", file=path) from None
    return df, _parquet_metadata(schema, path)


def _check_first_row(body: memoryview, sep: str, n_names: int, path: Path) -> None:
    """pandas silently drops what a first data row has beyond the header (or takes it for an
    index), so that row is counted here."""
    start = _BLANK_LINES.match(body).end()
    brk = _LINE_BREAK.search(body, start)
    first = bytes(body[start:brk.start() if brk else len(body)]).decode("utf-8")
    if not first:
        return
    try:
        n = len(next(csv.reader([first], delimiter=sep, skipinitialspace=True)))
    except csv.Error as exc:
        raise InputError(f"unreadable first data row ({describe(exc)})", file=path, row=0) from None
    if n > n_names:
        raise InputError(f"the first data row has {n} fields but the header has {n_names}", file=path, row=0)


def _read_csv(path: Path, check_columns) -> pd.DataFrame:
    """A CSV table. Rule: the separator is the one of ',', ';' or tab found in the header line;
    with ';' or tab, a comma between two digits anywhere in the data makes ',' the decimal mark
    (European spreadsheets), else it is '.'. ``check_columns(names, path)`` sees the header's
    names before the rows are parsed."""
    data = _csv_bytes(path)
    start = _BLANK_LINES.match(data).end()
    h = len(_LINE_BREAK.findall(data, 0, start))  # lines before the header
    brk = _LINE_BREAK.search(data, start)
    header = data[start:brk.start() if brk else len(data)].decode("utf-8")
    body = memoryview(data)[brk.end():] if brk else memoryview(b"")
    sep = _csv_separator(header, path)
    names = _csv_header(header, sep, path)
    check_columns(names, path)
    _check_first_row(body, sep, len(names), path)
    decimal = "," if sep != "," and _DECIMAL_COMMA.search(body) else "."
    try:
        with warnings.catch_warnings():
            # pandas drops the extra fields of a long first row with only a warning
            warnings.simplefilter("error", pd.errors.ParserWarning)
            df = pd.read_csv(io.BytesIO(body), encoding="utf-8", sep=sep, decimal=decimal, header=None,
                             names=names, index_col=False, skipinitialspace=True, low_memory=False)
    except pd.errors.ParserWarning:  # what _check_first_row does not see (a quoted line break)
        raise InputError(f"the first data row has more fields than the {len(names)} of the header",
                         file=path, row=0) from None
    except (pd.errors.ParserError, ValueError) as exc:
        m = _FIELDS.search(str(exc))
        if m is None:
            raise InputError(f"unreadable CSV file ({describe(exc)})", file=path) from None
        expected, line, saw = (int(g) for g in m.groups())
        row = sum(1 for x in _LINE_BREAK.split(body)[:line - 1] if x.strip())
        raise InputError(f"line {h + 1 + line} has {saw} fields, expected {expected} like the rows before",
                         file=path, row=row) from None
    df.attrs["decimal"] = decimal
    return df


def _read_table(path: Path, check_columns=lambda names, path: None) -> tuple[pd.DataFrame, dict]:
    """(table, file metadata) of a CSV or Parquet file, the file opened once; every failure is
    one InputError. ``check_columns(names, path)`` refuses a header before the rows are read, so
    a wrong column is answered first, as from the header alone (:func:`read_table_header`)."""
    kind = _check_file(path)
    if kind == "parquet":
        return _read_parquet(path, check_columns)
    try:
        return _read_csv(path, check_columns), {}
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror or describe(exc)})", file=path) from None


def numeric_column(df: pd.DataFrame, col: str, path: Path) -> np.ndarray:
    """Column ``col`` as finite float64 numbers (T,), or an InputError naming the first bad row."""
    s = df[col]
    if s.dtype.kind in "biuf":
        arr = s.to_numpy(dtype=np.float64)
    elif s.dtype.kind in "mM":
        raise InputError(f"expected numbers (seconds, radians, N*m), found a column of type {s.dtype}",
                         file=path, column=col)
    else:
        s = s.astype(object)
        num = _to_numbers(_decimal_points(s, df.attrs.get("decimal", ".")))
        if num.dtype.kind not in "biuf":
            raise InputError(f"expected real numbers, found values of type {num.dtype}", file=path, column=col)
        bad = (num.isna() & s.notna()).to_numpy()
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise InputError(f"expected a number, found {one_line(repr(s.iloc[row]), 40)}{_decimal_hint(df, s.iloc[row])}",
                             file=path, column=col, row=row)
        arr = num.to_numpy(dtype=np.float64)
    finite = np.isfinite(arr)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        found = "a missing value (empty or NaN)" if np.isnan(arr[row]) else arr[row]
        raise InputError(f"expected a finite number, found {found}", file=path, column=col, row=row)
    return arr


def _to_numbers(s: pd.Series) -> pd.Series:
    """pd.to_numeric with NaN for what is not a number and +-inf for integers beyond float64
    (CSV cells of 400 digits arrive as Python ints, which pandas refuses with OverflowError)."""
    try:
        return pd.to_numeric(s, errors="coerce")
    except OverflowError:
        return pd.to_numeric(s.map(_float_or_inf), errors="coerce")


def _float_or_inf(v):
    if isinstance(v, int) and not isinstance(v, bool):
        try:
            return float(v)
        except OverflowError:
            return np.inf if v > 0 else -np.inf
    return v


def _decimal_points(s: pd.Series, decimal: str) -> pd.Series:
    """Text cells of a decimal-comma file with '.' as decimal mark; a cell that has a point
    already is ambiguous there (2.500 may be a thousands mark) and becomes NaN (refused)."""
    if decimal == ".":
        return s
    return s.map(lambda v: (np.nan if "." in v else v.replace(",", ".")) if isinstance(v, str) else v)


def _decimal_hint(df: pd.DataFrame, cell) -> str:
    if df.attrs.get("decimal") == "," and isinstance(cell, str) and "." in cell:
        return " (the file uses decimal commas elsewhere)"
    return ""


# ---------------------------------------------------------------------------------------------
# Logs
# ---------------------------------------------------------------------------------------------

def _check_time(t: np.ndarray, path: Path) -> None:
    """'t' strictly increasing, without a step longer than MAX_TIME_STEP_S (see there why)."""
    with np.errstate(over="ignore", invalid="ignore"):
        dt = np.diff(t)
    if (dt <= 0).any():
        row = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise InputError(f"'t' must be strictly increasing: t[{row}]={t[row]} after t[{row-1}]={t[row-1]}",
                         file=path, column="t", row=row)
    if (dt > MAX_TIME_STEP_S).any():
        row = int(np.flatnonzero(dt > MAX_TIME_STEP_S)[0]) + 1
        raise InputError(f"'t' jumps by {dt[row - 1]:.4g} s from t[{row-1}]={t[row-1]:.10g} to "
                         f"t[{row}]={t[row]:.10g}: a pause longer than a day is a clock change (epoch "
                         "seconds after a restart?) or separate recordings; fix the time stamps or "
                         "give each recording as its own log file", file=path, column="t", row=row)


def read_log(path: str | os.PathLike, *, n_joints: int | None = None,
             joint_names: Sequence[str] | None = None, min_samples: int = MIN_SAMPLES) -> RobotLog:
    """Read and check one log (Parquet or CSV) per CONTRACT section 1.

    ``n_joints``/``joint_names`` come from the robot model when one is used; a log whose joint
    count disagrees is refused. Rows are reported 0-based, as data rows (header excluded).
    CSV: UTF-8; the separator is the one of ',', ';' or tab in the header line, and with ';' or
    tab the decimal mark may be ',' (see ``_read_csv``). 't' is in seconds, strictly increasing,
    with no step longer than a day (``MAX_TIME_STEP_S``).
    """
    path = Path(path)
    df, meta = _read_table(path, _log_columns)
    n, groups = _log_columns(list(df.columns), path)
    names = list(joint_names) if joint_names is not None else meta.get("joint_names")
    if meta.get("joint_names") is not None and len(meta["joint_names"]) != n:
        raise InputError(f"metadata joint_names lists {len(meta['joint_names'])} joints but the log has {n}",
                         file=path, column="q_0")
    _check_joint_count(n, n_joints, path)
    T = len(df)
    if T < min_samples:
        what = "no data rows (a header only)" if T == 0 else f"{T} rows"
        raise InputError(f"too few samples: {what}, at least {min_samples} needed", file=path, row=T)
    t = numeric_column(df, "t", path)
    _check_time(t, path)
    arrays = {}
    for kind in ("q", "dq", "ddq", "tau"):
        if groups[kind]:
            arrays[kind] = np.stack([numeric_column(df, f"{kind}_{j}", path) for j in range(n)], axis=1)
        else:
            arrays[kind] = None
    if names is not None:
        meta = dict(meta, joint_names=list(names))
    return RobotLog(path=str(path), t=t, q=arrays["q"], tau=arrays["tau"], dq=arrays["dq"],
                    ddq=arrays["ddq"], metadata=meta)


def _check_joint_count(n: int, n_joints: int | None, path) -> None:
    if n_joints is not None and n != n_joints:
        raise InputError(f"log has {n} joints (q_0..q_{n-1}) but the robot model has {n_joints}",
                         file=path, column=f"q_{min(n, n_joints)}" if n < n_joints else f"q_{n_joints}")


def for_robot(log: RobotLog, *, n_joints: int | None = None,
              joint_names: Sequence[str] | None = None) -> RobotLog:
    """A log read without its robot model (``read_log(path)``) as ``read_log(path, n_joints=...,
    joint_names=...)`` returns it: the joint count checked against the model's, the model's
    ``joint_names`` in its metadata. A command reads its log once, then finds the robot in it."""
    _check_joint_count(log.n_joints, n_joints, log.path)
    if joint_names is None:
        return log
    return log.replace(metadata=dict(log.metadata, joint_names=list(joint_names)))


# ---------------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------------

def _label_columns(df: pd.DataFrame, path: Path) -> pd.DataFrame:
    """``t``, ``disturbed`` (-1/0/1) and ``mode`` (int) of a labels table, checked."""
    out = pd.DataFrame({"t": numeric_column(df, "t", path)})
    if "disturbed" in df.columns:
        d = numeric_column(df, "disturbed", path)
        bad = ~np.isin(d, (-1, 0, 1))
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise InputError(f"expected 0, 1 or -1, found {d[row]}", file=path, column="disturbed", row=row)
        out["disturbed"] = d.astype(int)
    if "mode" in df.columns:
        m = numeric_column(df, "mode", path)
        bad = (m != np.round(m)) | (np.abs(m) >= 2.0 ** 31)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise InputError(f"expected an integer, found {m[row]}", file=path, column="mode", row=row)
        out["mode"] = m.astype(int)
    return out


def read_labels(path: str | os.PathLike, *, t: np.ndarray | None = None, atol: float = 1e-6) -> pd.DataFrame:
    """Read a ground-truth labels file: ``t`` and any of ``disturbed`` (0/1/-1), ``mode`` (int).

    When ``t`` (training times, (T,) s) is given, labels are matched to it by time; every
    training time must have a label within ``atol`` seconds. The file is read as
    :func:`read_log` reads a log (same CSV rules).
    """
    path = Path(path)
    df, _ = _read_table(path)
    if "t" not in df.columns:
        raise _missing_t(list(df.columns), path)
    if not ({"disturbed", "mode"} & set(df.columns)):
        raise InputError("labels need a 'disturbed' or a 'mode' column", file=path, column="disturbed")
    if len(df) == 0:
        raise InputError("no label rows (the file has a header only)", file=path, row=0)
    out = _label_columns(df, path)
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
              joint_names: Sequence[str] | None = None, start_time: str | None = None) -> Path:
    """Write a contract log (Parquet with file metadata, or CSV without) atomically.
    ``start_time``: the wall-clock time of the first sample (ISO 8601 with its offset)."""
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
    if start_time is not None:
        meta[START_TIME_KEY] = format_start_time(parse_start_time(start_time))
    write_table(path, df, metadata=meta)
    return path


def log_from_arrays(t, q, tau, dq=None, ddq=None) -> RobotLog:
    """A checked RobotLog from arrays (copies), each bad one named."""
    if t is None or q is None or tau is None:
        raise InputError("arrays need at least t, q and tau")
    t = np.array(t, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(f"t must be (T,), got shape {t.shape}", column="t")
    T = len(t)
    out = {}
    for name, a in (("q", q), ("tau", tau), ("dq", dq), ("ddq", ddq)):
        if a is None:
            out[name] = None
            continue
        a = np.array(a, dtype=np.float64)
        a = a.reshape(-1, 1) if a.ndim == 1 else a
        n = out["q"].shape[1] if name != "q" else a.shape[1]
        if a.ndim != 2 or a.shape != (T, n):
            raise InputError(f"{name} must be (T, n) = ({T}, {n}) like t and q, got shape {a.shape}", column=name)
        out[name] = a
    if T < MIN_SAMPLES:
        raise InputError(f"too few samples: {T}, at least {MIN_SAMPLES} needed", row=T)
    for name, a in [("t", t)] + [(k, v) for k, v in out.items() if v is not None]:
        bad = ~np.isfinite(a.reshape(T, -1)).all(1)
        if bad.any():
            raise InputError("NaN or inf", column=name, row=int(np.flatnonzero(bad)[0]))
    step = np.diff(t) <= 0
    if step.any():
        raise InputError("t must be strictly increasing", column="t", row=int(np.flatnonzero(step)[0]) + 1)
    return RobotLog(path="<arrays>", t=t, q=out["q"], tau=out["tau"], dq=out["dq"], ddq=out["ddq"])


def names_a_robot(log) -> bool:
    """Whether a log (path or RobotLog) names a robot or URDF in its metadata (read by
    :func:`read_table_header`, without the rows). A missing file answers True, so the robot
    loader reports it."""
    if hasattr(log, "metadata") and hasattr(log, "q"):
        meta = log.metadata
    elif not Path(log).is_file():
        return True
    else:
        meta = read_table_header(log)[1]
    return bool(meta.get("robot") or meta.get("urdf"))
