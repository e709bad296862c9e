"""Payload identification: the one place where a rigid mass added to a link is estimated.

A payload on a link adds ``tau = Y_link @ pi`` to the joint torques, with ``Y_link`` (T, n, 10)
the link's inertial regressor (``RobotModel.link_regressor``, or a block of Pinocchio's joint
torque regressor) and ``pi`` its 10 dynamic parameters (``mmgp.physics.inertial``). A *point
mass* m at c has ``pi = point_mass_parameters(m, c)``: nonlinear in c only through the inertia
``m (|c|^2 1 - c c^T)``. Linearised at a centre-of-mass guess c0 (:func:`linearised_columns`),
it is linear in ``(m, m c)``; re-estimating ``c0 = (m c) / m`` (:func:`com_from_moments`) and
refitting converges to the point-mass fit. Users:

* :func:`fit_point_mass`: the constrained core, on data linear in ``(m, h = m c)`` (a static
  regressor's first four columns of a body, or the linearisation at c0 = 0): ``m >= 0`` and the
  centre of mass inside a ball, a convex problem (a second-order cone). The compensator's
  rigid-body prior fits its payload with it directly (gravity data: exact, the inertia columns of
  a static regressor vanish).
* :func:`fit_payload`: a payload on a named link from a residual of the full dynamics (started
  from :func:`fit_point_mass` on the linearisation at c0 = 0, then the exact point-mass model;
  or all 10 parameters).
* the diagnosis's ``payload`` effect (``mmgp.physics.effects.Payload``): the same linearised
  columns inside the effect library, with the centre of mass re-estimated between fits.
* the EM's payload mean (``mean_basis: payload``) fits all 10 parameters of the distal body,
  linearly and robustly (``mmgp.data.regression.fit_shared_coefficients``), per mode: the
  unconstrained form of the same model, with no point-mass or m >= 0 constraint.
"""
from __future__ import annotations

from dataclasses import dataclass, field

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
class PointMassFit:
    """A point mass fitted by :func:`fit_point_mass`.

    ``mass`` (kg) >= 0; ``com`` (3,) m, with ``|com - com_centre| <= com_radius``; ``residual_rms``
    (units of ``b``); ``active``: the constraints the optimum touches (``"mass>=0"``,
    ``"com radius"``); ``unconstrained``: the free least-squares ``(m, h)`` (4,), for the record.
    """

    mass: float
    com: np.ndarray
    residual_rms: float
    active: list[str] = field(default_factory=list)
    unconstrained: np.ndarray | None = None

    def first_moments(self) -> np.ndarray:
        """``[m, m c_x, m c_y, m c_z]`` (4,)."""
        return np.concatenate([[self.mass], self.mass * self.com])


def fit_point_mass(A, b, *, com_centre=(0.0, 0.0, 0.0), com_radius: float = 0.5) -> PointMassFit:
    """Least squares ``min |A [m, h] - b|^2`` over ``m >= 0``, ``|h / m - com_centre| <= com_radius``.

    ``A`` (M, 4): the columns of ``m`` and ``h = m c`` (e.g. the first four columns of a body's
    static regressor, in which the torque is linear in (m, h)); ``b`` (M,). The feasible set is the
    second-order cone ``|h - m c0| <= r m``, so the problem is convex: SLSQP from the free optimum's
    projection and from the centre finds its minimum (a test checks it against a grid). A mass of
    exactly 0 is returned with ``com = com_centre``.
    """
    from scipy.optimize import minimize

    A = np.asarray(A, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    c0 = np.asarray(com_centre, dtype=np.float64).reshape(3)
    r = float(com_radius)
    if not r > 0:
        raise ValueError("com_radius must be positive")
    # variables z = (m, w), h = m c0 + r w, feasible iff |w| <= m; columns scaled to unit norm
    T = np.zeros((4, 4))
    T[0, 0] = 1.0
    T[1:, 0] = c0
    T[1:, 1:] = r * np.eye(3)
    B = A @ T
    scale = np.linalg.norm(B, axis=0)
    scale[scale == 0] = 1.0
    Bs = B / scale
    G, g, bb = Bs.T @ Bs, Bs.T @ b, float(b @ b)
    free = np.linalg.lstsq(Bs, b, rcond=None)[0]

    def f(zs):
        return float(zs @ G @ zs - 2 * g @ zs + bb), 2 * (G @ zs - g)

    def cone(zs):  # m^2 - |w|^2 >= 0 and m >= 0 together describe |w| <= m
        z = zs / scale
        return np.array([z[0], z[0] ** 2 - z[1:] @ z[1:]])

    def cone_jac(zs):
        z = zs / scale
        return np.array([[1.0, 0, 0, 0], [2 * z[0], *(-2 * z[1:])]]) / scale

    z_free = free / scale
    starts = [free]
    if not (cone(free) >= 0).all():
        m = max(z_free[0], np.linalg.norm(z_free[1:]), 1e-12)
        wn = np.linalg.norm(z_free[1:])
        starts = [np.concatenate([[m], z_free[1:] * (m / wn if wn > m else 1.0)]) * scale,
                  np.array([max(z_free[0], 1e-6), 0, 0, 0]) * scale]
    best = None
    for s in starts:
        res = minimize(f, s, jac=True, method="SLSQP", options={"maxiter": 500, "ftol": 1e-15},
                       constraints=[{"type": "ineq", "fun": cone, "jac": cone_jac}])
        if best is None or res.fun < best.fun:
            best = res
    z = best.x / scale
    m = max(float(z[0]), 0.0)
    w = z[1:]
    if np.linalg.norm(w) > m:  # SLSQP's constraint tolerance: pull back onto the cone
        w = w * (m / np.linalg.norm(w))
    com = c0 + (r * w / m if m > 0 else 0.0)
    active = (["mass>=0"] if m <= 1e-12 * max(1.0, abs(z_free[0])) else []) + (
        ["com radius"] if m > 0 and np.linalg.norm(w) >= m * (1 - 1e-6) else [])
    x = A @ np.concatenate([[m], m * com]) - b
    return PointMassFit(mass=m, com=com, residual_rms=float(np.sqrt(np.mean(x * x))), active=active,
                        unconstrained=T @ z_free)


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
    # the payload about the link origin), constrained, gives the start; then the exact model
    start = fit_point_mass(s.A[:, :4], s.b, com_radius=MAX_COM_NORM)
    z0 = np.concatenate([[start.mass], start.com])

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
