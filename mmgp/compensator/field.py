"""Passivity-safe position-only feedforward compensator.

A controller renders ``tau = tau_ff(q) + K_imp (q_d - q) - B_imp dq`` (or any impedance) on top of a
learned feedforward ``tau_ff(q)``: the trained model's nominal-mode torque at ``(q, dq=0, ddq=0)``
(gravity, springs, constant offsets; the rigid-body part included when the model has a robot).
For the loop to stay passive the feedforward must be the gradient of a storage function that is
bounded below, ``tau_ff = grad S``: then the work it does along any motion is ``S(q1) - S(q0)``,
zero around every closed loop, and the energy it can ever hand out is finite.

Two kinds are exported:

``"erf-1dof"`` (one joint)
    An ordinary RBF Gaussian process on the torque, ``tau(q) = sum_a w_a s2 exp(-(q-z_a)^2/(2 l^2))``.
    In one dimension every field is a gradient; its integral is
    ``V(q) = sum_a w_a s2 l sqrt(pi/2) erf((q - z_a)/(sqrt(2) l))``. (Haninger 2016 writes the squared
    distance inside ``erf``; that expression is not the integral of the kernel: its derivative is
    odd in ``q - z``, the kernel is even. The expression above is.)

``"curl-free-rbf"`` (several joints)
    Independent per-joint GPs are generally *not* the gradient of anything (their mixed partials
    differ), so a loop in joint space can pump energy. Instead we learn a scalar potential
    ``V ~ GP(0, k)`` with an ARD RBF kernel ``k(x, x') = s2 exp(-|(x - x')/l|^2 / 2)`` whose *gradient*
    is observed: ``y_a = grad V(x_a) + noise``. The gradient observations are jointly Gaussian with
    ``cov(dV/dx_i(x), dV/dx'_j(x')) = d^2 k / dx_i dx'_j = k/(l_i l_j) (delta_ij - u_i u_j)``,
    ``u = (x - x')/l`` (a curl-free matrix kernel). With ``alpha = (K + Sigma_noise)^{-1} y``
    (``N*n`` unknowns), the posterior mean is ``V(q) = sum_a k(q, z_a) u_a . gamma_a`` with
    ``u_a = (q - z_a)/l`` and ``gamma_a = alpha_a / l``, and ``tau_ff(q) = grad V(q)`` exactly:
    ``tau_i = sum_a k/l_i (gamma_ai - u_ai (u_a . gamma_a))``.

Boundedness. Each term satisfies ``|k u.gamma| <= s2 |gamma| max_t t exp(-t^2/2) = s2 |gamma| e^{-1/2}``,
so ``|V| <= s2 e^{-1/2} sum_a |gamma_a|`` on all of R^n (for erf-1dof, ``sum_a |A_a|``). That triangle
bound is rigorous but useless in practice (GP weights alternate in sign: 1e7-1e8 J for a Panda
gravity fit), so tighter rigorous bounds are used (see :func:`mmgp.compensator.passivity.potential_bounds`): the
RKHS bound ``|V| <= sqrt(s2 alpha^T K_dd alpha)`` (about 1e3 J for the Panda, against a sampled
range of tens of J) for curl-free-rbf, and a grid plus Lipschitz bound for erf-1dof (tight). With
``L <= inf V`` from these, the storage function is ``S(q) = V(q) - L >= 0`` everywhere.
A constant torque (constant gravity direction, a torque offset) has an unbounded
linear potential on R^n; a zero-mean RBF potential cannot have one, so the compensator reproduces
such torques only over the workspace its support points cover and fades to zero torque far
outside it (a safe default: no feedforward where nothing was learned). The multi-joint bound is
loose, so the export also reports ``storage_sampled_min``, the smallest ``S`` found over the
workspace box (random points, the support points and a local minimisation): the true infimum of
``S`` lies in ``[0, storage_sampled_min]``.

This module is the evaluator and the file format: numpy only (no torch, scipy or pinocchio), so a
controller process can load and evaluate a compensator cheaply. Fitting is in
:mod:`mmgp.compensator.fit` (the potential GPs of :mod:`mmgp.gp.gradient_field`), the bounds and
checks in :mod:`mmgp.compensator.passivity`, C export in :mod:`mmgp.compensator.csource`.
"""
from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from .passivity import potential_bounds

FORMAT = "mmgp-compensator"
VERSION = 1
KINDS = ("erf-1dof", "curl-free-rbf")
_SQRT_PI_2 = math.sqrt(math.pi / 2.0)


