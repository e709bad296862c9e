"""EM pieces (mmgp.labelling) against exact enumeration and brute-force GP refits.

Tiny chains (T = 4..7 samples, S = 2..4 states) are small enough to enumerate all S^T label
sequences, which gives the exact posterior marginals, the exact log marginal likelihood, the
exact single-site conditionals and the exact joint posterior for the samplers to match.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal, norm
from sklearn.metrics import adjusted_rand_score

import mmgp.gp.exact as gp_module
from mmgp.labelling.mstep import ModeFitter
from mmgp.labelling.sem import MultimodalSEM
from mmgp.data.folds import time_blocks
from mmgp.data.regression import basis_rank, fit_basis_coefficients
from mmgp.gp.kernels import rbf_kernel
from mmgp.gp.objectives import block_loo_log_predictive
from mmgp.gp.windowed import windowed_predictive
from mmgp.labelling.hmm import ffbs_sample, forward_backward, gibbs_conditionals, gibbs_sweep, sequence_log_prior, transition_matrix
from mmgp.gp.linalg import DTYPE
from mmgp.gp.exact import ExactGP
from mmgp.gp.hyper import Hyper
from mmgp.gp.objectives import log_marginal_likelihood


# ---------------------------------------------------------------------------------------------
# Enumeration references
# ---------------------------------------------------------------------------------------------

def random_chain(T, S, seed):
    rng = np.random.default_rng(seed)
    loglik = rng.normal(scale=2.0, size=(T, S)) - 50.0     # offset: scaling must not matter
    A = rng.dirichlet(np.ones(S) * 2.0, size=S)
    init = rng.dirichlet(np.ones(S) * 2.0)
    return loglik, A, init


def log_prior_ref(seq, A, init, starts):
    lp = 0.0
    for t, s in enumerate(seq):
        lp += math.log(init[s]) if t in starts else math.log(A[seq[t - 1], s])
    return lp


def enumerate_joint(loglik, A, init, starts):
    """All S^T sequences (n, T) and their log joint log p(s) + sum_t loglik[t, s_t] (n,)."""
    T, S = loglik.shape
    seqs = np.array(list(itertools.product(range(S), repeat=T)))
    lj = np.array([log_prior_ref(s, A, init, set(starts)) + loglik[np.arange(T), s].sum() for s in seqs])
    return seqs, lj


def normalise(logp):
    p = np.exp(logp - logp.max())
    return p / p.sum()


CASES = [(5, 2, (0,), 0), (6, 3, (0,), 1), (6, 3, (0, 2, 5), 2), (7, 2, (0, 4), 3), (4, 4, (0,), 4),
         (5, 4, (0, 1), 5)]


@pytest.mark.parametrize("T,S,starts,seed", CASES)
def test_forward_backward_matches_enumeration(T, S, starts, seed):
    loglik, A, init = random_chain(T, S, seed)
    seqs, lj = enumerate_joint(loglik, A, init, starts)
    post = normalise(lj)
    marg = np.stack([np.bincount(seqs[:, t], weights=post, minlength=S) for t in range(T)])
    logZ = lj.max() + math.log(np.exp(lj - lj.max()).sum())
    alpha, m, log_marg = forward_backward(loglik, A, init, starts)
    np.testing.assert_allclose(m, marg, atol=1e-10)
    assert abs(log_marg - logZ) < 1e-10 * max(1.0, abs(logZ))
    # Filtered alpha_t = p(s_t | y_0..t): enumerate the prefix only.
    for t in range(T):
        sq, lj_t = enumerate_joint(loglik[:t + 1], A, init, [s for s in starts if s <= t])
        filt = np.bincount(sq[:, t], weights=normalise(lj_t), minlength=S)
        np.testing.assert_allclose(alpha[t], filt, atol=1e-10)


def test_forward_backward_separate_logs_are_independent():
    # A restart makes the two halves independent: marginals equal those of each half alone.
    loglik, A, init = random_chain(8, 3, 11)
    _, m, lz = forward_backward(loglik, A, init, starts=(0, 5))
    _, m1, lz1 = forward_backward(loglik[:5], A, init)
    _, m2, lz2 = forward_backward(loglik[5:], A, init)
    np.testing.assert_allclose(m, np.vstack([m1, m2]), atol=1e-12)
    assert abs(lz - (lz1 + lz2)) < 1e-10


def sequence_index(seqs, S):
    return (seqs * (S ** np.arange(seqs.shape[1])[::-1])).sum(1)


@pytest.mark.parametrize("T,S,starts,seed", [(5, 2, (0,), 20), (5, 2, (0, 3), 21), (4, 3, (0,), 22)])
def test_ffbs_draws_follow_exact_joint_posterior(T, S, starts, seed):
    loglik, A, init = random_chain(T, S, seed)
    seqs, lj = enumerate_joint(loglik, A, init, starts)
    post = normalise(lj)
    alpha, _, _ = forward_backward(loglik, A, init, starts)
    rng = np.random.default_rng(seed)
    n = 20000
    draws = np.array([ffbs_sample(alpha, A, rng, starts) for _ in range(n)])
    counts = np.bincount(sequence_index(draws, S), minlength=S ** T) / n
    tv = 0.5 * np.abs(counts - post[np.argsort(sequence_index(seqs, S))]).sum()
    assert tv < 0.03, tv


@pytest.mark.parametrize("T,S,starts,seed", CASES)
def test_gibbs_conditionals_match_enumeration(T, S, starts, seed):
    loglik, A, init = random_chain(T, S, seed)
    seqs, lj = enumerate_joint(loglik, A, init, starts)
    table = dict(zip(map(tuple, seqs), lj))
    rng = np.random.default_rng(seed)
    for _ in range(5):
        states = rng.integers(0, S, T)
        p = gibbs_conditionals(loglik, A, init, states, np.arange(T), starts)
        for t in range(T):
            alt = [table[tuple(np.where(np.arange(T) == t, k, states))] for k in range(S)]
            np.testing.assert_allclose(p[t], normalise(np.array(alt)), atol=1e-12)
        # A subset of sites gives the same rows.
        sites = np.arange(1, T, 2)
        np.testing.assert_allclose(gibbs_conditionals(loglik, A, init, states, sites, starts), p[sites], atol=1e-15)


def test_sequence_log_prior_matches_reference():
    _, A, init = random_chain(6, 3, 9)
    rng = np.random.default_rng(9)
    for starts in [(0,), (0, 3)]:
        for _ in range(10):
            s = rng.integers(0, 3, 6)
            assert abs(sequence_log_prior(s, A, init, starts) - log_prior_ref(s, A, init, set(starts))) < 1e-12


def test_gibbs_sweep_leaves_exact_posterior_invariant():
    # Even-then-odd blocks are exact Gibbs: the chain's long-run distribution is the posterior.
    T, S, starts = 5, 2, (0, 3)
    loglik, A, init = random_chain(T, S, 30)
    loglik = loglik / 3.0  # flatter posterior: faster mixing
    seqs, lj = enumerate_joint(loglik, A, init, starts)
    post = normalise(lj)[np.argsort(sequence_index(seqs, S))]
    rng = np.random.default_rng(30)
    states = np.zeros(T, int)
    n = 30000
    counts = np.zeros(S ** T)
    for i in range(n + 200):
        states, probs = gibbs_sweep(loglik, A, init, states, rng, starts)
        if i >= 200:
            counts[sequence_index(states[None], S)[0]] += 1
    tv = 0.5 * np.abs(counts / n - post).sum()
    assert tv < 0.03, tv


@pytest.mark.parametrize("K,stay", [(1, 0.9), (2, 0.9), (3, 0.8), (4, 0.97)])
def test_transition_matrix_structure(K, stay):
    Pk = transition_matrix(K, stay)
    assert Pk.shape == (K, K)
    np.testing.assert_allclose(Pk.sum(1), 1.0, atol=1e-15)
    for a in range(K):
        for b in range(K):
            want = 1.0 if K == 1 else (stay if a == b else (1 - stay) / (K - 1))
            assert abs(Pk[a, b] - want) < 1e-15
    p_enter, p_leave = 0.07, 0.3
    P = transition_matrix(K, stay, p_enter, p_leave)
    assert P.shape == (2 * K, 2 * K)
    np.testing.assert_allclose(P.sum(1), 1.0, atol=1e-15)
    Pd = np.array([[1 - p_enter, p_enter], [p_leave, 1 - p_leave]])
    for s in range(2 * K):
        for r in range(2 * K):
            # state index k + K*d: the mode and the disturbance flag move independently
            assert abs(P[s, r] - Pd[s // K, r // K] * Pk[s % K, r % K]) < 1e-15


# ---------------------------------------------------------------------------------------------
# KEY: Gibbs conditional with the GP emission = exact conditional of the joint
# ---------------------------------------------------------------------------------------------

class _IdentityScaler:
    """No standardisation: makes ExactGP a GP with fixed hyperparameters in data units and zero
    prior mean, so that it is one fixed probabilistic model whatever subset it conditions on."""

    def fit(self, A):
        self.mean_ = np.zeros(A.shape[1])
        self.scale_ = np.ones(A.shape[1])
        return self

    def transform(self, A):
        return np.asarray(A, dtype=np.float64)


def test_gibbs_conditional_with_loo_gp_equals_enumeration(monkeypatch):
    """p(w, Y) = prod_k p(Y_k | GP) x Markov(w). Its exact conditional p(w_t | w_-t, Y), from
    enumerating all 2^6 labellings, must equal the normalised product of y_t's predictive under
    each mode's GP given the *other* samples of that mode (LOO for members) and the Markov
    neighbours: the em's emission, assembled by ModeFitter.predictive (the M-step's mode model) and
    gibbs_conditionals, and the same from ExactGP predict / loo_predictive directly.

    ExactGP re-standardises X and Y on every fit; with that, a fixed hyperparameter vector means a
    different kernel on each subset and no fixed joint exists to enumerate, so the standardiser is
    replaced by the identity here (see the report of the test author for the em consequence)."""
    monkeypatch.setattr(gp_module, "Standardiser", _IdentityScaler)
    rng = np.random.default_rng(0)
    N = 6
    x = np.sort(rng.uniform(-2, 2, N))
    w_true = np.array([0, 0, 1, 1, 1, 0])
    y = np.sin(x) + 1.5 * w_true + 0.1 * rng.normal(size=N)
    ls, sf, sn = 0.8, 1.3, 0.05
    hyper = Hyper(np.array([[ls]]), np.array([sf]), np.array([sn]))
    A = transition_matrix(2, 0.8)
    init = np.array([0.4, 0.6])

    def kern(a, b):
        return sf * np.exp(-0.5 * (a[:, None] - b[None, :]) ** 2 / ls ** 2)

    def log_evidence(idx):
        if len(idx) == 0:
            return 0.0
        Kn = kern(x[idx], x[idx]) + sn * np.eye(len(idx))
        ref = multivariate_normal(np.zeros(len(idx)), Kn).logpdf(y[idx])
        lml = float(log_marginal_likelihood(torch.as_tensor(Kn[None], dtype=DTYPE),
                                            torch.as_tensor(y[idx][None], dtype=DTYPE))[0])
        assert abs(lml - ref) < 1e-10
        return ref

    seqs = np.array(list(itertools.product(range(2), repeat=N)))
    table = {tuple(w): log_evidence(np.flatnonzero(w == 0)) + log_evidence(np.flatnonzero(w == 1))
             + log_prior_ref(w, A, init, {0}) for w in seqs}

    fitter = ModeFitter(x[:, None], y[:, None], MultimodalSEM(2, disturbance=False, max_support=100).settings.fitter)  # no time axis: LOO
    n_checked = 0
    for w in seqs:
        if min((w == 0).sum(), (w == 1).sum()) < 2:
            continue  # every mode keeps a sample besides t, so each GP has data to condition on
        exact = np.stack([normalise(np.array([table[tuple(np.where(np.arange(N) == t, k, w))] for k in range(2)]))
                          for t in range(N)])
        # (a) the em's own emission code
        loglik = np.empty((N, 2))
        for k in range(2):
            mean, var, *_ = fitter.predictive(np.flatnonzero(w == k), hyper, False)
            loglik[:, k] = norm.logpdf(y, mean[:, 0], np.sqrt(var[:, 0]))
        p_em = gibbs_conditionals(loglik, A, init, w, np.arange(N))
        np.testing.assert_allclose(p_em, exact, atol=1e-8)
        # (b) ExactGP directly: predictive of y_t given mode k's other members
        for t in range(N):
            logp = np.empty(2)
            for k in range(2):
                members = np.flatnonzero(w == k)
                gp = ExactGP(hyper=hyper, optimise=False).fit(x[members, None], y[members])
                if w[t] == k:
                    mu, sd = gp.loo_predictive()
                    i = int(np.flatnonzero(members == t)[0])
                    mu, sd = mu[i], sd[i]
                else:
                    mu, sd = gp.predict(x[[t], None], include_noise=True)
                    mu, sd = mu[0], sd[0]
                logp[k] = norm.logpdf(y[t], mu, sd)
                logp[k] += math.log(init[k]) if t == 0 else math.log(A[w[t - 1], k])
                if t < N - 1:
                    logp[k] += math.log(A[k, w[t + 1]])
            np.testing.assert_allclose(normalise(logp), exact[t], atol=1e-8)
        n_checked += 1
    assert n_checked == 50


# ---------------------------------------------------------------------------------------------
# Leave-window-out and leave-block-out predictives against brute-force refits
# ---------------------------------------------------------------------------------------------

def gp_predict_ref(Xtr, ytr, Xq, ls, sf, sn):
    """Zero-mean GP predictive (incl. noise) in the GP's standardised units, numpy."""
    if len(Xtr) == 0:
        return np.zeros(len(Xq)), np.full(len(Xq), sf + sn)

    def k(a, b):
        return sf * np.exp(-0.5 * (((a[:, None, :] - b[None, :, :]) / ls) ** 2).sum(-1))

    Kn = k(Xtr, Xtr) + sn * np.eye(len(Xtr))
    Ks = k(Xtr, Xq)
    sol = np.linalg.solve(Kn, np.column_stack([ytr, Ks]))
    return Ks.T @ sol[:, 0], sf - (Ks * sol[:, 1:]).sum(0) + sn


