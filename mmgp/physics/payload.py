"""Payload identification: the one place where a rigid mass added to a link is estimated.

A payload on a link adds ``tau = Y_link @ pi`` to the joint torques, with ``Y_link`` (T, n, 10)
the link's inertial regressor (``RobotModel.link_regressor``, or a block of Pinocchio's joint
torque regressor) and ``pi`` its 10 dynamic parameters (``mmgp.physics.inertial``). A *point
mass* m at c has ``pi = point_mass_parameters(m, c)``: nonlinear in c only through the inertia
``m (|c|^2 1 - c c^T)``. Linearised at a centre-of-mass guess c0 (:func:`linearised_columns`),
it is linear in ``(m, m c)``; re-estimating ``c0 = (m c) / m`` (:func:`com_from_moments`) and
refitting converges to the point-mass fit. Users:

* :func:`fit_payload`: a payload on a named link from a residual, by least squares (started from
  the linearisation at c0 = 0, then the exact point-mass model; or all 10 parameters).
* the diagnosis's ``payload`` effect (``mmgp.physics.effects.Payload``): the same linearised
  columns inside the effect library, with the centre of mass re-estimated between fits.
* the EM's payload mean (``mean_basis: payload``) fits all 10 parameters of the distal body,
  linearly and robustly (``mmgp.models.robust.fit_shared_coefficients``), per mode: the
  unconstrained form of the same model, with no point-mass or m >= 0 constraint.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .inertial import point_mass_inertia, point_mass_jacobian, point_mass_parameters, unvech

#: a centre of mass farther than this from the link frame (m) is not taken as a linearisation point
MAX_COM_NORM = 1.0


def linearised_columns(Y_link: np.ndarray, com: np.ndarray) -> np.ndarray:
    """(T, n, 4) columns of a point mass linearised at ``com`` (3,) m: coefficients (m, m c).

    The mass column carries the point-mass inertia at the guess (so a payload does not leak
    into armature-like terms on upstream joints); the other three are the first-moment columns.
    ``Y_link`` (T, n, 10) in the frame ``com`` is expressed in.
    """
    mass_col = Y_link[:, :, 0] + Y_link[:, :, 4:10] @ point_mass_inertia(com)
    return np.concatenate([mass_col[:, :, None], Y_link[:, :, 1:4]], axis=2)


def com_from_moments(mass: float, moments: np.ndarray) -> np.ndarray:
    """Centre of mass (3,) m = first moments (kg*m) / mass (kg), or the frame origin when the
    mass is not positive or the centre lies farther than ``MAX_COM_NORM`` from it."""
    if not mass > 0:
        return np.zeros(3)
    c = np.asarray(moments, dtype=np.float64) / mass
    return c if np.isfinite(c).all() and np.linalg.norm(c) < MAX_COM_NORM else np.zeros(3)


@dataclass
class PayloadFit:
    """A rigid payload identified on ``link``.

    ``mass`` (kg) >= 0; ``com`` (3,) m in the link frame; ``*_std`` one standard deviation from the
    residual variance and the normal matrix; ``inertia`` (3, 3) kg*m^2 about the com in the link
    frame (only with ``fit_inertia``); ``residual_rms`` N*m after the fit; ``n_samples`` used.
    """

    link: str
    mass: float
    com: np.ndarray
    mass_std: float
    com_std: np.ndarray
    inertia: np.ndarray | None = None
    residual_rms: float = float("nan")
    n_samples: int = 0

    def params(self) -> dict:
        """Contract ``payload`` params (CONTRACT section 3)."""
        return {"link": self.link, "mass": float(self.mass), "com": [float(c) for c in self.com]}


@dataclass
class _System:
    """Weighted stacked least-squares system ``A x ~ b`` of a payload fit."""

    A: np.ndarray        # (rows, 10) regressor rows times sqrt(weight)
    b: np.ndarray        # (rows,)
    w_sum: float
    n_samples: int
    link: str

    def lstsq(self, cols: np.ndarray) -> np.ndarray:
        scale = np.linalg.norm(self.A, axis=0)
        scale[scale == 0] = 1.0
        x = np.zeros(self.A.shape[1])
        x[cols] = np.linalg.lstsq(self.A[:, cols] / scale[cols], self.b, rcond=None)[0] / scale[cols]
        return x

    def covariance(self, J: np.ndarray, res: np.ndarray, p: int) -> np.ndarray:
        sigma2 = float(res @ res) / max(self.w_sum - p, 1.0)
        return sigma2 * np.linalg.pinv(J.T @ J)

    def rms(self, res: np.ndarray) -> float:
        return float(np.sqrt(res @ res / max(self.w_sum, 1e-300)))


def fit_payload(robot, q, dq, ddq, tau_residual, link: str, fit_inertia: bool = False,
                weights=None) -> PayloadFit:
    """Least-squares payload on ``link`` explaining ``tau_residual = tau - tau_rbd`` ``(T, n)`` N*m.

    ``robot``: an mmgp RobotModel. ``fit_inertia=False``: a point mass (mass >= 0, com), solved
    as a bounded nonlinear least squares started from the linearisation at com 0.
    ``fit_inertia=True``: all 10 parameters (linear; mass >= 0 enforced exactly by refitting at
    m = 0 when the free optimum is negative). ``weights``: per-sample ``(T,)`` or per-entry
    ``(T, n)`` non-negative weights, e.g. a mode's posterior probabilities (mode-wise fitting is
    the caller's job).
    """
    Y = robot.link_regressor(q, dq, ddq, link)
    if Y.ndim == 2:
        Y = Y[None]
    r = np.asarray(tau_residual, dtype=np.float64).reshape(Y.shape[0], Y.shape[1])
    w = np.ones_like(r) if weights is None else np.broadcast_to(
        np.asarray(weights, dtype=np.float64).reshape(Y.shape[0], -1), r.shape)
    if (w < 0).any() or not np.isfinite(w).all():
        raise ValueError("weights must be finite and non-negative")
    keep = w.reshape(-1) > 0
    sw = np.sqrt(w.reshape(-1)[keep])
    system = _System(Y.reshape(-1, 10)[keep] * sw[:, None], r.reshape(-1)[keep] * sw, float(w.sum()),
                     int((w > 0).any(axis=1).sum()), link)
    return _fit_ten(system) if fit_inertia else _fit_point_mass(system)


def _fit_ten(s: _System) -> PayloadFit:
    cols = np.arange(10)
    x = s.lstsq(cols)
    if x[0] < 0:  # one bound on a convex problem: the optimum then lies on m = 0
        x = s.lstsq(cols[1:])
    res = s.A @ x - s.b
    cov = s.covariance(s.A, res, 10)
    m, h = x[0], x[1:4]
    com = h / m if m > 0 else np.zeros(3)
    I_c = unvech(x[4:10]) - unvech(m * point_mass_inertia(com))
    # delta method for c = h / m
    G = np.zeros((3, 10))
    if m > 0:
        G[:, 0] = -h / m ** 2
        G[:, 1:4] = np.eye(3) / m
    com_cov = G @ cov @ G.T
    return PayloadFit(link=s.link, mass=float(m), com=com, mass_std=float(np.sqrt(max(cov[0, 0], 0))),
                      com_std=np.sqrt(np.clip(np.diag(com_cov), 0, None)), inertia=I_c,
                      residual_rms=s.rms(res), n_samples=s.n_samples)


def _fit_point_mass(s: _System) -> PayloadFit:
    from scipy.optimize import least_squares

    # the linearisation at com 0 (the first four regressor columns, no rotational inertia of
    # the payload about the link origin) gives the start; then the exact point-mass model
    x0 = s.lstsq(np.arange(4))
    z0 = np.concatenate([[max(x0[0], 0.0)], com_from_moments(x0[0], x0[1:4])])

    def fun(z):
        return s.A @ point_mass_parameters(z[0], z[1:]) - s.b

    def jac(z):
        return s.A @ point_mass_jacobian(z[0], z[1:])

    sol = least_squares(fun, z0, jac=jac, bounds=([0.0, -np.inf, -np.inf, -np.inf], np.inf),
                        x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200)
    z = sol.x
    res = fun(z)
    cov = s.covariance(jac(z), res, 4)
    return PayloadFit(link=s.link, mass=float(z[0]), com=z[1:].copy(),
                      mass_std=float(np.sqrt(max(cov[0, 0], 0))),
                      com_std=np.sqrt(np.clip(np.diag(cov)[1:], 0, None)), inertia=None,
                      residual_rms=s.rms(res), n_samples=s.n_samples)
