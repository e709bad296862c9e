"""Seed-independent labels (issue 10): the MPM E-step and the abstention test against exact
enumeration of tiny chains, the push prior's durations against simulation of its chain, and the
deterministic fit on planted data."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import norm

from mmgp.labelling.estep import chain_matrix, e_step
from mmgp.labelling.hmm import ffbs_sample, forward_backward
from mmgp.labelling.mstep import PushPrior, SweepParams, link_components, push_loglik, pushed_logpdf
from mmgp.labelling.sem import MultimodalSEM


def _enumerated(loglik, A, init):
    """Every state sequence's log joint (n,) and the sequences (n, T), one log, by brute force."""
    T, S = loglik.shape
    seqs = np.array(list(itertools.product(range(S), repeat=T)))
    lj = np.log(init[seqs[:, 0]]) + loglik[0, seqs[:, 0]]
    for t in range(1, T):
        lj = lj + np.log(A[seqs[:, t - 1], seqs[:, t]]) + loglik[t, seqs[:, t]]
    return seqs, lj


@pytest.mark.parametrize("T,K,seed", [(6, 1, 0), (5, 2, 1), (7, 1, 2)])
def test_mpm_labels_are_the_enumerated_most_probable_states(T, K, seed):
    rng = np.random.default_rng(seed)
    S = 2 * K
    loglik = rng.normal(scale=2.0, size=(T, S))
    A = chain_matrix(K, True, 0.9, 0.2, 0.4)
    init = np.full(S, 1.0 / S)
    seqs, lj = _enumerated(loglik, A, init)
    w = np.exp(lj - lj.max())
    marg = np.stack([np.bincount(seqs[:, t], weights=w, minlength=S) for t in range(T)])
    step = e_step(loglik, A, init, np.zeros(T, int), "mpm", None, [0])
    np.testing.assert_array_equal(step.states, marg.argmax(1))
    np.testing.assert_allclose(step.probs, marg / marg.sum(1, keepdims=True), atol=1e-12)


@pytest.mark.parametrize("T,K,n", [(6, 1, 1), (5, 2, 3)])
def test_disturbance_gain_is_the_enumerated_log_evidence_ratio_minus_bic(T, K, n):
    rng = np.random.default_rng(T + K)
    S = 2 * K
    loglik = rng.normal(scale=3.0, size=(T, S))
    params = SweepParams(hypers=[None] * K, stay=0.8, p_enter=0.3, p_leave=0.5, sigma_d=np.ones(n),
                         calib=np.ones((K, n)))
    sem = MultimodalSEM(K)
    sem.last_sweep_ = {"loglik": loglik}
    _, lj_full = _enumerated(loglik, chain_matrix(K, True, 0.8, 0.3, 0.5), np.full(S, 1.0 / S))
    _, lj_modes = _enumerated(loglik[:, :K], chain_matrix(K, False, 0.8, 0.0, 1.0), np.full(K, 1.0 / K))
    expected = logsumexp(lj_full) - logsumexp(lj_modes) - 0.5 * math.log(T) * (2 + n)
    assert abs(sem._disturbance_gain(params, [0]) - expected) < 1e-9


@pytest.mark.parametrize("rate_hz", [50.0, 100.0])
def test_push_prior_durations_are_seconds_at_any_rate(rate_hz):
    # Sequences drawn from the prior chain alone (flat likelihoods): mean push and gap lengths
    # in seconds are push_s and gap_s whatever the sampling rate.
    t = np.arange(int(1000 * rate_hz)) / rate_hz     # 1000 s: about 170 pushes
    prior = PushPrior.in_seconds(t, 1.0, 5.0, 3.0, 5.0)
    A = chain_matrix(1, True, 1.0, prior.p_enter, prior.p_leave)
    alpha, _, _ = forward_backward(np.zeros((len(t), 2)), A, np.array([1.0, 0.0]))
    s = ffbs_sample(alpha, A, np.random.default_rng(0))
    edges = np.flatnonzero(np.diff(s)) + 1
    runs = np.split(s, edges)[1:-1]          # whole runs only
    push = np.mean([len(r) for r in runs if r[0] == 1]) / rate_hz
    gap = np.mean([len(r) for r in runs if r[0] == 0]) / rate_hz
    # Geometric durations: standard errors about 0.08 s and 0.4 s.
    assert abs(push - 1.0) < 0.25 and abs(gap - 5.0) < 1.2, (push, gap)


def _planted(T=300, rate=20.0, pushes=True, seed=1):
    t = np.arange(T) / rate
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)
    rng = np.random.default_rng(seed)
    push = np.zeros(T)
    if pushes:
        for start, length in [(25, 6), (70, 12), (130, 9), (190, 15), (250, 7)]:
            push[start:start + length] = rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 0.9, length)
    return t, x[:, None], (np.sin(1.5 * x) + push + 0.05 * rng.normal(size=T))[:, None], push != 0