def toy_support(N=40, seed=0):
    rng = np.random.default_rng(seed)
    ts = np.sort(rng.uniform(0, 10, N))
    X = np.column_stack([np.sin(ts), np.cos(0.7 * ts) * 3.0])
    Y = np.column_stack([X[:, 0] * X[:, 1], np.sin(2 * X[:, 0])]) * 4.0 + 1.0 + 0.1 * rng.normal(size=(N, 2))
    return ts, X, Y


@pytest.mark.parametrize("radius", [0.0, 0.3, 1.5, 20.0])
def test_windowed_predictive_equals_brute_force_refits(radius):
    ts, X, Y = toy_support()
    hyper = Hyper(np.array([[0.7, 1.2], [0.9, 0.5]]), np.array([1.1, 0.8]), np.array([0.02, 0.05]))
    gp = ExactGP(hyper=hyper, optimise=False).fit(X, Y)
    rng = np.random.default_rng(1)
    tq = np.concatenate([ts[::3], rng.uniform(-1, 11, 10), ts[:2] + radius])   # members, others, window edges
    Xq = np.column_stack([np.sin(tq), np.cos(0.7 * tq) * 3.0]) + 0.05 * rng.normal(size=(len(tq), 2))
    mean, var = windowed_predictive(gp, Xq, tq, ts, radius, chunk=7)
    # one output alone (the friction band's branches): that output's column, by the same reference
    alone = [windowed_predictive(gp, Xq, tq, ts, radius, chunk=7, output=j) for j in range(2)]
    Xs, Ys = gp.Xs_.numpy(), gp.Ys_.numpy()
    Xq_s = gp.x_scaler_.transform(Xq)
    for i in range(len(tq)):
        # inclusive window [tq - r, tq + r], evaluated as the interval (exact at its float edges)
        keep = ~((ts >= tq[i] - radius) & (ts <= tq[i] + radius))
        for j in range(2):
            mu, v = gp_predict_ref(Xs[keep], Ys[keep, j], Xq_s[[i]], hyper.lengthscale[j], hyper.signal_var[j],
                                   hyper.noise_var[j])
            scale, shift = gp.y_scaler_.scale_[j], gp.y_scaler_.mean_[j]
            for m_, v_ in ((mean[i, j], var[i, j]), (alone[j][0][i, 0], alone[j][1][i, 0])):
                np.testing.assert_allclose(m_, mu[0] * scale + shift, rtol=1e-8, atol=1e-8 * scale)
                np.testing.assert_allclose(v_, v[0] * scale ** 2, rtol=1e-8)
    if radius == 0.0:  # nothing is left out at off-support times: the ordinary predictive
        off = np.array([np.abs(ts - s).min() > 0 for s in tq])
        m0, s0 = gp.predict(Xq[off], include_noise=True)
        np.testing.assert_allclose(mean[off], m0, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(var[off], s0 ** 2, rtol=1e-9)


def test_blocks_partition_sorted_times():
    ts = np.sort(np.random.default_rng(2).uniform(0, 10, 57))
    idx, valid = time_blocks(ts, 1.3)
    members = [idx[b][valid[b]] for b in range(len(idx))]
    np.testing.assert_array_equal(np.concatenate(members), np.arange(len(ts)))
    for b, mb in enumerate(members):
        assert ts[mb[-1]] - ts[mb[0]] <= 1.3
        if b + 1 < len(members):  # greedy: the next sample would have overflowed the block
            assert ts[members[b + 1][0]] - ts[mb[0]] > 1.3


@pytest.mark.parametrize("length", [0.0, 0.8, 3.0])
def test_block_loo_log_predictive_equals_brute_force_refits(length):
    ts, X, Y = toy_support(N=35, seed=3)
    Xs = (X - X.mean(0)) / X.std(0)
    Ys = (Y - Y.mean(0)) / Y.std(0)
    log_ls = np.log(np.array([[0.7, 1.2], [0.9, 0.5]]))
    log_sf = np.log(np.array([1.1, 0.8]))
    log_sn = np.log(np.array([0.02, 0.05]))
    floor = 1e-6
    idx, valid = time_blocks(ts, length)
    t = lambda a: torch.as_tensor(a, dtype=DTYPE)  # noqa: E731
    K = rbf_kernel(t(Xs), t(Xs), t(np.exp(log_ls)), t(np.exp(log_sf))) + t(np.exp(log_sn) + floor)[:, None, None] * torch.eye(len(ts), dtype=DTYPE)
    got = block_loo_log_predictive(K, t(Ys.T.copy()), idx, valid)
    want = np.zeros(2)
    for b in range(len(idx)):
        test = idx[b][valid[b]]
        train = np.setdiff1d(np.arange(len(ts)), test)
        for j in range(2):
            mu, v = gp_predict_ref(Xs[train], Ys[train, j], Xs[test], np.exp(log_ls[j]), np.exp(log_sf[j]),
                                   np.exp(log_sn[j]) + floor)
            want[j] += norm.logpdf(Ys[test, j], mu, np.sqrt(v)).sum()
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-8, atol=1e-8)