class Compensator:
    """An exported feedforward ``tau_ff(q) = grad S(q)`` with a storage function ``S >= 0``.

    Parameters (all float64)
    ----------
    kind : ``"erf-1dof"`` or ``"curl-free-rbf"``.
    support : (N, n) support positions ``z_a`` (rad, m for prismatic joints).
    weights : (N, n) for curl-free-rbf (``alpha``, N*m/rad... the solved GP weights), (N, 1) for erf-1dof.
    lengthscales : (n,) kernel lengthscales (rad).
    signal_var : kernel signal variance ``s2`` (J^2 for the potential GP, N^2 m^2 for erf-1dof).
    joint_names : n joint names.
    bounds : (2, n) workspace box (min, max of the support positions) used by checks.
    info : free-form dict (hyperparameters, fit figures); saved in the file.

    ``potential_lower_bound`` L and ``potential_upper_bound`` U (J) bound V rigorously on all of R^n
    (see :func:`mmgp.compensator.passivity.potential_bounds`); ``potential_bound = max(-L, U)``.
    ``storage(q) = potential(q) - L``, so ``0 <= S(q) <= U - L`` everywhere (``storage_offset = -L``).
    """

    def __init__(self, kind: str, support, weights, lengthscales, signal_var: float,
                 joint_names: Sequence[str] | None = None, bounds=None, info: dict | None = None,
                 storage_sampled_min: float | None = None):
        if kind not in KINDS:
            raise ValueError(f"unknown compensator kind {kind!r}; expected one of {KINDS}")
        self.kind = kind
        self.support = np.ascontiguousarray(np.asarray(support, dtype=np.float64))
        if self.support.ndim != 2:
            raise ValueError("support must be (N, n)")
        n = self.support.shape[1]
        if kind == "erf-1dof" and n != 1:
            raise ValueError("erf-1dof needs exactly one joint")
        self.weights = np.ascontiguousarray(np.asarray(weights, dtype=np.float64)
                                            .reshape(self.support.shape[0], -1))
        if self.weights.shape[1] != n:
            raise ValueError(f"weights must be (N, {n}), got {self.weights.shape}")
        self.lengthscales = np.asarray(lengthscales, dtype=np.float64).reshape(n)
        if np.any(self.lengthscales <= 0):
            raise ValueError("lengthscales must be positive")
        self.signal_var = float(signal_var)
        self.joint_names = list(joint_names) if joint_names is not None else [f"q_{i}" for i in range(n)]
        if len(self.joint_names) != n:
            raise ValueError("joint_names length does not match the support dimension")
        if bounds is None:
            bounds = np.stack([self.support.min(0), self.support.max(0)])
        self.bounds = np.asarray(bounds, dtype=np.float64).reshape(2, n)
        self.info = dict(info or {})
        # Quantities shared by the numpy and the C evaluators: computing them once, here, and
        # printing them with 17 significant digits makes both evaluators see the same numbers.
        self._inv_l = 1.0 / self.lengthscales
        self._zs = self.support * self._inv_l  # support in lengthscale units
        if kind == "curl-free-rbf":
            self._gamma = self.weights * self._inv_l
        else:
            self._gamma = self.weights[:, 0] * self.signal_var  # torque amplitude per support
            self._erf_amp = self._gamma * self.lengthscales[0] * _SQRT_PI_2
        lower, upper, self.bound_info = potential_bounds(self)
        self.potential_lower_bound = lower
        self.potential_upper_bound = upper
        self.potential_bound = max(-lower, upper)
        self.storage_offset = -lower
        self.storage_lower_bound = 0.0
        self.storage_sampled_min = storage_sampled_min

    # -- evaluation -----------------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return self.support.shape[1]

    def _prep(self, q):
        q = np.asarray(q, dtype=np.float64)
        single = q.ndim == 1
        q2 = q.reshape(1, -1) if single else q
        if q2.ndim != 2 or q2.shape[1] != self.n_joints:
            raise ValueError(f"q must be ({self.n_joints},) or (T, {self.n_joints}); got {q.shape}")
        return q2, single

    def _eval(self, q2, want_tau: bool, want_v: bool, chunk_elems: int = 4_000_000):
        T, n = q2.shape
        N = self.support.shape[0]
        tau = np.empty((T, n)) if want_tau else None
        V = np.empty(T) if want_v else None
        step = max(1, chunk_elems // max(1, N * n))
        qs = q2 * self._inv_l
        for s in range(0, T, step):
            U = qs[s:s + step, None, :] - self._zs[None, :, :]  # (t, N, n)
            k = self.signal_var * np.exp(-0.5 * np.sum(U * U, axis=2))  # (t, N)
            if self.kind == "curl-free-rbf":
                ug = np.sum(U * self._gamma[None], axis=2)  # (t, N)
                if want_v:
                    V[s:s + step] = np.sum(k * ug, axis=1)
                if want_tau:
                    tau[s:s + step] = self._inv_l * (k @ self._gamma - np.einsum("tb,tbi->ti", k * ug, U))
            else:
                u = U[:, :, 0]
                if want_tau:
                    tau[s:s + step, 0] = np.exp(-0.5 * u * u) @ self._gamma
                if want_v:
                    V[s:s + step] = _erf(u / math.sqrt(2.0)) @ self._erf_amp
        return tau, V

    def torque(self, q):
        """Feedforward torque tau_ff(q) (N*m). q: (n,) -> (n,), or (T, n) -> (T, n) (rad)."""
        q2, single = self._prep(q)
        tau, _ = self._eval(q2, True, False)
        return tau[0] if single else tau

    def potential(self, q):
        """Potential V(q) (J) with grad V = tau_ff and |V| <= potential_bound. (n,)->float, (T,n)->(T,)."""
        q2, single = self._prep(q)
        _, V = self._eval(q2, False, True)
        return float(V[0]) if single else V

    def storage(self, q):
        """Storage S(q) = V(q) - potential_lower_bound >= 0 (J). (n,) -> float, (T, n) -> (T,)."""
        q2, single = self._prep(q)
        _, V = self._eval(q2, False, True)
        S = V + self.storage_offset
        return float(S[0]) if single else S

    # -- export ---------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Everything needed to rebuild the evaluator, as plain Python (lists of floats)."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "kind": self.kind,
            "joint_names": list(self.joint_names),
            "n_joints": self.n_joints,
            "n_support": int(self.support.shape[0]),
            "kernel": "rbf-ard",
            "lengthscales": self.lengthscales.tolist(),
            "signal_var": self.signal_var,
            "support": self.support.tolist(),
            "weights": self.weights.tolist(),
            "bias": "none (zero prior mean: V is a pure RBF expansion, bounded on R^n)",
            "potential_bound": self.potential_bound,
            "potential_lower_bound": self.potential_lower_bound,
            "potential_upper_bound": self.potential_upper_bound,
            "potential_bound_method": self.bound_info,
            "storage_offset": self.storage_offset,
            "storage_lower_bound": self.storage_lower_bound,
            "storage_sampled_min": self.storage_sampled_min,
            "workspace_bounds": self.bounds.tolist(),
            "definition": _DEFINITIONS[self.kind],
            "info": self.info,
        }

    def save(self, path) -> Path:
        """Write the compensator to ``path`` (``.json``; anything else is written as NPZ).

        NPZ holds the arrays plus a JSON ``meta`` string; JSON holds everything as text
        (floats round-trip exactly). The file is written atomically (temporary file + rename).
        """
        from ..data.outputs import atomic_write_bytes

        path = Path(path)
        d = self.to_dict()
        if path.suffix.lower() == ".json":
            data = json.dumps(d, indent=1).encode()
        else:
            arrays = {k: np.asarray(d.pop(k), dtype=np.float64)
                      for k in ("support", "weights", "lengthscales", "workspace_bounds")}
            buf = io.BytesIO()
            np.savez(buf, meta=np.array(json.dumps(d)), **arrays)
            data = buf.getvalue()
        atomic_write_bytes(path, data)
        return path

    def write_c(self, dir_or_prefix, name: str | None = None):
        """Write dependency-free C99 source + header; returns ``(c_path, h_path)``.

        ``dir_or_prefix``: an existing directory (files ``mmgp_compensator.c/.h`` inside it) or a
        path prefix (``prefix.c``/``prefix.h``). The C functions are ``<name>_torque(q, tau)``,
        ``<name>_potential(q)`` and ``<name>_storage(q)``, ``<name>`` being the file stem.
        """
        from .csource import write_c_source

        return write_c_source(self, dir_or_prefix, name=name)

    def __repr__(self):
        return (f"Compensator(kind={self.kind!r}, n_joints={self.n_joints}, "
                f"n_support={self.support.shape[0]}, potential_bound={self.potential_bound:.4g})")