def test_the_seed_plays_no_part_in_the_default_fit():
    t, X, Y, _ = _planted()
    a = MultimodalSEM(1, max_sweeps=12, seed=0).fit(X, Y, t=t)
    b = MultimodalSEM(1, max_sweeps=12, seed=123).fit(X, Y, t=t)
    np.testing.assert_array_equal(a.p_disturbed_, b.p_disturbed_)
    # ... while the sampling E-step does depend on it (so the comparison above can fail).
    c = MultimodalSEM(1, estep="ffbs", max_sweeps=12, seed=0).fit(X, Y, t=t)
    d = MultimodalSEM(1, estep="ffbs", max_sweeps=12, seed=123).fit(X, Y, t=t)
    assert not np.array_equal(c.p_disturbed_, d.p_disturbed_)


def test_a_log_without_pushes_gets_nothing_flagged():
    t, X, Y, _ = _planted(pushes=False, seed=4)
    m = MultimodalSEM(1, max_sweeps=12).fit(X, Y, t=t)
    assert m.disturbed_.sum() == 0
    assert m.disturbance_gain_ <= 0.0
    # With pushes the disturbance states pay their price.
    t, X, Y, pushed = _planted(seed=4)
    m = MultimodalSEM(1, max_sweeps=12).fit(X, Y, t=t)
    assert m.disturbance_gain_ > 0.0
    assert m.disturbed_[pushed].mean() >= 0.9 and m.disturbed_[~pushed].mean() <= 0.05


def _brute_push_density(y, mu, var, sd, floor, links):
    """p(y | push) by enumeration: sum over the pushed link k (equal weights) of the product over
    joints of either the untouched normal (j > k) or the equal-weight mixture of normals with the
    spreads max(f Sigma_d, floor) (j <= k), from scipy's normal pdf."""
    n = len(y)
    total = 0.0
    for k in links:
        p = 1.0
        for j in range(n):
            if j < k:
                sds = [np.sqrt(var[j] + max(f * sd[j], floor[j])) for f in (1.0, 0.1, 0.01)]
                p *= np.mean([norm.pdf(y[j], mu[j], s) for s in sds])
            else:
                p *= norm.pdf(y[j], mu[j], np.sqrt(var[j]))
        total += p / len(links)
    return total


@pytest.mark.parametrize("n", [2, 3, 5])
def test_push_likelihood_is_the_enumerated_mixture_over_the_pushed_link(n):
    # Independent reference: products of scipy normal densities over the n "joints 1..k pushed"
    # subsets; every other subset (a distal joint pushed, a proximal one not) is absent.
    rng = np.random.default_rng(n)
    T = 6
    mu, var = rng.normal(size=(T, n)), rng.uniform(0.05, 0.5, (T, n))
    sd, floor = rng.uniform(0.5, 20.0, n), rng.uniform(0.1, 1.0, n)
    Y = mu + rng.normal(size=(T, n)) * np.sqrt(var) * rng.uniform(0.5, 6.0, (T, n))
    lu = norm.logpdf(Y, mu, np.sqrt(var))
    got = push_loglik(lu, pushed_logpdf(Y, mu, var, sd, floor))
    ref = [math.log(_brute_push_density(Y[t], mu[t], var[t], sd, floor, range(1, n + 1))) for t in range(T)]
    np.testing.assert_allclose(got, ref, rtol=1e-10)


def test_one_joint_push_is_the_single_normal_with_sigma_d():
    rng = np.random.default_rng(0)
    mu, var, y = rng.normal(size=(5, 1)), rng.uniform(0.1, 1.0, (5, 1)), rng.normal(size=(5, 1)) * 3
    got = push_loglik(norm.logpdf(y, mu, np.sqrt(var)), pushed_logpdf(y, mu, var, np.array([4.0]), np.array([1.0])))
    np.testing.assert_allclose(got, norm.logpdf(y[:, 0], mu[:, 0], np.sqrt(var[:, 0] + 4.0)), rtol=1e-12)


def test_a_proximal_push_favours_the_proximal_links():
    # A 7-joint sample off the model on joints 1-2 only: the link posterior (softmax of the
    # components) puts its mass on k = 2, where the enumeration's largest term sits.
    n = 7
    mu, var = np.zeros((1, n)), np.full((1, n), 0.01)
    Y = np.zeros((1, n))
    Y[0, :2] = [0.5, -0.4]
    sd, floor = np.full(n, 4.0), np.full(n, 0.25)
    comp = link_components(norm.logpdf(Y, mu, np.sqrt(var)), pushed_logpdf(Y, mu, var, sd, floor))[0]
    terms = [_brute_push_density(Y[0], mu[0], var[0], sd, floor, [k]) for k in range(1, n + 1)]
    assert int(np.argmax(comp)) == int(np.argmax(terms)) == 1
