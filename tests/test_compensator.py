"""Tests of the passive feedforward compensator against independent references.

References: closed-form gravity of a planar 2-link arm (a known potential), scipy quadrature,
scikit-learn's GP regressor, torch autograd double derivatives of the RBF kernel, libm's erf
(math.erf), and a gcc-compiled build of the generated C source.
"""
from __future__ import annotations

import ctypes
import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mmgp.compensator import Compensator, check_passivity, compensator_from_model, load_compensator
from mmgp.compensator.fit import FeedforwardSource
from mmgp.gp.gradient_field import CurlFreeGP, RBFGP, curl_free_kernel_np, curl_free_kernel_torch


class TwoLinkGravity:
    """Stand-in for a trained model: gravity torque of a planar 2-link arm in a vertical plane.

    Potential V(q) = g (m1 c1 + m2 l1) sin q1 + g m2 c2 sin(q1 + q2) (J); torque = grad V (N*m).
    """

    g, m1, m2, l1, c1, c2 = 9.81, 2.0, 1.5, 0.6, 0.3, 0.25

    def __init__(self, n_support=120, seed=0, half_width=1.5):
        rng = np.random.default_rng(seed)
        self.support_q_ = rng.uniform(-half_width, half_width, (n_support, 2))
        self.joint_names_ = ["shoulder", "elbow"]

    def potential(self, q):
        q = np.atleast_2d(q)
        return self.g * ((self.m1 * self.c1 + self.m2 * self.l1) * np.sin(q[:, 0])
                         + self.m2 * self.c2 * np.sin(q[:, 0] + q[:, 1]))

    def nominal_torque(self, q):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        t2 = self.g * self.m2 * self.c2 * np.cos(q[:, 0] + q[:, 1])
        t1 = self.g * (self.m1 * self.c1 + self.m2 * self.l1) * np.cos(q[:, 0]) + t2
        return np.stack([t1, t2], axis=1)


class Pendulum1:
    """Stand-in 1-DOF model: pendulum gravity, a joint spring and a torque offset (N*m)."""

    def __init__(self, n_support=60, seed=1):
        rng = np.random.default_rng(seed)
        self.support_q_ = rng.uniform(-2.0, 2.0, (n_support, 1))
        self.joint_names_ = ["j0"]

    def nominal_torque(self, q):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        return 4.0 * np.sin(q) + 1.5 * (q - 0.3) + 0.7


@pytest.fixture(scope="module")
def arm():
    return TwoLinkGravity()


@pytest.fixture(scope="module")
def comp2(arm):
    return compensator_from_model(arm, max_support=120, seed=0)


@pytest.fixture(scope="module")
def comp1():
    return compensator_from_model(Pendulum1(), seed=0)


# ---------------------------------------------------------------------------------------------
# 1-DOF erf storage
# ---------------------------------------------------------------------------------------------


def test_erf_storage_derivative_equals_gp_mean(comp1):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    assert comp1.kind == "erf-1dof"
    model = Pendulum1()
    q = np.linspace(-2.2, 2.2, 41)[:, None]
    # GP mean from an independent implementation with the same hyperparameters
    kern = (ConstantKernel(comp1.signal_var, "fixed") * RBF(comp1.lengthscales[0], "fixed")
            + WhiteKernel(comp1.info["noise_var"][0], "fixed"))
    Z = comp1.support
    gpr = GaussianProcessRegressor(kern, alpha=1e-300, optimizer=None, normalize_y=False)
    gpr.fit(Z, model.nominal_torque(Z)[:, 0])
    mean = gpr.predict(q)
    tau = comp1.torque(q)[:, 0]
    scale = np.max(np.abs(mean))
    assert np.max(np.abs(tau - mean)) < 1e-7 * scale
    # derivative of the erf storage, 4th-order central differences
    h = 1e-3
    S = [comp1.storage(q + c * h) for c in (-2, -1, 1, 2)]
    fd = (S[0] - 8 * S[1] + 8 * S[2] - S[3]) / (12 * h)
    assert np.max(np.abs(fd - tau)) < 1e-8 * scale