_DEFINITIONS = {
    "curl-free-rbf": (
        "u_a = (q - support_a)/lengthscales; k_a = signal_var*exp(-|u_a|^2/2); gamma_a = weights_a/lengthscales; "
        "V(q) = sum_a k_a (u_a . gamma_a); tau_i(q) = dV/dq_i = sum_a k_a/l_i (gamma_ai - u_ai (u_a . gamma_a)); "
        "storage(q) = V(q) + storage_offset, storage_offset = -potential_lower_bound (rigorous, RKHS: "
        "|V| <= sqrt(signal_var * alpha^T K_dd alpha))"),
    "erf-1dof": (
        "u_a = (q - support_a)/l; tau(q) = sum_a weights_a*signal_var*exp(-u_a^2/2); "
        "V(q) = sum_a weights_a*signal_var*l*sqrt(pi/2)*erf(u_a/sqrt(2)); "
        "storage(q) = V(q) + storage_offset, storage_offset = -potential_lower_bound (rigorous, grid + "
        "Lipschitz bound |tau| <= sqrt(signal_var * w^T K w))"),
}


# erf without scipy: a piecewise Taylor polynomial, built at import from math.erf (correctly rounded
# centres) and the Hermite recurrence for the derivatives, erf^(k)(c) = 2/sqrt(pi) (-1)^(k-1)
# H_{k-1}(c) e^{-c^2}. Intervals of width 1/8 with degree 15 leave a truncation error below 1e-18;
# the first interval uses the Maclaurin series so that erf(x) ~ 2x/sqrt(pi) keeps its relative
# accuracy near 0. Measured against math.erf: at most 2 ulp (scipy.special.erf: 3 ulp).
_ERF_STEP = 0.125
_ERF_ONE = 6.0  # erf(x) rounds to 1.0 in float64 from x = 5.93 on
_ERF_DEGREE = 15


