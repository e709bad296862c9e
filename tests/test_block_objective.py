"""The final GP's leave-block-out hyperparameters on densely sampled logs (issue 31 item 9):
the closed-form gradient of the objective, the correlation time that sets its blocks, and the
chosen hyperparameters against a brute-force objective and a far held-out stretch."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mmgp.data.folds import decorrelation_time
from mmgp.gp.hyper import RBFParams, default_hyper, rbf_value_and_grad
from mmgp.gp.linalg import DTYPE
from mmgp.gp.objectives import leave_block_out
from mmgp.labelling.sem import MultimodalSEM


def brute_block_lpd(X, Y, ts, length, ls, sf, sn):
    """numpy reference: sum over samples and outputs of log p(y_i | samples outside i's block),
    consecutive blocks spanning at most ``length`` s; ls (m, d), sf (m,), sn (m,)."""
    N, total, first = len(ts), 0.0, 0
    while first < N:
        test = np.flatnonzero((np.arange(N) >= first) & (ts - ts[first] <= length))
        first = test[-1] + 1
        train = np.setdiff1d(np.arange(N), test)
        for j in range(Y.shape[1]):
            k = lambda A, B: sf[j] * np.exp(-0.5 * (((A[:, None] - B[None]) / ls[j]) ** 2).sum(-1))  # noqa: E731
            Kt = k(X[train], X[train]) + sn[j] * np.eye(len(train))
            ks = k(X[train], X[test])
            mean = ks.T @ np.linalg.solve(Kt, Y[train, j])
            var = sf[j] + sn[j] - np.einsum("ij,ij->j", ks, np.linalg.solve(Kt, ks))
            total += np.sum(-0.5 * (np.log(2 * np.pi * var) + (Y[test, j] - mean) ** 2 / var))
    return total


def test_block_objective_gradient_matches_finite_differences_of_brute_force():
    rng = np.random.default_rng(1)
    ts = np.sort(rng.uniform(0, 4, 36))
    X = np.c_[np.sin(ts), np.cos(2 * ts)] + 0.05 * rng.normal(size=(36, 2))
    Y = np.c_[np.sin(3 * ts), np.cos(ts)] + 0.1 * rng.normal(size=(36, 2))
    params = RBFParams(2, 2)
    theta = params.pack(default_hyper(2, 2, 0.05)) + 0.3 * rng.normal(size=8)
    F, g = rbf_value_and_grad(params, leave_block_out(ts, 0.7), torch.as_tensor(X, dtype=DTYPE),
                              torch.as_tensor(Y.T.copy(), dtype=DTYPE), torch.as_tensor(theta, dtype=DTYPE))

    def brute(th):
        h = params.to_hyper(th)
        return brute_block_lpd(X, Y, ts, 0.7, h.lengthscale, h.signal_var, h.noise_var)

    eps = 1e-5
    fd = [(brute(theta + eps * e) - brute(theta - eps * e)) / (2 * eps) for e in np.eye(8)]
    assert float(F) == pytest.approx(brute(theta), rel=1e-9)
    np.testing.assert_allclose(g.numpy(), fd, rtol=1e-5, atol=1e-6)


def test_decorrelation_time_of_a_sinusoid_is_arccos_of_one_over_e():
    """x = sin(w t): autocorrelation cos(w h), 1/e at h = arccos(1/e) / w; a gap between two
    stretches of the log must not count as a lag."""
    w, dt = 1.3, 0.01
    t = np.r_[np.arange(0, 40, dt), 100 + np.arange(0, 40, dt)]
    X = np.c_[np.sin(w * t), np.full(len(t), 2.0)]            # the constant column is left out
    assert decorrelation_time(t, X) == pytest.approx(math.acos(math.exp(-1)) / w, abs=dt)


def smooth_noise(t, tau, sd, rng):
    """AR(1) noise of correlation time ``tau`` s and std ``sd`` at times t: neighbours in time
    share it, as filtered and differentiated robot signals do."""
    a = math.exp(-(t[1] - t[0]) / tau)
    e = np.empty(len(t))
    e[0] = rng.normal() * sd
    for i in range(1, len(t)):
        e[i] = a * e[i - 1] + math.sqrt(1 - a * a) * sd * rng.normal()
    return e


def test_final_gp_block_hyperparameters_beat_loo_on_a_far_stretch_and_optimise_the_brute_objective():
    """A densely sampled smooth 2-D trajectory (a Lissajous curve, so later stretches pass
    between earlier ones) with time-correlated noise: leave-one-out reads the noise as signal
    (neighbours share it) and picks short lengthscales, leave-block-out on the honest blocks
    does not. References: the error on a later stretch of the log against the noiseless
    function, the block length against the correlation time, and the chosen hyperparameters
    against the brute-force objective around them (no neighbouring point is better)."""
    rng = np.random.default_rng(0)
    t = np.arange(0, 36, 0.02)
    x = np.c_[np.sin(0.7 * t), np.sin(1.1 * t + 0.5)]
    f = np.sin(2 * x[:, 0]) * np.cos(1.5 * x[:, 1])
    y = f + smooth_noise(t, 0.3, 0.15, rng)
    fit, far = t < 28, t >= 28
    kw = dict(n_modes=1, disturbance=False, fit_points=400, fit_iter=40)
    loo = MultimodalSEM(**kw).fit(x[fit], y[fit, None])               # no times: leave-one-out
    block = MultimodalSEM(**kw).fit(x[fit], y[fit, None], t=t[fit])
    gp = block.gps_[0]
    assert gp.block_s == pytest.approx(4 * decorrelation_time(t[fit], x[fit]), rel=1e-12)
    err = {k: float(np.mean((m.gps_[0].predict(x[far], return_std=False).ravel() - f[far]) ** 2))
           for k, m in (("loo", loo), ("block", block))}
    assert err["block"] < 0.2 * err["loo"], (err, loo.gps_[0].hyper_, gp.hyper_)
    # the optimum scored by the brute-force objective on the rows it was fitted on (the GP's own
    # random subset of fit_points, seed 0), standardised as the GP standardised them
    Xs, Ys, h = gp.Xs_.numpy(), gp.Ys_.numpy(), gp.hyper_
    rows = np.sort(np.random.default_rng(0).choice(len(Xs), 400, replace=False))
    params = RBFParams(1, 2)
    theta = params.pack(h)

    def brute(hh):
        return brute_block_lpd(Xs[rows], Ys[rows], t[fit][rows], gp.block_s, hh.lengthscale, hh.signal_var,
                               hh.noise_var)

    best = brute(h)
    for e in np.eye(len(theta)):
        for step in (-0.2, 0.2):
            assert brute(params.to_hyper(theta + step * e)) < best + 0.5
