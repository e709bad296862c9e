"""Choosing the number of modes (``select_n_modes``): a mode must last, as a payload does."""
from __future__ import annotations

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

from mmgp.labelling.sem import MultimodalSEM, longest_runs_s, select_n_modes


def _brute_longest(labels, t, K, starts):
    """Longest stretch per mode by walking the samples one at a time."""
    dt = float(np.median(np.diff(t)))
    best = [0.0] * K
    begin = 0
    for i in range(1, len(labels) + 1):
        if i == len(labels) or labels[i] != labels[begin] or i in starts:
            best[labels[begin]] = max(best[labels[begin]], t[i - 1] - t[begin] + dt)
            begin = i
    return best


@pytest.mark.parametrize("seed", range(5))
def test_longest_runs_match_a_sample_by_sample_walk(seed):
    rng = np.random.default_rng(seed)
    T, K = 200, 3
    labels = np.repeat(rng.integers(0, K, 40), rng.integers(1, 9, 40))[:T]
    T = len(labels)
    t = np.cumsum(rng.uniform(0.01, 0.03, T))
    starts = sorted({0, int(rng.integers(1, T)), int(rng.integers(1, T))})
    np.testing.assert_allclose(longest_runs_s(labels, t, K, starts), _brute_longest(labels, t, K, starts), rtol=1e-12)


def test_a_mode_no_sample_carries_lasts_zero_and_no_times_count_samples():
    labels = np.array([0, 0, 0, 2, 2, 0])
    np.testing.assert_array_equal(longest_runs_s(labels, None, 3), [3.0, 0.0, 2.0])


def _signal(T, rate):
    t = np.arange(T) / rate
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)  # every 2 s visits the whole input range
    return t, x, np.sin(1.5 * x)


FAST = dict(disturbance=False, max_sweeps=8, fit_iter=20)


def test_short_offsets_are_not_taken_for_a_mode():
    # 1-2 s offsets of 1 N*m (push-like): a second mode raises the score, but none of its
    # stretches lasts 4 s, so one mode is chosen.
    t, x, f = _signal(400, 20.0)
    bumps = np.zeros(len(t), bool)
    for a, b in [(2.0, 3.5), (7.0, 8.0), (12.0, 14.0), (16.5, 17.5)]:
        bumps |= (t >= a) & (t < b)
    y = f + 1.0 * bumps + 0.05 * np.random.default_rng(0).normal(size=len(t))
    model, sel = select_n_modes(x[:, None], y[:, None], t=t, min_mode_s=4.0, **FAST)
    assert sel["scores"][2] > sel["scores"][1]                 # the score alone would take 2
    assert min(sel["longest_run_s"][2]) <= 2.5                # the offset mode: at most the 2 s bump
    assert sel["chosen"] == 1 and model.n_modes == 1 and 3 not in sel["scores"]


def test_lasting_modes_are_kept():
    t, x, f = _signal(480, 20.0)
    mode = (((t >= 4) & (t < 9.5)) | ((t >= 14) & (t < 19.5))).astype(int)     # every stretch >= 4 s
    y = f + 1.0 * mode + 0.05 * np.random.default_rng(0).normal(size=len(t))
    model, sel = select_n_modes(x[:, None], y[:, None], t=t, min_mode_s=4.0, **FAST)
    assert sel["chosen"] == 2 and adjusted_rand_score(mode, model.labels_) >= 0.95
    assert min(sel["longest_run_s"][2]) >= 4.0
    lab = model.labels_
    lengths = np.diff(np.r_[0, np.flatnonzero(lab[1:] != lab[:-1]) + 1, len(lab)])
    assert lengths.min() >= 80                                 # every stretch lasts 4 s (20 Hz)


