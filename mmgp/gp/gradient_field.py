"""Gaussian processes whose mean is the gradient of a potential: the fitting side of the
position-only feedforward compensator (:mod:`mmgp.compensator`).

``CurlFreeGP`` (several joints) learns a scalar potential ``V ~ GP(0, k)`` with an ARD RBF kernel
``k(x, x') = s2 exp(-|(x - x')/l|^2 / 2)`` from observations of its *gradient*,
``y_a = grad V(x_a) + noise``. Gradient observations are jointly Gaussian with
``cov(dV/dx_i(x), dV/dx'_j(x')) = d^2 k / dx_i dx'_j = k/(l_i l_j) (delta_ij - u_i u_j)``,
``u = (x - x')/l`` (a curl-free matrix kernel), so the posterior mean is exactly a gradient field.
``RBFGP`` (one output) is the ordinary zero-mean RBF GP; in one dimension every field is a gradient.

Both fit their hyperparameters by the log marginal likelihood (closed-form dF/dK, chained through
the kernel by autograd) with the package's one optimiser, :func:`mmgp.gp.hyper.maximise`, on a
random subset of at most ``max_hyper_points`` positions (each evaluation factorises an
``(points * outputs)`` square matrix); the final weights solve the full system.
"""
from __future__ import annotations

import time
from functools import partial

import numpy as np
import torch
from sklearn.base import BaseEstimator
from sklearn.utils.validation import check_is_fitted

from .hyper import chained_value_and_grad, maximise
from .kernels import rbf_kernel
from .linalg import DTYPE, robust_cholesky
from .objectives import MARGINAL


