"""Exact GP (mmgp.gp) and scalable GP (mmgp.gp_sparse) against independent references:
brute-force leave-one-out refits, scikit-learn's GaussianProcessRegressor, torch autograd."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from mmgp.gp.linalg import DTYPE, GPNumericalError, robust_cholesky
from mmgp.gp.exact import ExactGP
from mmgp.gp.hyper import Hyper, default_hyper, optimise_hyper
from mmgp.gp.objectives import _value_and_grad, log_marginal_likelihood, loo_log_predictive
from mmgp.gp.kernels import rbf_kernel


def toy(N=40, d=2, m=2, seed=0, noise=0.1):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, size=(N, d)) * np.arange(1, d + 1)  # unequal input scales
    F = np.stack([np.sin(X[:, 0]) + 0.3 * X[:, -1], np.cos(0.7 * X[:, 0] * X[:, -1])], 1)[:, :m]
    Y = 5.0 * F + 2.0 + noise * rng.normal(size=(N, m))
    return X, Y


def fixed_hyper(d, m):
    return Hyper(np.array([[0.8, 1.3], [1.1, 0.6]])[:m, :d], np.array([1.2, 0.7])[:m], np.array([0.05, 0.02])[:m])


def data_unit_kernel(gp, j, A, B):
    """RBF kernel of output j in data units, from the fitted GP's public learned state (numpy)."""
    ls = gp.lengthscale_[j]
    s2 = gp.hyper_.signal_var[j] * gp.y_scaler_.scale_[j] ** 2
    D = ((A[:, None, :] - B[None, :, :]) / ls) ** 2
    return s2 * np.exp(-0.5 * D.sum(-1))


def test_loo_closed_form_matches_brute_force_refits():
    X, Y = toy()
    gp = ExactGP().fit(X, Y, hyper=fixed_hyper(2, 2), optimise=False)
    mean, std = gp.loo_predictive()
    lpd = gp.loo_log_predictive()
    N = X.shape[0]
    total = 0.0
    for j in range(2):
        noise = gp.noise_std_[j] ** 2
        y = Y[:, j] - gp.y_scaler_.mean_[j]  # the GP's constant prior mean is the training mean
        for i in range(N):
            keep = np.arange(N) != i
            K = data_unit_kernel(gp, j, X[keep], X[keep]) + noise * np.eye(N - 1)
            k = data_unit_kernel(gp, j, X[keep], X[i:i + 1])[:, 0]
            kss = data_unit_kernel(gp, j, X[i:i + 1], X[i:i + 1])[0, 0]
            mu = k @ np.linalg.solve(K, y[keep]) + gp.y_scaler_.mean_[j]
            var = kss + noise - k @ np.linalg.solve(K, k)
            assert mean[i, j] == pytest.approx(mu, abs=1e-8 * max(1, abs(mu)))
            assert std[i, j] ** 2 == pytest.approx(var, rel=1e-8)
            total += -0.5 * (math.log(2 * math.pi * var) + (Y[i, j] - mu) ** 2 / var)
    assert lpd == pytest.approx(total, rel=1e-9)


