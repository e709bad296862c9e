"""A push lasts: flagged stretches shorter than ``min_push_s`` are model error, not pushes."""
from __future__ import annotations

import numpy as np
import pytest

from mmgp.labelling.estep import runs_shorter_than
from mmgp.labelling.sem import MultimodalSEM


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
    # 100 Hz, 20 s: five pushes of 0.4-1 s, and ten blips of 3 samples (0.03 s) as large as a
    # push (the model's own error at, e.g., a friction reversal).
    rate, T = 100.0, 2000
    t = np.arange(T) / rate
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)
    rng = np.random.default_rng(3)
    y = np.sin(1.5 * x) + 0.05 * rng.normal(size=T)
    pushed = np.zeros(T, bool)
    for a, n in [(150, 40), (520, 70), (900, 100), (1300, 50), (1700, 80)]:
        pushed[a:a + n] = True
        y[a:a + n] += rng.choice([-1, 1]) * rng.uniform(0.6, 0.9)
    blips = np.array([60, 330, 420, 700, 780, 1100, 1180, 1450, 1580, 1900])
    blip = (blips[:, None] + np.arange(3)).ravel()
    y[blip] += np.repeat(rng.choice([-1, 1], len(blips)), 3) * 0.8
    kw = dict(max_sweeps=12, seed=0)
    without = MultimodalSEM(1, min_push_s=0.0, **kw).fit(x[:, None], y[:, None], t=t)
    with_min = MultimodalSEM(1, min_push_s=0.15, **kw).fit(x[:, None], y[:, None], t=t)
    assert without.disturbed_[blip].mean() >= 0.5             # without a shortest push, blips are "pushes"
    assert not with_min.disturbed_[blip].any()
    assert with_min.disturbed_[pushed].mean() >= 0.9
    assert with_min.disturbed_[~pushed].mean() <= 0.02
    assert not runs_shorter_than(with_min.disturbed_, 15, (0,)).any()   # no flagged stretch under 0.15 s
    # The sweeps are the same; only the final labels differ, and only on short stretches.
    changed = without.disturbed_ != with_min.disturbed_
    assert runs_shorter_than(without.disturbed_, 15, (0,))[changed].all()
