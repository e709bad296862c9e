"""What a compensator file must hold before it is rebuilt (numpy only).

:func:`validate_compensator_dict` checks the plain content of a file written by
:meth:`mmgp.compensator.field.Compensator.save` (the JSON object, or the NPZ's ``meta`` with its
arrays) and raises one :class:`~mmgp.errors.InputError` naming the file and the key: format and
version, the keys the evaluator needs, their types, shapes and ranges, and the storage being
bounded below (the file's own claims about the lower bound must agree with ``S >= 0``).
``load_compensator`` runs it on every file, so a controller never evaluates a field that
``mmgp check-passivity`` would refuse. The bounds themselves (``storage_offset``) are recomputed
from the weights by the evaluator and compared with the file there.

``READ_ERRORS`` are the exceptions reading a damaged file can raise (a truncated ZIP, a cut
JSON text, bytes that are neither).
"""
from __future__ import annotations

import math
import os
import tokenize
import zipfile
import zlib

import numpy as np

from ..errors import InputError

#: the file format this package writes and reads (its name, version, the versions it reads, field kinds)
FORMAT = "mmgp-compensator"
VERSION = 2
READABLE_VERSIONS = (1, 2)
KINDS = ("curl-free-wendland", "curl-free-rbf", "erf-1dof")

# SyntaxError / TokenError: NumPy parses an .npy header with Python's tokenizer, and a damaged one fails there
READ_ERRORS = (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, zlib.error, RecursionError,
               SyntaxError, tokenize.TokenError)

# A joint position (rad, or m for a prismatic joint) or a lengthscale outside these is no robot's:
# the evaluator's exp(-u^2/2) and the checks' finite differences lose every digit long before.
_MAX_POSITION = 1e6
_LENGTHSCALE_RANGE = (1e-6, 1e6)
# A storage value that rounds to below -tol is a claim that the storage is not bounded below by 0.
_STORAGE_TOL = 1e-9


def _fail(file, message: str) -> InputError:
    return InputError(message, file=file)


def _number(d: dict, key: str, file, *, positive: bool = False, optional: bool = False) -> float | None:
    value = d.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(value)):
        raise _fail(file, f"'{key}' must be a finite number, found {_shown(value)}")
    if positive and value <= 0:
        raise _fail(file, f"'{key}' must be positive, found {value!r}")
    return float(value)


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _array(d: dict, key: str, file, shape: tuple) -> np.ndarray:
    """``d[key]`` as a finite float64 array of ``shape`` (-1: any length >= 1)."""
    value = d.get(key)
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        raise _fail(file, f"'{key}' must hold real numbers, found an array of {value.dtype}")
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise _fail(file, f"'{key}' must be a list of numbers of shape {_dims(shape)}, found {_shown(value)}") from None
    if a.ndim != len(shape) or any(want not in (-1, got) for want, got in zip(shape, a.shape)) or 0 in a.shape:
        raise _fail(file, f"'{key}' must have shape {_dims(shape)}, found {a.shape if a.ndim else _shown(value)}")
    if not np.all(np.isfinite(a)):
        raise _fail(file, f"'{key}' holds a value that is not a finite number")
    return a


def _dims(shape: tuple) -> str:
    return "(" + ", ".join("N" if s == -1 else str(s) for s in shape) + ")"


def _header(d, file) -> None:
    versions = READABLE_VERSIONS
    if not isinstance(d, dict):
        raise _fail(file, f"expected a JSON object with \"format\": \"{FORMAT}\", found a {type(d).__name__}")
    if d.get("format") != FORMAT:
        raise _fail(file, f"not an {FORMAT} file ('format' is {_shown(d.get('format'))}, expected '{FORMAT}')")
    version = d.get("version")
    if isinstance(version, bool) or not isinstance(version, (int, np.integer)) or version not in versions:
        raise _fail(file, f"{FORMAT} version {_shown(version)} is not supported (this mmgp reads version(s) "
                          f"{', '.join(map(str, versions))})")
    missing = [k for k in ("kind", "support", "weights", "lengthscales", "signal_var", "storage_offset") if k not in d]
    if missing:
        raise _fail(file, f"key(s) {missing} missing: the file is incomplete (export it again with 'mmgp export')")
    if d["kind"] not in KINDS:
        raise _fail(file, f"'kind' is {_shown(d['kind'])}, expected one of {list(KINDS)}")