def test_merging_short_stretches_by_hand():
    from mmgp.labelling.estep import merge_short_runs

    lab = np.array([0, 0, 0, 0, 1, 0, 0, 0, 2, 2, 1, 1, 1, 1, 1])
    # "1" (1 sample) joins the longer left stretch; then "2 2" (2) is between 8 zeros and 5 ones.
    np.testing.assert_array_equal(merge_short_runs(lab, 3), [0] * 10 + [1] * 5)
    # A new log at sample 5: the first log ends in the lone "1", which joins its own log's zeros.
    np.testing.assert_array_equal(merge_short_runs(lab, 3, (0, 5)), [0] * 8 + [1] * 7)
    np.testing.assert_array_equal(merge_short_runs(lab, 1), lab)
    # three lone samples: the first (shortest, earliest) joins its only neighbour, 0; the last
    # then joins the longer stretch of 0s
    np.testing.assert_array_equal(merge_short_runs(np.array([1, 0, 1]), 5), [0, 0, 0])


@pytest.mark.parametrize("seed", range(6))
def test_merged_stretches_all_last_and_long_ones_keep_their_label(seed):
    from mmgp.labelling.estep import merge_short_runs

    rng = np.random.default_rng(seed)
    lab = np.repeat(rng.integers(0, 3, 80), rng.integers(1, 12, 80))
    starts = sorted({0, int(rng.integers(1, len(lab)))})
    out = merge_short_runs(lab, 6, starts)
    long_before = ~_short_stretches(lab, 6, starts)
    np.testing.assert_array_equal(out[long_before], lab[long_before])
    bounds = starts + [len(lab)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        seg = out[a:b]
        lengths = np.diff(np.r_[0, np.flatnonzero(seg[1:] != seg[:-1]) + 1, len(seg)])
        assert len(lengths) == 1 or lengths.min() >= 6


def _short_stretches(lab, min_len, starts):
    out = np.zeros(len(lab), bool)
    begin = 0
    for i in range(1, len(lab) + 1):
        if i == len(lab) or lab[i] != lab[begin] or i in starts:
            out[begin:i] = (i - begin) < min_len
            begin = i
    return out


def test_a_candidate_whose_mode_cannot_last_is_abandoned_early():
    from mmgp.labelling.sem import MultimodalSEM

    # Offsets of 1 N*m lasting 3 s in all: a second mode made of them can never hold 4 s.
    t, x, f = _signal(400, 20.0)
    bumps = np.zeros(len(t), bool)
    for a, b in [(3.0, 4.0), (9.0, 10.0), (15.0, 16.0)]:
        bumps |= (t >= a) & (t < b)
    y = f + 1.0 * bumps + 0.05 * np.random.default_rng(1).normal(size=len(t))
    kw = dict(disturbance=False, max_sweeps=20, fit_iter=20, min_sweeps=4, patience=2)
    full = MultimodalSEM(n_modes=2, **kw).fit(x[:, None], y[:, None], t=t)
    assert np.bincount(full.labels_, minlength=2).min() * 0.05 < 4.0     # the small mode is under 4 s
    quick = MultimodalSEM(n_modes=2, abandon_short_modes=True, **kw).fit(x[:, None], y[:, None], t=t)
    assert quick.abandoned_ and not full.abandoned_
    assert len(quick.trace_) < len(full.trace_)
    _, sel = select_n_modes(x[:, None], y[:, None], t=t, **kw)
    assert sel["chosen"] == 1


def test_a_mode_of_many_short_stretches_is_abandoned_but_a_lasting_one_is_not():
    # Offsets on for 1.2 s, off for 0.8 s, for 12 s: 7.2 s of offset in all, none of it 4 s in
    # one stretch (the selection's test). Beside it, the same offset on and off every 6 s: a mode.
    t, x, f = _signal(480, 20.0)
    noise = 0.05 * np.random.default_rng(2).normal(size=len(t))
    kw = dict(disturbance=False, max_sweeps=20, fit_iter=20, min_sweeps=4, patience=2)
    flicker = (t >= 6) & (t < 18) & ((t - 6) % 2 < 1.2)
    full = MultimodalSEM(n_modes=2, **kw).fit(x[:, None], (f + flicker + noise)[:, None], t=t)
    assert np.bincount(full.labels_, minlength=2).min() * 0.05 > 4.0    # more than 4 s in all
    assert full.longest_stretch_s_.min() < 4.0 and not full.abandoned_
    quick = MultimodalSEM(n_modes=2, abandon_short_modes=True, **kw).fit(x[:, None], (f + flicker + noise)[:, None], t=t)
    assert quick.abandoned_ and len(quick.trace_) < len(full.trace_)
    blocks = ((t >= 6) & (t < 12)) | (t >= 18)
    lasting = MultimodalSEM(n_modes=2, abandon_short_modes=True, **kw).fit(x[:, None], (f + blocks + noise)[:, None], t=t)
    assert not lasting.abandoned_
    assert adjusted_rand_score(blocks, lasting.labels_) > 0.95


def test_the_selection_judges_stretches_before_merging():
    # Offsets on for 1.2 s, off for 0.8 s, for 12 s: no stretch lasts 4 s, but merging the short
    # stretches (the 0.8 s gaps first) would join the flicker into one 12 s block of the offset.
    t, x, f = _signal(480, 20.0)
    flicker = (t >= 6) & (t < 18) & ((t - 6) % 2 < 1.2)
    y = f + 1.0 * flicker + 0.05 * np.random.default_rng(2).normal(size=len(t))
    model, sel = select_n_modes(x[:, None], y[:, None], t=t, **FAST)
    assert sel["scores"][2] > sel["scores"][1]
    assert min(sel["longest_run_s"][2]) <= 1.5
    assert sel["chosen"] == 1


@pytest.mark.parametrize("seed", range(3))
def test_disturbance_given_a_fixed_mode_path_matches_enumeration(seed):
    # Every state sequence of the full chain (modes x disturbance, 4 states, 7 samples, two logs)
    # whose modes follow the path, weighed by its prior and likelihood.
    import itertools

    from mmgp.labelling.estep import chain_matrix, disturbed_given_modes

    rng = np.random.default_rng(seed)
    K, T, starts = 2, 7, (0, 4)
    loglik = rng.normal(scale=2.0, size=(T, 2 * K))
    modes = rng.integers(0, K, T)
    stay, p_enter, p_leave = 0.9, 0.2, 0.35
    A = chain_matrix(K, True, stay, p_enter, p_leave)
    init = np.full(2 * K, 1.0 / (2 * K))
    num, den = np.zeros(T), 0.0
    for d in itertools.product((0, 1), repeat=T):
        s = modes + K * np.array(d)
        w = np.exp(loglik[np.arange(T), s].sum())
        for i in range(T):
            w *= init[s[i]] if i in starts else A[s[i - 1], s[i]]
        num += w * np.array(d)
        den += w
    got = disturbed_given_modes(loglik, modes, K, p_enter, p_leave, starts)
    np.testing.assert_allclose(got, num / den, rtol=1e-10, atol=1e-12)


def test_a_push_that_looks_like_the_other_mode_for_a_moment_is_flagged():
    # Two lasting modes (a 1 N*m payload offset for 8 s of 24); inside the first mode a 0.5 s
    # push of the same 1 N*m and two larger ones. The push that equals the payload is, sample by
    # sample, the other mode's; a mode lasts 4 s, so it can only be the first mode's, pushed.
    t, x, f = _signal(480, 20.0)
    mode = ((t >= 10) & (t < 18)).astype(int)
    push = np.zeros(len(t))
    for a, b, size in [(3.0, 3.5, 1.0), (6.0, 7.0, 3.0), (14.0, 15.0, -3.0)]:
        push[(t >= a) & (t < b)] = size
    y = f + 1.0 * mode + push + 0.05 * np.random.default_rng(1).normal(size=len(t))
    model = MultimodalSEM(n_modes=2, disturbance=True, max_sweeps=12, fit_iter=20, min_mode_s=4.0).fit(
        x[:, None], y[:, None], t=t)
    assert adjusted_rand_score(mode, model.labels_) >= 0.95
    same = (t >= 3.0) & (t < 3.5)
    assert model.disturbed_[same].mean() >= 0.9
    assert model.disturbed_[push == 0].mean() <= 0.02
