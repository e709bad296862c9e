"""Physically consistent inertial parameters of rigid bodies (numpy; scipy only inside the fits).

Conventions (as :mod:`mmgp.physics.robot`): a body's parameters are Pinocchio's
``toDynamicParameters`` order ``pi = [m, h_x, h_y, h_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz]``
(kg, kg*m, kg*m^2) with ``h = m c`` (c the centre of mass) and the inertia ``I`` about the frame's
origin, all in the body's frame.

Consistency. A parameter vector belongs to some mass distribution (a non-negative density) iff
its *pseudo-inertia* ``J = [[Sigma, h], [h^T, m]]``, ``Sigma = tr(I)/2 * 1 - I`` (the second moment
``int r r^T dm``), is positive semi-definite (Wensing, Kim and Slotine, RA-L 2018). This implies
m >= 0, a positive semi-definite inertia about the centre of mass and the triangle inequalities of
its principal moments. A gravity-only model sees only ``(m, h)``; for those, consistency is exactly
``m >= 0`` and ``h = 0`` when ``m = 0`` (a point mass at ``h / m`` realises any other pair).

Log-Cholesky parameterisation (Rucker and Wensing, RA-L 2022), ten unconstrained reals
``theta = [alpha, d1, d2, d3, s12, s23, s13, t1, t2, t3]`` (Pinocchio's ``LogCholeskyParameters``
order), ``J = U U^T`` with ``U = e^alpha [[e^d1, s12, s13, t1], [0, e^d2, s23, t2],
[0, 0, e^d3, t3], [0, 0, 0, 1]]``: every theta gives a strictly consistent body (m = e^{2 alpha} > 0)
and every strictly consistent body has exactly one theta, so a least-squares fit over theta can
only return physical bodies.

Fit (a payload alone is :func:`mmgp.physics.payload.fit_point_mass`, the one payload identification):

* :func:`fit_consistent_parameters`: any number of bodies' full parameters from a regressor, over
  log-Cholesky coordinates, with a ridge towards reference parameters (the nominal model) for
  the directions the data do not determine.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "pseudo_inertia", "parameters_from_pseudo_inertia", "log_cholesky_to_parameters",
    "parameters_to_log_cholesky", "log_cholesky_jacobian", "consistency_problems", "first_moment_problems",
    "nearest_consistent", "fit_consistent_parameters",
]


def _body(pi) -> np.ndarray:
    pi = np.asarray(pi, dtype=np.float64)
    if pi.shape != (10,):
        raise ValueError(f"a body's inertial parameters are (10,), got {pi.shape}")
    return pi


def pseudo_inertia(pi) -> np.ndarray:
    """(4, 4) pseudo-inertia ``[[tr(I)/2 1 - I, h], [h^T, m]]`` of parameters ``pi`` (10,)."""
    m, h, v = _body(pi)[0], pi[1:4], pi[4:10]
    inertia = np.array([[v[0], v[1], v[3]], [v[1], v[2], v[4]], [v[3], v[4], v[5]]])
    J = np.empty((4, 4))
    J[:3, :3] = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    J[:3, 3] = J[3, :3] = h
    J[3, 3] = m
    return J


def parameters_from_pseudo_inertia(J) -> np.ndarray:
    """Inverse of :func:`pseudo_inertia`: (4, 4) symmetric -> (10,)."""
    J = np.asarray(J, dtype=np.float64)
    S = 0.5 * (J[:3, :3] + J[:3, :3].T)
    inertia = np.trace(S) * np.eye(3) - S
    return np.array([J[3, 3], *(0.5 * (J[:3, 3] + J[3, :3])), inertia[0, 0], inertia[0, 1], inertia[1, 1],
                     inertia[0, 2], inertia[1, 2], inertia[2, 2]])


def _log_cholesky_factor(theta) -> np.ndarray:
    a, d1, d2, d3, s12, s23, s13, t1, t2, t3 = np.asarray(theta, dtype=np.float64)
    return np.exp(a) * np.array([[np.exp(d1), s12, s13, t1], [0.0, np.exp(d2), s23, t2],
                                 [0.0, 0.0, np.exp(d3), t3], [0.0, 0.0, 0.0, 1.0]])


def log_cholesky_to_parameters(theta) -> np.ndarray:
    """Parameters (10,) of log-Cholesky coordinates ``theta`` (10,) (always consistent)."""
    U = _log_cholesky_factor(theta)
    return parameters_from_pseudo_inertia(U @ U.T)


def parameters_to_log_cholesky(pi) -> np.ndarray:
    """Log-Cholesky coordinates (10,) of strictly consistent parameters (pseudo-inertia > 0).

    ``J = U U^T`` with U upper triangular: U is the reversed lower Cholesky factor of the reversed
    J. Raises ValueError when J is not positive definite."""
    J = pseudo_inertia(pi)
    try:
        L = np.linalg.cholesky(J[::-1, ::-1])
    except np.linalg.LinAlgError:
        raise ValueError("parameters are not strictly physically consistent (pseudo-inertia not "
                         "positive definite)") from None
    U = L[::-1, ::-1]
    a = np.log(U[3, 3])
    Ub = U / U[3, 3]
    return np.array([a, np.log(Ub[0, 0]), np.log(Ub[1, 1]), np.log(Ub[2, 2]), Ub[0, 1], Ub[1, 2], Ub[0, 2],
                     Ub[0, 3], Ub[1, 3], Ub[2, 3]])


# (row, col) of U each log-Cholesky coordinate moves, beyond the common factor e^alpha.
_U_ENTRIES = ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))


def log_cholesky_jacobian(theta) -> np.ndarray:
    """d parameters / d theta, (10, 10) (column k: derivative along ``theta[k]``)."""
    U = _log_cholesky_factor(theta)
    out = np.empty((10, 10))
    for k in range(10):
        if k == 0:
            dU = U
        else:
            dU = np.zeros((4, 4))
            r, c = _U_ENTRIES[k - 1]
            dU[r, c] = U[r, c] if k <= 3 else np.exp(theta[0])
        dJ = dU @ U.T + U @ dU.T
        out[:, k] = parameters_from_pseudo_inertia(dJ)
    return out


def consistency_problems(pi, name: str = "body", rtol: float = 1e-10) -> list[str]:
    """What makes ``pi`` (10,) physically inconsistent, as sentences (empty list: consistent).

    Checks finiteness, ``m >= 0`` and ``J >= 0`` (smallest eigenvalue of the pseudo-inertia at
    least ``-rtol`` times its largest absolute eigenvalue)."""
    pi = _body(pi)
    if not np.isfinite(pi).all():
        return [f"{name}: inertial parameters are not finite"]
    out = []
    if pi[0] < 0:
        out.append(f"{name}: negative mass {pi[0]:.6g} kg")
    ev = np.linalg.eigvalsh(pseudo_inertia(pi))
    if ev[0] < -rtol * max(np.abs(ev).max(), 1e-300):
        out.append(f"{name}: pseudo-inertia has a negative eigenvalue {ev[0]:.3g} (no mass distribution "
                   f"has these parameters)")
    return out


def first_moment_problems(mass, com, name: str = "body", max_com_radius: float | None = None) -> list[str]:
    """Consistency of the parameters a gravity model uses, mass (kg) and centre of mass (3,) m.

    Consistent iff the mass is finite and >= 0 and the com finite; ``max_com_radius`` (m)
    additionally requires ``|com| <= max_com_radius`` (plausibility)."""
    com = np.asarray(com, dtype=np.float64).reshape(-1)
    if not (np.isfinite(mass) and com.shape == (3,) and np.isfinite(com).all()):
        return [f"{name}: mass or centre of mass is not finite (or the com is not 3 numbers)"]
    out = []
    if mass < 0:
        out.append(f"{name}: negative mass {mass:.6g} kg")
    if max_com_radius is not None and np.linalg.norm(com) > max_com_radius:
        out.append(f"{name}: centre of mass {np.linalg.norm(com):.3g} m from its frame, beyond {max_com_radius} m")
    return out


def nearest_consistent(pi, floor: float = 1e-9) -> np.ndarray:
    """Parameters whose pseudo-inertia is the Frobenius-nearest positive definite matrix to that
    of ``pi`` (eigenvalues clipped at ``floor`` times the largest, at least 1e-12)."""
    J = pseudo_inertia(pi)
    w, V = np.linalg.eigh(J)
    w = np.maximum(w, max(floor * np.abs(w).max(), 1e-12))
    return parameters_from_pseudo_inertia((V * w) @ V.T)


def fit_consistent_parameters(Y, tau, reference, *, ridge: float = 1e-4, max_nfev: int = 200):
    """Physically consistent parameters of B bodies minimising ``|Y pi - tau|^2 + ridge-term``.

    ``Y`` (M, 10 B) regressor (e.g. :meth:`mmgp.physics.robot.RobotModel.regressor` stacked over
    samples and joints), ``tau`` (M,), ``reference`` (10 B,) parameters (made strictly consistent by
    :func:`nearest_consistent` first). Each body is parameterised by log-Cholesky coordinates, so
    every iterate is physical. The ridge term ``ridge * sum_k (|Y_k| (pi_k - ref_k))^2`` (``|Y_k|`` the
    column norm, floored at 1e-6 of the largest) fixes the directions the data do not determine
    at the reference without favouring any unit. Returns ``(pi (10 B,), info)`` with
    ``residual_rms`` and scipy's ``status``.
    """
    from scipy.optimize import least_squares

    Y = np.asarray(Y, dtype=np.float64)
    tau = np.asarray(tau, dtype=np.float64).reshape(-1)
    ref = np.asarray(reference, dtype=np.float64).reshape(-1)
    nb = ref.size // 10
    if ref.size != 10 * nb or Y.shape != (tau.size, ref.size):
        raise ValueError(f"Y must be (M, 10 B) = ({tau.size}, {ref.size}) and reference (10 B,)")
    ref_c = np.concatenate([nearest_consistent(ref[10 * i:10 * i + 10]) for i in range(nb)])
    cn = np.linalg.norm(Y, axis=0)
    w = np.sqrt(ridge) * np.maximum(cn, 1e-6 * max(cn.max(), 1e-300))

    def params(theta):
        return np.concatenate([log_cholesky_to_parameters(theta[10 * i:10 * i + 10]) for i in range(nb)])

    def fun(theta):
        pi = params(theta)
        return np.concatenate([Y @ pi - tau, w * (pi - ref_c)])

    def jac(theta):
        D = np.zeros((ref.size, ref.size))
        for i in range(nb):
            D[10 * i:10 * i + 10, 10 * i:10 * i + 10] = log_cholesky_jacobian(theta[10 * i:10 * i + 10])
        return np.vstack([Y @ D, w[:, None] * D])

    theta0 = np.concatenate([parameters_to_log_cholesky(ref_c[10 * i:10 * i + 10]) for i in range(nb)])
    # Box of +-25 on every coordinate (masses e^{+-50} kg, com offsets up to 25 m): no physical body
    # is excluded, and the trust region cannot step into exp overflow.
    sol = least_squares(fun, np.clip(theta0, -25, 25), jac=jac, method="trf", x_scale="jac", max_nfev=max_nfev,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, bounds=(-25.0, 25.0))
    pi = params(sol.x)
    res = Y @ pi - tau
    return pi, {"residual_rms": float(np.sqrt(np.mean(res * res))), "status": int(sol.status),
                "n_eval": int(sol.nfev)}
