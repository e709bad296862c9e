"""Gaussian processes whose mean is the gradient of a potential: the fitting side of the
position-only feedforward compensator (:mod:`mmgp.compensator`).

``CurlFreeGP`` (several joints) learns a scalar potential ``V ~ GP(0, k)`` with an ARD RBF kernel
``k(x, x') = s2 exp(-|(x - x')/l|^2 / 2)`` from observations of its *gradient*,
``y_a = grad V(x_a) + noise``. Gradient observations are jointly Gaussian with
``cov(dV/dx_i(x), dV/dx'_j(x')) = d^2 k / dx_i dx'_j = k/(l_i l_j) (delta_ij - u_i u_j)``,
``u = (x - x')/l`` (a curl-free matrix kernel), so the posterior mean is exactly a gradient field.
``RBFGP`` (one output) is the ordinary zero-mean RBF GP; in one dimension every field is a gradient.

Any radial kernel ``k = s2 phi(|u|)`` gives the same structure with two radial functions,
``cov = s2 (A(r) delta_ij - B(r) u_i u_j) / (l_i l_j)``, ``A = -phi'/r``, ``B = (phi'' - phi'/r)/r^2``
(the RBF: ``A = B = exp(-r^2/2)``). ``CurlFreeGP(profile=...)`` takes such a profile object (methods
``A(r)``, ``B(r)`` written in plain arithmetic, so they evaluate numpy arrays and torch tensors),
e.g. the compactly supported :class:`mmgp.compensator.kernels.WendlandProfile`; the lengthscales
are then the kernel's support radii.

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


def curl_free_kernel_np(X1, X2, lengthscales, signal_var, profile=None) -> np.ndarray:
    """Gradient-gradient covariance of a radial potential kernel, closed form, numpy.

    Returns (N1*n, N2*n) with rows ordered (point, joint):
    ``K[(a,i),(b,j)] = s2 (A(r) delta_ij - B(r) u_i u_j) / (l_i l_j)``, ``u = (x_a - x_b)/l``, r = |u|;
    ``profile`` None: the RBF, ``A = B = exp(-r^2/2)``.
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
        ra, rb = _radial(np.sum(U * U, axis=2), profile, np.sqrt, np.exp)
        blk = ra[..., None, None] * eye[None, None] - rb[..., None, None] * (U[..., :, None] * U[..., None, :])
        out[s:s + step] = np.transpose(signal_var * blk * (il[:, None] * il[None, :]), (0, 2, 1, 3))
    return out.reshape(N1 * n, N2 * n)


def rbf_kernel_np(X1, X2, lengthscales, signal_var) -> np.ndarray:
    """(N1, N2) RBF kernel ``s2 exp(-|(x - x')/l|^2 / 2)``, numpy."""
    U = (np.asarray(X1, float)[:, None, :] - np.asarray(X2, float)[None]) / np.asarray(lengthscales, float)
    return signal_var * np.exp(-0.5 * np.sum(U * U, axis=2))


def _radial(r2, profile, sqrt, exp):
    """(A, B) at squared radii r2 for ``profile`` (None: the RBF)."""
    if profile is None:
        a = exp(-0.5 * r2)
        return a, a
    r = sqrt(r2)
    return profile.A(r), profile.B(r)


def _safe_sqrt(r2: torch.Tensor) -> torch.Tensor:
    # sqrt has an infinite derivative at 0 (the kernel's diagonal); clamping there gives the
    # correct zero gradient, since r2 does not move with the hyperparameters where x = x'.
    return torch.sqrt(r2.clamp_min(1e-300))