def test_erf_storage_is_the_integral(comp1):
    from scipy.integrate import quad

    f = lambda x: float(comp1.torque(np.array([x]))[0])
    for a, b in [(-1.9, 1.7), (0.2, -0.4), (-3.0, 3.5)]:
        ref, _ = quad(f, a, b, epsabs=1e-12, epsrel=1e-12, limit=200)
        assert comp1.storage(np.array([b])) - comp1.storage(np.array([a])) == pytest.approx(ref, abs=1e-9)
    # the Haninger (2016) form, erf of the squared distance, is not the integral: its derivative
    # is far from the torque, which rules out a sign/scale slip going unnoticed here
    z, w, l, s2 = comp1.support[:, 0], comp1.weights[:, 0], comp1.lengthscales[0], comp1.signal_var
    wrong = lambda x: np.sum(w * s2 * l * math.sqrt(math.pi / 2) * np.array(
        [math.erf((x - zi) ** 2 / (2 * l * l)) for zi in z]))
    fd_wrong = (wrong(0.5 + 1e-5) - wrong(0.5 - 1e-5)) / 2e-5
    assert abs(fd_wrong - f(0.5)) > 1e-2 * abs(f(0.5))


def test_erf_storage_bounds_hold(comp1):
    q = np.concatenate([np.linspace(-30, 30, 20001), [-1e6, 1e6]])[:, None]
    V = comp1.potential(q)
    assert V.min() >= comp1.potential_lower_bound
    assert V.max() <= comp1.potential_upper_bound
    assert comp1.storage(q).min() >= 0.0
    # the bound is not absurdly loose: within a few J of the sampled range
    assert comp1.potential_lower_bound > V.min() - 0.05 * (V.max() - V.min()) - 1.0


# ---------------------------------------------------------------------------------------------
# curl-free GP: closed form vs autograd brute force
# ---------------------------------------------------------------------------------------------


def _autograd_blocks(X1, X2, l, s2):
    """cov(dV/dx_i(x_a), dV/dx'_j(x_b)) = d^2 k / dx_i dx'_j by torch autograd (no closed form)."""
    import torch

    lt = torch.tensor(l, dtype=torch.float64)

    def k(x, xp):
        return s2 * torch.exp(-0.5 * (((x - xp) / lt) ** 2).sum())

    N1, n = X1.shape
    N2 = X2.shape[0]
    K = np.zeros((N1 * n, N2 * n))
    for a in range(N1):
        for b in range(N2):
            x = torch.tensor(X1[a], dtype=torch.float64)
            xp = torch.tensor(X2[b], dtype=torch.float64)
            H = torch.autograd.functional.hessian(k, (x, xp))
            K[a * n:(a + 1) * n, b * n:(b + 1) * n] = H[0][1].numpy()
    return K


def test_curl_free_kernel_matches_autograd():
    import torch

    rng = np.random.default_rng(3)
    X1, X2 = rng.normal(size=(5, 3)), rng.normal(size=(4, 3))
    l, s2 = np.array([0.7, 1.3, 0.9]), 2.5
    ref = _autograd_blocks(X1, X2, l, s2)
    assert np.max(np.abs(curl_free_kernel_np(X1, X2, l, s2) - ref)) < 1e-13 * np.max(np.abs(ref))
    Kt = curl_free_kernel_torch(torch.tensor(X1), torch.tensor(X2), torch.log(torch.tensor(l)),
                                 torch.log(torch.tensor(s2, dtype=torch.float64))).numpy()
    assert np.max(np.abs(Kt - ref)) < 1e-13 * np.max(np.abs(ref))