# ---------------------------------------------------------------------------------------------
# Planted structure
# ---------------------------------------------------------------------------------------------

def planted_signal(T=300, rate=20.0):
    t = np.arange(T) / rate
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)  # every stretch of >= 2 s visits the whole input range
    return t, x, np.sin(1.5 * x)


@pytest.mark.parametrize("estep", ["mpm", "ffbs", "gibbs"])
def test_planted_modes_are_recovered(estep):
    t, x, f = planted_signal()
    rng = np.random.default_rng(0)
    mode = (((t >= 4) & (t < 8)) | ((t >= 11) & (t < 13.5))).astype(int)
    y = f + 1.0 * mode + 0.05 * rng.normal(size=len(t))
    # min_mode_s 0: the planted stretches (4 and 2.5 s) test the E-steps, not the shortest mode.
    m = MultimodalSEM(n_modes=2, disturbance=False, estep=estep, max_sweeps=15, min_mode_s=0.0,
                      seed=0).fit(x[:, None], y[:, None], t=t)
    assert adjusted_rand_score(mode, m.labels_) >= 0.95
    assert m.p_mode_.shape == (len(t), 2)
    np.testing.assert_allclose(m.p_mode_.sum(1), 1.0, atol=1e-9)
    # Mode 0 (nominal) holds the most samples.
    assert (m.labels_ == 0).sum() >= (m.labels_ == 1).sum()