@pytest.mark.parametrize("include_noise", [False, True])
def test_predictions_match_sklearn_at_fixed_hyperparameters(include_noise):
    X, Y = toy(N=50)
    Xq = np.random.default_rng(1).uniform(-2, 2, size=(30, 2)) * [1, 2]
    hyp = fixed_hyper(2, 2)
    gp = ExactGP().fit(X, Y, hyper=hyp, optimise=False)
    mean, std = gp.predict(Xq, include_noise=include_noise)
    for j in range(2):
        # sklearn's normalize_y uses the same mean/population-std scaling of y, so the kernel
        # amplitudes are the standardised ones; its inputs are raw, so lengthscales in data units.
        noise = WhiteKernel(hyp.noise_var[j], noise_level_bounds="fixed")
        k = ConstantKernel(hyp.signal_var[j]) * RBF(gp.lengthscale_[j]) + noise
        sk = GaussianProcessRegressor(k, optimizer=None, normalize_y=True, alpha=0.0).fit(X, Y[:, j])
        m_sk, s_sk = sk.predict(Xq, return_std=True)  # includes the WhiteKernel noise
        if not include_noise:
            s_sk = np.sqrt(s_sk ** 2 - hyp.noise_var[j] * gp.y_scaler_.scale_[j] ** 2)
        np.testing.assert_allclose(mean[:, j], m_sk, rtol=0, atol=1e-8 * np.abs(m_sk).max())
        np.testing.assert_allclose(std[:, j], s_sk, rtol=1e-7, atol=1e-9)
        # and the marginal likelihood of the standardised outputs at the same theta
        theta = np.log([hyp.signal_var[j], *gp.lengthscale_[j]])
        lml_sk = sk.log_marginal_likelihood(theta)
        Xs = torch.as_tensor(gp.x_scaler_.transform(X), dtype=DTYPE)
        ys = torch.as_tensor(gp.y_scaler_.transform(Y)[:, j][None], dtype=DTYPE)
        K = rbf_kernel(Xs, Xs, torch.as_tensor(hyp.lengthscale[j:j + 1]), torch.as_tensor(hyp.signal_var[j:j + 1]))
        K = K + hyp.noise_var[j] * torch.eye(len(X), dtype=DTYPE)
        assert float(log_marginal_likelihood(K, ys)[0]) == pytest.approx(lml_sk, rel=1e-10)


