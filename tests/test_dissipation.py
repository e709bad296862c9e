"""Friction dissipates (mmgp.models.dissipation): the premise (Pinocchio: the rigid-body torque
and its regressor are even in the joint velocities), the odd part of a GP against the friction
it was trained on (closed form), the energy check on dissipative and energy-injecting friction,
and the refit on a MuJoCo replica whose first fit took pushes for friction."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mmgp.gp.exact import ExactGP
from mmgp.models.dissipation import VelocityReversal, energy_check, injecting_samples, odd_part
from mmgp.physics.robot import RobotModel


def test_rigid_body_torque_and_regressor_are_even_in_velocity():
    robot = RobotModel.from_name("panda", n_joints=7)
    rng = np.random.default_rng(0)
    q, dq, ddq = rng.uniform(-1.5, 1.5, (30, 7)), rng.normal(size=(30, 7)), rng.normal(size=(30, 7))
    np.testing.assert_allclose(robot.rnea(q, -dq, ddq), robot.rnea(q, dq, ddq), atol=1e-9)
    np.testing.assert_allclose(robot.regressor(q, -dq, ddq), robot.regressor(q, dq, ddq), atol=1e-9)
    # ... while friction is not: the velocity terms matter (the check is not vacuous)
    assert np.abs(robot.rnea(q, dq, ddq) - robot.rnea(q, 0 * dq, ddq)).max() > 0.1


def _lever(friction_sign: float, T: int = 400, seed: int = 0, level: float = 0.4, noise: float = 0.01):
    """A 1-DOF lever's inputs [q, dq, ddq, tanh(dq / 0.05)] and torque 2 cos q + s 0.4 tanh(dq / 0.05)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 40, T)
    q = 0.8 * np.sin(0.5 * t) + 0.3 * np.sin(1.3 * t)
    dq = 0.4 * np.cos(0.5 * t) + 0.39 * np.cos(1.3 * t)
    ddq = -0.2 * np.sin(0.5 * t) - 0.507 * np.sin(1.3 * t)
    sign = np.tanh(dq / 0.05)
    X = np.column_stack([q, dq, ddq, sign])
    y = 2.0 * np.cos(q) + friction_sign * level * sign + noise * rng.standard_normal(T)
    return X, y[:, None]


REV = VelocityReversal(dq_cols=[1], flip_cols=[1, 3])


def test_odd_part_is_the_friction_the_gp_learnt():
    X, Y = _lever(+1.0)
    gp = ExactGP(seed=0).fit(X, Y)
    odd = odd_part(gp, None, X, None, REV)
    sliding = np.abs(X[:, 1]) > 0.1
    np.testing.assert_allclose(odd[sliding, 0], 0.4 * np.tanh(X[sliding, 1] / 0.05), atol=0.05)


def test_odd_part_adds_the_basis_friction_columns():
    X, Y = _lever(+1.0)
    gp = ExactGP(seed=0).fit(X, np.zeros_like(Y) + 0.01 * np.random.default_rng(1).standard_normal(Y.shape))
    basis = np.stack([np.cos(X[:, 0]), X[:, 3]], axis=1)[:, None, :]      # (T, 1, 2): gravity, Coulomb
    coef = np.array([[2.0, 0.3]])
    rev = VelocityReversal(dq_cols=[1], flip_cols=[1, 3], odd_basis=1)
    odd = odd_part(gp, coef, X, basis, rev)
    np.testing.assert_allclose(odd[:, 0], 0.3 * X[:, 3], atol=0.02)


def _fitted(friction_sign: float, **lever):
    X, Y = _lever(friction_sign, **lever)
    T = len(Y)
    return X, SimpleNamespace(gps_=[ExactGP(seed=0).fit(X, Y)], coef_=[None], labels_=np.zeros(T, int),
                              disturbed_=np.zeros(T, bool), support_X_=[X], support_Y_=[Y])


def test_variance_gp_on_fewer_samples_bounds_the_full_one():
    # Conditioning on a subset never shrinks the posterior variance (the check's spread errs large).
    from mmgp.models import dissipation

    X, good = _fitted(+1.0)
    old = dissipation.VARIANCE_SUPPORT
    try:
        dissipation.VARIANCE_SUPPORT = 100
        small = dissipation._variance_gp(good, 0)
    finally:
        dissipation.VARIANCE_SUPPORT = old
    assert len(small.Xs_) == 100
    _, sd_full = good.gps_[0].predict(X, include_noise=False)
    _, sd_small = small.predict(X, include_noise=False)
    assert (np.asarray(sd_small) >= np.asarray(sd_full) - 1e-9).all()


