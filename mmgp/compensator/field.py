"""Passivity-safe position-only feedforward compensator: the evaluator and the file format.

A controller renders ``tau = tau_ff(q) + K_imp (q_d - q) - B_imp dq`` (or any impedance) on top of a
learned feedforward ``tau_ff(q)``: the trained model's nominal-mode torque at ``(q, dq=0, ddq=0)``
(gravity, springs, constant offsets). For the loop to stay passive the feedforward must be the
gradient of a storage function that is bounded below, ``tau_ff = grad S``: then the work it does
along any motion is ``S(q1) - S(q0)``, zero around every closed loop, and the energy it can ever
hand out is finite.

Structure. ``S(q) = V_rb(q) + V_dev(q) + storage_offset``:

* ``V_rb``, the mean: the rigid-body gravity potential of the robot with physically consistent
  masses (nominal URDF plus the payload identified from the model; :mod:`.prior`), evaluated from
  the file alone; zero for a model without a robot.
* ``V_dev``, a Gaussian-process potential of the deviation ``tau_model - grad V_rb``, learned from
  gradient observations: ``V_dev(q) = s2 sum_a A(r_a) (u_a . gamma_a)``, ``u_a = (q - z_a)/l``,
  ``r_a = |u_a|``, ``gamma_a = weights_a / l``, and exactly
  ``tau_dev,i = dV_dev/dq_i = s2/l_i sum_a (A(r_a) gamma_ai - B(r_a) u_ai (u_a . gamma_a))``
  (:mod:`.kernels`; the matrix kernel is curl-free, so the posterior mean is a gradient field).

Kinds (of the deviation):

``"curl-free-wendland"`` (what :func:`~mmgp.compensator.fit.compensator_from_model` builds)
    Wendland's compactly supported kernel: ``A(r) = B(r) = 0`` for ``r >= 1``. The **valid
    region** is the union of the ellipsoids ``|(q - z_a)/l| < 1`` around the support points (the
    data the model saw, radius 1 in the kernel's metric, i.e. ``l`` rad per joint); outside it the
    deviation is exactly zero and the compensator *is* the rigid-body prior, a field that is
    still an exact gradient. Near the boundary the deviation goes to zero smoothly with the kernel.
    :meth:`Compensator.region_distance` and ``torque(q, return_region=True)`` report where q is.
``"curl-free-rbf"``
    The Gaussian kernel ``A = B = exp(-r^2/2)`` (format version 1; ``kernel="rbf"``): no exact
    region, the deviation fades with distance.
``"erf-1dof"`` (one joint, format version 1)
    ``tau(q) = sum_a w_a s2 exp(-(q-z_a)^2/(2 l^2))`` and ``V = sum_a w_a s2 l sqrt(pi/2) erf((q - z_a)/(sqrt 2 l))``.

Bounds. ``V_dev`` lies in the kernel's RKHS with ``|V_dev|_H^2 = alpha^T K_dd alpha``, so
``|V_dev(q)| <= |V_dev|_H sqrt(s2)`` and ``|tau_dev,i(q)| <= |V_dev|_H sqrt(s2 A(0)) / l_i`` for every
q (:mod:`.passivity`): the second is the stated bound on how far the compensator can ever depart
from its prior (``deviation_torque_bound``). ``V_rb`` is bounded by the chain's reach
(:class:`~.prior.RigidBodyPrior`). With ``L`` the sum of the two lower bounds,
``S = V - L >= 0`` everywhere. ``storage_sampled_min``: the smallest S found over the support box.

This module is numpy only (no torch, scipy or pinocchio), so a controller process can load and
evaluate a compensator cheaply. Fitting is in :mod:`.fit`, bounds and checks in :mod:`.passivity`,
C export in :mod:`.csource`.
"""
from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError, describe
from .erf import erf
from .kernels import DEFAULT_SMOOTHNESS, WendlandProfile
from .passivity import potential_bounds
from .prior import RigidBodyPrior
from .validate import FORMAT, KINDS, READ_ERRORS, VERSION, validate_compensator_dict

_SQRT_PI_2 = math.sqrt(math.pi / 2.0)
_ARRAYS = ("support", "weights", "lengthscales", "workspace_bounds")


