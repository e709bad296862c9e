"""Reading delimited text tables (CSV, space- or semicolon-separated) with clear errors."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..errors import InputError
from ..data.logs import numeric_column

DELIMITERS = (",", ";", "\t", " ")


def first_line(path: Path) -> str:
    """The first non-empty line of a text file ('' when unreadable or binary)."""
    try:
        with open(path, "r", encoding="utf-8", errors="strict") as fh:
            for line in fh:
                if line.strip():
                    return line.rstrip("\r\n")
    except (OSError, UnicodeDecodeError):
        return ""
    return ""


def guess_delimiter(line: str) -> str:
    """The separator that splits the header line into the most fields (',' on a tie)."""
    counts = {d: len([f for f in line.split(d) if f != ""]) for d in DELIMITERS}
    return max(DELIMITERS, key=lambda d: (counts[d], -DELIMITERS.index(d)))


def header_names(path: Path) -> list[str]:
    """Column names of a text table's header line (no data read; [] when not a text table)."""
    line = first_line(path)
    if not line:
        return []
    sep = guess_delimiter(line)
    fields = line.split(sep) if sep != " " else line.split()
    return [f.strip().strip('"') for f in fields]


def read_table(path: Path, options: dict[str, Any] | None = None) -> pd.DataFrame:
    """A text table as a DataFrame: separator guessed unless the map gives ``delimiter``.

    Map keys honoured: ``delimiter``, ``decimal`` ('.' or ','), ``header`` (False: no header line,
    columns are 0, 1, ...).
    """
    options = options or {}
    if not path.is_file():
        raise InputError("file does not exist", file=path)
    line = first_line(path)
    if not line:
        raise InputError("not a text table (empty, binary or not UTF-8)", file=path)
    sep = options.get("delimiter") or guess_delimiter(line)
    decimal = options.get("decimal", ".")
    if decimal not in (".", ","):
        raise InputError(f"map key 'decimal' must be '.' or ',', found {decimal!r}", file=path)
    if sep == decimal:
        raise InputError(f"the delimiter and the decimal mark are both {sep!r}", file=path)
    header = 0 if options.get("header", True) else None
    try:
        kwargs = {"sep": r"\s+"} if sep == " " else {"sep": sep}
        df = pd.read_csv(path, decimal=decimal, header=header, skipinitialspace=True, **kwargs)
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise InputError(f"unreadable table ({type(exc).__name__}: {exc})", file=path) from None
    if header is not None:
        df.columns = [str(c).strip() for c in df.columns]
    return df


def numeric_block(df: pd.DataFrame, columns: list, path: Path) -> np.ndarray:
    """Columns as a (T, k) float64 array; a missing, non-numeric or non-finite cell is an error."""
    missing = [c for c in columns if c not in df.columns]
    if missing:
        shown = [str(c) for c in df.columns[:12]]
        raise InputError(f"column not found; the table has {shown}{' ...' if len(df.columns) > 12 else ''}",
                         file=path, column=str(missing[0]))
    return np.stack([numeric_column(df, c, path) for c in columns], axis=1)


def indexed_columns(names: list[str], pattern: str, path: Path | None = None,
                    what: str = "") -> list[str]:
    """Names matching ``pattern`` (a regex with one group: the joint index), ordered 0..n-1.

    [] when none match; an error when the indices are not 0..n-1 without gaps.
    """
    rx = re.compile(pattern)
    found: dict[int, str] = {}
    for nm in names:
        m = rx.search(nm)
        if m:
            found.setdefault(int(m.group(1)), nm)
    if not found:
        return []
    n = max(found) + 1
    gaps = [j for j in range(n) if j not in found]
    if gaps:
        raise InputError(f"{what or pattern} columns must be numbered 0..{n - 1} without gaps; "
                         f"index {gaps[0]} is missing", file=path)
    return [found[j] for j in range(n)]
