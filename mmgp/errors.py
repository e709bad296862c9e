"""The one error type for bad input: the command line prints it as one line and exits with 2."""
from __future__ import annotations

import os
import re

_LINE_BREAKS = re.compile(r"\s*[\r\n]+\s*")


def one_line(text: str, limit: int | None = None) -> str:
    """``text`` with its line breaks folded into "; " (and cut to ``limit`` characters), so that
    messages quoted from other libraries keep the one-line promise."""
    text = _LINE_BREAKS.sub("; ", str(text).strip())
    if limit is not None and len(text) > limit:
        text = text[: max(limit - 3, 0)].rstrip() + "..."
    return text


def describe(exc: BaseException, limit: int = 160) -> str:
    """``"TypeName: first words of the message"`` of a foreign exception, on one line."""
    return one_line(f"{type(exc).__name__}: {exc}", limit)


class InputError(ValueError):
    """Bad input: one clear message naming the file, the column and the row where known.

    ``str(err)`` is always one line: ``"file F, column 'C', row R: message"`` (the parts that are
    known). ``row`` counts data rows from 0, the header excluded.
    """

    def __init__(self, message: str, *, file: str | os.PathLike | None = None,
                 column: str | None = None, row: int | None = None):
        self.file = None if file is None else str(file)
        self.column = column
        self.row = row
        self.message = one_line(message)
        where = []
        if self.file is not None:
            where.append(f"file {self.file}")
        if column is not None:
            where.append(f"column '{column}'")
        if row is not None:
            where.append(f"row {row}")
        prefix = one_line(", ".join(where)) + ": " if where else ""
        super().__init__(prefix + self.message)
