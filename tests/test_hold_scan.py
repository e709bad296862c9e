"""Pushes at a held pose: where the whole robot holds still, a stuck joint holds any torque within
its friction band, so the push scan reads the torque beyond the band there (issue 30: an arm
holding several poses while pushed; issue 29 item 2: a stuck joint is not a pushed joint).

References: a brute-force definition of the holds, the soft threshold in closed form, the
coverage of the band's upper confidence bound over many noise draws (the MuJoCo recording of an arm
pushed at held poses: tests/test_carried_folds.py).
"""
from types import SimpleNamespace

import numpy as np
import pytest
from mmgp.diagnosis import separation as sep
from mmgp.diagnosis import stages as st


def _interiors_by_window(M_scan, h):
    # inside a hold: every sample within 2h of it lies in the log and is still (a hold that
    # starts at the first sample is trimmed there too: the zero-phase filter pads the ends)
    still = ~(M_scan > 0).any(1)
    T = len(still)
    return np.array([i - 2 * h >= 0 and i + 2 * h < T and bool(still[i - 2 * h:i + 2 * h + 1].all())
                     for i in range(T)])


@pytest.mark.parametrize("seed", range(6))
def test_hold_interiors_match_a_window_definition(seed):
    rng = np.random.default_rng(seed)
    T, n = 120, 3
    M_scan = (rng.random((T, n)) < 0.15).astype(float)
    M_scan[rng.random(T) < 0.6] = 0.0          # whole-robot stills of varied lengths
    t = np.arange(T) * 0.01
    f_c = 1.0 / (2 * 0.01 * 3)                  # half a cutoff period = 3 samples
    got = sep.hold_interiors(M_scan, t, f_c)
    np.testing.assert_array_equal(got, _interiors_by_window(M_scan, 3))
    # without a filter the holds are the stills themselves
    np.testing.assert_array_equal(sep.hold_interiors(M_scan, t, None), ~(M_scan > 0).any(1))


def test_beyond_band_is_the_soft_threshold():
    e = np.array([[-3.0, 0.2], [-1.0, -0.2], [0.0, 0.7], [0.5, -0.9], [2.0, 0.4]])
    band = np.array([1.0, 0.5])
    np.testing.assert_allclose(sep.beyond_band(e, band),
                               [[-2.0, 0.0], [0.0, 0.0], [0.0, 0.2], [0.0, -0.4], [1.0, 0.0]])


def _problem(dq, v_s, t):
    # no filter; each joint's Coulomb column tanh(dq / v_s) on its own joint, written out
    def coulomb_columns(effects, ctx):
        n = dq.shape[1]
        A = np.zeros((len(t), n, n))
        A[:, np.arange(n), np.arange(n)] = np.tanh(dq / v_s)
        return [("sign", j) for j in range(n)], A

    return SimpleNamespace(lowpass_atoms=coulomb_columns, ctx=SimpleNamespace(dq=dq, v_s=v_s), t=t, f_c=None)


def test_band_bound_covers_the_true_coulomb_level_at_its_level():
    # e = c sign(dq) + offset + white noise on a joint that slides both ways: the one-sided 95%
    # upper bound lies above the true c in 95% of draws
    rng = np.random.default_rng(0)
    T = 400
    t = np.arange(T) * 0.01
    dq = np.stack([np.sin(2 * np.pi * 0.7 * t), 0.5 + 0.2 * np.sin(t)], axis=1)
    v_s = np.array([0.05, 0.05])
    prob = _problem(dq, v_s, t)
    sign = np.tanh(dq / v_s)
    c, o, sd = 0.3, 0.1, 0.2
    covered = []
    for _ in range(600):
        e = c * sign + o + sd * rng.standard_normal((T, 2))
        ub = st.band_uncertainty(prob, e, np.ones((T, 2), bool))
        covered.append(ub[0] >= c)
        # a joint that slides one way only cannot tell its friction from an offset
        assert ub[1] == np.inf
    assert 0.93 <= np.mean(covered) <= 0.97


def test_a_stuck_joint_within_its_band_is_no_push_and_torque_beyond_it_is():
    rng = np.random.default_rng(1)
    T, n = 3000, 2
    t = np.arange(T) * 0.01
    sd, band = 0.05, np.array([1.0, 2.0])
    e = sd * rng.standard_normal((T, n))
    valid = np.zeros((T, n), bool)
    valid[:1500] = True                          # moving: scanned as before
    hold = ~valid[:, 0]
    # stuck in the band: a torque that wanders within it (the controller ramps while the joint
    # sticks), never beyond it
    e[1500:, 0] += 0.9 * np.sin(np.linspace(0, 7, 1500))
    e[1500:, 1] += -1.8
    B = band * hold[:, None]
    flagged, _ = sep.scan_disturbances(e, t, valid=valid | hold[:, None], reference=valid, band=B)
    assert not flagged.any()
    # a push at the hold: 0.5 N*m beyond the second joint's band for 0.5 s
    e[2200:2250, 1] = -2.5 + sd * rng.standard_normal(50)
    flagged, _ = sep.scan_disturbances(e, t, valid=valid | hold[:, None], reference=valid, band=B)
    np.testing.assert_array_equal(np.flatnonzero(flagged), np.arange(2200, 2250))
    # the same residual judged without the band is a push all along the hold
    flagged, _ = sep.scan_disturbances(e, t, valid=valid | hold[:, None], reference=valid)
    assert flagged[1500:].mean() > 0.9
