"""A push is a sustained offset: the pooled residual scan (mmgp.labelling.scan) and its use in the
final labels of the EM."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from mmgp.labelling.scan import masked_moving_average, scan_probability, sustained_offset_scan
from mmgp.labelling.sem import MultimodalSEM


def _brute_average(z, ok, window):
    # Window of `window` samples centred as scipy's uniform filter centres it (origin 0).
    T = len(z)
    lo = window // 2
    mean = np.zeros_like(z)
    frac = np.zeros(T)
    for i in range(T):
        idx = [j for j in range(i - lo, i - lo + window) if 0 <= j < T]
        good = [j for j in idx if ok[j]]
        frac[i] = len(good) / window
        if good:
            mean[i] = z[good].mean(0)
    return mean, frac


@pytest.mark.parametrize("window", [1, 2, 5, 8])
def test_masked_average_matches_a_loop(window):
    rng = np.random.default_rng(window)
    z = rng.normal(size=(40, 3))
    ok = rng.random(40) < 0.7
    mean, frac = masked_moving_average(z, ok, window)
    ref_mean, ref_frac = _brute_average(z, ok, window)
    np.testing.assert_allclose(frac, ref_frac, atol=1e-12)
    np.testing.assert_allclose(mean, ref_mean, atol=1e-12)


def test_light_sustained_offset_is_found_where_no_sample_shows_it():
    rng = np.random.default_rng(0)
    T, n, window = 20000, 3, 20
    z = rng.normal(size=(T, n))
    planted = np.zeros(T, bool)
    for a in (3000, 9000, 15000):
        planted[a:a + 60] = True
        z[a:a + 60, 1] += 1.5          # 1.5 standard deviations for 60 samples
    assert (np.abs(z[planted]).max(1) > 5).mean() < 0.05     # per sample it is noise
    flags, _ = sustained_offset_scan(z, np.ones(T, bool), window, 6.0)
    assert flags[planted].mean() >= 0.5     # the middle of each (its edges average in noise)
    # Nothing away from the planted offsets (a window's half-width around them may count).
    near = np.convolve(planted, np.ones(window + 1), mode="same") > 0
    assert not flags[~near].any()


def test_time_correlated_error_is_measured_not_taken_for_pushes():
    # AR(1) residuals (correlation 0.9 per sample): averages of 20 samples spread ~3.5x wider
    # than white noise's. Judged against a white-noise spread, 1/sqrt(20), they "stand off";
    # judged against their measured spread, they do not.
    rng = np.random.default_rng(1)
    T, window = 20000, 20
    e = rng.normal(size=T)
    z = np.empty(T)
    z[0] = e[0]
    for i in range(1, T):
        z[i] = 0.9 * z[i - 1] + np.sqrt(1 - 0.81) * e[i]
    avg, _ = masked_moving_average(z[:, None], np.ones(T, bool), window)
    assert (np.abs(avg[:, 0]) * np.sqrt(window) > 6.0).mean() > 0.001   # a white-noise scale flags
    flags, _ = sustained_offset_scan(z[:, None], np.ones(T, bool), window, 6.0)
    assert not flags.any()


def test_flagged_samples_are_left_out_and_windows_stay_inside_their_log():
    rng = np.random.default_rng(2)
    T, window = 4000, 10
    z = rng.normal(size=(T, 1))
    ok = np.ones(T, bool)
    z[1980:2000] += 30.0          # a hard push the chain already flagged
    ok[1980:2000] = False
    flags, _ = sustained_offset_scan(z, ok, window, 6.0, starts=(0, 2000))
    assert not flags.any()
    # Without the mask the hard push is part of the scan (and of its own neighbourhood).
    flags_all, _ = sustained_offset_scan(z, np.ones(T, bool), window, 6.0, starts=(0, 2000))
    assert flags_all[1975:2000].any()
    # Across a log boundary, an offset at the end of one log does not leak into the next.
    z2 = rng.normal(size=(T, 1))
    z2[1970:2000] += 3.0
    f2, _ = sustained_offset_scan(z2, np.ones(T, bool), window, 6.0, starts=(0, 2000))
    assert f2[1975:1995].all() and not f2[2000:].any()


def test_scan_probability_is_bonferroni():
    stat = np.array([0.0, 4.0, 6.0, 8.0])
    p = scan_probability(stat, 1000)
    np.testing.assert_allclose(p, np.clip(1 - 1000 * 2 * norm.sf(stat), 0, 1))
    assert p[0] == 0.0 and p[2] > 0.99


def _log(push_size, seed=4):
    rate, T = 100.0, 3000
    t = np.arange(T) / rate
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)
    rng = np.random.default_rng(seed)
    y = np.sin(1.5 * x) + 0.05 * rng.normal(size=T)
    pushed = np.zeros(T, bool)
    for a, n in [(400, 60), (1200, 80), (2100, 50)]:
        pushed[a:a + n] = True
        y[a:a + n] += push_size * np.sign(rng.normal())
    return t, x, y, pushed


def test_light_pushes_are_flagged_by_the_scan_and_a_clean_log_stays_clean():
    # Pushes of 1.6 noise standard deviations for 0.5-0.8 s: the chain's disturbance state (a
    # floor of 5 predictive standard deviations) takes none of them; the scan takes part (their
    # middles: 0.2 s averages of the residual stand > 6 of their spread off), nothing else.
    t, x, y, pushed = _log(0.08)
    kw = dict(max_sweeps=10, seed=0)
    off = MultimodalSEM(1, push_scan_s=0.0, **kw).fit(x[:, None], y[:, None], t=t)
    on = MultimodalSEM(1, **kw).fit(x[:, None], y[:, None], t=t)
    assert off.disturbed_[pushed].mean() < 0.05
    assert on.disturbed_[pushed].mean() >= 0.2
    assert on.disturbed_[~pushed].mean() <= 0.005
    assert on.scan_flagged_ > 0 and off.scan_flagged_ == 0
    t, x, y, _ = _log(0.0)
    clean = MultimodalSEM(1, **kw).fit(x[:, None], y[:, None], t=t)
    assert clean.disturbed_.mean() < 0.01


def test_a_few_large_residuals_do_not_make_a_push():
    # Three samples 16 standard deviations off in a 20-sample window: unclipped, their average
    # alone stands ~11 of its spread off; clipped at CLIP_Z they are a blip, not a push.
    from mmgp.labelling.scan import CLIP_Z
    rng = np.random.default_rng(5)
    T, window = 6000, 20
    z = rng.normal(size=(T, 1))
    for a in range(500, T - 500, 700):
        z[a:a + 3] += 16.0
    flags, _ = sustained_offset_scan(z, np.ones(T, bool), window, 6.0)
    assert not flags.any()
    avg, _ = masked_moving_average(z, np.ones(T, bool), window)
    assert (np.abs(avg) * np.sqrt(window) > 6.0).any() and CLIP_Z * 3 / np.sqrt(window) < 6.0