def test_curl_free_prediction_matches_brute_force():
    import torch

    rng = np.random.default_rng(4)
    Q = rng.uniform(-1, 1, (25, 3))
    Y = np.stack([np.cos(Q[:, 0]) + Q[:, 1], Q[:, 0] + 0.5 * np.sin(Q[:, 2]), 0.3 * Q[:, 2]], 1)
    gp = CurlFreeGP(max_hyper_points=25, max_iter=20).fit(Q, Y)
    comp = Compensator("curl-free-rbf", gp.support_, gp.alpha_, gp.lengthscales_, gp.signal_var_)
    l, s2 = gp.lengthscales_, gp.signal_var_
    # brute force: autograd kernel blocks, a dense solve, autograd cross-covariance and gradient
    K = _autograd_blocks(Q, Q, l, s2) + np.diag(np.tile(gp.noise_var_, Q.shape[0]))
    alpha = torch.tensor(np.linalg.solve(K, Y.reshape(-1)))
    lt = torch.tensor(l)
    Zt = torch.tensor(Q)
    for q in rng.uniform(-1.3, 1.3, (6, 3)):
        qt = torch.tensor(q, requires_grad=True)
        zt = Zt.clone().requires_grad_(True)
        k = s2 * torch.exp(-0.5 * (((qt[None] - zt) / lt) ** 2).sum(1))
        # cov(V(q), dV/dz_bj) = dk(q, z_b)/dz_bj
        (dk_dz,) = torch.autograd.grad(k.sum(), zt, create_graph=True)
        V = (dk_dz.reshape(-1) * alpha).sum()
        (tau,) = torch.autograd.grad(V, qt)
        assert comp.potential(q) == pytest.approx(float(V.detach()), rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(comp.torque(q), tau.numpy(), rtol=1e-9, atol=1e-12)
    # RKHS norm used by the rigorous bound: alpha^T K_dd alpha from the brute-force matrix
    Kdd = _autograd_blocks(Q, Q, l, s2)
    a = gp.alpha_.reshape(-1)
    B_ref = math.sqrt(s2 * float(a @ Kdd @ a))
    assert comp.bound_info["rkhs_bound"] == pytest.approx(B_ref, rel=1e-8)


# ---------------------------------------------------------------------------------------------
# multi-joint passivity on the 2-link arm
# ---------------------------------------------------------------------------------------------


def test_two_link_accuracy_and_passivity(arm, comp2):
    assert comp2.kind == "curl-free-rbf"
    assert comp2.joint_names == ["shoulder", "elbow"]
    rng = np.random.default_rng(7)
    Qt = rng.uniform(-1.4, 1.4, (400, 2))
    ref = arm.nominal_torque(Qt)
    err = comp2.torque(Qt) - ref
    assert np.sqrt(np.mean(err ** 2)) < 1e-3 * np.sqrt(np.mean(ref ** 2))
    # the learned potential matches the true one up to a constant
    dV = comp2.potential(Qt) - arm.potential(Qt)
    assert np.std(dV) < 1e-3 * np.std(arm.potential(Qt))
    res = check_passivity(comp2, n_configs=100, n_loops=30, seed=1)
    assert res["passed"], res
    assert res["loop_max_rel_work"] < 1e-9
    assert res["grad_max_rel_err"] < 1e-6


def test_multi_joint_loop_integrals_vanish(comp2):
    """Work of tau_ff around hand-built loops (Gauss-Legendre on each edge of a polygon)."""
    x, w = np.polynomial.legendre.leggauss(40)
    rng = np.random.default_rng(11)
    scale = np.max(np.abs(comp2.torque(comp2.support)))
    for _ in range(10):
        P = rng.uniform(-1.4, 1.4, (5, 2))
        P = np.vstack([P, P[:1]])
        W = 0.0
        for a, b in zip(P[:-1], P[1:]):
            s = 0.5 * (x + 1)
            q = a + s[:, None] * (b - a)
            W += 0.5 * np.sum(w * (comp2.torque(q) @ (b - a)))
        assert abs(W) < 1e-9 * scale


def test_storage_rigorous_bound(comp2):
    rng = np.random.default_rng(5)
    Q = np.concatenate([rng.uniform(-1.5, 1.5, (3000, 2)), rng.uniform(-20, 20, (3000, 2))])
    V = comp2.potential(Q)
    B = comp2.potential_bound
    assert np.all(np.abs(V) <= B)
    assert np.all(comp2.storage(Q) >= 0)
    assert comp2.storage_sampled_min >= 0
    assert B <= comp2.bound_info["triangle_bound"]
    # far from the data the feedforward fades out (no learned torque where nothing was seen)
    assert np.max(np.abs(comp2.torque(np.array([[40.0, -35.0]])))) < 1e-8


def test_non_conservative_fields_fail(arm):
    A = np.array([[1.0, 2.0], [-1.0, 1.0]])

    class Linear:
        bounds = np.array([[-1.0, -1.0], [1.0, 1.0]])

        def torque(self, q):
            return np.asarray(q) @ A.T

        def storage(self, q):  # a candidate: the potential of the symmetric part
            q = np.asarray(q)
            return 0.5 * np.einsum("...i,ij,...j->...", q, 0.5 * (A + A.T), q)

    res = check_passivity(Linear(), n_configs=50, n_loops=20)
    assert not res["passed"] and not res["loop_pass"]
    # loop work of A q around a loop is (A21 - A12) * area: far above any tolerance
    assert res["loop_max_rel_work"] > 1e-3

    # per-joint GPs fitted to a conservative field: their mixed partials differ slightly, which the
    # loop test must catch (the storage candidate does not matter for it)
    Q = arm.support_q_
    gps = [RBFGP(max_hyper_points=120, max_iter=40).fit(Q, arm.nominal_torque(Q)[:, i]) for i in range(2)]

    class PerJoint:
        bounds = np.stack([Q.min(0), Q.max(0)])

        def torque(self, q):
            return np.stack([g.predict(np.atleast_2d(q)) for g in gps], axis=1).reshape(np.shape(q))

        def storage(self, q):
            return np.zeros(np.atleast_2d(q).shape[0])

    res = check_passivity(PerJoint(), n_configs=50, n_loops=20)
    assert not res["loop_pass"] and not res["passed"], res
    assert res["loop_max_rel_work"] > 1e-7

    # the checker is not failing everything: the exact analytic field and potential pass
    class Exact:
        bounds = np.array([[-1.5, -1.5], [1.5, 1.5]])
        torque = staticmethod(arm.nominal_torque)

        def storage(self, q):
            return arm.potential(q) + 20.0

    assert check_passivity(Exact(), n_configs=50, n_loops=20)["passed"]


# ---------------------------------------------------------------------------------------------
# export: file round trip, numpy-only loading, C source
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_save_load_roundtrip(comp2, comp1, tmp_path, suffix):
    rng = np.random.default_rng(2)
    for comp in (comp2, comp1):
        p = comp.save(tmp_path / f"c{comp.n_joints}{suffix}")
        back = load_compensator(p)
        Q = rng.uniform(-2, 2, (50, comp.n_joints))
        np.testing.assert_array_equal(back.torque(Q), comp.torque(Q))
        np.testing.assert_array_equal(back.storage(Q), comp.storage(Q))
        assert back.joint_names == comp.joint_names and back.kind == comp.kind
        # shapes of the contract
        assert back.torque(Q[0]).shape == (comp.n_joints,)
        assert isinstance(back.storage(Q[0]), float)
        assert back.storage(Q).shape == (50,)


def test_file_header_and_version_errors(comp2, tmp_path):
    p = comp2.save(tmp_path / "c.json")
    d = json.loads(p.read_text())
    assert d["format"] == "mmgp-compensator" and d["version"] == 1 and d["kind"] == "curl-free-rbf"
    d["version"] = 2
    (tmp_path / "v2.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="version 2"):
        load_compensator(tmp_path / "v2.json")
    d["version"] = 1
    d["weights"][0][0] *= 3.0  # tampered weights no longer match the recorded storage offset
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="storage_offset"):
        load_compensator(tmp_path / "bad.json")


_BLOCKED_RUN = """
import importlib.abc, os, sys
BLOCKED = ("torch", "scipy", "pinocchio")

class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is blocked in this test")
        return None

if os.environ.get("BLOCK_IMPORTS") == "1":
    sys.meta_path.insert(0, Refuse())
import numpy as np
import mmgp.compensator.field as field
out = []
for p in sys.argv[1:]:
    c = field.load_compensator(p)
    q = np.linspace(-1.0, 1.0, 5 * c.n_joints).reshape(5, c.n_joints)
    out += list(c.torque(q).ravel()) + list(c.storage(q)) + [c.potential(q[0])]
print(repr(out))
print(sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED))
"""


def test_evaluator_runs_with_torch_scipy_and_pinocchio_blocked(comp2, comp1, tmp_path):
    paths = [str(comp2.save(tmp_path / "c2.npz")), str(comp1.save(tmp_path / "c1.json"))]
    ref = []
    for c in (comp2, comp1):
        q = np.linspace(-1.0, 1.0, 5 * c.n_joints).reshape(5, c.n_joints)
        ref += list(c.torque(q).ravel()) + list(c.storage(q)) + [c.potential(q[0])]
    # blocked: loading and evaluating work without them; not blocked: nothing imports them anyway
    for block in ("1", "0"):
        out = subprocess.run([sys.executable, "-c", _BLOCKED_RUN, *paths], capture_output=True, text=True, check=True,
                             env={**os.environ, "BLOCK_IMPORTS": block})
        values, modules = out.stdout.strip().splitlines()
        assert modules == "[]"
        np.testing.assert_array_equal(np.array(eval(values)), np.array(ref))


def test_erf_matches_libm():
    from mmgp.compensator.field import _erf

    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(size=20000) * 3, rng.uniform(-7, 7, 20000), 10.0 ** rng.uniform(-300, 0.8, 5000),
                        [0.0, -0.0, 5e-324, 0.125, 0.1875, 1.0, 5.93, 6.0, -6.0, 50.0, np.inf, -np.inf]])
    ref = np.array([math.erf(v) for v in x])
    got = _erf(x.reshape(-1, 4)).ravel()  # any shape
    assert np.all(np.abs(got - ref) <= 2 * np.spacing(np.abs(ref)))
    assert np.isnan(_erf(np.array([np.nan]))[0])


