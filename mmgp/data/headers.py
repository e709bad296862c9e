"""A log's header (CONTRACT section 1) read and checked without its rows and without pandas:
the file's kind, a Parquet schema or a CSV header line, the contract's column names. Commands
check their logs with :func:`check_log_header` before loading their heavy libraries, so a wrong
path or column answers at once; :mod:`mmgp.data.logs` reads the rows with the same checks."""
from __future__ import annotations

import csv
import json
import os
import re
from pathlib import Path
from typing import Sequence

from ..errors import InputError, describe, one_line
from .times import START_TIME_KEY, parse_start_time

# exactly the contract's names: ASCII digits without leading zeros ('q_00', 'q_\u0661' are not q_0, q_1)
_COL = re.compile(r"(q|dq|ddq|tau)_(0|[1-9][0-9]*)")
SEPARATORS = {",": "','", ";": "';'", "\t": "tab"}
_QUOTED = re.compile(r'"[^"]*"')
_LINE_BREAK = re.compile(rb"\r\n|\r|\n")
_BLANK_LINES = re.compile(rb"(?:[ \t\f\v]*(?:\r\n|\r|\n))*")


def _check_file(path: Path) -> str:
    """The file's kind ("parquet" or "csv"), or an InputError when it cannot be a table."""
    if not path.exists():
        raise InputError("file does not exist", file=path)
    if not path.is_file():
        raise InputError("not a regular file", file=path)
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        return "parquet"
    if suffix in (".csv", ".txt"):
        return "csv"
    raise InputError(f"unsupported file type '{suffix}': expected .parquet or .csv", file=path)


def _refuse_duplicates(names: Sequence[str], path: Path) -> None:
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        if name in seen:
            raise InputError(f"the column name appears twice (columns {seen[name]} and {i}, counted "
                             "from 0): every column needs its own name", file=path, column=name)
        seen[name] = i


def open_parquet(path: Path):
    """The Parquet file opened once (a ``pyarrow.parquet.ParquetFile``: its schema, then its rows
    from the same handle; close it, or use it as a context manager), or an InputError."""
    import pyarrow.parquet as pq

    try:
        return pq.ParquetFile(path)
    except Exception as exc:  # pyarrow raises several types for files that are not Parquet
        raise InputError(f"unreadable Parquet file ({describe(exc)})", file=path) from None


def _parquet_metadata(schema, path: Path) -> dict:
    """The contract's file metadata (robot, urdf, joint_names, start_time) of a Parquet schema;
    ``start_time`` is checked (:func:`mmgp.data.times.parse_start_time`) and kept as written."""
    meta = {}
    for k, v in (schema.metadata or {}).items():
        key = k.decode(errors="replace")
        if key in ("robot", "urdf", "joint_names", START_TIME_KEY):
            meta[key] = v.decode(errors="replace")
    if START_TIME_KEY in meta:
        parse_start_time(meta[START_TIME_KEY], path)
    if "joint_names" in meta:
        try:
            names = json.loads(meta["joint_names"])
            if not (isinstance(names, list) and all(isinstance(s, str) for s in names)):
                raise ValueError
        except (ValueError, RecursionError):
            raise InputError("metadata 'joint_names' is not a JSON list of strings", file=path) from None
        meta["joint_names"] = names
    return meta


def _csv_bytes(path: Path) -> bytes:
    """The file's bytes, checked to be UTF-8 text without NUL bytes (and without the UTF-8
    byte-order mark, which is allowed). Bytes, not text: pandas parses them twice as fast."""
    data = path.read_bytes()
    if data.startswith(b"PAR1"):
        raise InputError("this is a Parquet file with a CSV name: rename it to .parquet", file=path)
    for mark, name in ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
                       (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16")):
        if data.startswith(mark):
            raise InputError(f"the text is {name}: save the file as UTF-8", file=path)
    if b"\x00" in data:
        line = data[: data.index(b"\x00")].count(b"\n") + 1
        raise InputError(f"binary content (a NUL byte on line {line}): expected CSV text", file=path)
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text (byte 0x{data[exc.start]:02X} on line {line}): expected a CSV "
                         "file saved as UTF-8", file=path) from None
    data = data.removeprefix(b"\xef\xbb\xbf")
    if not data or data.isspace():
        raise InputError("the file is empty: expected a header line such as 't,q_0,tau_0' and data rows",
                         file=path)
    return data