class Compensator:
    """An exported feedforward ``tau_ff(q) = grad S(q)`` with a storage function ``S >= 0``.

    Parameters (all float64)
    ----------
    kind : one of :data:`KINDS`.
    support : (N, n) support positions ``z_a`` (rad, m for prismatic joints).
    weights : (N, n) solved GP weights ``alpha`` for the curl-free kinds, (N, 1) for erf-1dof.
    lengthscales : (n,) kernel lengthscales (rad); for curl-free-wendland the support radii.
    signal_var : kernel signal variance ``s2`` (J^2 for the potential GP, N^2 m^2 for erf-1dof).
    joint_names : n joint names.
    bounds : (2, n) workspace box (min, max of the support positions) used by checks.
    info : free-form dict (hyperparameters, fit figures); saved in the file.
    prior : :class:`~.prior.RigidBodyPrior` or None (zero mean). Refused when inconsistent.
    smoothness : Wendland smoothness k (curl-free-wendland only).

    Attributes: ``potential_lower_bound`` L, ``potential_upper_bound`` U (J, rigorous on all of R^n,
    prior included), ``potential_bound = max(-L, U)``, ``storage_offset = -L``,
    ``deviation_torque_bound`` (n,) N*m (``|tau_ff - tau_prior| <= it`` everywhere),
    ``deviation_sampled_max`` (n,) or None (the largest deviation a search found; not a proof),
    ``region_radius`` (1 for Wendland, inf otherwise), ``bound_info``.
    """

    def __init__(self, kind: str, support, weights, lengthscales, signal_var: float,
                 joint_names: Sequence[str] | None = None, bounds=None, info: dict | None = None,
                 storage_sampled_min: float | None = None, *, prior: RigidBodyPrior | None = None,
                 smoothness: int = DEFAULT_SMOOTHNESS, deviation_sampled_max=None):
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
        if not np.all(self.lengthscales > 0) or not np.isfinite(self.lengthscales).all():
            raise ValueError("lengthscales must be positive and finite")
        self.signal_var = float(signal_var)
        self.joint_names = list(joint_names) if joint_names is not None else [f"q_{i}" for i in range(n)]
        if len(self.joint_names) != n:
            raise ValueError("joint_names length does not match the support dimension")
        if bounds is None:
            bounds = np.stack([self.support.min(0), self.support.max(0)])
        self.bounds = np.asarray(bounds, dtype=np.float64).reshape(2, n)
        self.info = dict(info or {})
        if prior is not None and prior.n_joints != n:
            raise ValueError(f"the prior has {prior.n_joints} joints, the support {n}")
        self.prior = prior
        self.profile = WendlandProfile(n, smoothness) if kind == "curl-free-wendland" else None
        self.region_radius = 1.0 if self.profile is not None else math.inf
        # Quantities shared by the numpy and the C evaluators: computing them once, here, and
        # printing them with 17 significant digits makes both evaluators see the same numbers.
        self._inv_l = 1.0 / self.lengthscales
        self._zs = self.support * self._inv_l  # support in lengthscale units
        if kind == "erf-1dof":
            self._gamma = self.weights[:, 0] * self.signal_var  # torque amplitude per support
            self._erf_amp = self._gamma * self.lengthscales[0] * _SQRT_PI_2
        else:
            self._gamma = self.weights * self._inv_l
        lower, upper, self.bound_info = potential_bounds(self)
        self.deviation_torque_bound = np.asarray(self.bound_info["torque_bound"], dtype=np.float64)
        if prior is not None:
            lower, upper = lower + prior.potential_lower_bound, upper + prior.potential_upper_bound
            self.bound_info["prior_bound"] = prior.potential_upper_bound
        self.potential_lower_bound = lower
        self.potential_upper_bound = upper
        self.potential_bound = max(-lower, upper)
        self.storage_offset = -lower
        self.storage_lower_bound = 0.0
        self.storage_sampled_min = storage_sampled_min
        self.deviation_sampled_max = (None if deviation_sampled_max is None else
                                      np.asarray(deviation_sampled_max, dtype=np.float64).reshape(n))

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

    def _radial(self, r2):
        """(s2 A, s2 B) at squared scaled distances r2."""
        if self.profile is None:
            a = self.signal_var * np.exp(-0.5 * r2)
            return a, a
        r = np.sqrt(r2)
        return self.signal_var * self.profile.A(r), self.signal_var * self.profile.B(r)

    def _eval(self, q2, want_tau: bool, want_v: bool, with_prior: bool = True, chunk_elems: int = 4_000_000):
        """(tau (T, n) or None, V (T,) or None, region distance (T,))."""
        T, n = q2.shape
        N = self.support.shape[0]
        tau = np.empty((T, n)) if want_tau else None
        V = np.empty(T) if want_v else None
        dist = np.empty(T)
        step = max(1, chunk_elems // max(1, N * n))
        qs = q2 * self._inv_l
        for s in range(0, T, step):
            U = qs[s:s + step, None, :] - self._zs[None, :, :]  # (t, N, n)
            r2 = np.sum(U * U, axis=2)  # (t, N)
            dist[s:s + step] = np.sqrt(r2.min(axis=1))
            if self.kind == "erf-1dof":
                u = U[:, :, 0]
                if want_tau:
                    tau[s:s + step, 0] = np.exp(-0.5 * r2) @ self._gamma
                if want_v:
                    V[s:s + step] = erf(u / math.sqrt(2.0)) @ self._erf_amp
                continue
            a, b = self._radial(r2)
            ug = np.sum(U * self._gamma[None], axis=2)  # (t, N)
            if want_v:
                V[s:s + step] = np.sum(a * ug, axis=1)
            if want_tau:
                tau[s:s + step] = self._inv_l * (a @ self._gamma - np.einsum("tb,tbi->ti", b * ug, U))
        if with_prior and self.prior is not None:
            if want_tau:
                tau += self.prior.torque(q2)
            if want_v:
                V += self.prior.potential(q2)
        return tau, V, dist

    def torque(self, q, return_region: bool = False):
        """Feedforward torque tau_ff(q) (N*m). q: (n,) -> (n,), or (T, n) -> (T, n) (rad).

        ``return_region=True`` also returns ``rho = min(region_distance(q), region_radius)``
        (float or (T,)): below ``region_radius`` q is inside the valid region; at it, the torque is
        the rigid-body prior alone. The C function ``<p>_torque`` returns the same number."""
        q2, single = self._prep(q)
        tau, _, dist = self._eval(q2, True, False)
        rho = np.minimum(dist, self.region_radius)
        if single:
            return (tau[0], float(rho[0])) if return_region else tau[0]
        return (tau, rho) if return_region else tau

    def deviation_torque(self, q):
        """tau_ff - tau_prior (N*m), the learned part alone; ``|.| <= deviation_torque_bound``."""
        q2, single = self._prep(q)
        tau, _, _ = self._eval(q2, True, False, with_prior=False)
        return tau[0] if single else tau

    def prior_torque(self, q):
        """The rigid-body prior's gravity torque (N*m) (zeros without a prior)."""
        q2, single = self._prep(q)
        tau = self.prior.torque(q2) if self.prior is not None else np.zeros_like(q2)
        return tau[0] if single else tau

    def region_distance(self, q):
        """Distance ``min_a |(q - z_a)/l|`` to the nearest support point in the kernel's metric:
        inside the valid region iff below ``region_radius``. (n,) -> float, (T, n) -> (T,)."""
        q2, single = self._prep(q)
        qs = q2 * self._inv_l
        out = np.empty(q2.shape[0])
        step = max(1, 4_000_000 // max(1, self._zs.size))
        for s in range(0, q2.shape[0], step):
            U = qs[s:s + step, None, :] - self._zs[None]
            out[s:s + step] = np.sqrt(np.min(np.sum(U * U, axis=2), axis=1))
        return float(out[0]) if single else out

    def potential(self, q):
        """Potential V(q) (J) with grad V = tau_ff and |V| <= potential_bound. (n,)->float, (T,n)->(T,)."""
        q2, single = self._prep(q)
        _, V, _ = self._eval(q2, False, True)
        return float(V[0]) if single else V

    def storage(self, q):
        """Storage S(q) = V(q) - potential_lower_bound >= 0 (J). (n,) -> float, (T, n) -> (T,)."""
        q2, single = self._prep(q)
        _, V, _ = self._eval(q2, False, True)
        S = V + self.storage_offset
        return float(S[0]) if single else S

    # -- export ---------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Everything needed to rebuild the evaluator, as plain Python (lists of floats)."""
        kernel = self.profile.as_dict() if self.profile is not None else {"name": "rbf-ard"}
        return {
            "format": FORMAT, "version": VERSION, "kind": self.kind,
            "joint_names": list(self.joint_names), "n_joints": self.n_joints,
            "n_support": int(self.support.shape[0]), "kernel": kernel,
            "lengthscales": self.lengthscales.tolist(), "signal_var": self.signal_var,
            "support": self.support.tolist(), "weights": self.weights.tolist(),
            "prior": self.prior.to_dict() if self.prior is not None else None,
            "valid_region": {
                "definition": "min_a |(q - support_a) / lengthscales| < radius (outside: the prior alone)",
                "radius": self.region_radius if math.isfinite(self.region_radius) else None},
            "deviation_torque_bound": self.deviation_torque_bound.tolist(),
            "deviation_sampled_max": (None if self.deviation_sampled_max is None
                                      else self.deviation_sampled_max.tolist()),
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
            arrays = {k: np.asarray(d.pop(k), dtype=np.float64) for k in _ARRAYS}
            buf = io.BytesIO()
            np.savez(buf, meta=np.array(json.dumps(d)), **arrays)
            data = buf.getvalue()
        atomic_write_bytes(path, data)
        return path

    def write_c(self, dir_or_prefix, name: str | None = None):
        """Write dependency-free C99 source + header; returns ``(c_path, h_path)``.

        ``dir_or_prefix``: an existing directory (files ``mmgp_compensator.c/.h`` inside it) or a
        path prefix (``prefix.c``/``prefix.h``). The C functions are ``<name>_torque(q, tau)``
        (returns the region figure of ``torque(q, return_region=True)``), ``<name>_potential(q)``,
        ``<name>_storage(q)``, ``<name>_prior_torque(q, tau)``, ``<name>` being the file stem.
        """
        from .csource import write_c_source

        return write_c_source(self, dir_or_prefix, name=name)

    def __repr__(self):
        return (f"Compensator(kind={self.kind!r}, n_joints={self.n_joints}, n_support={self.support.shape[0]}, "
                f"prior={self.prior is not None}, potential_bound={self.potential_bound:.4g})")


_CURL_FREE = ("u_a = (q - support_a)/lengthscales; r_a = |u_a|; gamma_a = weights_a/lengthscales; "
              "V(q) = V_prior(q) + signal_var sum_a A(r_a) (u_a . gamma_a); tau_i(q) = dV/dq_i = tau_prior_i(q) "
              "+ signal_var/l_i sum_a (A(r_a) gamma_ai - B(r_a) u_ai (u_a . gamma_a)); storage(q) = V(q) + "
              "storage_offset, storage_offset = -potential_lower_bound (rigorous: RKHS bound of the deviation "
              "plus the prior's reach bound). ")
_DEFINITIONS = {
    "curl-free-wendland": _CURL_FREE + (
        "A(r) = psi_{l,k-1}(r)/psi_{l,k}(0), B(r) = psi_{l,k-2}(r)/psi_{l,k}(0), Wendland's functions of "
        "degree l and smoothness k (kernel), both 0 for r >= 1."),
    "curl-free-rbf": _CURL_FREE + "A(r) = B(r) = exp(-r^2/2).",
    "erf-1dof": (
        "u_a = (q - support_a)/l; tau(q) = sum_a weights_a*signal_var*exp(-u_a^2/2); "
        "V(q) = sum_a weights_a*signal_var*l*sqrt(pi/2)*erf(u_a/sqrt(2)) (+ the prior); "
        "storage(q) = V(q) + storage_offset, storage_offset = -potential_lower_bound (rigorous, grid + "
        "Lipschitz bound |tau| <= sqrt(signal_var * w^T K w))"),
}


def _read(path: Path) -> dict:
    try:
        if path.suffix.lower() == ".json":
            with open(path) as fh:
                return json.load(fh)
        with np.load(path, allow_pickle=False) as z:
            d = json.loads(str(z["meta"]))
            for k in _ARRAYS:
                d[k] = z[k]
            return d
    except READ_ERRORS as exc:
        raise InputError(f"not a readable {FORMAT} file: expected the JSON text or NPZ archive 'mmgp export' "
                         f"writes ({describe(exc)})", file=path) from None


def load_compensator(path) -> Compensator:
    """Load a compensator file written by :meth:`Compensator.save` (numpy only, no torch).

    Every refusal is one :class:`~mmgp.errors.InputError` (a ValueError) naming the file and what
    was expected: a file that cannot be read (truncated, neither JSON nor NPZ), one of another
    format or version or with a bad key (:func:`validate_compensator_dict`), one whose prior is
    physically inconsistent (negative mass, non-rotation placements, ...), and one whose stored
    storage offset does not match the offset recomputed from its contents (edited or corrupt)."""
    path = Path(path)
    d = _read(path)
    validate_compensator_dict(d, path)
    try:
        prior = RigidBodyPrior.from_dict(d["prior"]) if d.get("prior") else None
        kernel = d.get("kernel") if isinstance(d.get("kernel"), dict) else {}
        comp = Compensator(d["kind"], d["support"], d["weights"], d["lengthscales"], d["signal_var"],
                           joint_names=d.get("joint_names"), bounds=d.get("workspace_bounds"),
                           info=d.get("info"), storage_sampled_min=d.get("storage_sampled_min"), prior=prior,
                           smoothness=int(kernel.get("smoothness", DEFAULT_SMOOTHNESS)),
                           deviation_sampled_max=d.get("deviation_sampled_max"))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"cannot rebuild the compensator ({exc}): expected a field 'mmgp export' wrote",
                         file=path) from None
    # The bounds are recomputed from the weights and the prior, never trusted from the file; a
    # mismatch means the file was edited or corrupted.
    if not np.isclose(comp.storage_offset, float(d["storage_offset"]), rtol=1e-9,
                      atol=1e-12 * comp.bound_info["triangle_bound"]):
        raise InputError(f"'storage_offset' is {d['storage_offset']!r}, expected {comp.storage_offset!r} (the "
                         "offset recomputed from the weights and prior): the file was edited or corrupted", file=path)
    return comp