@pytest.mark.parametrize("objective", ["loo", "marginal"])
@pytest.mark.parametrize("ard", [True, False])
def test_analytic_gradient_matches_autograd(objective, ard):
    rng = np.random.default_rng(2)
    N, d, m = 35, 3, 2
    X = torch.as_tensor(rng.normal(size=(N, d)), dtype=DTYPE)
    y = torch.as_tensor(rng.normal(size=(m, N)), dtype=DTYPE)
    log_ls = torch.as_tensor(rng.normal(scale=0.3, size=(m, d if ard else 1)), dtype=DTYPE).requires_grad_()
    log_sf = torch.as_tensor(rng.normal(scale=0.3, size=m), dtype=DTYPE).requires_grad_()
    log_sn = torch.as_tensor(rng.normal(size=m) - 2, dtype=DTYPE).requires_grad_()
    K = rbf_kernel(X, X, torch.exp(log_ls), torch.exp(log_sf)) + (torch.exp(log_sn) + 1e-6)[:, None, None] * torch.eye(N, dtype=DTYPE)
    F_ref = (loo_log_predictive if objective == "loo" else log_marginal_likelihood)(K, y)
    F_ref.sum().backward()
    with torch.no_grad():
        F, g_ls, g_sf, g_sn = _value_and_grad(X, y, log_ls, log_sf, log_sn, 1e-6, objective)
    torch.testing.assert_close(F, F_ref.detach(), rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(g_ls, log_ls.grad, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(g_sf, log_sf.grad, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(g_sn, log_sn.grad, rtol=1e-9, atol=1e-9)


def test_optimiser_improves_loo_objective_and_reports_it():
    X, Y = toy(N=80, noise=0.2)
    Xs = torch.as_tensor((X - X.mean(0)) / X.std(0), dtype=DTYPE)
    Ys = torch.as_tensor((Y - Y.mean(0)) / Y.std(0), dtype=DTYPE)
    init = default_hyper(2, 2)

    def loo(h):
        lt, st, nt = h.to_torch("cpu")
        K = rbf_kernel(Xs, Xs, lt, st) + nt[:, None, None] * torch.eye(len(X), dtype=DTYPE)
        return float(loo_log_predictive(K, Ys.T).sum()) / len(X)

    start = loo(init)
    hyp, value = optimise_hyper(Xs, Ys, init, objective="loo", max_iter=60)
    assert value == pytest.approx(loo(hyp), rel=1e-9)
    assert value > start + 0.5  # per-sample log density, summed over 2 outputs
    # the noise std was 0.2 on outputs of amplitude ~5: the learned noise must be of that order
    gp = ExactGP().fit(X, Y)
    assert np.all((gp.noise_std_ > 0.1) & (gp.noise_std_ < 0.4))


def test_duplicated_inputs_with_tiny_noise_factorise_with_jitter():
    X, Y = toy(N=30)
    X = np.repeat(X, 3, axis=0)  # every input three times: K is singular without noise
    Y = np.repeat(Y, 3, axis=0)
    hyp = Hyper(np.ones((2, 2)), np.ones(2), np.zeros(2))  # noise-free: K has rank 30 of 90
    gp = ExactGP().fit(X, Y, hyper=hyp, optimise=False)
    assert gp.jitter_ > 0
    mean, std = gp.predict(X[:5])
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
    np.testing.assert_allclose(mean, Y[:5], atol=1e-3 * np.abs(Y).max())


def test_hopeless_matrix_raises_clear_error():
    K = torch.eye(4, dtype=DTYPE).expand(2, 4, 4).clone()
    K[1, 2, 2] = float("nan")
    with pytest.raises(GPNumericalError, match="NaN or inf"):
        robust_cholesky(K)
    indefinite = torch.diag(torch.tensor([1.0, -1.0, 1.0], dtype=DTYPE))
    with pytest.raises(GPNumericalError, match="not positive definite"):
        robust_cholesky(indefinite)
    X, Y = toy(N=20)
    X[3, 1] = np.nan
    with pytest.raises(GPNumericalError):
        ExactGP().fit(X, Y, hyper=fixed_hyper(2, 2), optimise=False)


def test_batched_outputs_equal_single_output_fits():
    X, Y = toy(N=60, noise=0.1)
    Xq = X[:7] + 0.1
    hyp = fixed_hyper(2, 2)
    both = ExactGP().fit(X, Y, hyper=hyp, optimise=False)
    mean, std = both.predict(Xq)
    lm, ls = both.loo_predictive()
    opt_both = ExactGP(coarse_fit_points=0).fit(X, Y)
    for j in range(2):
        hj = Hyper(hyp.lengthscale[j:j + 1], hyp.signal_var[j:j + 1], hyp.noise_var[j:j + 1])
        one = ExactGP().fit(X, Y[:, j], hyper=hj, optimise=False)
        m1, s1 = one.predict(Xq)
        assert m1.shape == (7,)
        np.testing.assert_allclose(mean[:, j], m1, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(std[:, j], s1, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(lm[:, j], one.loo_predictive()[0], rtol=1e-12, atol=1e-12)
        # optimised jointly vs alone: the objective is a sum of independent terms, so both
        # optimisers should reach the same optimum (not bit-identical: the line search is joint)
        opt_one = ExactGP(coarse_fit_points=0).fit(X, Y[:, j])
        np.testing.assert_allclose(opt_both.predict(Xq)[0][:, j], opt_one.predict(Xq)[0],
                                   atol=2e-3 * np.abs(Y[:, j]).std())


# ---------------------------------------------------------------- scalable GP (mmgp.gp_sparse)
from mmgp.gp.sparse import SparseGP, make_gp


def test_sparse_gp_with_all_inputs_inducing_equals_exact_gp():
    X, Y = toy(N=40)
    hyp = Hyper(np.full((2, 2), 0.7), np.ones(2), np.array([0.05, 0.02]))
    ex = ExactGP().fit(X, Y, hyper=hyp, optimise=False)
    sp = SparseGP(n_inducing=len(X)).fit(X, Y, hyper=hyp, optimise=False)  # Z = X: Qff = Kff
    Xq = X[:9] + 0.05
    for a, b in zip(ex.predict(Xq, include_noise=True), sp.predict(Xq, include_noise=True)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * np.abs(Y).max())
    for a, b in zip(ex.loo_predictive(), sp.loo_predictive()):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * np.abs(Y).max())
    assert sp.loo_log_predictive() == pytest.approx(ex.loo_log_predictive(), rel=1e-6)


def test_sparse_gp_matches_dense_sgpr_formulas_and_dtc_loo_refits():
    X, Y = toy(N=60, m=1)
    y = Y[:, 0]
    hyp = Hyper(np.array([[0.9, 1.4]]), np.array([1.3]), np.array([0.03]))
    sp = SparseGP(n_inducing=12).fit(X, y, hyper=hyp, optimise=False)
    assert sp.Z_.shape == (12, 2)
    # dense numpy reference in standardised units, from the textbook SGPR / DTC expressions
    Xs, Z = sp.x_scaler_.transform(X), sp.Z_
    Xq = sp.x_scaler_.transform(X[:10] * 0.9)
    ys = (y - sp.y_scaler_.mean_[0]) / sp.y_scaler_.scale_[0]
    k = lambda A, B: 1.3 * np.exp(-0.5 * (((A[:, None] - B[None]) / hyp.lengthscale[0]) ** 2).sum(-1))  # noqa: E731
    s2 = 0.03
    Kuu, Kuf, Ksu = k(Z, Z), k(Z, Xs), k(Xq, Z)
    Sigma = np.linalg.inv(Kuu + Kuf @ Kuf.T / s2)
    mean = Ksu @ Sigma @ Kuf @ ys / s2
    var = 1.3 - np.einsum("ij,ji->i", Ksu, np.linalg.solve(Kuu, Ksu.T)) + np.einsum("ij,jk,ki->i", Ksu, Sigma, Ksu.T)
    m_sp, s_sp = sp.predict(X[:10] * 0.9)
    sc = sp.y_scaler_.scale_[0]
    np.testing.assert_allclose(m_sp, mean * sc + sp.y_scaler_.mean_[0], rtol=1e-7, atol=1e-7 * sc)
    np.testing.assert_allclose(s_sp, np.sqrt(var) * sc, rtol=1e-6)
    # LOO of the approximate model by brute force: condition Qff + s2 I on all rows but one
    C = Kuf.T @ np.linalg.solve(Kuu, Kuf) + s2 * np.eye(len(X))
    lm, lsd = sp.loo_predictive()
    for i in range(0, len(X), 7):
        r = np.arange(len(X)) != i
        w = np.linalg.solve(C[np.ix_(r, r)], C[r, i])
        assert lm[i] == pytest.approx(w @ ys[r] * sc + sp.y_scaler_.mean_[0], rel=1e-7)
        assert lsd[i] == pytest.approx(np.sqrt(C[i, i] - C[r, i] @ w) * sc, rel=1e-7)


def test_make_gp_switches_at_threshold_and_sparse_fit_is_accurate():
    assert type(make_gp(3000, n_inducing=50)) is ExactGP
    assert type(make_gp(3001, n_inducing=50)) is SparseGP
    assert type(make_gp(500, exact_threshold=100)) is SparseGP
    X, Y = toy(N=600, noise=0.05)
    Xq, Yq = toy(N=200, noise=0.0, seed=5)
    sp = make_gp(len(X), exact_threshold=200, n_inducing=60, max_fit_points=200, max_iter=30).fit(X, Y)
    ex = ExactGP(max_fit_points=200, max_iter=30).fit(X, Y)
    nmse = lambda gp: (((gp.predict(Xq, return_std=False) - Yq) ** 2).mean(0) / Yq.var(0))  # noqa: E731
    assert np.all(nmse(sp) < 0.01) and np.all(nmse(ex) < 0.01)  # smooth 2-d target, 600 samples


def test_subset_method_loo_is_exact_on_subset_and_held_out_elsewhere():
    X, Y = toy(N=120)
    hyp = fixed_hyper(2, 2)
    sp = SparseGP(method="subset", n_subset=50).fit(X, Y, hyper=hyp, optimise=False)
    lm, ls = sp.loo_predictive()
    rest = np.setdiff1d(np.arange(len(X)), sp.subset_)
    # reference: an exact GP on the subset, with the scalers of the full data
    ex = ExactGP().fit(X[sp.subset_], Y[sp.subset_], hyper=hyp, optimise=False)
    m_ref, s_ref = ex.predict(X[rest], include_noise=True)
    np.testing.assert_allclose(lm[rest], m_ref, rtol=1e-12)
    np.testing.assert_allclose(ls[rest], s_ref, rtol=1e-12)
    np.testing.assert_allclose(lm[sp.subset_], ex.loo_predictive()[0], rtol=1e-12)
    ref = -0.5 * (np.log(2 * np.pi * ls ** 2) + ((Y - lm) / ls) ** 2).sum()
    assert sp.loo_log_predictive() == pytest.approx(ref, rel=1e-12)