def _csv_separator(header: str, path: Path) -> str:
    """The one of ',', ';' and tab that the header line uses (',' for a single column)."""
    bare = _QUOTED.sub("", header)
    found = [s for s in SEPARATORS if s in bare]
    if len(found) > 1:
        raise InputError(f"the header line mixes separators {' and '.join(SEPARATORS[s] for s in found)}: "
                         "expected one of ',', ';' or tab between column names", file=path)
    if not found and len(bare.split()) > 1:
        raise InputError(f"the header line {one_line(header, 60)!r} separates columns by spaces: "
                         "expected ',', ';' or tab", file=path)
    return found[0] if found else ","


def _csv_header(header: str, sep: str, path: Path) -> list[str]:
    try:
        names = [c.strip() for c in next(csv.reader([header], delimiter=sep, skipinitialspace=True))]
    except csv.Error as exc:
        raise InputError(f"unreadable header line ({describe(exc)})", file=path) from None
    names = [c if c else f"Unnamed: {i}" for i, c in enumerate(names)]
    _refuse_duplicates(names, path)
    return names


def read_table_header(path: str | os.PathLike) -> tuple[list[str], dict]:
    """(column names, file metadata) of a log or labels file, read as :func:`read_log` reads it
    but without its rows: a Parquet file's schema, a CSV file's header line (CSV carries no
    metadata)."""
    path = Path(path)
    if _check_file(path) == "parquet":
        with open_parquet(path) as pf:
            schema = pf.schema_arrow
        _refuse_duplicates(list(schema.names), path)
        return [str(c) for c in schema.names], _parquet_metadata(schema, path)
    try:
        data = _csv_bytes(path)
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror or describe(exc)})", file=path) from None
    start = _BLANK_LINES.match(data).end()
    brk = _LINE_BREAK.search(data, start)
    header = data[start:brk.start() if brk else len(data)].decode("utf-8")
    return _csv_header(header, _csv_separator(header, path), path), {}


def _missing_t(cols: list, path: Path) -> InputError:
    near = [c for c in cols if str(c).strip().lower() in ("t", "time", "timestamp", "time_s")]
    if near:
        hint = f" (found '{near[0]}'; rename it to 't')"
    elif cols and all(_is_number(c) for c in cols):
        hint = "; the first line holds numbers: the file needs a header line such as 't,q_0,tau_0'"
    else:
        hint = f"; the header has {one_line(str([str(c) for c in cols[:8]]), 120)}"
    return InputError(f"required column 't' is missing{hint}", file=path, column="t")


def _is_number(text) -> bool:
    try:
        float(str(text).replace(",", "."))
    except ValueError:
        return False
    return True


def _joint_columns(cols: list, path: Path) -> tuple[int, dict[str, dict[int, str]]]:
    """(n joints, {kind: {joint: column}}) of a log's columns, checked against CONTRACT section 1."""
    groups: dict[str, dict[int, str]] = {"q": {}, "dq": {}, "ddq": {}, "tau": {}}
    for c in cols:
        m = _COL.fullmatch(str(c))
        if m:
            groups[m.group(1)][int(m.group(2))] = c
    if not groups["q"]:
        unknown = [str(c) for c in cols if c != "t" and not _COL.fullmatch(str(c))]
        extra = f"; unrecognised columns: {one_line(str(unknown[:5]), 120)}" if unknown else ""
        raise InputError(f"no joint position columns 'q_0'..'q_(n-1)' found{extra}", file=path, column="q_0")
    n = max(groups["q"]) + 1
    for j in range(n):
        if j not in groups["q"]:
            raise InputError(f"joint positions must be q_0..q_{n-1} without gaps", file=path, column=f"q_{j}")
    for j in range(n):
        if j not in groups["tau"]:
            raise InputError(f"required column is missing (log has {n} joints from q_*)",
                             file=path, column=f"tau_{j}")
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
    return n, groups


def _log_columns(cols: list, path: Path) -> tuple[int, dict[str, dict[int, str]]]:
    """(n joints, {kind: {joint: column}}) of a log's columns: 't' and the joint columns checked."""
    if "t" not in cols:
        raise _missing_t(cols, path)
    return _joint_columns(cols, path)


def check_log_header(path: str | os.PathLike) -> int:
    """The number of joints of a log, from its header alone (a Parquet schema, a CSV header line),
    checked as :func:`read_log` checks it: a wrong path, file type or column is refused without
    reading the rows (commands call this before loading their heavy libraries)."""
    cols, _ = read_table_header(path)
    return _log_columns(cols, Path(path))[0]
