"""Physically consistent inertial parameters (mmgp.physics.consistent).

References: Pinocchio's PseudoInertia and LogCholeskyParameters (a second implementation),
finite differences, a brute-force grid over the centre-of-mass ball, and closed-form bodies
(a point mass, a body violating the triangle inequality).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from mmgp.physics.consistent import (consistency_problems, first_moment_problems, fit_consistent_parameters,
                                     log_cholesky_jacobian, log_cholesky_to_parameters,
                                     nearest_consistent, parameters_from_pseudo_inertia, parameters_to_log_cholesky,
                                     pseudo_inertia)
from mmgp.physics.payload import fit_point_mass
from mmgp.physics.robot import RobotModel

PANDA = [f"panda_joint{i}" for i in range(1, 8)]


def _random_inertia(rng) -> pin.Inertia:
    """A body with a random positive definite second moment Sigma about its com (a real body)."""
    A = rng.normal(size=(3, 3))
    m = float(rng.uniform(0.2, 3.0))
    sigma = m * (A @ A.T * 0.01 + 1e-3 * np.eye(3))
    return pin.Inertia(m, rng.normal(size=3) * 0.2, np.trace(sigma) * np.eye(3) - sigma)


def test_pseudo_inertia_and_log_cholesky_match_pinocchio():
    rng = np.random.default_rng(0)
    for _ in range(20):
        inertia = _random_inertia(rng)
        pi = inertia.toDynamicParameters()
        J_ref = inertia.toPseudoInertia().toMatrix()
        np.testing.assert_allclose(pseudo_inertia(pi), J_ref, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(parameters_from_pseudo_inertia(J_ref), pi, rtol=1e-12, atol=1e-14)
        theta = rng.normal(size=10) * 0.5
        ref = pin.Inertia.FromLogCholeskyParameters(pin.LogCholeskyParameters(theta)).toDynamicParameters()
        np.testing.assert_allclose(log_cholesky_to_parameters(theta), ref, rtol=1e-12, atol=1e-14)
        # and back: the coordinates of a consistent body reproduce it
        back = log_cholesky_to_parameters(parameters_to_log_cholesky(pi))
        np.testing.assert_allclose(back, pi, rtol=1e-10, atol=1e-13)


def test_log_cholesky_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    theta = rng.normal(size=10) * 0.4
    J = log_cholesky_jacobian(theta)
    h = 1e-6
    for k in range(10):
        e = np.zeros(10)
        e[k] = h
        fd = (log_cholesky_to_parameters(theta + e) - log_cholesky_to_parameters(theta - e)) / (2 * h)
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-6, atol=1e-8)


def test_consistency_problems_on_known_bodies():
    point = np.concatenate([[2.0], 2.0 * np.array([0.1, 0.0, 0.3]), np.zeros(6)])
    point[4:] = pin.Inertia(2.0, np.array([0.1, 0.0, 0.3]), np.zeros((3, 3))).toDynamicParameters()[4:]
    assert consistency_problems(point) == []  # a point mass is consistent (J is rank one)
    neg = point.copy()
    neg[0] = -0.5
    assert any("negative mass" in p for p in consistency_problems(neg))
    # principal moments 1, 1, 3 about the com violate Ixx + Iyy >= Izz: no mass distribution has them
    tri = pin.Inertia(1.0, np.zeros(3), np.diag([1.0, 1.0, 3.0])).toDynamicParameters()
    assert any("pseudo-inertia" in p for p in consistency_problems(tri, name="link"))
    with pytest.raises(ValueError, match="strictly"):
        parameters_to_log_cholesky(tri)
    fixed = nearest_consistent(tri)
    assert consistency_problems(fixed) == []
    assert np.linalg.eigvalsh(pseudo_inertia(fixed)).min() > 0
    assert first_moment_problems(0.0, [0, 0, 0]) == []
    assert "negative mass" in first_moment_problems(-1.0, [0, 0, 0])[0]
    assert "beyond" in first_moment_problems(1.0, [0, 0, 2.0], max_com_radius=0.5)[0]
    assert "not finite" in first_moment_problems(np.nan, [0, 0, 0])[0]


def _grid_optimum(A, b, c0, r, n=41):
    """Brute force: com on a grid filling the ball, the best mass >= 0 in closed form for each."""
    g = np.linspace(-1, 1, n)
    V = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    V = V[np.sum(V * V, 1) <= 1]
    Ac = A[:, :1] + A[:, 1:] @ (c0 + r * V).T  # (M, G): the torque of 1 kg at each grid com
    m = np.maximum(0.0, (b @ Ac) / np.sum(Ac * Ac, axis=0))
    obj = float(b @ b) - 2 * m * (b @ Ac) + m * m * np.sum(Ac * Ac, axis=0)
    return min(float(b @ b), float(obj.min()))  # the first: mass 0


@pytest.mark.parametrize("case", ["interior", "radius", "mass"])
def test_fit_point_mass_is_the_constrained_optimum(case):
    robot = RobotModel.from_name("panda", PANDA)
    rng = np.random.default_rng(2)
    Q = rng.uniform(-2, 2, (60, 7))
    A = robot.regressor(Q)[..., -10:-6].reshape(-1, 4)
    truth = {"interior": (0.8, [0.02, -0.01, 0.2]), "radius": (0.8, [0.0, 0.0, 0.9]),
             "mass": (-0.7, [0.01, 0.02, 0.1])}[case]
    b = A @ np.concatenate([[truth[0]], truth[0] * np.asarray(truth[1])]) + rng.normal(size=A.shape[0]) * 0.01
    fit = fit_point_mass(A, b, com_radius=0.5)
    obj = float(np.sum((A @ fit.first_moments() - b) ** 2))
    ref = _grid_optimum(A, b, np.zeros(3), 0.5)
    assert obj <= ref + 1e-9 * max(ref, 1.0)  # at least as good as every grid point
    assert fit.mass >= 0 and np.linalg.norm(fit.com) <= 0.5 + 1e-12
    if case == "interior":
        assert fit.active == [] and fit.mass == pytest.approx(0.8, abs=0.01)
        np.testing.assert_allclose(fit.com, truth[1], atol=0.01)
    elif case == "radius":
        assert fit.active == ["com radius"]
    else:
        assert fit.unconstrained[0] < 0 and fit.mass == pytest.approx(0.0, abs=1e-9) and "mass>=0" in fit.active


def test_fit_consistent_parameters_recovers_and_constrains():
    robot = RobotModel.from_name("panda", PANDA)
    rng = np.random.default_rng(3)
    Q, dQ, ddQ = rng.uniform(-2, 2, (25, 7)), rng.normal(size=(25, 7)), rng.normal(size=(25, 7)) * 3
    Y = robot.regressor(Q, dQ, ddQ).reshape(-1, 70)
    truth = robot.dynamic_parameters()
    # noise-free data of the nominal robot: the fit explains them and stays consistent
    pi, info = fit_consistent_parameters(Y, Y @ truth, truth * 1.3, ridge=1e-10)
    assert info["residual_rms"] < 1e-4 * np.sqrt(np.mean((Y @ truth) ** 2))
    for i in range(7):
        assert consistency_problems(pi[10 * i:10 * i + 10], rtol=1e-9) == []
    # data of a body with a negative mass (unphysical): the unconstrained least squares follows
    # it, the consistent fit cannot, and it is no worse than the (consistent) nominal model
    bad = truth.copy()
    bad[60] = -1.0
    tau = Y @ bad
    free = np.linalg.lstsq(Y, tau, rcond=None)[0]
    pi_c, info_c = fit_consistent_parameters(Y, tau, truth, ridge=1e-8)
    assert any(consistency_problems(free[10 * i:10 * i + 10]) for i in range(7))
    assert all(not consistency_problems(pi_c[10 * i:10 * i + 10], rtol=1e-9) for i in range(7))
    assert info_c["residual_rms"] <= np.sqrt(np.mean((Y @ truth - tau) ** 2))
