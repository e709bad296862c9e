"""The one settings loader: YAML sections + command-line flags -> keyword arguments.

A settings file has top-level sections, each holding the keyword arguments of one thing:

- ``train:``    :class:`mmgp.MultimodalGP` (``mmgp train``)
- ``diagnose:`` :class:`mmgp.Diagnoser` (``mmgp diagnose``)
- ``compare:``  the held-out model comparison (``mmgp compare``)
- ``export:``   :meth:`mmgp.MultimodalGP.to_compensator` (``mmgp export``)

Each setting is documented once, where it is a parameter (the class or method docstring). This
module checks the names, and has the values checked when they are loaded (by the class's own
validation, or against a function's defaults) so that a refusal names the file with the setting.
"""
from __future__ import annotations

import difflib
import inspect
import math
import re
from pathlib import Path
from typing import Any, Callable

import yaml

from .errors import InputError

SECTIONS = ("train", "diagnose", "compare", "export")


def parameter_names(target: Any) -> list[str]:
    """The settings ``target`` takes: a scikit-learn style class (``_get_param_names``), or any
    class or function (its keyword parameters, ``self`` and ``*args``/``**kwargs`` excluded)."""
    if hasattr(target, "_get_param_names"):
        return list(target._get_param_names())
    params = inspect.signature(target).parameters.values()
    return [p.name for p in params if p.name != "self"
            and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]


def _unknown(kind: str, key: str, known: list[str], file=None) -> InputError:
    near = difflib.get_close_matches(key, known, n=1)
    hint = f" (did you mean '{near[0]}'?)" if near else ""
    return InputError(f"unknown {kind} '{key}'{hint}; known: {', '.join(known)}", file=file)


def read_sections(path: str | Path) -> dict:
    """The sections of a settings file: {section: {key: value}}; refuses unknown sections and
    reports invalid YAML as one line (file, line, column, what)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("settings file does not exist", file=path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): "
                         "save the settings file as UTF-8", file=path) from None
    except OSError as exc:
        raise InputError(f"cannot read the settings file ({exc.strerror or exc})", file=path) from None
    try:
        loaded = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        # Where the broken construct starts (an unclosed quote or bracket is reported by the
        # parser at the end of the file), and what is wrong, on one line.
        mark = getattr(exc, "context_mark", None) or getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        what = "; ".join(str(x) for x in (getattr(exc, "context", None), getattr(exc, "problem", None)) if x)
        what = " ".join((what or str(exc)).split())
        raise InputError(f"{where}not valid YAML ({what})", file=path) from None
    if not isinstance(loaded, dict):
        raise InputError(f"expected sections {', '.join(SECTIONS)} at the top level", file=path)
    for name, body in loaded.items():
        if name not in SECTIONS:
            raise _unknown("section", str(name), list(SECTIONS), file=path)
        if body is not None and not isinstance(body, dict):
            raise InputError(f"section '{name}' must be a mapping of setting: value", file=path)
    return {name: dict(body or {}) for name, body in loaded.items()}


def load_settings(path: str | Path | None, section: str, target: type | Callable, **overrides) -> dict:
    """Keyword arguments for ``target`` from ``section`` of the YAML file ``path`` (optional),
    with the ``overrides`` that are not None (command-line flags) on top.

    Every key, in the file or in ``overrides``, must be a parameter of ``target`` (see
    :func:`parameter_names`); an unknown one is refused naming it and the known ones. The values
    are checked here too (:func:`check_values`), so that a bad value read from the file is refused
    naming the file as well as the setting.
    Example: ``MultimodalGP(**load_settings("configs/default.yaml", "train", MultimodalGP, seed=3))``.
    """
    if section not in SECTIONS:
        raise ValueError(f"section must be one of {SECTIONS}, got {section!r}")
    known = parameter_names(target)
    values = read_sections(path).get(section, {}) if path is not None else {}
    for key in values:
        if key not in known:
            raise _unknown(f"{section} setting", str(key), known, file=path)
    from_file = set(values)
    for key, value in overrides.items():
        if key not in known:
            raise ValueError(f"{key!r} is not a parameter of {getattr(target, '__qualname__', target)}")
        if value is not None:
            values[key] = value
            from_file.discard(key)
    if path is not None:
        check_values(target, values, file=path, from_file=from_file)
    return values


_SETTING = re.compile(r"setting '([^']+)'")


def check_values(target: type | Callable, values: dict, file=None, from_file=None) -> None:
    """Refuse a bad value in ``values`` (settings of ``target``) with one :class:`InputError`
    naming the setting, and ``file`` when the value came from it (``from_file``: those keys; all
    when None).

    A class is asked itself: its ``_validate`` (or ``_check``) method on an instance built from
    ``values``, whose refusals start with ``setting 'NAME'``. A function's values are checked
    against its defaults: where the default is a bool the value must be true or false, an
    integer an integer no smaller than the default or 1 (counts are positive, seeds >= 0), a
    float a finite number.
    """
    from_file = set(values) if from_file is None else set(from_file)
    try:
        check = getattr(target, "_validate", None) or getattr(target, "_check", None)
        if isinstance(target, type) and check is not None:
            check(target(**values))
        elif not isinstance(target, type):
            _check_by_defaults(target, values)
    except InputError as exc:
        key = _SETTING.match(exc.message)
        if file is not None and exc.file is None and key is not None and key.group(1) in from_file:
            raise InputError(exc.message, file=file) from None
        raise


def _check_by_defaults(target: Callable, values: dict) -> None:
    defaults = {p.name: p.default for p in inspect.signature(target).parameters.values()}
    for key, value in values.items():
        default = defaults.get(key, inspect.Parameter.empty)
        if isinstance(default, bool):
            ok, expected = isinstance(value, bool), "true or false"
        elif isinstance(default, int):
            low = min(default, 1)
            ok = isinstance(value, int) and not isinstance(value, bool) and value >= low
            expected = "a positive integer" if low == 1 else f"an integer >= {low}"
        elif isinstance(default, float):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            expected = "a finite number"
        else:
            continue
        if not ok:
            raise InputError(f"setting '{key}': expected {expected}, got {value!r}")
