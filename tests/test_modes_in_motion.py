"""A mode switch is a payload that changes, seen where the robot moves (issue 30): a push held at
one pose is a constant torque at a constant pose, which a second "payload" matches there.

Closed-form physics: a planar two-link arm (links 0.5 m and 0.4 m, gravity in the plane) with a
point mass m at its tip has the gravity torque m g [l1 cos q1 + l2 cos(q1 + q2), l2 cos(q1 + q2)];
a hand force F at the tip adds J(q)^T F. The modes' coefficients are each mode's least squares,
as the switching fit would give them.
"""
import numpy as np

from mmgp.diagnosis.modes import _stretch_centred, modes_differ_in_motion

G, L1, L2 = 9.81, 0.5, 0.4
RATE = 100.0


def _columns(q: np.ndarray) -> np.ndarray:
    """(T, 2, 1): the tip mass's gravity torque per kg."""
    c1, c12 = np.cos(q[:, 0]), np.cos(q[:, 0] + q[:, 1])
    return G * np.stack([L1 * c1 + L2 * c12, L2 * c12], 1)[:, :, None]


def _tip_jacobian_T(q: np.ndarray) -> np.ndarray:
    """(T, 2, 2): J(q)^T of the tip's position."""
    s1, s12 = np.sin(q[:, 0]), np.sin(q[:, 0] + q[:, 1])
    c1, c12 = np.cos(q[:, 0]), np.cos(q[:, 0] + q[:, 1])
    J = np.stack([np.stack([-L1 * s1 - L2 * s12, -L2 * s12], 1), np.stack([L1 * c1 + L2 * c12, L2 * c12], 1)], 1)
    return np.transpose(J, (0, 2, 1))


def _mode_fits(C, y, labels):
    return np.array([np.linalg.lstsq(C[labels == k].reshape(-1, 1), y[labels == k].ravel(), rcond=None)[0]
                     for k in range(2)])


def _decide(C, y, labels, t):
    V = np.ones(y.shape)
    return modes_differ_in_motion(C, y, np.ones(2), V, labels, _mode_fits(C, y, labels), t, None, 10, 0.025)


def _stretches(T: int, length: int) -> np.ndarray:
    return (np.arange(T) // length) % 2


def test_a_payload_switched_while_the_arm_moves_is_two_modes():
    rng = np.random.default_rng(0)
    t = np.arange(6000) / RATE
    q = np.stack([0.8 * np.sin(0.7 * t), 0.6 * np.sin(1.1 * t + 0.4)], 1)
    labels = _stretches(len(t), 500)
    mass = np.where(labels == 1, 2.0, 0.0)
    C = _columns(q)
    y = (C[:, :, 0] * mass[:, None]) + rng.normal(0, 0.1, (len(t), 2))
    assert _decide(C, y, labels, t)


def test_pushes_held_at_one_pose_are_not_a_second_payload():
    rng = np.random.default_rng(1)
    t = np.arange(6000) / RATE
    q = np.array([0.3, -0.9]) + rng.normal(0, 1e-4, (len(t), 2))    # held, a little sag
    labels = _stretches(len(t), 300)
    C = _columns(q)
    y = 2.5 * C[:, :, 0] + rng.normal(0, 0.1, (len(t), 2))
    JT = _tip_jacobian_T(q)
    for a in np.flatnonzero(np.diff(np.r_[0, labels]) == 1):        # each pushed stretch: its own force
        F = rng.uniform(-40, 40, 2)
        y[a:a + 300] += JT[a:a + 300] @ F
    fits = _mode_fits(C, y, labels)
    # in the raw residual the pushed stretches look like another mass (what the switch test sees)
    assert abs(fits[1, 0] - fits[0, 0]) > 0.2
    assert not _decide(C, y, labels, t)


def test_the_same_payload_in_both_modes_is_not_two_modes():
    rng = np.random.default_rng(2)
    t = np.arange(6000) / RATE
    q = np.stack([0.8 * np.sin(0.7 * t), 0.6 * np.sin(1.1 * t + 0.4)], 1)
    labels = _stretches(len(t), 500)
    C = _columns(q)
    y = 1.5 * C[:, :, 0] + rng.normal(0, 0.1, (len(t), 2))
    assert not _decide(C, y, labels, t)


def test_stretch_centring_against_closed_forms():
    labels = np.repeat([0, 1, 0, 1], [4, 6, 5, 3])
    bounds = np.r_[0, np.cumsum([4, 6, 5, 3])]
    level = np.repeat([3.0, -1.0, 7.0, 0.5], [4, 6, 5, 3])
    ramp = np.concatenate([np.arange(b - a, dtype=float) for a, b in zip(bounds[:-1], bounds[1:])])
    x = np.stack([level, level + 2 * ramp], 1)
    out = _stretch_centred(x, np.ones_like(x), labels)
    # a level per stretch leaves nothing; a ramp 0..L-1 leaves itself minus (L - 1) / 2
    half = np.concatenate([np.full(b - a, (b - a - 1) / 2) for a, b in zip(bounds[:-1], bounds[1:])])
    np.testing.assert_allclose(out[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], 2 * (ramp - half), atol=1e-12)
    # zero-weight samples do not pull a stretch's mean
    W = np.ones_like(x)
    W[0, 1] = 0.0
    out = _stretch_centred(x, W, labels)
    np.testing.assert_allclose(out[1:4, 1], 2 * (ramp[1:4] - 2.0), atol=1e-12)