def curl_free_kernel_np(X1, X2, lengthscales, signal_var) -> np.ndarray:
    """Gradient-gradient covariance of an RBF potential, closed form, numpy.

    Returns (N1*n, N2*n) with rows ordered (point, joint):
    ``K[(a,i),(b,j)] = s2 exp(-|u|^2/2) (delta_ij - u_i u_j) / (l_i l_j)``, ``u = (x_a - x_b)/l``.
    """
    X1, X2 = np.asarray(X1, float), np.asarray(X2, float)
    l = np.asarray(lengthscales, float)
    N1, n = X1.shape
    N2 = X2.shape[0]
    out = np.empty((N1, n, N2, n))
    eye = np.eye(n)
    il = 1.0 / l
    step = max(1, 2_000_000 // max(1, N2 * n * n))
    for s in range(0, N1, step):
        U = (X1[s:s + step, None, :] - X2[None]) * il  # (t, N2, n)
        k = signal_var * np.exp(-0.5 * np.sum(U * U, axis=2))
        B = (eye[None, None] - U[..., :, None] * U[..., None, :]) * (il[:, None] * il[None, :])
        out[s:s + step] = np.transpose(k[..., None, None] * B, (0, 2, 1, 3))
    return out.reshape(N1 * n, N2 * n)


def rbf_kernel_np(X1, X2, lengthscales, signal_var) -> np.ndarray:
    """(N1, N2) RBF kernel ``s2 exp(-|(x - x')/l|^2 / 2)``, numpy."""
    U = (np.asarray(X1, float)[:, None, :] - np.asarray(X2, float)[None]) / np.asarray(lengthscales, float)
    return signal_var * np.exp(-0.5 * np.sum(U * U, axis=2))


def curl_free_kernel_torch(X1: torch.Tensor, X2: torch.Tensor, log_l: torch.Tensor, log_s2: torch.Tensor) -> torch.Tensor:
    """:func:`curl_free_kernel_np` in torch, differentiable in the log lengthscales (n,) and log s2."""
    l = torch.exp(log_l)
    U = (X1[:, None, :] - X2[None]) / l
    k = torch.exp(log_s2 - 0.5 * (U * U).sum(-1))
    n = X1.shape[1]
    eye = torch.eye(n, dtype=X1.dtype)
    B = (eye - U[..., :, None] * U[..., None, :]) / (l[:, None] * l[None, :])
    K = (k[..., None, None] * B).permute(0, 2, 1, 3)
    return K.reshape(X1.shape[0] * n, X2.shape[0] * n)


def _rbf_kernel_torch(X1: torch.Tensor, X2: torch.Tensor, log_l: torch.Tensor, log_s2: torch.Tensor) -> torch.Tensor:
    return rbf_kernel(X1, X2, torch.exp(log_l)[None], torch.exp(log_s2).reshape(1))[0]


class _PotentialGP(BaseEstimator):
    """Shared settings and fitting of the potential GPs (subclasses pick the kernel).

    Settings: ``max_hyper_points`` (hyperparameter subset size; None: the class default),
    ``max_iter`` (L-BFGS iterations; None: the class default), ``noise_floor_rel``, ``seed``.
    ``fit(Q (N, n) rad, Y (N, d))`` sets ``lengthscales_`` (n,), ``signal_var_``, ``noise_var_``
    (d,), ``nll_`` (negative log marginal likelihood per datum on the subset), ``support_`` (N, n),
    ``alpha_`` (N, d) (the solved weights), ``jitter_``, ``hyper_time_s_``, ``solve_time_s_``.
    """

    default_hyper_points: int
    default_iter: int
    _gradient_targets: bool
    _kernel_torch: staticmethod
    _kernel_np: staticmethod

    def __init__(self, max_hyper_points: int | None = None, max_iter: int | None = None,
                 noise_floor_rel: float = 1e-8, seed: int = 0):
        self.max_hyper_points = max_hyper_points
        self.max_iter = max_iter
        self.noise_floor_rel = noise_floor_rel
        self.seed = seed

    def fit(self, Q, Y):
        Q = np.asarray(Q, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64).reshape(Q.shape[0], -1)
        N, d = Y.shape
        rng = np.random.default_rng(self.seed)
        sub = rng.permutation(N)[: min(N, self.max_hyper_points or self.default_hyper_points)]
        t0 = time.perf_counter()
        l, s2, noise, nll = fit_potential_hyper(Q[sub], Y[sub], self._kernel_torch,
                                                gradient_targets=self._gradient_targets,
                                                max_iter=self.max_iter or self.default_iter,
                                                noise_floor_rel=self.noise_floor_rel)
        t1 = time.perf_counter()
        K = torch.from_numpy(self._kernel_np(Q, Q, l, s2))
        K.diagonal().add_(torch.from_numpy(np.tile(noise, N)))
        L, self.jitter_ = robust_cholesky(K)
        del K
        alpha = torch.cholesky_solve(torch.from_numpy(Y.reshape(-1, 1)), L)
        self.hyper_time_s_ = t1 - t0
        self.solve_time_s_ = time.perf_counter() - t1
        self.lengthscales_, self.signal_var_, self.noise_var_, self.nll_ = l, s2, noise, nll
        self.support_ = Q
        self.alpha_ = alpha.numpy().reshape(N, d)
        return self


class CurlFreeGP(_PotentialGP):
    """GP on a scalar potential V(q) fitted to gradient observations (torques), Y (N, n).

    The fitted state feeds :class:`mmgp.compensator.Compensator` ("curl-free-rbf"): with
    ``gamma_a = alpha_a / l``, ``V(q) = sum_a k(q, z_a) u_a . gamma_a`` and tau_ff = grad V.
    Defaults: 150 hyperparameter points (each evaluation factorises a (150 n) square matrix), 75
    iterations.
    """

    default_hyper_points = 150
    default_iter = 75
    _gradient_targets = True
    _kernel_torch = staticmethod(curl_free_kernel_torch)
    _kernel_np = staticmethod(curl_free_kernel_np)


class RBFGP(_PotentialGP):
    """Ordinary zero-mean ARD-RBF GP for one output, y (N,) or (N, 1) (erf-1dof export).

    ``predict(Q (T, n)) -> (T,)`` is the posterior mean. Defaults: 500 hyperparameter points, 100
    iterations.
    """

    default_hyper_points = 500
    default_iter = 100
    _gradient_targets = False
    _kernel_torch = staticmethod(_rbf_kernel_torch)
    _kernel_np = staticmethod(rbf_kernel_np)

    def predict(self, Q):
        check_is_fitted(self, "alpha_")
        Q = np.asarray(Q, dtype=np.float64)
        out = np.empty(Q.shape[0])
        step = max(1, 4_000_000 // max(1, self.support_.size))
        for s in range(0, Q.shape[0], step):
            out[s:s + step] = rbf_kernel_np(Q[s:s + step], self.support_, self.lengthscales_,
                                            self.signal_var_) @ self.alpha_[:, 0]
        return out


def fit_potential_hyper(X, Y, kernel, *, gradient_targets: bool, max_iter: int = 100, noise_floor_rel: float = 1e-8):
    """Maximise the marginal likelihood of a zero-mean GP with ``kernel(X1, X2, log_l, log_s2)``.

    X: (m, n) positions, Y: (m, d) targets: d = n gradient components (``gradient_targets``, the
    curl-free kernel) or d = 1 values (the RBF kernel); rows of the (m d, m d) kernel are ordered
    (point, output).
    Parameters: log lengthscales (n), log signal variance, log noise variance per output column.
    The noise is floored at ``noise_floor_rel`` times the mean square target (at least 1e-6 of
    the mean over outputs), because targets taken from a model's prediction are almost noise-free
    and an unfloored likelihood drives the noise to zero and the system to singularity.
    Returns (lengthscales (n,), signal_var, noise_var (d,), negative log likelihood per datum).
    """
    X_t = torch.as_tensor(X, dtype=DTYPE)
    Y_t = torch.as_tensor(Y, dtype=DTYPE)
    m, n = X_t.shape
    d = Y_t.shape[1]
    ms = torch.clamp((Y_t ** 2).mean(0), min=1e-12)  # per-output mean square (zero-mean GP)
    sd = torch.clamp(X_t.std(0), min=1e-3)
    # the gradient variance of an RBF potential is s2 / l^2
    s2_0 = (ms * sd ** 2).mean() if gradient_targets else ms.mean()
    # A joint whose torque is ~0 everywhere (e.g. a vertical first axis) would get a ~0 floor;
    # the outputs are coupled through V, so tie its floor to the overall torque scale too.
    floor = noise_floor_rel * torch.clamp(ms, min=1e-6 * float(ms.mean()))
    y = Y_t.reshape(1, -1)
    noise_cols = torch.arange(m * d) % d

    def gram(theta):
        K = kernel(X_t, X_t, theta[:n], theta[n])
        return (K + torch.diag((floor + torch.exp(theta[n + 1:]))[noise_cols])).unsqueeze(0)

    theta0 = torch.cat([torch.log(sd), torch.log(s2_0).reshape(1), torch.log(1e-3 * ms)]).numpy()
    # Matrices of a few thousand rows gain little from threads, and on a shared machine extra
    # threads oversubscribe the cores (measured 10x slower with 2 threads under load).
    best = maximise(partial(chained_value_and_grad, MARGINAL, gram, y), theta0, n=y.numel(), max_iter=max_iter,
                    rows=y.numel(), history=20)
    theta = theta0 if best is None else best.theta
    # A torque that does not depend on a joint (a vertical first axis) drives its lengthscale
    # to overflow; 1e6 x the data spread is already constant to 1e-12 and keeps files finite.
    l_out = np.minimum(np.exp(theta[:n]), 1e6 * max(float(sd.max()), 1.0))
    nll = float("nan") if best is None else -best.value
    return l_out, float(np.exp(theta[n])), (floor + torch.exp(torch.as_tensor(theta[n + 1:]))).numpy().copy(), nll
