"""Physical mean bases of the modes (mmgp.model mean_basis, mmgp.em.fit_basis_coefficients).

References: Pinocchio's own dynamics of the Panda with a payload added to its model (a different
code path from the regressor), and the trained model reloaded from disk.
"""
from __future__ import annotations

import numpy as np
import pytest

from mmgp.data.regression import fit_basis_coefficients, fit_shared_coefficients
from mmgp.errors import InputError
from mmgp import MultimodalGP
from mmgp.labelling.features import MeanBasis, resolve_mean_basis
from mmgp.physics.robot import load_robot
import mmgp
from mmgp.sim import panda_modes

PANDA7 = [f"panda_joint{i}" for i in range(1, 8)]


def _states(rng, robot, T):
    lo, hi = robot.pin_model.lowerPositionLimit[:7], robot.pin_model.upperPositionLimit[:7]
    return (lo + (hi - lo) * rng.random((T, 7)), rng.normal(scale=0.5, size=(T, 7)),
            rng.normal(scale=1.0, size=(T, 7)))


def test_rbd_basis_learns_a_payload_that_extrapolates_exactly():
    """Torque of a 2 kg payload = Pinocchio with the payload minus without. Coefficients fitted on
    states in one half of the joint-1 range predict the other half to numerical precision."""
    robot = load_robot("panda", joint_names=PANDA7)
    heavy = robot.add_payload("panda_link8", 2.0, [0.01, -0.02, 0.12])
    rng = np.random.default_rng(0)
    q, dq, ddq = _states(rng, robot, 600)
    payload = heavy.rnea(q, dq, ddq) - robot.rnea(q, dq, ddq)
    basis = robot.regressor(q, dq, ddq)
    train_rows, test_rows = q[:, 0] < 0.0, q[:, 0] >= 0.0
    coef = fit_basis_coefficients(basis[train_rows], payload[train_rows])
    pred = np.einsum("tjp,jp->tj", basis[test_rows], coef)
    scale = np.abs(payload[test_rows]).max()
    np.testing.assert_allclose(pred, payload[test_rows], atol=1e-6 * scale)


def test_shared_payload_coefficients_extrapolate_and_match_stacked_least_squares():
    """A payload loads every joint through the same 10 parameters of the distal body: one shared
    vector fitted on half of the joint-1 range predicts the other half exactly, and a single
    IRLS pass is the stacked weighted least squares (rows scaled by each joint's spread)."""
    robot = load_robot("panda", joint_names=PANDA7)
    heavy = robot.add_payload("panda_link8", 2.0, [0.01, -0.02, 0.12])
    rng = np.random.default_rng(1)
    q, dq, ddq = _states(rng, robot, 500)
    payload = heavy.rnea(q, dq, ddq) - robot.rnea(q, dq, ddq)
    basis = robot.regressor(q, dq, ddq)[..., -10:]
    tr, te = q[:, 0] < 0.0, q[:, 0] >= 0.0
    coef = fit_shared_coefficients(basis[tr], payload[tr])
    assert coef.shape == (7, 10) and np.all(coef == coef[0])
    pred = np.einsum("tjp,jp->tj", basis[te], coef)
    np.testing.assert_allclose(pred, payload[te], atol=1e-6 * np.abs(payload[te]).max())
    noisy = payload + rng.normal(scale=0.05, size=payload.shape)
    one = fit_shared_coefficients(basis, noisy, n_irls=1)[0]
    s = noisy.std(0)
    ref, *_ = np.linalg.lstsq((basis / s[None, :, None]).reshape(-1, 10), (noisy / s).ravel(), rcond=None)
    np.testing.assert_allclose(basis.reshape(-1, 10) @ one, basis.reshape(-1, 10) @ ref, atol=1e-8)


def test_mean_basis_resolution():
    robot = object()
    assert resolve_mean_basis("auto", robot, "residual") == MeanBasis("payload")
    assert resolve_mean_basis("rbd", robot, "residual") == MeanBasis("rbd")
    assert resolve_mean_basis("auto", None, "residual") is None
    assert resolve_mean_basis("auto", robot, "feature") is None
    assert resolve_mean_basis("none", robot, "residual") is None
    assert resolve_mean_basis("payload", robot, "residual", friction=True) == MeanBasis("payload", friction=True)
    with pytest.raises(InputError, match="rbd"):
        resolve_mean_basis("rbd", None, "residual")
    with pytest.raises(InputError, match="mean_basis"):
        MultimodalGP(mean_basis="linear").fit(t=np.arange(20) * 0.01, q=np.zeros((20, 1)), tau=np.zeros((20, 1)))


def test_mean_basis_names_round_trip_and_others_are_refused():
    every = [MeanBasis(body, friction=f) for body in ("rbd", "payload") for f in (False, True)]
    assert [b.name for b in every] == ["rbd", "rbd+friction", "payload", "payload+friction"]
    assert all(MeanBasis.parse(b.name) == b for b in every) and MeanBasis.parse(None) is None
    assert [b.shared for b in every] == [False, False, True, True]
    assert [b.n_dry(7) for b in every] == [0, 14, 0, 14]
    for bad in ("linear", "payload+viscous", "rbd+", "none", ""):
        with pytest.raises(ValueError):
            MeanBasis.parse(bad)


