"""Friction dissipates (mmgp.labelling.dissipation): the premise (Pinocchio: the rigid-body torque
and its regressor are even in the joint velocities), the odd part of a GP against the friction
it was trained on (closed form), the energy check on dissipative and energy-injecting friction,
and the refit on a MuJoCo replica whose first fit took pushes for friction."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mmgp.gp.exact import ExactGP
from mmgp.labelling.dissipation import VelocityReversal, energy_check, injecting_samples, odd_part
from mmgp.labelling.mstep import Start
from mmgp.labelling.settings import EMSettings
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
    from mmgp.labelling import dissipation

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
    from mmgp.labelling.dissipation import _odd_z, _sliding

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
    from mmgp.labelling.dissipation import effective_sample_size

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
    from mmgp.labelling.dissipation import depth_p_value, effective_sample_size

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
    from mmgp.labelling.dissipation import depth_p_value, effective_sample_size

    rng = np.random.default_rng(5)
    z = 3.0 + 0.3 * _ar1(rng, 300, 0.9)
    z[100:130] = -5.0 + 0.3 * rng.standard_normal(30)
    assert depth_p_value(z, effective_sample_size(z)) < 1e-3


START_LABEL = {"stuck-aware": 0, "every-sample": 1}


class _StubSEM:
    """What fit_dissipative reads off a fitted MultimodalSEM, with a chosen evidence."""

    n_modes, settings = 1, EMSettings()

    def __init__(self, evidence: dict):
        self.evidence = evidence

    def fit(self, X, Y, *, start="stuck-aware", init_states=None, **kw):
        begun = start if isinstance(start, Start) else self.begin(X, Y, start=start)
        self.start_ = None if init_states is not None else begun.name
        self.other_start_ = True
        self.log_marginal_ = self.evidence[self.start_ or "swapped labels"]
        self.trace_, self.labels_, self.disturbed_ = [object()], np.zeros(len(Y), int), np.zeros(len(Y), bool)
        self.start_states_ = begun.states
        return self

    def begin(self, X, Y, *, start="stuck-aware", **kw):
        return Start(start, np.full(len(Y), START_LABEL[start]), None)


def test_the_kept_fit_is_the_best_evidence_among_the_dissipative_ones(monkeypatch):
    """Every combination of which start's fit dissipates and which has the higher evidence,
    against the rule enumerated by hand: the best evidence among the dissipative fits, and where
    none dissipates (no sample to swap, so no refit) the fit with the largest p-value."""
    import itertools

    from mmgp.labelling import dissipation

    X, Y = np.zeros((6, 4)), np.zeros((6, 1))
    for phys_a, phys_b, (ev_a, ev_b) in itertools.product((True, False), (True, False), ((-5.0, 3.0), (3.0, -5.0))):
        physical = {"stuck-aware": phys_a, "every-sample": phys_b}
        p_value = {"stuck-aware": 0.01, "every-sample": 0.03}
        monkeypatch.setattr(dissipation, "energy_check", lambda sem, *a: {
            "physical": physical[sem.start_], "p_value": p_value[sem.start_] if not physical[sem.start_] else 1.0,
            "worst": 0.0})
        monkeypatch.setattr(dissipation, "injecting_samples", lambda sem, X, *a: np.zeros(len(X), bool))
        evidence = {"stuck-aware": ev_a, "every-sample": ev_b}
        sem, record = dissipation.fit_dissipative(lambda: _StubSEM(evidence), X, Y, REV)
        starts = ["stuck-aware", "every-sample"]
        assert [f["start"] for f in record["fits"]] == starts
        kept = [s for s in starts if physical[s]]
        expected = max(kept, key=evidence.get) if kept else "every-sample"   # the larger p-value
        assert sem.start_ == expected and record["fits"][record["chosen"]]["start"] == expected
        assert record["runner_up_gap"] == evidence[expected] - evidence[next(s for s in starts if s != expected)]
    # Both starts with the same labels: the second EM is not run.
    monkeypatch.setitem(START_LABEL, "every-sample", 0)
    sem, record = dissipation.fit_dissipative(lambda: _StubSEM(evidence), X, Y, REV)
    assert len(record["fits"]) == 1 and record["other_start_same_labels"] is True


def test_a_long_push_that_the_stuck_aware_start_gives_to_the_payload_is_found_from_the_other_start(tmp_path):
    """A family lever (seed 15128774: 20 Hz, q only, pushes of 16-42 N for 1.2-1.8 s on 36% of
    the samples, mostly while the PD holds a waypoint). From the stuck-aware start the payload
    columns take the pushes (inertia 8 kg*m^2 on a 0.04 kg*m^2 lever) and the EM abstains:
    nothing flagged. The every-sample start ends 116 nats higher in log evidence with the
    pushes flagged; the evidence keeps it. Scored against the recording's own truth."""
    from mmgp import MultimodalGP
    from mmgp.sim import family

    import pandas as pd

    spec = family.draw(15128774, "source", max_samples=1500)
    log, labels = family.write_scenario(family.record(spec), tmp_path, "lever")
    model = MultimodalGP(seed=0).fit(str(log))
    d = model.report_["dissipation"]
    assert [f["start"] for f in d["fits"][:2]] == ["stuck-aware", "every-sample"]
    assert d["fits"][0]["log_marginal"] < d["fits"][1]["log_marginal"] - 50 and d["chosen"] == 1
    truth = pd.read_parquet(labels)["disturbed"].to_numpy()
    flagged = model.sem_.disturbed_.astype(bool)
    tp, fp, fn = (flagged & (truth == 1)).sum(), (flagged & (truth == 0)).sum(), (~flagged & (truth == 1)).sum()
    assert 2 * tp / (2 * tp + fp + fn) > 0.6            # 0.70 (Huber's 0.92); 0.0 from the stuck-aware start
