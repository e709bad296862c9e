"""The compactly supported (Wendland) potential kernel, the valid region and the C export with a prior.

References: Wendland's recursion integrated exactly with numpy's polynomial algebra (not the
closed forms of the module), polynomial derivatives, torch autograd double derivatives of the
kernel, eigenvalues of kernel matrices, a brute-force nearest-support loop, and a gcc-compiled
build of the generated C source.
"""
from __future__ import annotations

import ctypes
import shutil
import subprocess

import numpy as np
import pytest
import torch
from numpy.polynomial import Polynomial

from mmgp.compensator import Compensator, check_passivity, compensator_from_model, load_compensator
from mmgp.compensator.kernels import WendlandProfile
from mmgp.compensator.prior import prior_from_robot
from mmgp.gp.gradient_field import CurlFreeGP, curl_free_kernel_np, curl_free_kernel_torch
from mmgp.physics.robot import RobotModel


def _psi(l, j) -> Polynomial:
    """psi_{l,j}(1 - s) as a polynomial in s = 1 - r, by the recursion psi_{l,j+1}(r) =
    int_r^1 t psi_{l,j}(t) dt = int_0^s (1 - sigma) psi_{l,j}(1 - sigma) dsigma."""
    p = Polynomial([0.0, 1.0]) ** l
    for _ in range(j):
        p = (Polynomial([1.0, -1.0]) * p).integ()
    return p


@pytest.mark.parametrize("n,k", [(1, 2), (1, 3), (2, 3), (6, 2), (7, 3)])
def test_wendland_profile_matches_the_recursion(n, k):
    prof = WendlandProfile(n, k)
    assert prof.degree == n // 2 + k + 1
    l = prof.degree
    c0 = _psi(l, k)(1.0)
    r = np.concatenate([np.linspace(0, 1, 101), [1.0 + 1e-9, 1.5, 7.0]])
    inside = r < 1
    for got, ref in ((prof.phi(r), _psi(l, k)), (prof.A(r), _psi(l, k - 1)), (prof.B(r), _psi(l, k - 2))):
        # the expanded reference polynomial cancels near r = 1: compare against its scale there
        want = ref(1.0 - r[inside]) / c0
        np.testing.assert_allclose(got[inside], want, rtol=1e-11, atol=1e-12 * np.abs(want).max())
        np.testing.assert_array_equal(got[~inside], 0.0)
    # A = -phi'/r and B = (phi'' - phi'/r)/r^2, the radial functions of the curl-free kernel
    phi = _psi(l, k) / c0  # in s = 1 - r: d/dr = -d/ds
    rr = np.linspace(0.05, 0.95, 19)
    d1, d2 = -phi.deriv()(1.0 - rr), phi.deriv(2)(1.0 - rr)
    for got, want in ((prof.A(rr), -d1 / rr), (prof.B(rr), (d2 - d1 / rr) / rr ** 2)):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-11 * np.abs(want).max())


def test_wendland_kernels_are_positive_definite():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (150, 7))
    prof = WendlandProfile(7)
    D = np.linalg.norm((X[:, None] - X[None]) / 0.9, axis=2)
    assert np.linalg.eigvalsh(prof.phi(D)).min() > 0
    K = curl_free_kernel_np(X[:60], X[:60], np.full(7, 0.9), 1.3, profile=prof)
    assert np.linalg.eigvalsh(K).min() > 0 and np.abs(K - K.T).max() < 1e-12 * np.abs(K).max()


def _autograd_kernel_blocks(X1, X2, l, s2, prof):
    """d^2 k / dx_i dx'_j of k = s2 phi(|(x - x')/l|) by torch autograd (points distinct)."""
    lt = torch.tensor(l)

    def k(x, xp):
        return s2 * prof.phi(torch.sqrt((((x - xp) / lt) ** 2).sum()))

    n = X1.shape[1]
    K = np.zeros((X1.shape[0] * n, X2.shape[0] * n))
    for a, xa in enumerate(X1):
        for b, xb in enumerate(X2):
            H = torch.autograd.functional.hessian(k, (torch.tensor(xa), torch.tensor(xb)))
            K[a * n:(a + 1) * n, b * n:(b + 1) * n] = H[0][1].numpy()
    return K