def test_mean_basis_columns_are_the_regressor_and_the_closed_form_friction_columns():
    robot = mmgp.load_robot(robot="panda")
    n = robot.n_joints
    rng = np.random.default_rng(2)
    q, dq, ddq = (rng.normal(size=(9, n)) for _ in range(3))
    tau_rbd, sign = robot.rnea(q, dq, ddq), np.sign(rng.normal(size=(9, n)))
    Y = robot.regressor(q, dq, ddq)
    np.testing.assert_array_equal(MeanBasis("rbd").columns(robot, q, dq, ddq, tau_rbd, None), Y)
    B = MeanBasis("payload", friction=True).columns(robot, q, dq, ddq, tau_rbd, sign)
    assert B.shape == (9, n, 10 + 2 * n)
    np.testing.assert_array_equal(B[..., :10], Y[..., -10:])
    for j in range(n):   # column 10 + j: Coulomb of joint j; 10 + n + j: its load-dependent friction
        want_c, want_l = np.zeros((9, n)), np.zeros((9, n))
        want_c[:, j], want_l[:, j] = sign[:, j], sign[:, j] * np.abs(tau_rbd[:, j])
        np.testing.assert_array_equal(B[:, :, 10 + j], want_c)
        np.testing.assert_array_equal(B[:, :, 10 + n + j], want_l)


def test_trained_payload_model_round_trips_through_disk(tmp_path):
    rec = panda_modes(seed=3, n_samples=400)
    log = tmp_path / "panda.parquet"
    rec.write(log)
    robot = load_robot(log_path=log)
    model = MultimodalGP(robot=robot, max_sweeps=3, min_sweeps=2, average_last=1, fit_iter=8, fit_points=150,
                         max_support=200).fit(log)
    # the payload's 10 inertial parameters (7-10 identifiable) and 2 friction levels per joint (rest_band)
    assert model.report_["mean_basis"]["kind"] == "payload+friction"
    assert 7 + 2 * 7 <= model.report_["mean_basis"]["rank"] <= 10 + 2 * 7
    model.save(tmp_path)
    back = MultimodalGP.load(tmp_path)
    assert back.mean_basis_.name == "payload+friction"
    np.testing.assert_array_equal(back.basis_coef_[0], model.basis_coef_[0])
    rows = slice(20, 90)   # after the start transient, before the first push (t >= 1 s)
    q, dq, ddq = rec.q[rows], rec.info["dq_true"][rows], rec.info["ddq_true"][rows]
    m1, s1 = model.predict(q, dq, ddq)
    m2, s2 = back.predict(q, dq, ddq)
    np.testing.assert_allclose(m2, m1, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(s2, s1, rtol=1e-10, atol=1e-12)
    # The model carries the rigid body and the basis: undisturbed torques are matched far below
    # their spread.
    assert rec.info["tau_push"][rows].max() == 0.0
    err = m1 - rec.info["tau_true"][rows]
    assert np.sqrt(np.mean(err ** 2)) < 0.05 * rec.info["tau_true"][rows].std()


def test_robust_regression_solves_its_estimating_equations_and_ignores_outliers():
    """The diagnosis's whole-library fit (coefficients shared by all outputs, masked equations,
    Huber then Tukey steps, Gram solves): at convergence the coefficients solve the Tukey
    M-estimating equations sum_t w(r_tj / (k s_j)) r_tj A_tj = 0 with the final residuals'
    MAD scale; gross outliers (pushes) get weight zero, so the fit agrees with least squares on
    the clean equations alone."""
    from mmgp.data.regression import TUKEY_K, robust_regression

    rng = np.random.default_rng(7)
    N, n, p = 600, 3, 4
    A = rng.normal(size=(N, n, p))
    truth = np.array([0.5, -1.0, 2.0, 0.3])
    Y = A @ truth + 0.05 * rng.normal(size=(N, n))
    pushed = np.zeros((N, n), bool)
    pushed[100:130] = True
    Y[pushed] += 20.0
    mask = (rng.uniform(size=(N, n)) > 0.2).astype(float)
    fit = robust_regression(A, Y, mask=mask, huber_steps=50, tukey_steps=50, tol=1e-12, centre=False, solver="gram")
    r = Y - A @ fit.coef
    s = np.array([1.4826 * np.median(np.abs(r[mask[:, j] > 0, j])) for j in range(n)])
    u = np.abs(r) / (TUKEY_K * s)
    w = mask * np.where(u < 1, (1 - u ** 2) ** 2, 0.0)
    score = np.einsum("tj,tj,tjp->p", w, r, A)
    assert np.abs(score).max() < 1e-5 * np.abs(np.einsum("tj,tjp->p", w * np.abs(r), np.abs(A))).max()
    assert (fit.weights[pushed] == 0).all()
    clean = (mask > 0) & ~pushed
    ols, *_ = np.linalg.lstsq(A[clean], Y[clean], rcond=None)
    se = 0.05 / np.sqrt(clean.sum())
    np.testing.assert_allclose(fit.coef, ols, atol=5 * se * np.sqrt(p))
