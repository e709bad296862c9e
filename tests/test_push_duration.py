"""A push lasts: flagged stretches shorter than ``min_push_s`` are model error, not pushes."""
from __future__ import annotations

import numpy as np
import pytest

from mmgp.models.estep import runs_shorter_than
from mmgp.models.sem import MultimodalSEM


def _brute_short(flags, min_len, starts):
    out = np.zeros(len(flags), bool)
    begin = None
    for i in range(len(flags) + 1):
        boundary = i == len(flags) or i in starts
        if begin is not None and (boundary or not flags[i]):
            out[begin:i] = (i - begin) < min_len
            begin = None
        if i < len(flags) and flags[i] and begin is None:
            begin = i
    return out


@pytest.mark.parametrize("seed", range(6))
def test_short_runs_match_a_sample_by_sample_walk(seed):
    rng = np.random.default_rng(seed)
    flags = np.repeat(rng.random(60) < 0.4, rng.integers(1, 7, 60))
    starts = sorted({0, int(rng.integers(1, len(flags))), int(rng.integers(1, len(flags)))})
    for min_len in (0, 1, 2, 3.5, 5):
        np.testing.assert_array_equal(runs_shorter_than(flags, min_len, starts), _brute_short(flags, min_len, starts))


def test_blips_of_model_error_are_not_flagged_but_pushes_are():
    # 20 Hz, 30 s: five pushes of 0.4-1 s, and ten one-sample spikes as large as a push (the
    # model's own error at, e.g., a friction reversal).
    rate, T = 20.0, 600
    t = np.arange(T) / rate
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)
    rng = np.random.default_rng(3)
    y = np.sin(1.5 * x) + 0.05 * rng.normal(size=T)
    pushed = np.zeros(T, bool)
    for a, n in [(40, 8), (150, 14), (260, 20), (380, 10), (500, 16)]:
        pushed[a:a + n] = True
        y[a:a + n] += rng.choice([-1, 1]) * rng.uniform(0.6, 0.9)
    spikes = np.array([20, 95, 120, 210, 230, 330, 350, 440, 470, 560])
    y[spikes] += rng.choice([-1, 1], len(spikes)) * 0.8
    kw = dict(max_sweeps=15, seed=0)
    without = MultimodalSEM(1, min_push_s=0.0, **kw).fit(x[:, None], y[:, None], t=t)
    with_min = MultimodalSEM(1, min_push_s=0.15, **kw).fit(x[:, None], y[:, None], t=t)
    assert without.disturbed_[spikes].mean() >= 0.5           # without a shortest push, spikes are "pushes"
    assert not with_min.disturbed_[spikes].any()
    assert with_min.disturbed_[pushed].mean() >= 0.9
    assert with_min.disturbed_[~pushed].mean() <= 0.02
    short = runs_shorter_than(with_min.disturbed_, 3, (0,))
    assert not short.any()                                     # no flagged stretch under 0.15 s = 3 samples