def test_models_need_only_the_feedforward_protocol():
    assert isinstance(TwoLinkGravity(), FeedforwardSource) and isinstance(Pendulum1(), FeedforwardSource)

    class NoNames:  # joint_names_ is optional
        support_q_ = np.random.default_rng(0).uniform(-1, 1, (30, 1))

        def nominal_torque(self, q):
            return 2.0 * np.cos(q)

    comp = compensator_from_model(NoNames(), seed=0)
    assert comp.joint_names == ["q_0"]
    q = np.linspace(-0.9, 0.9, 50)[:, None]
    np.testing.assert_allclose(comp.torque(q), 2.0 * np.cos(q), atol=1e-3)
    with pytest.raises(ValueError, match="support_q_"):
        compensator_from_model(type("Bad", (), {"support_q_": np.zeros(3), "nominal_torque": NoNames.nominal_torque})())


def _build_c(comp, tmp_path, stem):
    gcc = shutil.which("gcc")
    assert gcc is not None, "gcc is required to test the generated C source"
    c_path, h_path = comp.write_c(tmp_path / stem)
    so = tmp_path / f"lib{stem}.so"
    subprocess.run([gcc, "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror", "-shared",
                    "-fPIC", "-o", str(so), str(c_path), "-lm"], check=True, capture_output=True)
    lib = ctypes.CDLL(str(so))
    dp = ctypes.POINTER(ctypes.c_double)
    getattr(lib, f"{stem}_torque").argtypes = [dp, dp]
    getattr(lib, f"{stem}_torque").restype = None
    for f in ("storage", "potential"):
        getattr(lib, f"{stem}_{f}").argtypes = [dp]
        getattr(lib, f"{stem}_{f}").restype = ctypes.c_double
    return lib, h_path


