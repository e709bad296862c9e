"""The diagnosis's learner on a push that holds the robot still at a pose the log visits only
then: the hold is one observation, so the rest of the same push must not explain it."""
from __future__ import annotations

import numpy as np
import pytest

from mmgp.diagnosis import separation


def _quintic(s):
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s ** 2)


def held_push_log(seed: int, push: float = 6.0):
    """A lever (gravity 3 sin q, Coulomb 0.8, viscous 0.5; N*m) swinging within +-0.9 rad at
    20 Hz; from 13 s a hand pushes it (up to ``push`` N*m) to -1.5 rad, holds it there still for
    2 s and lets go by 17 s. Returns t, q, dq, ddq, the nominal residual (T, 1) and the truth:
    pushed (T,), held (T,)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 24.0, 0.05)
    w = _quintic(t - 13.0) * (1.0 - _quintic(t - 16.0))
    q = (1.0 - w) * 0.9 * np.sin(0.7 * t) + w * -1.5
    dq = np.gradient(q, t)
    ddq = np.gradient(dq, t)
    resid = 3.0 * np.sin(q) + 0.8 * np.tanh(dq / 0.05) + 0.5 * dq + push * w + 0.05 * rng.standard_normal(len(t))
    return t, q[:, None], dq[:, None], ddq[:, None], resid[:, None], (t >= 13.0) & (t < 17.0), (t >= 14.0) & (t < 16.0)


@pytest.mark.parametrize("seed", range(3))
def test_a_push_held_at_a_pose_visited_once_is_flagged(seed):
    t, q, dq, ddq, resid, pushed, held = held_push_log(seed)
    p = separation.em_separate(resid, q, dq, ddq, t)["p_disturbed"]
    assert (p[held] > 0.5).mean() >= 0.95           # the whole hold (2 s, longer than the 1 s window)
    assert (p[~pushed] > 0.5).mean() <= 0.05        # the free swing stays undisturbed