def _field_arrays(d: dict, file) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    support = _array(d, "support", file, (-1, -1))
    N, n = support.shape
    if d["kind"] == "erf-1dof" and n != 1:
        raise _fail(file, f"kind 'erf-1dof' needs one joint, 'support' has {n} columns")
    weights = _array(d, "weights", file, (N, n))
    lengthscales = _array(d, "lengthscales", file, (n,))
    lo, hi = _LENGTHSCALE_RANGE
    if np.any(lengthscales < lo) or np.any(lengthscales > hi):
        raise _fail(file, f"'lengthscales' must lie between {lo:g} and {hi:g}, found {lengthscales.tolist()}")
    if np.max(np.abs(support)) > _MAX_POSITION:
        raise _fail(file, f"'support' holds a joint position beyond +-{_MAX_POSITION:g} (rad or m)")
    return support, weights, lengthscales


def _workspace(d: dict, file, n: int) -> None:
    if d.get("workspace_bounds") is None:
        return
    bounds = _array(d, "workspace_bounds", file, (2, n))
    if np.max(np.abs(bounds)) > _MAX_POSITION:
        raise _fail(file, f"'workspace_bounds' reach beyond +-{_MAX_POSITION:g} (rad or m): expected the "
                          "range of joint positions the field was fitted on")
    if np.any(bounds[0] > bounds[1]):
        raise _fail(file, "'workspace_bounds' must be [lower, upper] with lower <= upper for every joint")


def _names(d: dict, file, n: int) -> None:
    names = d.get("joint_names")
    if names is None:
        return
    if not isinstance(names, list) or len(names) != n or not all(isinstance(s, str) for s in names):
        raise _fail(file, f"'joint_names' must be a list of {n} names, found {_shown(names)}")


def _storage_claims(d: dict, file, s2: float, weights: np.ndarray, lengthscales: np.ndarray) -> None:
    """The storage S = V + storage_offset is bounded below by 0: the file may not claim otherwise,
    and the weights must keep V finite (its triangle bound a finite number)."""
    _number(d, "storage_offset", file)
    claimed = _number(d, "storage_lower_bound", file, optional=True)
    if claimed is not None and claimed != 0.0:
        raise _fail(file, f"'storage_lower_bound' is {claimed!r}: the format defines the storage with lower bound 0")
    sampled = _number(d, "storage_sampled_min", file, optional=True)
    if sampled is not None and sampled < -_STORAGE_TOL * max(1.0, abs(_number(d, "storage_offset", file))):
        raise _fail(file, f"'storage_sampled_min' is {sampled!r}: the storage goes below its lower bound 0, "
                          "so the field is not passive (the file was edited or corrupted)")
    with np.errstate(over="ignore", invalid="ignore"):
        scale = s2 * np.sum(np.abs(weights)) * max(float(np.max(lengthscales)), float(np.max(1.0 / lengthscales)))
    if not math.isfinite(scale):
        raise _fail(file, "'weights' and 'signal_var' are too large: the potential would overflow")


def validate_compensator_dict(d, file: str | os.PathLike | None = None) -> None:
    """Refuse (one :class:`InputError` naming ``file``) a compensator file's content ``d`` that the
    evaluator cannot be rebuilt from: not a JSON object, another format or version, a missing key
    (``kind``, ``support``, ``weights``, ``lengthscales``, ``signal_var``, ``storage_offset``), a
    value of the wrong type, shape or range (positions within +-1e6 rad or m, lengthscales in
    [1e-6, 1e6], everything finite; ``info`` and ``prior`` objects or null), or a claim that the
    storage goes below 0. Versions: those :data:`READABLE_VERSIONS` lists.

    ``d``: the parsed JSON object (arrays as nested lists) or the NPZ's ``meta`` with its arrays
    (``support`` (N, n), ``weights`` (N, n), ``lengthscales`` (n,), ``workspace_bounds`` (2, n)).
    """
    _header(d, file)
    support, weights, lengthscales = _field_arrays(d, file)
    n = support.shape[1]
    _workspace(d, file, n)
    _names(d, file, n)
    s2 = _number(d, "signal_var", file, positive=True)
    _storage_claims(d, file, s2, weights, lengthscales)
    for key in ("info", "prior"):  # the prior's content is checked by the evaluator (physical consistency)
        if d.get(key) is not None and not isinstance(d[key], dict):
            raise _fail(file, f"'{key}' must be a JSON object or null, found {_shown(d[key])}")
    if d.get("deviation_sampled_max") is not None:
        _array(d, "deviation_sampled_max", file, (n,))
