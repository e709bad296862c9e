"""Hypothesis strategies and the reader invariant, shared by every fuzz test of a file reader.

A reader is fuzzed by starting from a valid file and corrupting it at the level its format
has: bytes (any file: truncation, flipped, inserted, deleted, duplicated bytes), text lines and
cells (CSV, YAML), JSON values (model.json, compensator files, Parquet metadata) and, in the
tests of each reader, table columns and types. The invariant, :func:`assert_clean`: the reader
returns or raises one :class:`InputError` naming the file on one line; it never raises anything
else and never changes the file.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Callable

from hypothesis import HealthCheck, event, settings
from hypothesis import strategies as st

from mmgp.errors import InputError

# The fuzz suite's size: MMGP_FUZZ_SCALE=20 runs 20 times as many examples; MMGP_FUZZ_RANDOM=1
# draws new ones on every run (hunting) instead of CI's fixed, reproducible set.
SCALE = float(os.environ.get("MMGP_FUZZ_SCALE", "1"))
RANDOM = os.environ.get("MMGP_FUZZ_RANDOM", "") == "1"


def fuzz_settings(max_examples: int):
    """Settings of one fuzz test: reproducible in CI (derandomized unless MMGP_FUZZ_RANDOM=1, no
    example database written into the repository), no per-example deadline (shared machines)."""
    return settings(max_examples=max(1, int(max_examples * SCALE)), deadline=None, derandomize=not RANDOM,
                    database=None, print_blob=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large, HealthCheck.filter_too_much])


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def digests(paths) -> dict[str, str | None]:
    """The digest of every file under ``paths`` (files or folders; None for a missing path)."""
    out = {}
    for path in map(Path, paths):
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            out[str(f)] = digest(f) if f.is_file() else None
    return out


def assert_clean(reader: Callable[[Path], object], path: Path, also: tuple = ()):
    """Call ``reader(path)``: returns its result, or None after a clean InputError. Anything
    else fails the test, as does a change of the file (or of the files and folders in ``also``,
    further inputs the error may name too) or a message that is not one line."""
    inputs = (path, *also)
    before = digests(inputs)
    try:
        result = reader(path)
    except InputError as err:
        msg = str(err)
        assert "\n" not in msg and "\r" not in msg, msg
        assert err.file in {str(p) for p in inputs}, msg
        label = re.sub(r"\d+", "N", re.split(r"[:(]", err.message)[0])[:50].strip()
        # a message may quote a lone surrogate from the input; hypothesis's statistics need UTF-8
        event("InputError: " + label.encode("utf-8", "backslashreplace").decode())
        result = None
    else:
        event("read")
    assert digests(inputs) == before, "the reader changed its input"
    return result


# ---------------------------------------------------------------------------------------------
# Bytes: any file
# ---------------------------------------------------------------------------------------------

@st.composite
def mutated_bytes(draw, data: bytes) -> bytes:
    """``data`` after one to three random byte-level corruptions."""
    for _ in range(draw(st.integers(1, 3))):
        n = len(data)
        pos = draw(st.integers(0, n))
        kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "repeat", "append", "empty"]))
        if kind == "truncate":
            data = data[:pos]
        elif kind == "flip" and n:
            i = min(pos, n - 1)
            data = data[:i] + bytes([data[i] ^ draw(st.integers(1, 255))]) + data[i + 1:]
        elif kind == "insert":
            data = data[:pos] + draw(st.binary(min_size=1, max_size=16)) + data[pos:]
        elif kind == "delete":
            data = data[:pos] + data[pos + draw(st.integers(1, 64)):]
        elif kind == "repeat":
            data = data[:pos] + data[pos:pos + draw(st.integers(1, 256))] + data[pos:]
        elif kind == "append":
            data = data + draw(st.binary(min_size=1, max_size=64))
        elif kind == "empty":
            data = b""
    return data


# ---------------------------------------------------------------------------------------------
# Text: lines and cells (CSV, YAML)
# ---------------------------------------------------------------------------------------------

NASTY_CELLS = ["", " ", "nan", "NaN", "inf", "-inf", "1e999", "-1e999", "1e-320", "-0", "abc", "1,5",
               "1.5.0", "0x10", "1_000", "\u0661", "\uff11", "TRUE", "None", "null", '"', '""', "'",
               "1e5", "+3", " 7 ", "\t", "\u00e9", "\u2212" "1", "9" * 400, "1." + "0" * 400, "#"]


def nasty_cells() -> st.SearchStrategy[str]:
    """Cell texts that readers misread: non-finite, locale, unicode digits, quotes, huge."""
    return st.one_of(st.sampled_from(NASTY_CELLS),
                     st.floats(allow_nan=True, allow_infinity=True).map(repr),
                     st.integers(-(10 ** 30), 10 ** 30).map(str),
                     st.text(max_size=8))


@st.composite
def mutated_lines(draw, text: str, sep: str = ",") -> str:
    """``text`` after one to three line- or cell-level corruptions (``sep`` separates cells)."""
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 3))):
        if not lines:
            lines = [""]
        i = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["cell", "cell", "cell", "drop", "repeat", "swap", "split",
                                     "join", "cut", "blank", "add_cell", "drop_cell"]))
        cells = lines[i].split(sep)
        j = draw(st.integers(0, max(len(cells) - 1, 0)))
        if kind == "cell":
            cells[j] = draw(nasty_cells())
            lines[i] = sep.join(cells)
        elif kind == "drop":
            del lines[i]
        elif kind == "repeat":
            lines.insert(i, lines[i])
        elif kind == "swap":
            k = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[k] = lines[k], lines[i]
        elif kind == "split":
            cut = draw(st.integers(0, len(lines[i])))
            lines[i:i + 1] = [lines[i][:cut], lines[i][cut:]]
        elif kind == "join" and i + 1 < len(lines):
            lines[i:i + 2] = [lines[i] + lines[i + 1]]
        elif kind == "cut":
            lines = lines[:i]
        elif kind == "blank":
            lines.insert(i, draw(st.sampled_from(["", " ", "\t", "\r"])))
        elif kind == "add_cell":
            lines[i] = sep.join(cells + [draw(nasty_cells())])
        elif kind == "drop_cell" and len(cells) > 1:
            del cells[j]
            lines[i] = sep.join(cells)
    return "\n".join(lines)


ENCODINGS = ["utf-8", "utf-8-sig", "utf-16", "utf-16-le", "utf-32", "latin-1", "cp1252"]


@st.composite
def encoded(draw, text: str) -> bytes:
    """``text`` in a random encoding and line-ending convention (what other tools save)."""
    ending = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    text = text.replace("\n", ending)
    encoding = draw(st.sampled_from(ENCODINGS))
    return text.encode(encoding, errors="replace")


# ---------------------------------------------------------------------------------------------
# JSON-like values: saved models, compensator files, configs, metadata
# ---------------------------------------------------------------------------------------------

def nasty_values() -> st.SearchStrategy:
    """A JSON-able value of any type and shape in place of the expected one."""
    leaves = st.one_of(st.none(), st.booleans(), st.integers(-(2 ** 70), 2 ** 70),
                       st.floats(allow_nan=False, allow_infinity=False), st.sampled_from([1e308, -1e308, 5e-324]),
                       st.text(max_size=12), st.sampled_from(NASTY_CELLS))
    return st.recursive(leaves, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                        st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                        max_leaves=6)


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


@st.composite
def mutated_json(draw, obj):
    """A deep copy of ``obj`` (nested dicts/lists) with one value replaced by a nasty one,
    or one key or item removed."""
    obj = json.loads(json.dumps(obj))
    path = draw(st.sampled_from(list(_paths(obj))))
    if not path:
        return draw(nasty_values())
    parent = obj
    for key in path[:-1]:
        parent = parent[key]
    if draw(st.booleans()):
        parent[path[-1]] = draw(nasty_values())
    else:
        del parent[path[-1]]
    return obj
