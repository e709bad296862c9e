"""Reading a saved model's files (``model.json`` + ``model.npz``) and refusing damaged ones.

Every way a saved model can be damaged (a truncated or missing file, text that is not JSON, a key
of the wrong type, an array missing, of another shape or not finite) ends in one
:class:`~mmgp.errors.InputError` naming the file and what was expected, before any GP is built
from it. :class:`mmgp.MultimodalGP.load` uses these readers.
"""
from __future__ import annotations

import json
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .errors import InputError, describe

# SyntaxError / TokenError: NumPy parses an .npy header with Python's tokenizer, and a damaged one fails there
_NPZ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, SyntaxError,
               tokenize.TokenError)


def _v1_settings(meta: dict, path: Path) -> dict:
    # v1 kept the settings of the former TrainConfig under "config"; "modes" is now n_modes.
    config = meta.pop("config", None)
    if not isinstance(config, dict) or "modes" not in config:
        raise InputError("model.json v1 needs a 'config' object with 'modes'", file=path)
    settings = dict(config)
    settings["n_modes"] = settings.pop("modes")
    spec = meta.get("robot") if isinstance(meta.get("robot"), dict) else {}
    settings["robot"] = spec.get("robot") or spec.get("urdf")
    return settings


def read_model_meta(model_dir: Path, fmt: str, versions: tuple) -> dict:
    """model.json of ``model_dir`` checked, its settings under "settings" whatever the version
    (``versions``: those this mmgp reads, the newest last)."""
    path = model_dir / "model.json"
    if not path.is_file():
        raise InputError("not a trained model folder (model.json missing; run 'mmgp train' first)", file=model_dir)
    try:
        meta = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as exc:
        raise InputError(f"model.json is not valid JSON ({describe(exc)})", file=path) from None
    version = meta.get("version") if isinstance(meta, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != fmt or isinstance(version, bool) or version not in versions:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise InputError(f"unsupported model format {found!r} version {json.dumps(version)} (this mmgp "
                         f"reads {fmt} versions {versions[0]} to {versions[-1]})", file=path)
    if version == 1:
        meta["settings"] = _v1_settings(meta, path)
    _check_meta(meta, path)
    if not (model_dir / "model.npz").is_file():
        raise InputError("model.npz missing (the folder holds model.json only: copy both files, or train again)",
                         file=model_dir)
    return meta


def _check_meta(meta: dict, path: Path) -> None:
    def bad(key: str, expected: str):
        return InputError(f"'{key}' must be {expected}, found {json.dumps(meta.get(key))[:60]}", file=path)

    K = meta.get("n_modes")
    if isinstance(K, bool) or not isinstance(K, int) or not 1 <= K <= 100:
        raise bad("n_modes", "a number of modes from 1 to 100")
    names = meta.get("joint_names")
    if not isinstance(names, list) or not names or not all(isinstance(s, str) for s in names):
        raise bad("joint_names", "a non-empty list of joint names")
    if not isinstance(meta.get("settings"), dict):
        raise bad("settings", "an object of training settings")
    if meta.get("robot") is not None and not _robot_spec_ok(meta["robot"]):
        raise bad("robot", "an object with 'robot' (a name) or 'urdf' (a path) and 'joint_names' (names), or null")
    kinds = meta.get("gp_kinds")
    if kinds is not None and (not isinstance(kinds, list) or len(kinds) != K
                              or not all(k in ("exact", "sgpr", "subset") for k in kinds)):
        raise bad("gp_kinds", f"a list of {K} of 'exact', 'sgpr', 'subset'")
    digests = meta.get("gp_weights_sha256")
    if digests is not None and (not isinstance(digests, list) or len(digests) != K or not all(
            d is None or isinstance(d, str) and len(d) == 64 for d in digests)):
        raise bad("gp_weights_sha256", f"a list of {K} SHA-256 hex digests or nulls")
    if not isinstance(meta.get("sign_fades", False), bool):
        raise bad("sign_fades", "true or false")
    from .labelling.features import MeanBasis

    try:
        MeanBasis.parse(meta.get("mean_basis"))
    except ValueError:
        raise bad("mean_basis", "'payload', 'rbd' (optionally '+friction') or null") from None


def _robot_spec_ok(spec) -> bool:
    if not isinstance(spec, dict):
        return False
    robot, urdf, names = spec.get("robot"), spec.get("urdf"), spec.get("joint_names")
    text = (robot is None or isinstance(robot, str)) and (urdf is None or isinstance(urdf, str))
    return text and (names is None or isinstance(names, list) and all(isinstance(s, str) for s in names))


def _finite(arrays: dict, key: str, path: Path, shape: tuple) -> np.ndarray:
    """``arrays[key]``, real and finite, of ``shape`` (None: any size >= 1 there)."""
    if key not in arrays:
        raise InputError(f"array '{key}' missing: the file is incomplete (train again)", file=path)
    a = arrays[key]
    if a.dtype.kind not in "iuf" or a.ndim != len(shape) or 0 in a.shape or \
            any(want is not None and want != got for want, got in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"array '{key}' must be real numbers of shape {want}, found {a.dtype} {a.shape}", file=path)
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(f"array '{key}' holds a value that is not a finite number", file=path)
    return a


def _n_inputs(meta: dict, raw: dict) -> int:
    """GP inputs per sample: q, dq, ddq, then the sliding sign with friction, tau_rbd as a feature."""
    n = len(meta["joint_names"])
    rbd = bool(meta.get("robot")) and meta["settings"].get("semiparametric") == "feature"
    return n * (3 + ("friction_scale" in raw) + rbd)


def read_model_arrays(model_dir: Path, meta: dict) -> dict:
    """The arrays of ``model_dir/model.npz`` checked against ``meta`` (from :func:`read_model_meta`):
    per mode k ``X_k`` (N, n_inputs) (n_inputs: 3n, plus n with ``friction_scale``, plus n for
    ``semiparametric: feature`` with a robot), ``Y_k`` (N, n), ``lengthscale_k`` (m, n_inputs),
    ``signal_var_k`` and ``noise_var_k`` (m,) positive (m = 1 or n), optional ``basis_coef_k``
    (n, p), ``inducing_k`` (M, n_inputs) and ``weights_k`` (n, N) (:func:`store_gp_weights`);
    optional ``friction_scale`` (n,) positive."""
    path = model_dir / "model.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
    except _NPZ_ERRORS as exc:
        raise InputError(f"model.npz is damaged or not a NumPy archive ({describe(exc)})", file=path) from None
    n, n_inputs = len(meta["joint_names"]), _n_inputs(meta, raw)
    out = {}
    for k in range(int(meta["n_modes"])):
        X = out[f"X_{k}"] = _finite(raw, f"X_{k}", path, (None, n_inputs))
        out[f"Y_{k}"] = _finite(raw, f"Y_{k}", path, (len(X), n))
        ls = out[f"lengthscale_{k}"] = _finite(raw, f"lengthscale_{k}", path, (None, n_inputs))
        if len(ls) not in (1, n):
            raise InputError(f"array 'lengthscale_{k}' must have 1 or {n} rows, found {len(ls)}", file=path)
        for key in (f"lengthscale_{k}", f"signal_var_{k}", f"noise_var_{k}"):
            out[key] = _finite(raw, key, path, (len(ls),) if key != f"lengthscale_{k}" else ls.shape)
            if np.any(out[key] <= 0):
                raise InputError(f"array '{key}' must be positive", file=path)
        for key, shape in ((f"basis_coef_{k}", (n, None)), (f"inducing_{k}", (None, n_inputs)),
                           (f"weights_{k}", (n, len(X)))):
            if key in raw:
                out[key] = _finite(raw, key, path, shape)
    if "friction_scale" in raw:
        out["friction_scale"] = _finite(raw, "friction_scale", path, (n,))
        if np.any(out["friction_scale"] <= 0):
            raise InputError("array 'friction_scale' must be positive", file=path)
    return out


def read_model_robot(spec: dict | None, meta_path: Path):
    """The RobotModel a saved model names in ``model.json`` (``spec``: its checked "robot" entry),
    or None; one that cannot be loaded here (an unknown name, a missing URDF) is refused naming
    ``meta_path``."""
    if not spec:
        return None
    from .physics.robot import load_robot

    try:
        return load_robot(robot=spec.get("robot"), urdf=spec.get("urdf"), joint_names=spec.get("joint_names"))
    except InputError as exc:
        raise InputError(f"'robot' (the rigid-body model it was trained with): {exc}", file=meta_path) from None


# The solved GP weights K^-1 y of a large exact GP: training solves them (its friction check
# predicts every mode's mean), and re-solving them at load is the O(N^3) per output that made
# `mmgp export` of a 10,000-sample model take minutes. They are stored with a digest of what they
# were solved from, and used only where that still matches.
_SOLVED_FROM = ("X", "Y", "lengthscale", "signal_var", "noise_var")


def support_digest(arrays: dict, k: int) -> str:
    """SHA-256 (hex) of mode ``k``'s support and hyperparameter arrays in ``arrays`` (as
    :meth:`mmgp.MultimodalGP.save` writes them): names, shapes and float64 bytes."""
    import hashlib

    h = hashlib.sha256()
    for name in _SOLVED_FROM:
        a = np.ascontiguousarray(arrays[f"{name}_{k}"], dtype="<f8")
        h.update(f"{name}_{k}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def store_gp_weights(n_modes: int, gps: list | None, stored: list | None, arrays: dict) -> list:
    """Put each mode's solved weights (m, N) into ``arrays`` as ``weights_k``: those of its fitted
    GP ``gps[k]`` when that is a large exact GP that has solved them (``per_output_``; a small one
    solves them in no time), or, for a mode whose GP is not built, ``stored[k]`` (the weights it
    was loaded with). Returns the per-mode digests (None where no weights) for model.json's
    ``gp_weights_sha256``."""
    gps, stored = gps or [None] * n_modes, stored or [None] * n_modes
    out = []
    for k in range(n_modes):
        gp = gps[k]
        w = stored[k] if gp is None else (gp.solved_weights() if getattr(gp, "per_output_", False) else None)
        if w is None:
            out.append(None)
            continue
        arrays[f"weights_{k}"] = np.asarray(w, dtype=np.float64)
        out.append(support_digest(arrays, k))
    return out


def read_gp_weights(meta: dict, arrays: dict) -> list:
    """Per mode the stored weights (m, N) (``arrays`` from :func:`read_model_arrays`), or None where there are none or their digest no longer
    matches the support and hyperparameters (the file was edited: the weights are solved again)."""
    digests = meta.get("gp_weights_sha256") or [None] * int(meta["n_modes"])
    out = []
    for k, digest in enumerate(digests):
        key = f"weights_{k}"
        if digest is None or key not in arrays:
            out.append(None)
            continue
        out.append(arrays[key] if digest == support_digest(arrays, k) else None)
    return out
