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
gravity fit), so tighter rigorous bounds are used (see ``Compensator._potential_bounds``): the
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

Fitting uses torch float64 (marginal likelihood by L-BFGS on a random subset of at most
``max_hyper_points`` positions, because each likelihood evaluation costs ``O((m n)^3)``); the final
weights solve the full ``N*n`` system with scipy. Evaluation (``Compensator``, ``load_compensator``,
``check_passivity``) uses numpy only: this module does not import torch at import time.
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Sequence

import numpy as np

FORMAT = "mmgp-compensator"
VERSION = 1
KINDS = ("erf-1dof", "curl-free-rbf")
_EXP_M_HALF = math.exp(-0.5)
_SQRT_PI_2 = math.sqrt(math.pi / 2.0)
LOG_2PI = math.log(2 * math.pi)


# ----------------------------------------------------------------------------------------------
# Evaluator (numpy only)
# ----------------------------------------------------------------------------------------------


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
    (see :meth:`_potential_bounds`); ``potential_bound = max(-L, U)``.
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
        lower, upper, self.bound_info = self._potential_bounds()
        self.potential_lower_bound = lower
        self.potential_upper_bound = upper
        self.potential_bound = max(-lower, upper)
        self.storage_offset = -lower
        self.storage_lower_bound = 0.0
        self.storage_sampled_min = storage_sampled_min

    # -- bounds ---------------------------------------------------------------------------------
    def _potential_bounds(self):
        """Rigorous (lower, upper) bounds of V on all of R^n, and how they were obtained.

        Triangle bound (always valid, usually very loose because GP weights alternate in sign):
        curl-free ``B_tri = s2 e^{-1/2} sum_a |gamma_a|``; erf-1dof ``B_tri = sum_a |A_a|``.

        curl-free, RKHS bound: V = sum_ai alpha_ai d k(., z_a)/dz_i lies in the RKHS of k with
        ``|V|_H^2 = alpha^T K_dd alpha``, and ``|V(q)| = |<V, k(., q)>| <= |V|_H sqrt(s2)``.
        The quadratic form needs only (N, N) matrices: with ``P = zs gamma^T``, ``d_a = zs_a.gamma_a``,
        ``alpha^T K alpha = sum_ab k_ab (gamma_a.gamma_b - (d_a - P_ba)(P_ab - d_b))``.

        erf-1dof, grid bound: |tau| <= T = sqrt(s2 w^T K w) (same RKHS argument for tau), so on a
        grid of spacing h covering the support +- 12 l, ``V >= min_grid V - T h / 2`` between
        nodes; beyond the grid ``|V(q) - V(end)| <= sum_a |A_a| erfc(12/sqrt 2)``, negligible.

        Each bound is widened by a rounding allowance (1e-12 of the sum of absolute terms).
        """
        N = self.support.shape[0]
        if self.kind == "curl-free-rbf":
            G = self._gamma
            tri = float(self.signal_var * _EXP_M_HALF * np.sum(np.sqrt(np.sum(G * G, axis=1))))
            D = self._zs[:, None, :] - self._zs[None, :, :] if N * N * self.n_joints <= 2e7 else None
            if D is not None:
                k = self.signal_var * np.exp(-0.5 * np.sum(D * D, axis=2))
            else:
                sq = np.sum(self._zs ** 2, axis=1)
                k = self.signal_var * np.exp(-0.5 * np.maximum(sq[:, None] + sq[None] - 2 * self._zs @ self._zs.T, 0))
            P = self._zs @ G.T
            d = np.sum(self._zs * G, axis=1)
            terms = k * (G @ G.T - (d[:, None] - P.T) * (P - d[None, :]))
            qf = float(np.sum(terms)) + 1e-12 * float(np.sum(np.abs(terms)))
            rkhs = math.sqrt(self.signal_var * max(qf, 0.0))
            B = min(tri, rkhs) * (1 + 1e-12) + 1e-12 * tri
            return -B, B, {"method": "rkhs" if rkhs < tri else "triangle", "triangle_bound": tri,
                           "rkhs_bound": rkhs}
        A = self._erf_amp
        tri = float(np.sum(np.abs(A)))
        l = self.lengthscales[0]
        z = self.support[:, 0]
        U = (z[:, None] - z[None, :]) / l
        wKw = float(self.weights[:, 0] @ (self.signal_var * np.exp(-0.5 * U * U)) @ self.weights[:, 0])
        T = math.sqrt(self.signal_var * max(wKw, 0.0))
        span = float(z.max() - z.min()) + 24 * l
        h = max(l / 200.0, span / 20000.0)  # cap the grid; a coarser step only widens the slack
        grid = np.arange(z.min() - 12 * l, z.max() + 12 * l + h, h)
        V = self.potential(grid[:, None])
        tail = tri * math.erfc(12 / math.sqrt(2))
        slack = T * h / 2 + tail + 1e-12 * tri
        lo, hi = float(V.min()) - slack, float(V.max()) + slack
        lo, hi = max(lo, -tri), min(hi, tri)
        return lo, hi, {"method": "grid+rkhs-lipschitz", "triangle_bound": tri, "torque_bound": T,
                        "grid_step": float(h)}

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
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        d = self.to_dict()
        tmp = path.with_name(path.name + ".tmp")
        if path.suffix.lower() == ".json":
            with open(tmp, "w") as fh:
                json.dump(d, fh, indent=1)
        else:
            arrays = {k: np.asarray(d.pop(k), dtype=np.float64)
                      for k in ("support", "weights", "lengthscales", "workspace_bounds")}
            with open(tmp, "wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(d)), **arrays)
        os.replace(tmp, path)
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


try:  # scipy's erf is vectorised; math.erf (libm) is the numpy-only fallback, same values to 1 ulp
    from scipy.special import erf as _erf
except ImportError:  # pragma: no cover
    def _erf(x):
        return np.vectorize(math.erf, otypes=[np.float64])(x)


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


# ----------------------------------------------------------------------------------------------
# Passivity checks (numpy only; work on any object with torque() and storage())
# ----------------------------------------------------------------------------------------------


def check_passivity(comp, n_configs: int = 200, n_loops: int = 50, bounds=None, seed: int = 0, *,
                    n_quad: int = 512, grad_rtol: float = 1e-6, loop_rtol: float = 1e-9,
                    n_storage_samples: int = 20000) -> dict:
    """Numerically check that ``comp.torque`` is the gradient of a storage bounded below.

    Works on any object with ``torque(q)`` ((T, n) -> (T, n)) and ``storage(q)`` ((T, n) -> (T,));
    for a non-conservative field ``storage`` may be any candidate: the loop test fails regardless.

    1. Gradient: at ``n_configs`` uniform configurations in ``bounds``, 4th-order central
       differences of ``storage`` (step ``1e-3`` of the box width) against ``torque``; figure:
       max |fd - tau| / torque scale, pass below ``grad_rtol``.
    2. Loops: ``n_loops`` random smooth closed curves ``q(s) = c + sum_k a_k cos 2 pi k s + b_k sin 2 pi k s``
       (k = 1..3) in the box; work ``W = int_0^1 tau(q(s)) . q'(s) ds`` by the trapezoid rule on
       ``n_quad`` nodes, which converges geometrically for periodic analytic integrands.
       Figure: max |W| / (torque scale * loop length); pass below ``loop_rtol``.
    3. Lower bound: ``storage`` at ``n_storage_samples`` points in the box and in a box 5x wider;
       pass if the minimum is finite and not below ``comp.storage_lower_bound`` (when present).

    ``bounds``: (2, n) box; default ``comp.bounds`` if present, else [-pi, pi]^n.
    Returns a dict of worst figures and ``passed`` (all three).
    """
    rng = np.random.default_rng(seed)
    if bounds is None:
        bounds = getattr(comp, "bounds", None)
    if bounds is None:
        n = _infer_n(comp)
        bounds = np.stack([-np.pi * np.ones(n), np.pi * np.ones(n)])
    bounds = np.asarray(bounds, dtype=np.float64)
    lo, hi = bounds[0], bounds[1]
    n = lo.shape[0]
    width = np.where(hi > lo, hi - lo, 1.0)

    # 1. gradient
    Q = lo + rng.random((n_configs, n)) * width
    tau = np.asarray(comp.torque(Q), dtype=np.float64).reshape(n_configs, n)
    h = 1e-3 * width
    fd = np.empty_like(tau)
    for i in range(n):
        e = np.zeros(n)
        e[i] = h[i]
        s = [np.asarray(comp.storage(Q + c * e), dtype=np.float64) for c in (-2, -1, 1, 2)]
        fd[:, i] = (s[0] - 8 * s[1] + 8 * s[2] - s[3]) / (12 * h[i])
    tau_scale = float(max(np.max(np.abs(tau)), 1e-300))
    grad_err = float(np.max(np.abs(fd - tau)) / tau_scale)

    # 2. closed loops
    s = np.arange(n_quad) / n_quad
    worst_rel, worst_abs = 0.0, 0.0
    K = 3
    for _ in range(n_loops):
        c = lo + (0.3 + 0.4 * rng.random(n)) * width
        amp = rng.normal(size=(2, K, n)) / (np.arange(1, K + 1)[None, :, None] ** 1.5)
        # keep the curve inside the box: scale so the largest excursion is 0.25 of the width
        scale = 0.25 * width / np.maximum(np.sum(np.abs(amp), axis=(0, 1)), 1e-12)
        a, b = amp[0] * scale, amp[1] * scale
        w = 2 * np.pi * np.arange(1, K + 1)
        cs, sn = np.cos(np.outer(s, w)), np.sin(np.outer(s, w))  # (M, K)
        qs = c + cs @ a + sn @ b
        dqs = (-sn * w) @ a + (cs * w) @ b
        tq = np.asarray(comp.torque(qs), dtype=np.float64).reshape(n_quad, n)
        W = float(np.mean(np.sum(tq * dqs, axis=1)))
        length = float(np.mean(np.linalg.norm(dqs, axis=1)))
        scale_t = max(float(np.max(np.abs(tq))), tau_scale)
        worst_abs = max(worst_abs, abs(W))
        worst_rel = max(worst_rel, abs(W) / (scale_t * length))

    # 3. bounded below
    Qs = lo + rng.random((n_storage_samples, n)) * width
    Qw = (lo + hi) / 2 + (rng.random((n_storage_samples // 4, n)) - 0.5) * 5 * width
    S = np.concatenate([np.asarray(comp.storage(Qs), dtype=np.float64).ravel(),
                        np.asarray(comp.storage(Qw), dtype=np.float64).ravel()])
    s_min = float(np.min(S))
    lb = getattr(comp, "storage_lower_bound", None)
    bounded = bool(np.isfinite(s_min) and (lb is None or s_min >= lb - 1e-12 * max(1.0, abs(s_min))))

    res = {
        "n_configs": n_configs, "n_loops": n_loops,
        "torque_scale": tau_scale,
        "grad_max_rel_err": grad_err, "grad_pass": bool(grad_err <= grad_rtol),
        "loop_max_rel_work": worst_rel, "loop_max_abs_work": worst_abs,
        "loop_pass": bool(worst_rel <= loop_rtol),
        "storage_min_sampled": s_min,
        "storage_lower_bound": None if lb is None else float(lb),
        "storage_bounded_pass": bounded,
    }
    res["passed"] = bool(res["grad_pass"] and res["loop_pass"] and res["storage_bounded_pass"])
    return res


def _infer_n(comp) -> int:
    for attr in ("n_joints", "n"):
        if hasattr(comp, attr):
            return int(getattr(comp, attr))
    raise ValueError("check_passivity: pass bounds= for an object without bounds/n_joints")


# ----------------------------------------------------------------------------------------------
# Fitting (torch float64 for hyperparameters, scipy for the final solve); imported lazily
# ----------------------------------------------------------------------------------------------


def curl_free_kernel_np(X1, X2, lengthscales, signal_var):
    """Gradient-gradient covariance of an RBF potential, closed form, numpy.

    Returns (N1*n, N2*n) with rows ordered (point, joint):
    ``K[(a,i),(b,j)] = s2 exp(-|u|^2/2) (delta_ij - u_i u_j) / (l_i l_j)``, ``u = (x_a - x_b)/l``.
    """
    X1, X2 = np.asarray(X1, float), np.asarray(X2, float)
    l = np.asarray(lengthscales, float)
    N1, n = X1.shape
    N2 = X2.shape[0]
    out = np.empty((N1, n, N2, n))
    eye = np.eye(n)
    il = 1.0 / l
    step = max(1, 2_000_000 // max(1, N2 * n * n))
    for s in range(0, N1, step):
        U = (X1[s:s + step, None, :] - X2[None]) * il  # (t, N2, n)
        k = signal_var * np.exp(-0.5 * np.sum(U * U, axis=2))
        B = (eye[None, None] - U[..., :, None] * U[..., None, :]) * (il[:, None] * il[None, :])
        out[s:s + step] = np.transpose(k[..., None, None] * B, (0, 2, 1, 3))
    return out.reshape(N1 * n, N2 * n)


def _curl_free_kernel_torch(X1, X2, log_l, log_s2):
    import torch

    l = torch.exp(log_l)
    U = (X1[:, None, :] - X2[None]) / l
    k = torch.exp(log_s2 - 0.5 * (U * U).sum(-1))
    n = X1.shape[1]
    eye = torch.eye(n, dtype=X1.dtype)
    B = (eye - U[..., :, None] * U[..., None, :]) / (l[:, None] * l[None, :])
    K = (k[..., None, None] * B).permute(0, 2, 1, 3)
    return K.reshape(X1.shape[0] * n, X2.shape[0] * n)


def _rbf_kernel_torch(X1, X2, log_l, log_s2):
    import torch

    U = (X1[:, None, :] - X2[None]) / torch.exp(log_l)
    return torch.exp(log_s2 - 0.5 * (U * U).sum(-1))


def _fit_hyper(X, Y, kernel_kind: str, *, max_iter: int = 100, noise_floor_rel: float = 1e-8):
    """Maximise the marginal likelihood (torch float64, L-BFGS with strong-Wolfe line search).

    X: (m, n) positions, Y: (m, d) targets (d = n gradient components for "curl-free", d = 1
    for "rbf"). Parameters: log lengthscales (n), log signal variance, log noise variance per
    output column. The noise is floored at ``noise_floor_rel`` times the mean square target
    (at least 1e-6 of the mean over outputs),
    because targets taken from a model's prediction are almost noise-free and an unfloored
    likelihood drives the noise to zero and the system to singularity.
    Returns (lengthscales (n,), signal_var, noise_var (d,), nll per datum).
    """
    import torch

    X_t = torch.as_tensor(X, dtype=torch.float64)
    Y_t = torch.as_tensor(Y, dtype=torch.float64)
    m, n = X_t.shape
    d = Y_t.shape[1]
    ms = torch.clamp((Y_t ** 2).mean(0), min=1e-12)  # per-output mean square (zero-mean GP)
    sd = torch.clamp(X_t.std(0), min=1e-3)
    log_l = torch.log(sd).clone().requires_grad_(True)
    if kernel_kind == "curl-free":
        s2_0 = (ms * sd ** 2).mean()  # gradient variance of an RBF potential is s2 / l^2
    else:
        s2_0 = ms.mean()
    log_s2 = torch.log(s2_0).clone().requires_grad_(True)
    # A joint whose torque is ~0 everywhere (e.g. a vertical first axis) would get a ~0 floor;
    # the outputs are coupled through V, so tie its floor to the overall torque scale too.
    floor = noise_floor_rel * torch.clamp(ms, min=1e-6 * float(ms.mean()))
    log_noise = torch.log(1e-3 * ms).clone().requires_grad_(True)
    y = Y_t.reshape(-1)
    noise_cols = torch.arange(m * d) % d

    def kernel():
        if kernel_kind == "curl-free":
            K = _curl_free_kernel_torch(X_t, X_t, log_l, log_s2)
        else:
            K = _rbf_kernel_torch(X_t, X_t, log_l, log_s2)
        return K + torch.diag((floor + torch.exp(log_noise))[noise_cols])

    def nll_and_w(K):
        """NLL value and W = K^-1 - a a^T (so that d NLL = tr(W dK) / 2), without autograd."""
        with torch.no_grad():
            L, info = torch.linalg.cholesky_ex(K)
            if int(info) != 0:
                K = K + 1e-8 * K.diagonal().mean() * torch.eye(K.shape[0], dtype=K.dtype)
                L = torch.linalg.cholesky(K)
            a = torch.cholesky_solve(y[:, None], L)
            v = 0.5 * (y[:, None] * a).sum() + torch.log(L.diagonal()).sum() + 0.5 * y.numel() * LOG_2PI
            return v, torch.cholesky_inverse(L) - a @ a.T

    params = [log_l, log_s2, log_noise]
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-7, tolerance_change=1e-10, history_size=20)

    def closure():
        # Backpropagating through the Cholesky factor is several times slower than this
        # surrogate, whose gradient tr(W dK)/2 is exactly the NLL gradient.
        opt.zero_grad()
        K = kernel()
        v, W = nll_and_w(K.detach())
        (0.5 * (W * K).sum()).backward()
        return v

    # Matrices of a few thousand rows gain little from threads, and on a shared machine extra
    # threads oversubscribe the cores (measured 10x slower with 2 threads under load).
    n_threads = torch.get_num_threads()
    if y.numel() <= 3000:
        torch.set_num_threads(1)
    try:
        opt.step(closure)
    except RuntimeError:
        pass  # a failed line search leaves the last good parameters in place
    finally:
        torch.set_num_threads(n_threads)
    with torch.no_grad():
        v = float(nll_and_w(kernel())[0]) / y.numel()
        # A torque that does not depend on a joint (a vertical first axis) drives its lengthscale
        # to overflow; 1e6 x the data spread is already constant to 1e-12 and keeps files finite.
        l_out = np.minimum(torch.exp(log_l).numpy(), 1e6 * max(float(sd.max()), 1.0))
        return (l_out, float(torch.exp(log_s2)),
                (floor + torch.exp(log_noise)).numpy().copy(), v)


def _solve_psd(K, y):
    """Solve (K) x = y for a symmetric positive (semi)definite K, adding jitter if needed."""
    from scipy.linalg import cho_factor, cho_solve, LinAlgError

    jitter = 0.0
    base = float(np.mean(np.diag(K)))
    for _ in range(6):
        try:
            c = cho_factor(K + jitter * np.eye(K.shape[0]), lower=True, check_finite=False)
            return cho_solve(c, y, check_finite=False), jitter
        except LinAlgError:
            jitter = base * (1e-10 if jitter == 0.0 else jitter / base * 100)
    raise LinAlgError("kernel matrix not positive definite even with jitter")


class CurlFreeGP:
    """GP on a scalar potential V(q) fitted to gradient observations (torques).

    Settings: ``max_hyper_points`` (hyperparameter subset size), ``max_iter`` (L-BFGS iterations),
    ``noise_floor_rel``, ``seed``. ``fit(Q (N, n) rad, Y (N, n) N*m)`` sets ``lengthscales_``,
    ``signal_var_``, ``noise_var_`` (n,), ``support_`` (N, n), ``alpha_`` (N, n), ``nll_``.
    """

    def __init__(self, max_hyper_points: int = 150, max_iter: int = 75, noise_floor_rel: float = 1e-8,
                 seed: int = 0):
        self.max_hyper_points = max_hyper_points
        self.max_iter = max_iter
        self.noise_floor_rel = noise_floor_rel
        self.seed = seed

    def fit(self, Q, Y):
        Q = np.asarray(Q, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        N, n = Q.shape
        rng = np.random.default_rng(self.seed)
        sub = rng.permutation(N)[: min(N, self.max_hyper_points)]
        t0 = time.perf_counter()
        l, s2, noise, v = _fit_hyper(Q[sub], Y[sub], "curl-free", max_iter=self.max_iter,
                                     noise_floor_rel=self.noise_floor_rel)
        t1 = time.perf_counter()
        K = curl_free_kernel_np(Q, Q, l, s2)
        K[np.diag_indices_from(K)] += np.tile(noise, N)
        alpha, jitter = _solve_psd(K, Y.reshape(-1))
        self.hyper_time_s_ = t1 - t0
        self.solve_time_s_ = time.perf_counter() - t1
        self.lengthscales_, self.signal_var_, self.noise_var_, self.nll_ = l, s2, noise, v
        self.jitter_ = jitter
        self.support_ = Q
        self.alpha_ = alpha.reshape(N, n)
        return self

    def to_compensator(self, joint_names=None, bounds=None, info=None) -> Compensator:
        return Compensator("curl-free-rbf", self.support_, self.alpha_, self.lengthscales_,
                           self.signal_var_, joint_names=joint_names, bounds=bounds, info=info)


class RBFGP:
    """Ordinary zero-mean ARD-RBF GP for one output (used for erf-1dof and as the per-joint baseline).

    ``fit(Q (N, n), y (N,))`` sets ``lengthscales_``, ``signal_var_``, ``noise_var_``, ``support_``,
    ``alpha_`` (N,). ``predict(Q (T, n)) -> (T,)``.
    """

    def __init__(self, max_hyper_points: int = 500, max_iter: int = 100, noise_floor_rel: float = 1e-8,
                 seed: int = 0):
        self.max_hyper_points = max_hyper_points
        self.max_iter = max_iter
        self.noise_floor_rel = noise_floor_rel
        self.seed = seed

    def fit(self, Q, y):
        Q = np.asarray(Q, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        N = Q.shape[0]
        rng = np.random.default_rng(self.seed)
        sub = rng.permutation(N)[: min(N, self.max_hyper_points)]
        l, s2, noise, v = _fit_hyper(Q[sub], y[sub, None], "rbf", max_iter=self.max_iter,
                                     noise_floor_rel=self.noise_floor_rel)
        U = (Q[:, None, :] - Q[None]) / l
        K = s2 * np.exp(-0.5 * np.sum(U * U, axis=2))
        K[np.diag_indices_from(K)] += noise[0]
        self.alpha_, self.jitter_ = _solve_psd(K, y)
        self.lengthscales_, self.signal_var_, self.noise_var_, self.nll_ = l, s2, float(noise[0]), v
        self.support_ = Q
        return self

    def predict(self, Q):
        Q = np.asarray(Q, dtype=np.float64)
        out = np.empty(Q.shape[0])
        step = max(1, 4_000_000 // max(1, self.support_.size))
        for s in range(0, Q.shape[0], step):
            U = (Q[s:s + step, None, :] - self.support_[None]) / self.lengthscales_
            out[s:s + step] = (self.signal_var_ * np.exp(-0.5 * np.sum(U * U, axis=2))) @ self.alpha_
        return out


class IndependentJointGPs:
    """Unconstrained baseline: one RBF GP per joint torque (not a gradient field in general).

    ``storage`` is the naive candidate a per-joint design would use: each joint's torque
    integrated along its own axis (an erf in that coordinate times the Gaussian in the others).
    Its gradient matches the torque only on the diagonal, and the loop work of ``torque`` is
    generally non-zero: :func:`check_passivity` must reject it.
    """

    def __init__(self, max_hyper_points: int = 500, max_iter: int = 100, seed: int = 0):
        self.max_hyper_points = max_hyper_points
        self.max_iter = max_iter
        self.seed = seed

    def fit(self, Q, Y):
        Q = np.asarray(Q, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        self.gps_ = [RBFGP(self.max_hyper_points, self.max_iter, seed=self.seed).fit(Q, Y[:, i])
                     for i in range(Y.shape[1])]
        self.n_joints = Q.shape[1]
        self.bounds = np.stack([Q.min(0), Q.max(0)])
        return self

    def torque(self, q):
        q = np.asarray(q, dtype=np.float64)
        q2 = q.reshape(-1, self.n_joints)
        out = np.stack([g.predict(q2) for g in self.gps_], axis=1)
        return out[0] if q.ndim == 1 else out

    def storage(self, q):
        q = np.asarray(q, dtype=np.float64)
        q2 = q.reshape(-1, self.n_joints)
        S = np.zeros(q2.shape[0])
        for i, g in enumerate(self.gps_):
            U = (q2[:, None, :] - g.support_[None]) / g.lengthscales_
            others = np.exp(-0.5 * (np.sum(U * U, axis=2) - U[:, :, i] ** 2))
            amp = g.signal_var_ * g.lengthscales_[i] * _SQRT_PI_2 * g.alpha_
            S += (_erf(U[:, :, i] / math.sqrt(2.0)) * others) @ amp
        return float(S[0]) if q.ndim == 1 else S


def _storage_sampled_min(comp: Compensator, seed: int = 0, n_samples: int = 20000) -> tuple[float, np.ndarray]:
    """Smallest storage found over the workspace box: random points, support points, then a
    bounded L-BFGS-B polish (gradient = torque) from the five best. Returns (min, argmin)."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    lo, hi = comp.bounds
    cand = np.concatenate([lo + rng.random((n_samples, comp.n_joints)) * (hi - lo), comp.support])
    S = comp.storage(cand)
    best = np.argsort(S)[:5]
    s_min, q_min = float(S[best[0]]), cand[best[0]]
    for i in best:
        r = minimize(lambda x: (comp.storage(x), comp.torque(x)), cand[i], jac=True,
                     method="L-BFGS-B", bounds=list(zip(lo, hi)), options={"maxiter": 200})
        if r.fun < s_min:
            s_min, q_min = float(r.fun), r.x
    return s_min, q_min


def compensator_from_model(model, *, max_support: int = 1000, seed: int = 0,
                           max_hyper_points: int | None = None, max_iter: int = 75) -> Compensator:
    """Build the passive feedforward from a trained model.

    ``model`` must provide ``nominal_torque(q (T, n)) -> (T, n)`` (torque at dq = ddq = 0, nominal
    mode, rigid-body part included), ``support_q_`` ((N, n) positions of the nominal training
    samples) and ``joint_names_``. Support points are a random subset of ``support_q_`` of size
    ``max_support`` (the final solve has ``max_support * n`` unknowns, O((N n)^3) time;
    1000 points x 7 joints is a 7000 system, a few seconds). Targets are the model's own
    prediction at those points, so the compensator approximates the model, not the raw data.
    One joint -> ``"erf-1dof"``; several -> ``"curl-free-rbf"``. Hyperparameters are fitted on
    ``max_hyper_points`` of the support points (default 500 for one joint, 150 for several: each
    likelihood evaluation factors a (150 n) x (150 n) matrix; 75 L-BFGS iterations take about a
    minute for 7 joints on one core).
    """
    t0 = time.perf_counter()
    Q = np.asarray(model.support_q_, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[0] < 2:
        raise ValueError("model.support_q_ must be (N, n) with N >= 2")
    names = list(getattr(model, "joint_names_", None) or [f"q_{i}" for i in range(Q.shape[1])])
    rng = np.random.default_rng(seed)
    # Exact duplicates make the kernel matrix singular and carry no information.
    Q = np.unique(Q, axis=0)
    if Q.shape[0] > max_support:
        Q = Q[np.sort(rng.choice(Q.shape[0], max_support, replace=False))]
    Y = np.asarray(model.nominal_torque(Q), dtype=np.float64).reshape(Q.shape)
    n = Q.shape[1]
    bounds = np.stack([Q.min(0), Q.max(0)])
    if n == 1:
        gp = RBFGP(max_hyper_points or 500, max_iter, seed=seed).fit(Q, Y[:, 0])
        info = {"lengthscales": gp.lengthscales_.tolist(), "signal_var": gp.signal_var_,
                "noise_var": [gp.noise_var_], "nll_per_datum": gp.nll_, "jitter": gp.jitter_}
        comp = Compensator("erf-1dof", Q, gp.alpha_[:, None], gp.lengthscales_, gp.signal_var_,
                           joint_names=names, bounds=bounds, info=info)
    else:
        gp = CurlFreeGP(max_hyper_points or 150, max_iter, seed=seed).fit(Q, Y)
        info = {"lengthscales": gp.lengthscales_.tolist(), "signal_var": gp.signal_var_,
                "noise_var": gp.noise_var_.tolist(), "nll_per_datum": gp.nll_, "jitter": gp.jitter_,
                "hyper_time_s": gp.hyper_time_s_, "solve_time_s": gp.solve_time_s_}
        comp = gp.to_compensator(joint_names=names, bounds=bounds, info=info)
    fit = comp.torque(Q)
    info["train_rmse_per_joint"] = np.sqrt(np.mean((fit - Y) ** 2, axis=0)).tolist()
    info["train_nmse_per_joint"] = (np.mean((fit - Y) ** 2, axis=0)
                                    / np.maximum(np.var(Y, axis=0), 1e-300)).tolist()
    s_min, q_min = _storage_sampled_min(comp, seed=seed)
    comp.storage_sampled_min = s_min
    info["storage_sampled_argmin"] = np.asarray(q_min).tolist()
    info["build_time_s"] = time.perf_counter() - t0
    comp.info = info
    return comp
