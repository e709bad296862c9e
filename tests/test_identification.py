"""Physically constrained least squares (``identification.fit_admissible``) against references
that do not use it or its solver: scipy's bounded least squares, the closed-form projection onto a
second-order cone, and a brute-force search over bodies built as mass distributions (a
pseudo-inertia ``L L^T``), so that every point it tries is physical."""
import numpy as np
import pytest
from scipy.optimize import least_squares, lsq_linear

from mmgp.physics.identification import fit_admissible, fit_consistent


def _normal(A, b):
    return A.T @ A, A.T @ b


def test_bounds_match_scipy_bounded_least_squares():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((40, 5))
    # a target whose unconstrained fit breaks both bounds
    b = A @ np.array([-1.0, 2.0, 0.5, 3.0, -0.2]) + 0.1 * rng.standard_normal(40)
    x, info = fit_admissible(*_normal(A, b), nonneg=[0, 4], upper=[(1, 1.5), (3, 2.0)])
    lo = np.array([0, -np.inf, -np.inf, -np.inf, 0])
    hi = np.array([np.inf, 1.5, np.inf, 2.0, np.inf])
    ref = lsq_linear(A, b, bounds=(lo, hi), tol=1e-12).x
    np.testing.assert_allclose(x, ref, atol=1e-5)
    assert info["status"].startswith("optimal")


@pytest.mark.parametrize("v", [(0.5, 0.3, -0.4, 0.2), (-0.3, 0.1, 0.2, 0.05), (2.0, 0.1, 0.0, 0.1)])
def test_a_point_mass_within_reach_is_the_projection_onto_its_cone(v):
    """min |x - v|^2 with |x[1:]| <= r x[0]: on the cone's surface h = rho v_h / |v_h|,
    m = rho / r, rho = max(0, (v_m / r + |v_h|) / (1 / r^2 + 1)), unless v is inside it."""
    v, r = np.array(v), 0.8
    x, _ = fit_admissible(np.eye(4), v, cones=[(0, [1, 2, 3], r)])
    vm, vh = v[0], v[1:]
    if np.linalg.norm(vh) <= r * vm:
        want = v
    else:
        rho = max(0.0, (vm / r + np.linalg.norm(vh)) / (1 / r ** 2 + 1))
        want = np.concatenate([[rho / r], rho * vh / np.linalg.norm(vh)])
    np.testing.assert_allclose(x, want, atol=1e-6)


def _pi_of_pseudo_inertia(J):
    """Pinocchio's ten parameters of a pseudo-inertia J (4, 4): Sigma = J[:3, :3], I = tr(Sigma) 1
    - Sigma, h = J[:3, 3], m = J[3, 3]."""
    S = J[:3, :3]
    inertia = np.trace(S) * np.eye(3) - S
    return np.array([J[3, 3], *J[:3, 3], inertia[0, 0], inertia[0, 1], inertia[1, 1], inertia[0, 2],
                     inertia[1, 2], inertia[2, 2]])


def _pseudo_inertia(p):
    inertia = np.array([[p[4], p[5], p[7]], [p[5], p[6], p[8]], [p[7], p[8], p[9]]])
    return np.block([[0.5 * np.trace(inertia) * np.eye(3) - inertia, p[1:4, None]], [p[None, 1:4], p[None, :1]]])


def test_a_body_is_the_best_mass_distribution_brute_force():
    """Data from a body with negative mass (no mass distribution has it): the fit beside its
    nominal parameters is physically consistent and as good as the best of many local searches
    over L L^T, each step of which is a mass distribution."""
    rng = np.random.default_rng(3)
    Y = rng.standard_normal((60, 10))
    pi0 = _pi_of_pseudo_inertia(np.diag([0.01, 0.02, 0.015, 1.0]))
    target = pi0 + np.array([-1.6, 0.05, -0.02, 0.03, 0.01, 0.0, -0.02, 0.0, 0.01, 0.03])
    tau = Y @ target + 0.01 * rng.standard_normal(60)
    dx, _ = fit_admissible(*_normal(Y, tau - Y @ pi0), bodies=[(np.arange(10), pi0)], ridge=0.0)
    pi = pi0 + dx
    assert np.linalg.eigvalsh(_pseudo_inertia(pi)).min() > -1e-7

    tril = np.tril_indices(4)

    def resid(v):
        L = np.zeros((4, 4))
        L[tril] = v
        return Y @ _pi_of_pseudo_inertia(L @ L.T) - tau

    best = min((least_squares(resid, rng.standard_normal(10) * 0.3, xtol=1e-14, ftol=1e-14, gtol=1e-14)
                for _ in range(8)), key=lambda s: s.cost)
    ours = 0.5 * np.sum((Y @ pi - tau) ** 2)
    assert ours <= best.cost * (1 + 1e-6) + 1e-10
    assert ours >= best.cost * (1 - 1e-4)


def test_consistent_fit_holds_bodies_first_then_non_negative_effects():
    """``fit_consistent`` (P body parameters first, then effects) on a physical body's data with a
    non-negative effect whose data want it negative: its column orthogonal to the others, so the
    fit is scipy's bounded least squares with that coefficient at zero and the body untouched."""
    rng = np.random.default_rng(5)
    Y, _ = np.linalg.qr(rng.standard_normal((80, 12)))
    Y = Y * np.array([3.0] * 10 + [1.0, 1.0])
    pi0 = _pi_of_pseudo_inertia(np.diag([0.02, 0.03, 0.01, 2.0]))
    true = np.concatenate([0.1 * pi0, [0.4, -0.7]])
    tau = Y @ true + 0.001 * rng.standard_normal(80)
    x, _ = fit_consistent(*_normal(Y, tau), pi0, nonneg=np.array([True, True]), ridge=0.0)
    lo = np.concatenate([np.full(10, -np.inf), [0.0, 0.0]])
    ref = lsq_linear(Y, tau, bounds=(lo, np.full(12, np.inf)), tol=1e-12).x
    np.testing.assert_allclose(x, ref, atol=1e-5)
    assert x[11] == pytest.approx(0.0, abs=1e-6) and x[10] == pytest.approx(0.4, abs=0.01)