def test_curl_free_wendland_kernel_matches_autograd():
    rng = np.random.default_rng(1)
    X1, X2 = rng.uniform(-0.5, 0.5, (5, 3)), rng.uniform(-0.5, 0.5, (4, 3))
    l, s2, prof = np.array([0.9, 1.2, 0.8]), 1.7, WendlandProfile(3)
    ref = _autograd_kernel_blocks(X1, X2, l, s2, prof)
    np.testing.assert_allclose(curl_free_kernel_np(X1, X2, l, s2, prof), ref, rtol=1e-10, atol=1e-12)
    Kt = curl_free_kernel_torch(torch.tensor(X1), torch.tensor(X2), torch.log(torch.tensor(l)),
                                torch.log(torch.tensor(s2, dtype=torch.float64)), prof).numpy()
    np.testing.assert_allclose(Kt, ref, rtol=1e-10, atol=1e-12)
    # at x = x' (autograd's sqrt is singular there): s2 A(0) / l_i^2 on the diagonal block
    np.testing.assert_allclose(curl_free_kernel_np(X1[:1], X1[:1], l, s2, prof), np.diag(s2 * prof.a0 / l ** 2))


def test_wendland_compensator_is_the_gradient_of_its_potential():
    """V(q) = sum_aj alpha_aj dk(q, z_a)/dz_aj and tau = dV/dq by autograd, against the evaluator."""
    rng = np.random.default_rng(2)
    Z, W, l, s2 = rng.uniform(-1, 1, (12, 3)), rng.normal(size=(12, 3)), np.array([0.9, 1.4, 1.1]), 0.7
    comp = Compensator("curl-free-wendland", Z, W, l, s2)
    prof, lt = comp.profile, torch.tensor(l)
    for q in rng.uniform(-1.3, 1.3, (8, 3)):
        qt = torch.tensor(q, requires_grad=True)
        zt = torch.tensor(Z, requires_grad=True)
        k = s2 * prof.phi(torch.sqrt((((qt[None] - zt) / lt) ** 2).sum(1)))
        (dk_dz,) = torch.autograd.grad(k.sum(), zt, create_graph=True)
        V = (dk_dz * torch.tensor(W)).sum()
        (tau,) = torch.autograd.grad(V, qt)
        assert comp.potential(q) == pytest.approx(float(V.detach()), rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(comp.torque(q), tau.numpy(), rtol=1e-9, atol=1e-12)


def test_region_and_compact_support():
    rng = np.random.default_rng(3)
    Z = rng.uniform(-1, 1, (40, 4))
    comp = Compensator("curl-free-wendland", Z, rng.normal(size=(40, 4)), np.array([0.5, 0.7, 0.6, 0.8]), 2.0)
    Q = rng.uniform(-1.5, 1.5, (300, 4))
    ref = np.array([min(np.linalg.norm((q - z) / comp.lengthscales) for z in Z) for q in Q])
    np.testing.assert_allclose(comp.region_distance(Q), ref, rtol=1e-12)
    tau, rho = comp.torque(Q, return_region=True)
    np.testing.assert_allclose(rho, np.minimum(ref, 1.0), rtol=1e-12)
    outside = ref >= 1
    assert 20 < outside.sum() < 280
    np.testing.assert_array_equal(tau[outside], 0.0)  # exactly: no prior here
    assert np.all(np.abs(tau[~outside]).sum(1) > 0)
    # the rigorous bound on the deviation holds wherever it is sampled
    assert np.all(np.abs(tau) <= comp.deviation_torque_bound)
    assert np.all(np.abs(comp.potential(Q)) <= comp.potential_bound)


class GravityPlusSpring:
    """Stand-in model with a robot: UR5 gravity with a 0.4 kg payload plus a spring on the vertical
    first joint (conservative; gravity has no torque there, so the payload fit cannot absorb it),
    on 120 poses within +-0.7 rad of a home pose."""

    def __init__(self):
        self.robot = RobotModel.from_name("ur5")
        self._truth = self.robot.add_payload("wrist_3_link", 0.4, [0.0, 0.1, 0.0])
        self.home = np.array([0.0, -1.2, 1.0, -1.4, -1.57, 0.0])
        self.support_q_ = self.home + np.random.default_rng(4).uniform(-0.7, 0.7, (120, 6))

    def nominal_torque(self, q):
        tau = self._truth.gravity(np.atleast_2d(q))
        tau[:, 0] += 3.0 * np.atleast_2d(q)[:, 0]
        return tau


def test_learned_deviation_over_prior_is_passive_and_safe():
    model = GravityPlusSpring()
    comp = compensator_from_model(model, max_support=120, max_hyper_points=60, max_iter=25)
    assert comp.kind == "curl-free-wendland" and comp.prior is not None
    assert comp.prior.identification["payload"]["mass"] == pytest.approx(0.4, abs=1e-3)
    near = model.home + np.random.default_rng(5).uniform(-0.5, 0.5, (200, 6))
    err = comp.torque(near) - model.nominal_torque(near)
    assert np.sqrt(np.mean(err ** 2)) < 0.05 * np.sqrt(np.mean(model.nominal_torque(near) ** 2))
    far = np.random.default_rng(6).uniform(-6.0, 6.0, (200, 6))
    far = far[comp.region_distance(far) >= 1]
    np.testing.assert_allclose(comp.torque(far), model._truth.gravity(far), atol=0.2)  # the prior, payload fitted
    assert np.all(comp.deviation_sampled_max <= comp.deviation_torque_bound)
    assert np.all(np.abs(comp.deviation_torque(near)) <= comp.deviation_torque_bound)
    res = check_passivity(comp, n_configs=60, n_loops=15)
    assert res["passed"], res


def _build(comp, tmp_path, stem):
    gcc = shutil.which("gcc")
    assert gcc is not None, "gcc is required to test the generated C source"
    c_path, h_path = comp.write_c(tmp_path / stem)
    so = tmp_path / f"lib{stem}.so"
    subprocess.run([gcc, "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror", "-shared", "-fPIC", "-o",
                    str(so), str(c_path), "-lm"], check=True, capture_output=True)
    lib = ctypes.CDLL(str(so))
    dp = ctypes.POINTER(ctypes.c_double)
    for f, res, args in (("torque", ctypes.c_double, [dp, dp]), ("prior_torque", None, [dp, dp]),
                         ("potential", ctypes.c_double, [dp]), ("storage", ctypes.c_double, [dp])):
        getattr(lib, f"{stem}_{f}").argtypes = args
        getattr(lib, f"{stem}_{f}").restype = res
    return lib, h_path.read_text()


@pytest.mark.parametrize("with_prior", [True, False])
def test_c_source_with_prior_matches_python(with_prior, tmp_path):
    robot = RobotModel.from_name("panda", [f"panda_joint{i}" for i in range(1, 8)])
    rng = np.random.default_rng(7)
    lo, hi = robot.pin_model.lowerPositionLimit, robot.pin_model.upperPositionLimit
    Z = lo + (hi - lo) * rng.random((300, 7))
    prior = prior_from_robot(robot, payload=(0.5, np.array([0.0, 0.0, 0.2]))) if with_prior else None
    comp = Compensator("curl-free-wendland", Z, rng.normal(size=(300, 7)), 0.3 * (hi - lo), 0.05, prior=prior)
    comp = load_compensator(comp.save(tmp_path / "c.npz"))
    lib, header = _build(comp, tmp_path, "ff")
    assert "#define FF_REGION_RADIUS 1.0" in header and "Valid region" in header
    Q = np.concatenate([Z[:20] + rng.normal(size=(20, 7)) * 0.05, lo + (hi - lo) * rng.random((200, 7))])
    tau_py, rho_py = comp.torque(Q, return_region=True)
    S_py, prior_py = comp.storage(Q), comp.prior_torque(Q)
    assert 0 < np.mean(rho_py < 1) < 1
    dp = ctypes.POINTER(ctypes.c_double)
    out, pout = np.zeros(7), np.zeros(7)
    scale, s_scale = np.abs(tau_py).max(), np.abs(S_py).max()
    for q, t_ref, r_ref, s_ref, p_ref in zip(Q, tau_py, rho_py, S_py, prior_py):
        qc = np.ascontiguousarray(q)
        rho = lib.ff_torque(qc.ctypes.data_as(dp), out.ctypes.data_as(dp))
        lib.ff_prior_torque(qc.ctypes.data_as(dp), pout.ctypes.data_as(dp))
        assert np.max(np.abs(out - t_ref)) < 1e-10 * scale
        assert np.max(np.abs(pout - p_ref)) < 1e-10 * max(scale, 1.0)
        assert abs(rho - r_ref) < 1e-12
        assert abs(lib.ff_storage(qc.ctypes.data_as(dp)) - s_ref) < 1e-10 * s_scale


def test_c_source_on_a_trajectory_support_matches_python(tmp_path):
    """1,000 support points along a random walk (the shape of logged data: the C evaluator's leaf and
    chunk boxes prune most of them), an even joint count (no row padding), queries on the support
    points, near them and far away: the C torque, region distance and storage equal numpy's
    brute force over every support point."""
    rng = np.random.default_rng(11)
    Z = np.cumsum(rng.normal(size=(1000, 6)) * 0.05, axis=0)
    radii = 0.15 * (Z.max(0) - Z.min(0))
    comp = Compensator("curl-free-wendland", Z, rng.normal(size=Z.shape), radii, 0.3)
    lib, _ = _build(comp, tmp_path, "traj")
    Q = np.concatenate([Z[::50], Z[rng.integers(1000, size=200)] + rng.normal(size=(200, 6)) * 0.3 * radii,
                        Z.min(0) - 3 * radii + rng.random((20, 6)) * (Z.max(0) - Z.min(0) + 6 * radii)])
    tau_py, rho_py = comp.torque(Q, return_region=True)
    S_py = comp.storage(Q)
    within = np.sum(np.sum(((Q[:, None] - Z[None]) / radii) ** 2, 2) < 1, 1)
    assert within[:220].mean() > 20 and within.max() < 500 and np.any(within == 0)  # many, not all
    dp = ctypes.POINTER(ctypes.c_double)
    out = np.zeros(6)
    scale, s_scale = np.abs(tau_py).max(), np.abs(S_py).max()
    for q, t_ref, r_ref, s_ref in zip(Q, tau_py, rho_py, S_py):
        qc = np.ascontiguousarray(q)
        rho = lib.traj_torque(qc.ctypes.data_as(dp), out.ctypes.data_as(dp))
        assert np.max(np.abs(out - t_ref)) < 1e-10 * scale
        assert abs(rho - r_ref) < 1e-12
        assert abs(lib.traj_storage(qc.ctypes.data_as(dp)) - s_ref) < 1e-10 * s_scale
    np.testing.assert_array_equal(tau_py[within == 0], 0.0)  # no prior: exactly zero outside


@pytest.mark.parametrize("n,N", [(1, 1), (1, 5), (2, 9), (3, 17)])
def test_c_source_small_supports_match_python(n, N, tmp_path):
    """Supports that leave the C evaluator's leaves and chunks part empty (padding points), odd and
    even joint counts: torque, region distance and potential equal numpy's brute force."""
    rng = np.random.default_rng(n * 100 + N)
    Z = np.cumsum(rng.normal(size=(N, n)) * 0.1, axis=0)
    radii = 0.5 * (Z.max(0) - Z.min(0)) + 0.2
    comp = Compensator("curl-free-wendland", Z, rng.normal(size=Z.shape), radii, 0.7)
    lib, _ = _build(comp, tmp_path, "small")
    Q = np.concatenate([Z, Z + rng.normal(size=Z.shape) * 0.4 * radii, Z.min(0) - 3 * radii + rng.random((30, n))
                        * (Z.max(0) - Z.min(0) + 6 * radii)])
    tau_py, rho_py = comp.torque(Q, return_region=True)
    V_py = comp.potential(Q)
    assert 0 < np.mean(rho_py < 1) < 1
    dp = ctypes.POINTER(ctypes.c_double)
    out = np.zeros(n)
    for q, t_ref, r_ref, v_ref in zip(Q, tau_py, rho_py, V_py):
        qc = np.ascontiguousarray(q)
        rho = lib.small_torque(qc.ctypes.data_as(dp), out.ctypes.data_as(dp))
        assert np.max(np.abs(out - t_ref)) < 1e-10 * np.abs(tau_py).max()
        assert abs(rho - r_ref) < 1e-12
        assert abs(lib.small_potential(qc.ctypes.data_as(dp)) - v_ref) < 1e-10 * np.abs(V_py).max()


def test_neighbour_budget_is_the_largest_scale_that_keeps_it():
    from mmgp.gp.gradient_field import neighbour_limited_scale

    rng = np.random.default_rng(8)
    Z = np.cumsum(rng.normal(size=(300, 5)) * 0.05, axis=0)  # a random walk, like a trajectory
    D = np.linalg.norm(Z[:, None] - Z[None], axis=2)
    for K in (10, 40, 120):
        c = neighbour_limited_scale(Z, K)
        assert np.mean(np.sum(D < c, axis=1)) <= K < np.mean(np.sum(D < c * (1 + 1e-9), axis=1))
    # sparse enough already (only themselves within 1), or a budget above the point count
    assert neighbour_limited_scale(Z * 100, 1) == 1.0 and neighbour_limited_scale(Z, 400) == 1.0
