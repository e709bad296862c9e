"""The one error type for bad input: the command line prints it as one line and exits with 2."""
from __future__ import annotations

import os


class InputError(ValueError):
    """Bad input: one clear message naming the file, the column and the row where known."""

    def __init__(self, message: str, *, file: str | os.PathLike | None = None,
                 column: str | None = None, row: int | None = None):
        self.file = None if file is None else str(file)
        self.column = column
        self.row = row
        where = []
        if self.file is not None:
            where.append(f"file {self.file}")
        if column is not None:
            where.append(f"column '{column}'")
        if row is not None:
            where.append(f"row {row}")
        prefix = (", ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)
