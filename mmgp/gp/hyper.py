"""Hyperparameters in the GP's standardised units, the standardiser, and the one optimiser."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .linalg import DTYPE, GPNumericalError, _TorchThreads
from .objectives import _value_and_grad


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