def _erf_table() -> tuple[np.ndarray, np.ndarray]:
    n_int = int(_ERF_ONE / _ERF_STEP)
    C = np.zeros((_ERF_DEGREE + 1, n_int))
    two_over_sqrt_pi = 2.0 / math.sqrt(math.pi)
    for j in range(_ERF_DEGREE // 2 + 1):
        C[2 * j + 1, 0] = two_over_sqrt_pi * (-1) ** j / (math.factorial(j) * (2 * j + 1))
    centres = (np.arange(n_int) + 0.5) * _ERF_STEP
    centres[0] = 0.0
    for i in range(1, n_int):
        c = centres[i]
        C[0, i] = math.erf(c)
        g = two_over_sqrt_pi * math.exp(-c * c)
        h_prev, h = 0.0, 1.0  # H_{k-2}(c), H_{k-1}(c)
        for k in range(1, _ERF_DEGREE + 1):
            C[k, i] = g * (-1) ** (k - 1) * h / math.factorial(k)
            h_prev, h = h, 2 * c * h - 2 * (k - 1) * h_prev
    return C, centres


_ERF_COEF, _ERF_CENTRES = _erf_table()


def _erf(x, chunk: int = 32768) -> np.ndarray:
    """Error function of a float64 array, elementwise (numpy only)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    xf, of = x.reshape(-1), out.reshape(-1)
    for s in range(0, xf.size, chunk):  # chunks that stay in cache across the Horner passes
        xc = xf[s:s + chunk]
        a = np.abs(xc)
        i = np.minimum((np.fmin(a, _ERF_ONE) * (1.0 / _ERF_STEP)).astype(np.intp), _ERF_COEF.shape[1] - 1)
        t = a - _ERF_CENTRES[i]
        p = _ERF_COEF[_ERF_DEGREE].take(i)
        for k in range(_ERF_DEGREE - 1, -1, -1):
            p *= t
            p += _ERF_COEF[k].take(i)
        of[s:s + chunk] = np.copysign(np.where(a >= _ERF_ONE, 1.0, p), xc)
    return out


def load_compensator(path) -> Compensator:
    """Load a compensator file written by :meth:`Compensator.save` (numpy only, no torch)."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".json":
            with open(path) as fh:
                d = json.load(fh)
        else:
            with np.load(path, allow_pickle=False) as z:
                d = json.loads(str(z["meta"]))
                for k in ("support", "weights", "lengthscales", "workspace_bounds"):
                    d[k] = z[k]
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"file {path}: not a readable {FORMAT} file ({exc})") from exc
    if d.get("format") != FORMAT:
        raise ValueError(f"file {path}: format is {d.get('format')!r}, expected {FORMAT!r}")
    if int(d.get("version", -1)) != VERSION:
        raise ValueError(f"file {path}: {FORMAT} version {d.get('version')} is not supported "
                         f"(this mmgp reads version {VERSION})")
    comp = Compensator(d["kind"], d["support"], d["weights"], d["lengthscales"], d["signal_var"],
                       joint_names=d.get("joint_names"), bounds=d.get("workspace_bounds"),
                       info=d.get("info"), storage_sampled_min=d.get("storage_sampled_min"))
    # The bounds are recomputed from the weights, never trusted from the file; a mismatch means
    # the file was edited or corrupted.
    if not np.isclose(comp.storage_offset, float(d["storage_offset"]), rtol=1e-9,
                      atol=1e-12 * comp.bound_info["triangle_bound"]):
        raise ValueError(f"file {path}: storage_offset {d['storage_offset']} does not match the weights "
                         f"({comp.storage_offset}); corrupt file")
    return comp