@pytest.mark.parametrize("which", ["comp2", "comp1"])
def test_c_source_matches_python(which, request, tmp_path):
    comp = request.getfixturevalue(which)
    stem = f"ff_{which}"
    lib, h_path = _build_c(comp, tmp_path, stem)
    assert f"#define FF_{which.upper()}_N_JOINTS {comp.n_joints}" in h_path.read_text()
    n = comp.n_joints
    rng = np.random.default_rng(9)
    Q = np.concatenate([rng.uniform(-2.5, 2.5, (200, n)), comp.support[:5]])
    tau_py, S_py = comp.torque(Q), comp.storage(Q)
    tau_scale = max(1.0, np.max(np.abs(tau_py)))
    S_scale = max(1.0, np.max(np.abs(S_py)))
    out = np.zeros(n)
    dp = ctypes.POINTER(ctypes.c_double)
    for q, t_ref, s_ref in zip(Q, tau_py, S_py):
        qc = np.ascontiguousarray(q)
        getattr(lib, f"{stem}_torque")(qc.ctypes.data_as(dp), out.ctypes.data_as(dp))
        assert np.max(np.abs(out - t_ref)) < 1e-10 * tau_scale
        s = getattr(lib, f"{stem}_storage")(qc.ctypes.data_as(dp))
        assert abs(s - s_ref) < 1e-10 * S_scale
