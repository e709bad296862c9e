"""A logged velocity that lags its position (a drive's filtered estimate) is found and replaced.

References: a pure delay of k samples (lag k exactly); a first-order low-pass of a sinusoid, whose
phase delay is arctan(w tau) / w in closed form; the analytic derivative of the positions."""
import numpy as np
from scipy.signal import lfilter

from mmgp.data.differentiation import SavitzkyGolay, complete_derivatives, delayed_joints, velocity_delay
from mmgp.data.logs import RobotLog
from mmgp.physics.plausibility import log_checks

DT = 0.01
T = np.arange(0.0, 40.0, DT)


def first_order(x: np.ndarray, tau: float) -> np.ndarray:
    """The exact zero-order-hold discretisation of 1 / (tau s + 1) applied causally to x."""
    a = np.exp(-DT / tau)
    return lfilter([1 - a], [1, -a], x, axis=0)


def test_a_pure_delay_is_found_to_the_sample_and_a_true_velocity_at_zero():
    rng = np.random.default_rng(3)
    q = np.column_stack([np.sin(0.9 * T) + 0.2 * np.sin(3.1 * T), 0.4 * np.cos(1.7 * T)])
    dq = np.column_stack([0.9 * np.cos(0.9 * T) + 0.62 * np.cos(3.1 * T), -0.68 * np.sin(1.7 * T)])
    for k in (0, 3, 17):
        late = np.vstack([np.repeat(dq[:1], k, axis=0), dq[:len(T) - k]])
        got, se = velocity_delay(T, q, late + rng.normal(0.0, 1e-3, dq.shape))
        assert np.all(np.abs(got - k) < 0.5) and np.all(se < 0.5), (k, got, se)
        judged = delayed_joints(T, q, late)
        assert judged.tolist() == [0.0, 0.0] if k < 2 else np.all(np.abs(judged - k) < 0.5), (k, judged)


def test_a_first_order_filter_delays_a_sinusoid_by_its_phase_over_w():
    for w, tau in ((0.8, 0.15), (2.0, 0.05), (1.3, 0.3)):
        q = np.sin(w * T)[:, None]
        late = first_order(w * np.cos(w * T)[:, None], tau)
        expected = np.arctan(w * tau) / w / DT
        got = velocity_delay(T[200:], q[200:], late[200:])[0][0]   # past the filter's start
        assert abs(got - expected) <= 0.5, (w, tau, got, expected)


def test_a_velocity_of_noise_or_a_still_joint_is_not_judged():
    rng = np.random.default_rng(0)
    q = np.column_stack([np.sin(T), np.full_like(T, 0.3), np.sin(T)])
    dq = np.column_stack([rng.normal(size=len(T)), rng.normal(0.0, 1e-3, len(T)), np.zeros_like(T)])
    delay, se = velocity_delay(T, q, dq)
    assert delay.tolist() == [0, 0, 0] and np.isinf(se).all()
    assert delayed_joints(T, q, dq).tolist() == [0, 0, 0]


def test_lagging_joints_are_replaced_by_the_positions_derivative_and_the_rest_kept():
    q = np.column_stack([np.sin(0.7 * T), 0.5 * np.cos(1.1 * T)])
    dq = np.column_stack([0.7 * np.cos(0.7 * T), -0.55 * np.sin(1.1 * T)])
    ddq = np.column_stack([-0.49 * np.sin(0.7 * T), -0.605 * np.cos(1.1 * T)])
    logged = np.column_stack([first_order(dq[:, 0], 0.15), dq[:, 1]])
    log = RobotLog("log.parquet", T, q, np.zeros_like(q), dq=logged, metadata={"joint_names": ["a", "b"]})
    out = complete_derivatives(log, SavitzkyGolay(cv=True))
    inner = slice(100, -100)
    assert np.abs(out.dq[inner, 0] - dq[inner, 0]).max() < 1e-4        # the analytic derivative
    assert np.abs(out.ddq[inner, 0] - ddq[inner, 0]).max() < 1e-3
    assert np.array_equal(out.dq[:, 1], logged[:, 1])                   # the timely joint untouched
    delay = out.metadata["velocity_delay_s"]
    assert list(delay) == ["a"] and abs(delay["a"] - np.arctan(0.7 * 0.15) / 0.7) <= DT
    assert np.array_equal(log.dq, logged)                               # the input is not modified
    suspect, notes = log_checks(out, ["a", "b"])
    assert not suspect
    assert any("lags the derivative of the logged position" in n and "(a)" in n for n in notes)


def test_a_log_whose_velocity_is_timely_is_returned_as_read():
    q = np.column_stack([np.sin(0.7 * T)])
    dq = np.column_stack([0.7 * np.cos(0.7 * T)])
    ddq = np.column_stack([-0.49 * np.sin(0.7 * T)])
    log = RobotLog("log.parquet", T, q, np.zeros_like(q), dq=dq, ddq=ddq)
    out = complete_derivatives(log)
    assert out.dq is dq and out.ddq is ddq and "velocity_delay_s" not in out.metadata
    assert not out.dq_estimated