@pytest.mark.parametrize("estep", ["mpm", "ffbs", "gibbs"])
def test_planted_disturbance_bursts_are_flagged(estep):
    t, x, f = planted_signal()
    rng = np.random.default_rng(1)
    T = len(t)
    disturbed = np.zeros(T, bool)
    push = np.zeros(T)
    for start, length in [(25, 6), (70, 12), (130, 9), (190, 15), (250, 7)]:
        disturbed[start:start + length] = True
        push[start:start + length] = rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 0.9, length)
    y = f + push + 0.05 * rng.normal(size=T)
    m = MultimodalSEM(1, disturbance=True, estep=estep, max_sweeps=15, seed=0).fit(x[:, None], y[:, None], t=t)
    flagged = m.disturbed_
    recall = flagged[disturbed].mean()
    false_alarm = flagged[~disturbed].mean()
    assert recall >= 0.9, recall
    assert false_alarm <= 0.05, false_alarm
    np.testing.assert_array_equal(flagged, m.p_disturbed_ > 0.5)


# ---------------------------------------------------------------------------------------------
# Linear basis mean (rigid-body regressor)
# ---------------------------------------------------------------------------------------------

def test_basis_coefficients_equal_least_squares_without_outliers():
    rng = np.random.default_rng(0)
    N, n, p = 300, 3, 5
    basis = rng.normal(size=(N, n, p)) * np.array([1.0, 10.0, 0.1, 3.0, 1.0])
    coef = rng.normal(size=(n, p))
    Y = np.einsum("tjp,jp->tj", basis, coef) + 0.01 * rng.normal(size=(N, n))
    # One IRLS step has unit weights: ordinary least squares per output, the reference.
    ols = fit_basis_coefficients(basis, Y, n_irls=1)
    for j in range(n):
        ref, *_ = np.linalg.lstsq(basis[:, j, :], Y[:, j], rcond=None)
        np.testing.assert_allclose(ols[j], ref, rtol=1e-8, atol=1e-10)
    # The Huber fit stays within 4 standard errors of the truth: noise / (column scale sqrt(N)).
    se = 0.01 / (np.array([1.0, 10.0, 0.1, 3.0, 1.0]) * math.sqrt(N))
    assert (np.abs(fit_basis_coefficients(basis, Y) - coef) < 4 * se).all()


