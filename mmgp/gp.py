"""Exact Gaussian processes with an RBF kernel, batched over outputs (joints), in float64 torch.

Each output column gets its own hyperparameters (lengthscales, signal and noise variance); the
math is batched over outputs as ``(m, N, N)`` tensors instead of a Python loop.

Hyperparameters are chosen by maximising the full leave-one-out log predictive density
(Rasmussen & Williams, GPML section 5.4.2), whose closed form needs one inverse of ``K``:

    mu_i  = y_i - [K^-1 y]_i / [K^-1]_ii          sigma2_i = 1 / [K^-1]_ii
    log p = sum_i -0.5 log sigma2_i - (y_i - mu_i)^2 / (2 sigma2_i) - 0.5 log 2 pi

The log-variance term matters: without it (as in the source dissertation) the objective rewards
inflating the predictive variance. The log marginal likelihood is available as an alternative.

Fitting cost: L-BFGS-B (scipy) on hand-derived gradients (one K^-1 and one (N, N) product per
evaluation, see ``_value_and_grad``), first on a small coarse subset, then on the fitting subset.
On 2,000 real Barrett WAM samples (7 outputs, 21 inputs) this fits several times faster than
scikit-learn's GaussianProcessRegressor at lower held-out error (benchmarks/bench_gp_speed.py).
For more than a few thousand samples use ``mmgp.gp_sparse.make_gp`` (SGPR above 3,000).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

DTYPE = torch.float64
LOG_2PI = math.log(2 * math.pi)


class GPNumericalError(RuntimeError):
    """The kernel matrix could not be factorised even with the largest allowed jitter."""


def resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but no CUDA device is available")
    return dev


def rbf_kernel(X1: torch.Tensor, X2: torch.Tensor, lengthscale: torch.Tensor,
               signal_var: torch.Tensor) -> torch.Tensor:
    """RBF kernel batched over outputs.

    X1 (N1, d), X2 (N2, d), lengthscale (m, d) (or (m, 1) isotropic), signal_var (m,)
    -> (m, N1, N2) with k = s2 exp(-|x - x'|^2_l / 2).
    """
    A = X1.unsqueeze(0) / lengthscale.unsqueeze(1)          # (m, N1, d)
    B = X2.unsqueeze(0) / lengthscale.unsqueeze(1)          # (m, N2, d)
    sq = (A * A).sum(-1).unsqueeze(-1) + (B * B).sum(-1).unsqueeze(-2) - 2.0 * A @ B.transpose(-1, -2)
    return signal_var[:, None, None] * torch.exp(-0.5 * sq.clamp_min(0.0))


def robust_cholesky(K: torch.Tensor, *, base_jitter: float = 1e-10, max_tries: int = 7) -> tuple[torch.Tensor, float]:
    """Cholesky of a batch of SPD matrices K (..., N, N), adding growing diagonal jitter on failure.

    Tries jitter 0, then base_jitter * 100^k (k = 0 .. max_tries - 2), relative to the mean
    diagonal. Returns (L, jitter used). Raises GPNumericalError when K holds NaN/inf or when
    even the largest jitter fails.
    """
    if not bool(torch.isfinite(K).all()):
        raise GPNumericalError(
            f"kernel matrix of size {K.shape[-1]} contains NaN or inf: the inputs, outputs or "
            "hyperparameters are not finite (check the log for NaN rows and the hyperparameters for overflow)")
    scale = K.diagonal(dim1=-2, dim2=-1).mean().detach().clamp_min(1e-300)
    eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
    jitter = 0.0
    for attempt in range(max_tries):
        jitter = 0.0 if attempt == 0 else base_jitter * (100.0 ** (attempt - 1))
        L, info = torch.linalg.cholesky_ex(K + jitter * scale * eye if jitter else K)
        if not bool((info > 0).any()):
            return L, jitter
    raise GPNumericalError(
        f"kernel matrix of size {K.shape[-1]} is not positive definite even with jitter {jitter:.1e} x "
        "mean diagonal: inputs are probably duplicated or badly scaled; try downsampling or a larger noise floor")


def inverse_from_cholesky(L: torch.Tensor) -> torch.Tensor:
    """K^-1 from its lower Cholesky factor L (..., N, N).

    Triangular solve then one product: on a busy shared CPU this was 5-15x faster than
    torch.cholesky_inverse (LAPACK potri), whose multithreaded path stalls when cores are taken.
    """
    eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device).expand_as(L)
    Li = torch.linalg.solve_triangular(L, eye, upper=False)
    return Li.transpose(-1, -2) @ Li


def loo_from_inverse(Kinv: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form LOO predictive. Kinv (m, N, N), y (m, N) -> mean (m, N), var (m, N)."""
    alpha = (Kinv @ y.unsqueeze(-1)).squeeze(-1)
    diag = Kinv.diagonal(dim1=-2, dim2=-1)
    return y - alpha / diag, 1.0 / diag


def gaussian_logpdf(y: torch.Tensor, mean: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    return -0.5 * (LOG_2PI + torch.log(var) + (y - mean) ** 2 / var)


def loo_log_predictive(K: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Sum over samples of the LOO log predictive density, per output: K (m,N,N) incl. noise, y (m,N) -> (m,)."""
    L, _ = robust_cholesky(K)
    Kinv = inverse_from_cholesky(L)
    mu, var = loo_from_inverse(Kinv, y)
    return gaussian_logpdf(y, mu, var).sum(-1)


def log_marginal_likelihood(K: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Log marginal likelihood per output: K (m,N,N) incl. noise, y (m,N) -> (m,)."""
    L, _ = robust_cholesky(K)
    alpha = torch.cholesky_solve(y.unsqueeze(-1), L).squeeze(-1)
    logdet = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    N = y.shape[-1]
    return -0.5 * (y * alpha).sum(-1) - 0.5 * logdet - 0.5 * N * LOG_2PI


@dataclass
class Hyper:
    """Hyperparameters in the GP's standardised units: lengthscale (m, d), signal_var (m,), noise_var (m,)."""

    lengthscale: np.ndarray
    signal_var: np.ndarray
    noise_var: np.ndarray

    def to_torch(self, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=DTYPE, device=device)  # noqa: E731
        return t(self.lengthscale), t(self.signal_var), t(self.noise_var)

    def as_dict(self) -> dict:
        return {"lengthscale": self.lengthscale.tolist(), "signal_var": self.signal_var.tolist(),
                "noise_var": self.noise_var.tolist()}


def _value_and_grad(X: torch.Tensor, y: torch.Tensor, log_ls: torch.Tensor, log_sf: torch.Tensor,
                    log_sn: torch.Tensor, noise_floor: float, objective: str):
    """Objective per output and its analytic gradient w.r.t. the log-hyperparameters.

    X (N, d), y (m, N), log_ls (m, d) or (m, 1), log_sf (m,), log_sn (m,) with noise variance
    exp(log_sn) + noise_floor. Returns F (m,), dF/dlog_ls, dF/dlog_sf, dF/dlog_sn.

    Hand-written rather than autograd: the gradient w.r.t. K is one (N, N) matrix G
    (LOO: G = -P diag(a) P - sym(P b alpha^T), GPML eq. 5.13 rewritten; marginal:
    G = (alpha alpha^T - P) / 2, with P = K^-1), and every kernel derivative is then an O(N^2 d)
    contraction with G * K. Backpropagating through cholesky_inverse instead costs several
    more O(N^3) products per evaluation and keeps more (m, N, N) buffers alive.
    """
    N = X.shape[0]
    ls = torch.exp(log_ls)
    Z = X.unsqueeze(0) / ls.unsqueeze(1)                                 # (m, N, d)
    zz = (Z * Z).sum(-1)
    Kf = zz.unsqueeze(-1) + zz.unsqueeze(-2) - 2.0 * Z @ Z.transpose(-1, -2)
    Kf = torch.exp_(Kf.clamp_min_(0.0).mul_(-0.5)).mul_(torch.exp(log_sf)[:, None, None])
    K = Kf.clone()
    K.diagonal(dim1=-2, dim2=-1).add_((torch.exp(log_sn) + noise_floor)[:, None])
    L, _ = robust_cholesky(K)
    del K
    P = inverse_from_cholesky(L)
    alpha = (P @ y.unsqueeze(-1)).squeeze(-1)
    if objective == "loo":
        c = P.diagonal(dim1=-2, dim2=-1)
        F = (0.5 * torch.log(c) - 0.5 * alpha ** 2 / c).sum(-1) - 0.5 * N * LOG_2PI
        a = 0.5 / c + 0.5 * alpha ** 2 / c ** 2              # dF/d[P]_ii
        b = -alpha / c                                       # dF/dalpha_i
        Pb = P @ b.unsqueeze(-1)
        G = (P * a.unsqueeze(-2)) @ P
        G.neg_()
        G -= 0.5 * (Pb @ alpha.unsqueeze(-2) + alpha.unsqueeze(-1) @ Pb.transpose(-1, -2))
    else:
        F = (-0.5 * (y * alpha).sum(-1) - torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
             - 0.5 * N * LOG_2PI)
        G = P.mul_(-0.5)
        G += 0.5 * alpha.unsqueeze(-1) * alpha.unsqueeze(-2)
    g_sn = G.diagonal(dim1=-2, dim2=-1).sum(-1) * torch.exp(log_sn)
    W = G.mul_(Kf)                                           # G is symmetric, so rows = columns
    g_sf = W.sum((-1, -2))
    rs = W.sum(-1)
    g_ls = 2.0 * (Z * Z * rs.unsqueeze(-1)).sum(1) - 2.0 * (Z * (W @ Z)).sum(1)
    if log_ls.shape[-1] == 1 and X.shape[1] != 1:
        g_ls = g_ls.sum(-1, keepdim=True)
    return F, g_ls, g_sf, g_sn


class _TorchThreads:
    """Temporarily cap torch's intra-op threads (restored on exit)."""

    def __init__(self, n: int | None):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n is not None and self.n < self.old:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)


# Below this many samples one objective evaluation is a few ms of BLAS per output, and thread
# hand-offs dominate: on the shared 2-core machine a 300-sample, 7-output evaluation took
# 0.09 s with 1 thread and 0.2-0.9 s with 2 threads.
SINGLE_THREAD_BELOW = 600


def optimise_hyper(X: torch.Tensor, Y: torch.Tensor, init: Hyper, *, objective: str = "loo",
                   ard: bool = True, max_iter: int = 60, noise_floor: float = 1e-6,
                   weights: torch.Tensor | None = None) -> tuple[Hyper, float]:
    """Maximise the LOO log predictive (or the marginal likelihood) over log-hyperparameters.

    X (N, d) and Y (N, m) standardised. Returns the optimum and the objective value (summed over
    outputs, per sample). A weak log-normal prior on the lengthscales keeps them away from the
    degenerate extremes on tiny data sets. ``weights`` is unused padding for subclasses.

    L-BFGS-B (scipy) on analytic gradients, with box bounds on the log-parameters so that trial
    steps of the line search stay in a region where K can be factorised. ``max_iter`` bounds the
    L-BFGS iterations (function evaluations are capped at 1.5x that).
    """
    from scipy.optimize import minimize

    if objective not in ("loo", "marginal"):
        raise ValueError(f"objective must be 'loo' or 'marginal', got {objective!r}")
    dev = X.device
    N, d = X.shape
    m = Y.shape[1]
    ls0 = np.asarray(init.lengthscale, dtype=np.float64).reshape(m, -1)
    if not ard:
        ls0 = ls0.mean(-1, keepdims=True)
    dl = ls0.shape[1]
    sn0 = np.maximum(np.asarray(init.noise_var, dtype=np.float64) - noise_floor, 1e-8)
    theta0 = np.concatenate([np.log(ls0).ravel(), np.log(np.asarray(init.signal_var, dtype=np.float64)),
                             np.log(sn0)])
    # Standardised units: lengthscales far below the data spacing or far beyond the data range
    # are indistinguishable from their bounds, and a noise variance of 1e-8 of the output
    # variance is already below float64 Cholesky resolution at N ~ 1e3.
    bounds = ([(math.log(1e-2), math.log(1e3))] * (m * dl) + [(math.log(1e-4), math.log(1e3))] * m
              + [(math.log(1e-9), math.log(10.0))] * m)
    theta0 = np.clip(theta0, [b[0] for b in bounds], [b[1] for b in bounds])
    y = Y.T.contiguous()

    def unpack(theta):
        t = torch.as_tensor(theta, dtype=DTYPE, device=dev)
        return t[:m * dl].reshape(m, dl), t[m * dl:m * dl + m], t[m * dl + m:]

    best = {"loss": math.inf, "theta": theta0}

    def fun(theta):
        log_ls, log_sf, log_sn = unpack(theta)
        try:
            with torch.no_grad():
                F, g_ls, g_sf, g_sn = _value_and_grad(X, y, log_ls, log_sf, log_sn, noise_floor, objective)
        except GPNumericalError:
            return 1e10, np.zeros_like(theta)  # rejected by the line search, which then backtracks
        prior = -0.5 * ((log_ls / 1.5) ** 2).sum() - 0.5 * ((log_sf / 2.0) ** 2).sum()
        loss = float(-(F.sum() + prior) / N)
        g = torch.cat([(g_ls - log_ls / 1.5 ** 2).ravel(), g_sf - log_sf / 4.0, g_sn]) * (-1.0 / N)
        if not math.isfinite(loss) or not bool(torch.isfinite(g).all()):
            return 1e10, np.zeros_like(theta)
        if loss < best["loss"]:
            best.update(loss=loss, theta=np.array(theta), value=float(F.sum()) / N)
        return loss, g.cpu().numpy()

    with _TorchThreads(1 if (N <= SINGLE_THREAD_BELOW and dev.type == "cpu") else None):
        minimize(fun, theta0, jac=True, method="L-BFGS-B", bounds=bounds,
                 options={"maxiter": max_iter, "maxfun": int(1.5 * max_iter) + 5, "ftol": 1e-9, "gtol": 1e-6})
    if not math.isfinite(best["loss"]):
        return init, float("nan")
    log_ls, log_sf, log_sn = (t.cpu().numpy() for t in unpack(best["theta"]))
    ls = np.exp(log_ls)
    if not ard:
        ls = np.repeat(ls, d, axis=1)
    hyp = Hyper(ls.copy(), np.exp(log_sf).copy(), np.exp(log_sn) + noise_floor)
    value = best["value"]
    return hyp, value


def fit_hyper_subsets(Xs: torch.Tensor, Ys: torch.Tensor, init: Hyper, *, warm: bool, est) -> tuple[Hyper, float]:
    """ExactGP's hyperparameter procedure, shared with the scalable GP.

    Xs (N, d), Ys (N, m) standardised; ``est`` supplies the settings (max_fit_points,
    coarse_fit_points, max_iter, objective, ard, noise_floor, seed). Cold starts (``warm`` False)
    climb on a small coarse subset first, then refine on the fitting subset.
    """
    rng = np.random.default_rng(est.seed)
    N = Xs.shape[0]
    idx = np.arange(N)
    if N > est.max_fit_points:
        idx = np.sort(rng.choice(N, est.max_fit_points, replace=False))
    opts = dict(objective=est.objective, ard=est.ard, noise_floor=est.noise_floor)
    n_c = int(est.coarse_fit_points or 0)
    max_iter = est.max_iter
    if not warm and n_c > 0 and len(idx) > 2 * n_c:
        coarse = np.sort(rng.choice(idx, n_c, replace=False))
        init, _ = optimise_hyper(Xs[coarse], Ys[coarse], init, max_iter=est.max_iter, **opts)
        max_iter = max(10, est.max_iter // 3)
    return optimise_hyper(Xs[idx], Ys[idx], init, max_iter=max_iter, **opts)


def default_hyper(d: int, m: int, noise: float = 0.1) -> Hyper:
    """Starting point in standardised units: unit lengthscales scaled with sqrt(d)."""
    return Hyper(np.full((m, d), max(1.0, math.sqrt(d) / 2.0)), np.ones(m), np.full(m, noise))


class Standardiser:
    """Column-wise affine map to zero mean and unit variance; zero-variance columns keep scale 1."""

    def fit(self, A: np.ndarray) -> "Standardiser":
        self.mean_ = A.mean(0)
        std = A.std(0)
        self.scale_ = np.where(std > 1e-12 * (np.abs(self.mean_) + 1), std, 1.0)
        return self

    def transform(self, A: np.ndarray) -> np.ndarray:
        return (A - self.mean_) / self.scale_


def check_xy(X, Y) -> tuple[np.ndarray, np.ndarray, bool]:
    """float64 X (N, d) and Y (N, m), and whether Y was given as a vector (N,)."""
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    vector = Y.ndim == 1
    if vector:
        Y = Y[:, None]
    if X.ndim != 2 or Y.shape[0] != X.shape[0]:
        raise ValueError(f"X must be (N, d) and Y (N, m) with the same N; got {X.shape} and {Y.shape}")
    return X, Y, vector


def prepare_fit(est, X, Y) -> tuple[np.ndarray, np.ndarray]:
    """Start of every GP's fit: checked float64 arrays; sets ``est``'s ``_vector_output``,
    ``dev_`` (from ``est.device``) and the input/output standardisers."""
    X, Y, est._vector_output = check_xy(X, Y)
    est.dev_ = resolve_device(est.device)
    est.x_scaler_ = Standardiser().fit(X)
    est.y_scaler_ = Standardiser().fit(Y)
    return X, Y


class ExactGP:
    """Exact GP regression with an RBF kernel, one independent GP per output column.

    Parameters
    ----------
    ard : per-input lengthscales (True) or one lengthscale per output (False).
    objective : "loo" (full LOO log predictive, default) or "marginal".
    max_fit_points : hyperparameters are optimised on a random subset of at most this many
        samples (the predictor then conditions on all of them); keeps fitting O(subset^3).
    max_iter : L-BFGS iterations.
    coarse_fit_points : on a cold start (no ``hyper`` given) with more than twice this many
        fitting samples, the optimiser first runs ``max_iter`` iterations on a random subset of
        this size, then ``max(10, max_iter // 3)`` on the full fitting subset. Most of the climb
        happens far from the optimum, where a small subset points the same way at ~1/30 of the
        cost (Barrett WAM, 21 inputs: same held-out error as 60 full iterations, ~3x faster).
        0 disables it.
    noise_floor : smallest noise variance, as a fraction of each output's variance.
    device : torch device ("cpu", "cuda", "auto").

    Learned: ``hyper_`` (standardised units), ``lengthscale_`` (m, d) and ``noise_std_`` (m,) in
    data units, ``objective_value_`` (per-sample objective on the fitting subset).
    """

    def __init__(self, *, ard: bool = True, objective: str = "loo", max_fit_points: int = 1000,
                 max_iter: int = 60, noise_floor: float = 1e-6, device: str | None = "cpu", seed: int = 0,
                 coarse_fit_points: int = 300):
        self.coarse_fit_points = coarse_fit_points
        self.ard = ard
        self.objective = objective
        self.max_fit_points = max_fit_points
        self.max_iter = max_iter
        self.noise_floor = noise_floor
        self.device = device
        self.seed = seed

    def fit(self, X: np.ndarray, Y: np.ndarray, *, hyper: Hyper | None = None, optimise: bool = True) -> "ExactGP":
        """X (N, d), Y (N, m) or (N,). ``hyper`` (standardised units) warm-starts or fixes hyperparameters."""
        X, Y = prepare_fit(self, X, Y)
        Xs = torch.as_tensor(self.x_scaler_.transform(X), dtype=DTYPE, device=self.dev_)
        Ys = torch.as_tensor(self.y_scaler_.transform(Y), dtype=DTYPE, device=self.dev_)
        init = hyper if hyper is not None else default_hyper(X.shape[1], Y.shape[1])
        self.objective_value_ = float("nan")
        if optimise:
            init, self.objective_value_ = fit_hyper_subsets(Xs, Ys, init, warm=hyper is not None, est=self)
        self.hyper_ = init
        self._condition(Xs, Ys)
        return self

    def _condition(self, Xs: torch.Tensor, Ys: torch.Tensor) -> None:
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        K = rbf_kernel(Xs, Xs, ls, sf) + sn[:, None, None] * torch.eye(Xs.shape[0], dtype=DTYPE, device=self.dev_)
        self.L_, self.jitter_ = robust_cholesky(K)
        self.alpha_ = torch.cholesky_solve(Ys.T.unsqueeze(-1), self.L_).squeeze(-1)  # (m, N)
        self.Xs_ = Xs
        self.Ys_ = Ys
        self.lengthscale_ = self.hyper_.lengthscale * self.x_scaler_.scale_[None, :]
        self.noise_std_ = np.sqrt(self.hyper_.noise_var) * self.y_scaler_.scale_

    def _out(self, a: np.ndarray) -> np.ndarray:
        return a[:, 0] if self._vector_output else a

    def predict(self, X: np.ndarray, *, include_noise: bool = False, return_std: bool = True):
        """Posterior mean (M, m) and std (M, m) at X (M, d), in data units.

        ``include_noise`` adds the observation noise (predictive of a new measurement).
        """
        Xq = torch.as_tensor(self.x_scaler_.transform(np.asarray(X, dtype=np.float64)), dtype=DTYPE, device=self.dev_)
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        mean_s, var_s = [], []
        # chunks keep each (m, N, chunk) buffer near 32 MB: prediction memory stays O(N m)
        chunk_size = max(64, int(4e6 // max(1, self.alpha_.shape[0] * self.alpha_.shape[1])))
        for chunk in torch.split(Xq, chunk_size):
            Ks = rbf_kernel(self.Xs_, chunk, ls, sf)                   # (m, N, M)
            mean_s.append((Ks * self.alpha_.unsqueeze(-1)).sum(1).T)    # (M, m)
            if return_std:
                V = torch.linalg.solve_triangular(self.L_, Ks, upper=False)
                var = (sf[:, None] - (V * V).sum(1)).clamp_min(1e-12)
                if include_noise:
                    var = var + sn[:, None]
                var_s.append(var.T)
        mean = torch.cat(mean_s).cpu().numpy() * self.y_scaler_.scale_ + self.y_scaler_.mean_
        if not return_std:
            return self._out(mean)
        std = np.sqrt(torch.cat(var_s).cpu().numpy()) * self.y_scaler_.scale_
        return self._out(mean), self._out(std)

    def loo_predictive(self) -> tuple[np.ndarray, np.ndarray]:
        """Leave-one-out predictive mean and std (N, m) of the training outputs (closed form)."""
        Kinv = inverse_from_cholesky(self.L_)
        mu, var = loo_from_inverse(Kinv, self.Ys_.T)
        mean = mu.T.cpu().numpy() * self.y_scaler_.scale_ + self.y_scaler_.mean_
        std = np.sqrt(var.T.cpu().numpy()) * self.y_scaler_.scale_
        return self._out(mean), self._out(std)

    def loo_log_predictive(self) -> float:
        """Sum over samples and outputs of the LOO log predictive density, in data units."""
        mean, std = self.loo_predictive()
        Y = self.Ys_.T.cpu().numpy().T * self.y_scaler_.scale_ + self.y_scaler_.mean_
        if self._vector_output:
            mean, std = mean[:, None], std[:, None]
        return float((-0.5 * (LOG_2PI + 2 * np.log(std) + ((Y - mean) / std) ** 2)).sum())