def curl_free_kernel_torch(X1: torch.Tensor, X2: torch.Tensor, log_l: torch.Tensor, log_s2: torch.Tensor,
                           profile=None) -> torch.Tensor:
    """:func:`curl_free_kernel_np` in torch, differentiable in the log lengthscales (n,) and log s2."""
    l = torch.exp(log_l)
    U = (X1[:, None, :] - X2[None]) / l
    ra, rb = _radial((U * U).sum(-1), profile, _safe_sqrt, torch.exp)
    n = X1.shape[1]
    eye = torch.eye(n, dtype=X1.dtype)
    blk = ra[..., None, None] * eye - rb[..., None, None] * (U[..., :, None] * U[..., None, :])
    K = (torch.exp(log_s2) * blk / (l[:, None] * l[None, :])).permute(0, 2, 1, 3)
    return K.reshape(X1.shape[0] * n, X2.shape[0] * n)


#: the potential GPs' noise floor, relative to the mean square target (:func:`fit_potential_hyper`)
NOISE_FLOOR_REL = 1e-8

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
    lengthscale_init: float = 1.0
    max_lengthscale = None
    noise_init: float = 1e-3

    def __init__(self, max_hyper_points: int | None = None, max_iter: int | None = None,
                 noise_floor_rel: float = NOISE_FLOOR_REL, seed: int = 0):
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
        kernel_torch, kernel_np = self._kernels()
        hyper = partial(fit_potential_hyper, Q[sub], Y[sub], kernel_torch, gradient_targets=self._gradient_targets,
                        max_iter=self.max_iter or self.default_iter, noise_floor_rel=self.noise_floor_rel,
                        noise_init=self.noise_init)
        l, s2, noise, nll = hyper(lengthscale_init=self.lengthscale_init, max_lengthscale=self.max_lengthscale)
        # (the signal and noise variances are not fitted again for shrunk radii: doing so changed
        # no figure; benchmarks/README.md, "sixth session: tuning history")
        l = self._limit_support(Q, l)
        t1 = time.perf_counter()
        K = torch.from_numpy(kernel_np(Q, Q, l, s2))
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

    def _kernels(self):
        return self._kernel_torch, self._kernel_np

    def _limit_support(self, Q, lengthscales):
        return lengthscales


class CurlFreeGP(_PotentialGP):
    """GP on a scalar potential V(q) fitted to gradient observations (torques), Y (N, n).

    The fitted state feeds :class:`mmgp.compensator.Compensator` ("curl-free-rbf", or
    "curl-free-wendland" with a Wendland ``profile``): with ``gamma_a = alpha_a / l``,
    ``V(q) = s2 sum_a A(r_a) u_a . gamma_a`` and tau_ff = grad V.
    Defaults: 150 hyperparameter points (each evaluation factorises a (150 n) square matrix), 75
    iterations. Extra settings: ``profile`` (None: RBF), ``lengthscale_init`` (the starting
    lengthscales are this times the data's standard deviation per input), ``max_lengthscale``
    (None, a number or (n,) upper bounds on the fitted lengthscales, input units) and, for a
    compactly supported profile, ``max_neighbours``: after the hyperparameter fit, all lengthscales
    (support radii) are shrunk by one factor until the support points have at most this many
    support points within their radius on average (:func:`neighbour_limited_scale`); the
    evaluation cost of the exported field grows with that number. ``radius_scale_`` records the
    factor (1: no shrinking). ``noise_init``: the noise variances start at this times the targets'
    mean squares (the likelihood has a low-noise optimum that interpolates, and, for targets that
    are not exactly a gradient field, a second one that calls the non-conservative part noise;
    which one the optimiser reaches depends on where it starts).
    """

    default_hyper_points = 150
    default_iter = 75
    _gradient_targets = True
    _kernel_torch = staticmethod(curl_free_kernel_torch)
    _kernel_np = staticmethod(curl_free_kernel_np)

    def __init__(self, max_hyper_points: int | None = None, max_iter: int | None = None,
                 noise_floor_rel: float = NOISE_FLOOR_REL, seed: int = 0, profile=None, lengthscale_init: float = 1.0,
                 max_lengthscale=None, max_neighbours: int | None = None, noise_init: float = 1e-3):
        super().__init__(max_hyper_points, max_iter, noise_floor_rel, seed)
        self.noise_init = noise_init
        self.profile = profile
        self.lengthscale_init = lengthscale_init
        self.max_lengthscale = max_lengthscale
        self.max_neighbours = max_neighbours

    def _limit_support(self, Q, lengthscales):
        self.radius_scale_ = 1.0
        if self.profile is None or self.max_neighbours is None:
            return lengthscales
        self.radius_scale_ = neighbour_limited_scale(Q / lengthscales, self.max_neighbours)
        return lengthscales * self.radius_scale_

    def _kernels(self):
        if self.profile is None:
            return self._kernel_torch, self._kernel_np
        return (partial(curl_free_kernel_torch, profile=self.profile),
                partial(curl_free_kernel_np, profile=self.profile))


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