def test_basis_coefficients_resist_gross_outliers_and_ignore_invisible_columns():
    rng = np.random.default_rng(1)
    N, n, p = 400, 2, 4
    basis = rng.normal(size=(N, n, p))
    basis[:, 0, 3] = 0.0                     # a parameter joint 0 cannot see
    basis[:, 1, 2] = basis[:, 1, 1]          # two columns joint 1 cannot tell apart
    coef = np.array([[1.0, -2.0, 0.5, 0.0], [0.3, 1.0, 1.0, -1.0]])
    Y = np.einsum("tjp,jp->tj", basis, coef) + 0.02 * rng.normal(size=(N, n))
    Y[rng.choice(N, 40, replace=False)] += 20.0          # 10% pushes of 1,000 noise sigmas
    got = fit_basis_coefficients(basis, Y)
    plain = np.linalg.lstsq(basis[:, 0, :3], Y[:, 0], rcond=None)[0]
    assert np.abs(plain - coef[0, :3]).max() > 0.2      # least squares is dragged away ...
    np.testing.assert_allclose(got[0, :3], coef[0, :3], atol=0.02)   # ... Huber is not
    assert got[0, 3] == 0.0
    # Only the sum of the twin columns is identifiable; the minimum-norm split is even.
    np.testing.assert_allclose(got[1, 1] + got[1, 2], 2.0, atol=0.02)
    np.testing.assert_allclose(got[1, 1], got[1, 2], atol=1e-6)
    np.testing.assert_allclose(got[1, [0, 3]], coef[1, [0, 3]], atol=0.02)
    assert basis_rank(basis) == 3 + 3