def test_energy_check_passes_dissipative_friction_and_catches_injected_energy():
    X, good = _fitted(+1.0)
    ok = energy_check(good, X, None, REV)
    assert ok["physical"] and ok["worst"] < 0.01 and ok["work_share"][0][0] < 0.01
    X, bad = _fitted(-1.0)
    wrong = energy_check(bad, X, None, REV)
    assert not wrong["physical"] and wrong["worst"] > 0.9 and wrong["work_share"][0][0] > 0.99
    flips = injecting_samples(bad, X, None, REV)
    sliding = np.abs(X[:, 1]) > 0.1
    assert flips[sliding].mean() > 0.9 and not injecting_samples(good, X, None, REV).any()


def test_injection_within_what_the_model_cannot_explain_is_not_called_physics():
    """Friction of the wrong sign at 0.02 N*m under 0.1 N*m of noise: the GP learns it with a
    latent spread far below 0.02 (400 samples), so against the latent spread alone most sliding
    samples would 'inject'; against the predictive spread (noise included, ~0.1) none does. At
    0.4 N*m (4x the noise) the check fires either way."""
    from mmgp.models.dissipation import _odd_z, _sliding

    X, faint = _fitted(-1.0, level=0.02, noise=0.1)
    dq, sliding = _sliding(X, REV)
    rows = np.flatnonzero(sliding[:, 0])
    _, z_latent = _odd_z(faint, 0, rows, X, None, REV, dq, with_noise=False)
    assert np.mean(z_latent[:, 0] < -2) > 0.3
    assert energy_check(faint, X, None, REV)["physical"]
    X, strong = _fitted(-1.0, level=0.4, noise=0.1)
    assert not energy_check(strong, X, None, REV)["physical"]


def test_a_first_fit_that_injects_energy_is_not_returned():
    from mmgp import MultimodalGP
    from mmgp.evaluation.metrics import classification_figures
    from mmgp.sim import actuator_replica

    # Replica seed 6: from the default start the EM takes pushes that oppose the motion for
    # friction (its friction injects energy on 39% of the sliding samples; 0.858 / 0.390).
    rec = actuator_replica(seed=6)
    model = MultimodalGP().fit(t=rec.t, q=rec.q, tau=rec.tau)
    d = model.report_["dissipation"]
    assert not d["fits"][0]["physical"] and d["fits"][0]["worst"] > 0.2
    assert d["chosen"] > 0 and d["physical"] and d["runner_up_gap"] > 0
    f = classification_figures(model.labels_, rec.labels)
    assert f["unperturbed_correct"] >= 0.95 and f["perturbed_missed"] <= 0.05


def test_effective_sample_size_matches_the_ar1_closed_form():
    from mmgp.models.dissipation import effective_sample_size

    rng = np.random.default_rng(3)
    n = 20000
    for rho in (0.0, 0.5, 0.9):
        e = rng.standard_normal(n)
        x = np.empty(n)
        x[0] = e[0]
        for t in range(1, n):
            x[t] = rho * x[t - 1] + np.sqrt(1 - rho ** 2) * e[t]
        expected = n * (1 - rho) / (1 + rho)
        assert abs(effective_sample_size(x) - expected) < 0.15 * expected
    assert effective_sample_size(np.ones(50)) == 1.0


def _ar1(rng, n, rho):
    x = np.empty(n)
    x[0] = rng.standard_normal()
    for t in range(1, n):
        x[t] = rho * x[t - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal()
    return x


def test_depth_test_is_calibrated_on_dissipative_series_and_ignores_a_lone_glitch():
    """Monte Carlo: z-scores of a model exactly at the dissipation boundary (zero-mean, unit
    spread; white and strongly correlated) reject at most about as often as the level says."""
    from mmgp.models.dissipation import depth_p_value, effective_sample_size

    rng = np.random.default_rng(4)
    for rho in (0.0, 0.95):
        ps = []
        for _ in range(300):
            z = _ar1(rng, 600, rho)
            ps.append(depth_p_value(z, effective_sample_size(z)))
        assert np.mean(np.array(ps) < 0.05) <= 0.08
    z = rng.standard_normal(600)
    z[300] = -15.0                                   # one sample at a log's edge
    assert depth_p_value(z, effective_sample_size(z)) > 0.05


def test_depth_test_finds_a_region_whose_friction_injects_energy():
    # The replica's wrong basin: 30 consecutive samples at -5 standard deviations among
    # dissipative ones (z around +3).
    from mmgp.models.dissipation import depth_p_value, effective_sample_size

    rng = np.random.default_rng(5)
    z = 3.0 + 0.3 * _ar1(rng, 300, 0.9)
    z[100:130] = -5.0 + 0.3 * rng.standard_normal(30)
    assert depth_p_value(z, effective_sample_size(z)) < 1e-3