def neighbour_limited_scale(Z, max_neighbours: int) -> float:
    """Largest factor c <= 1 such that the points Z (N, n) (in units of their support radii) have on
    average at most ``max_neighbours`` points (themselves included) closer than c.

    The ordered pairs closer than c number at most ``max_neighbours * N`` exactly when c is at most
    the next pairwise distance in sorted order."""
    Z = np.asarray(Z, dtype=np.float64)
    N = Z.shape[0]
    if max_neighbours >= N:
        return 1.0
    d = np.empty((N, N))
    step = max(1, 2_000_000 // max(1, Z.size))
    for s in range(0, N, step):  # differences, not the Gram expansion: the evaluators' own rounding
        D = Z[s:s + step, None, :] - Z[None]
        d[s:s + step] = np.sqrt(np.sum(D * D, axis=2))
    d = d.ravel()
    k = int(max_neighbours) * N
    return float(min(1.0, np.partition(d, k)[k]))


def fit_potential_hyper(X, Y, kernel, *, gradient_targets: bool, max_iter: int = 100, noise_floor_rel: float = NOISE_FLOOR_REL,
                        lengthscale_init: float = 1.0, max_lengthscale=None, noise_init: float = 1e-3):
    """Maximise the marginal likelihood of a zero-mean GP with ``kernel(X1, X2, log_l, log_s2)``.

    X: (m, n) positions, Y: (m, d) targets: d = n gradient components (``gradient_targets``, the
    curl-free kernel) or d = 1 values (the RBF kernel); rows of the (m d, m d) kernel are ordered
    (point, output).
    Parameters: log lengthscales (n), log signal variance, log noise variance per output column
    (started at ``noise_init`` times each column's mean square);
    lengthscales start at ``lengthscale_init`` times the inputs' standard deviations and are
    bounded above by ``max_lengthscale`` (None, scalar or (n,), input units) when given.
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

    theta0 = torch.cat([torch.log(lengthscale_init * sd), torch.log(s2_0).reshape(1), torch.log(noise_init * ms)]).numpy()
    bounds = None
    if max_lengthscale is not None:
        cap = np.log(np.broadcast_to(np.asarray(max_lengthscale, dtype=np.float64), (n,)))
        theta0[:n] = np.minimum(theta0[:n], cap)
        bounds = [(None, c) for c in cap] + [(None, None)] * (1 + d)
    # Matrices of a few thousand rows gain little from threads, and on a shared machine extra
    # threads oversubscribe the cores (mmgp.threads).
    best = maximise(partial(chained_value_and_grad, MARGINAL, gram, y), theta0, n=y.numel(), max_iter=max_iter,
                    rows=y.numel(), history=20, bounds=bounds)
    theta = theta0 if best is None else best.theta
    # A torque that does not depend on a joint (a vertical first axis) drives its lengthscale
    # to overflow; 1e6 x the data spread is already constant to 1e-12 and keeps files finite.
    l_out = np.minimum(np.exp(theta[:n]), 1e6 * max(float(sd.max()), 1.0))
    nll = float("nan") if best is None else -best.value
    return l_out, float(np.exp(theta[n])), (floor + torch.exp(torch.as_tensor(theta[n + 1:]))).numpy().copy(), nll