def test_basis_mean_extrapolates_a_planted_mode_offset():
    """Two modes that differ by a linear term in a known regressor (a 'payload'): with the basis
    the difference is learned as coefficients and predicted exactly far outside the data; the
    GP alone can only revert to its mean there."""
    t, x, _ = planted_signal()
    rng = np.random.default_rng(2)
    mode = (((t >= 4) & (t < 8)) | ((t >= 11) & (t < 13.5))).astype(int)

    def regressor(x):
        return np.stack([np.cos(x), np.sin(x), np.ones_like(x)], axis=-1)[:, None, :]   # (T, 1, 3)

    # Shared physics in the basis plus a small wiggle only the GP can follow.
    y = 0.8 * np.sin(x) + 0.2 * np.sin(3.0 * x) + mode * 1.5 * np.cos(x) + 0.05 * rng.normal(size=len(t))
    basis = regressor(x)
    m = MultimodalSEM(n_modes=2, disturbance=False, max_sweeps=15, min_mode_s=0.0, seed=0).fit(
        x[:, None], y[:, None], t=t, basis=basis)
    assert adjusted_rand_score(mode, m.labels_) >= 0.95
    payload = 1 if (m.labels_[mode == 1] == 1).mean() > 0.5 else 0
    xq = np.linspace(4.0, 6.0, 50)            # the data span |x| <= 2.3
    bq = regressor(xq)
    diff = m.predict(xq[:, None], mode=payload, basis=bq)[0] - m.predict(xq[:, None], mode=1 - payload, basis=bq)[0]
    np.testing.assert_allclose(diff.ravel(), 1.5 * np.cos(xq), atol=0.1)
    with pytest.raises(ValueError, match="basis"):
        m.predict(xq[:, None], mode=0)


def test_a_mode_no_sample_ends_in_still_gets_a_defined_gp():
    """K = 3 on a log with two planted modes: the empty mode's GP conditions on the samples most
    likely in it instead of on nothing (which gave NaN means)."""
    t, x, f = planted_signal()
    mode = (((t >= 4) & (t < 8)) | ((t >= 11) & (t < 13.5))).astype(int)
    y = f + 1.0 * mode + 0.05 * np.random.default_rng(0).normal(size=len(t))
    m = MultimodalSEM(n_modes=3, disturbance=False, max_sweeps=10, min_mode_s=0.0, seed=0).fit(
        x[:, None], y[:, None], t=t)
    sizes = np.bincount(m.labels_, minlength=3)
    assert (sizes == 0).any(), sizes            # the case under test happens
    for k in range(3):
        mean, std = m.predict(x[:20, None], mode=k)
        assert np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()
    assert adjusted_rand_score(mode, m.labels_) >= 0.9


def test_true_runs_against_a_loop_over_every_short_mask():
    """separation.runs (from estep.stretches) against a plain loop, on every mask of up to 10 samples."""
    import itertools

    from mmgp.diagnosis.separation import runs

    def loop(mask):
        out, start = [], None
        for i, m in enumerate(list(mask) + [False]):
            if m and start is None:
                start = i
            elif not m and start is not None:
                out.append((start, i))
                start = None
        return out

    for T in range(11):
        for bits in itertools.product([False, True], repeat=T):
            assert runs(np.array(bits, bool)) == loop(bits)


def test_windowed_predictive_own_windows_equal_brute_force_refits():
    """Each query's own window (a hold widened beyond the radius) leaves exactly the support
    points inside it out: against refits on the rest, window by window."""
    ts, X, Y = toy_support()
    hyper = Hyper(np.array([[0.7, 1.2], [0.9, 0.5]]), np.array([1.1, 0.8]), np.array([0.02, 0.05]))
    gp = ExactGP(hyper=hyper, optimise=False).fit(X, Y)
    rng = np.random.default_rng(3)
    tq = np.concatenate([ts[::2], rng.uniform(-1, 11, 8)])
    Xq = np.column_stack([np.sin(tq), np.cos(0.7 * tq) * 3.0]) + 0.05 * rng.normal(size=(len(tq), 2))
    start = tq - rng.uniform(0.0, 3.0, len(tq))
    windows = np.stack([start, np.maximum(start, tq + rng.uniform(-0.5, 3.0, len(tq)))], 1)
    windows[::5] = windows[0]                     # queries far apart sharing one window
    mean, var = windowed_predictive(gp, Xq, tq, ts, 99.0, chunk=6, windows=windows)
    Xs, Ys = gp.Xs_.numpy(), gp.Ys_.numpy()
    Xq_s = gp.x_scaler_.transform(Xq)
    for i in range(len(tq)):
        keep = ~((ts >= windows[i, 0]) & (ts <= windows[i, 1]))
        for j in range(2):
            mu, v = gp_predict_ref(Xs[keep], Ys[keep, j], Xq_s[[i]], hyper.lengthscale[j], hyper.signal_var[j],
                                   hyper.noise_var[j])
            scale, shift = gp.y_scaler_.scale_[j], gp.y_scaler_.mean_[j]
            np.testing.assert_allclose(mean[i, j], mu[0] * scale + shift, rtol=1e-8, atol=1e-8 * scale)
            np.testing.assert_allclose(var[i, j], v[0] * scale ** 2, rtol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_hold_windows_cover_each_hold_against_a_walk(seed):
    """A still sample's window reaches its hold's first and last sample (a hold ends where a log
    starts), never less than t +- radius; a moving sample's is t +- radius: against a walk."""
    from mmgp.labelling.mstep import hold_windows

    rng = np.random.default_rng(seed)
    T, radius = 120, 0.35
    t = np.cumsum(rng.uniform(0.01, 0.2, T))
    still = rng.random(T) < 0.7
    starts = sorted({0, *rng.choice(np.arange(1, T), 3, replace=False).tolist()})
    out = hold_windows(t, still, radius, starts)
    for i in range(T):
        lo, hi = t[i] - radius, t[i] + radius
        if still[i]:
            a = i
            while a > 0 and still[a - 1] and a not in starts:
                a -= 1
            b = i
            while b + 1 < T and still[b + 1] and b + 1 not in starts:
                b += 1
            lo, hi = min(lo, t[a]), max(hi, t[b])
        np.testing.assert_allclose(out[i], [lo, hi], rtol=0, atol=0)
