"""Hyperparameters in the GP's standardised units, the standardiser, and the one optimiser.

:func:`maximise` is the single hyperparameter optimiser of the package: L-BFGS-B (scipy) on an
objective's value and gradient (closed form or autograd, see :mod:`mmgp.gp.objectives`), with box
bounds, weak log-normal priors, best-so-far bookkeeping, numerical-failure handling and a thread
policy. :func:`optimise_hyper` applies it to the batched RBF GP (ExactGP, SparseGP, the EM's
leave-block-out fits); :mod:`mmgp.gp.gradient_field` applies it to the potential GPs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

import numpy as np
import torch

from .kernels import rbf_kernel, rbf_log_param_grads
from ..threads import threads_for_rows
from .linalg import DTYPE, robust_cholesky
from .objectives import Objective, get_objective, leave_block_out
from .settings import GP_DEFAULTS as _GP, HyperProcedure


@dataclass
class Hyper:
    """Hyperparameters in the GP's standardised units: lengthscale (m, d), signal_var (m,), noise_var (m,)."""

    lengthscale: np.ndarray
    signal_var: np.ndarray
    noise_var: np.ndarray

    def to_torch(self, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=DTYPE, device=device)  # noqa: E731
        return t(self.lengthscale), t(self.signal_var), t(self.noise_var)

    def output(self, j: int) -> "Hyper":
        """Output j's hyperparameters alone (m = 1)."""
        return Hyper(self.lengthscale[j:j + 1], self.signal_var[j:j + 1], self.noise_var[j:j + 1])

    @staticmethod
    def stack(parts: Sequence["Hyper"]) -> "Hyper":
        """One Hyper from per-output ones, in order."""
        return Hyper(np.vstack([p.lengthscale for p in parts]), np.concatenate([p.signal_var for p in parts]),
                     np.concatenate([p.noise_var for p in parts]))

    def as_dict(self) -> dict:
        return {"lengthscale": self.lengthscale.tolist(), "signal_var": self.signal_var.tolist(),
                "noise_var": self.noise_var.tolist()}


@dataclass(frozen=True)
class LogNormalPrior:
    """Weak prior N(0, sd^2) on the log-parameters ``theta[start:stop]`` (log-normal, median 1)."""

    start: int
    stop: int
    sd: float


@dataclass(frozen=True)
class Optimum:
    """Best point of :func:`maximise`: ``theta`` and the objective per sample there (prior excluded)."""

    theta: np.ndarray
    value: float


def maximise(value_and_grad: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]], theta0: np.ndarray, *,
             n: int, bounds: Sequence[tuple[float | None, float | None]] | None = None,
             priors: Sequence[LogNormalPrior] = (), max_iter: int = 60, rows: int = 0, device="cpu",
             ftol: float = 1e-9, gtol: float = 1e-6,
             history: int = 10) -> Optimum | None:
    """Maximise ``F(theta) + log prior(theta)`` over log-hyperparameters by L-BFGS-B.

    ``value_and_grad(theta)`` takes theta (p,) as a float64 tensor on ``device`` and returns F (a
    0-d tensor, summed over outputs) and dF/dtheta (p,); it raises RuntimeError (GPNumericalError,
    torch's LinAlgError) where the kernel matrix cannot be factorised. The loss handed to scipy is
    ``-(F + log prior) / n`` (per sample, so tolerances mean the same for every data size).

    Failures and non-finite values count as a loss of 1e10 with zero gradient, which the line
    search rejects and backtracks from. The best point evaluated is returned (a line search that
    ends on failed trials does not lose it), or None when no evaluation was finite. ``max_iter``
    bounds the iterations, function evaluations are capped at 1.5x that. Threads: the policy of
    :func:`mmgp.threads.threads_for` for kernel matrices of ``rows`` rows on ``device``.
    """
    from scipy.optimize import minimize

    dev = torch.device(device)
    best = {"loss": math.inf}

    def fun(theta):
        t = torch.as_tensor(theta, dtype=DTYPE, device=dev)
        try:
            F, g = value_and_grad(t)
        except RuntimeError:
            return 1e10, np.zeros_like(theta)
        prior = 0.0
        g = g.detach().clone()
        for p in priors:
            prior = prior + (-0.5 * ((t[p.start:p.stop] / p.sd) ** 2).sum())
            g[p.start:p.stop] -= t[p.start:p.stop] / p.sd ** 2
        loss = float(-(F + prior) / n)
        g *= -1.0 / n
        if not math.isfinite(loss) or not bool(torch.isfinite(g).all()):
            return 1e10, np.zeros_like(theta)
        if loss < best["loss"]:
            best.update(loss=loss, theta=np.array(theta), value=float(F) / n)
        return loss, g.cpu().numpy()

    theta0 = np.asarray(theta0, dtype=np.float64)
    if bounds is not None:
        theta0 = np.clip(theta0, [-math.inf if b[0] is None else b[0] for b in bounds],
                         [math.inf if b[1] is None else b[1] for b in bounds])
    with threads_for_rows(rows, dev):
        minimize(fun, theta0, jac=True, method="L-BFGS-B", bounds=bounds,
                 options={"maxiter": max_iter, "maxfun": int(1.5 * max_iter) + 5, "ftol": ftol, "gtol": gtol,
                          "maxcor": history})
    if not math.isfinite(best["loss"]):
        return None
    return Optimum(best["theta"], best["value"])


def chained_value_and_grad(objective: Objective, gram: Callable[[torch.Tensor], torch.Tensor], y: torch.Tensor,
                           theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``F = objective.value(gram(theta), y).sum()`` and dF/dtheta by autograd through ``gram``.

    ``gram(theta)`` builds K (m, N, N) including the noise. Where the objective has a closed-form
    dF/dK ``G``, only ``sum(G * K)`` is backpropagated (several times cheaper than differentiating
    through the Cholesky factor, same gradient); otherwise the whole objective is.
    """
    th = theta.detach().clone().requires_grad_(True)
    K = gram(th)
    if objective.value_and_dK is None:
        F = objective.value(K, y).sum()
        F.backward()
        return F.detach(), th.grad
    with torch.no_grad():
        L, _ = robust_cholesky(K.detach())
        F, G = objective.value_and_dK(L, y)
    (G * K).sum().backward()
    return F.sum(), th.grad


class RBFParams:
    """The batched RBF GP's hyperparameters as one vector for :func:`maximise`.

    theta = [log lengthscale (m, d or 1), log signal variance (m,), log(noise variance - floor) (m,)]
    in standardised units, with box bounds and weak log-normal priors on the first two groups
    (median 1, log-sd 1.5 and 2): they keep lengthscales away from the degenerate extremes on
    tiny data sets.
    """

    def __init__(self, m: int, d: int, *, ard: bool = _GP.ard, noise_floor: float = _GP.noise_floor):
        self.m, self.d, self.ard, self.noise_floor = m, d, ard, noise_floor
        self.dl = d if ard else 1
        a, b = m * self.dl, m * self.dl + m
        # Standardised units: lengthscales far below the data spacing or far beyond the data range
        # are indistinguishable from their bounds, and a noise variance of 1e-8 of the output
        # variance is already below float64 Cholesky resolution at N ~ 1e3.
        self.bounds = ([(math.log(1e-2), math.log(1e3))] * a + [(math.log(1e-4), math.log(1e3))] * m
                       + [(math.log(1e-9), math.log(10.0))] * m)
        self.priors = (LogNormalPrior(0, a, 1.5), LogNormalPrior(a, b, 2.0))

    def pack(self, h: Hyper) -> np.ndarray:
        ls = np.asarray(h.lengthscale, dtype=np.float64).reshape(self.m, -1)
        if not self.ard:
            ls = ls.mean(-1, keepdims=True)
        sn = np.maximum(np.asarray(h.noise_var, dtype=np.float64) - self.noise_floor, 1e-8)
        return np.concatenate([np.log(ls).ravel(), np.log(np.asarray(h.signal_var, dtype=np.float64)), np.log(sn)])

    def unpack(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        a, m = self.m * self.dl, self.m
        return t[:a].reshape(m, self.dl), t[a:a + m], t[a + m:]

    def to_hyper(self, theta: np.ndarray) -> Hyper:
        log_ls, log_sf, log_sn = (t.cpu().numpy() for t in self.unpack(torch.as_tensor(theta, dtype=DTYPE)))
        ls = np.exp(log_ls)
        if not self.ard:
            ls = np.repeat(ls, self.d, axis=1)
        return Hyper(ls.copy(), np.exp(log_sf).copy(), np.exp(log_sn) + self.noise_floor)

    def gram(self, X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """K (m, N, N) including the noise, differentiable in theta."""
        log_ls, log_sf, log_sn = self.unpack(theta)
        K = rbf_kernel(X, X, torch.exp(log_ls), torch.exp(log_sf))
        return K + (torch.exp(log_sn) + self.noise_floor)[:, None, None] * torch.eye(X.shape[0], dtype=X.dtype,
                                                                                     device=X.device)


def rbf_value_and_grad(params: RBFParams, objective: Objective, X: torch.Tensor, y: torch.Tensor,
                       theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Objective (summed over outputs) and its gradient w.r.t. theta for the batched RBF GP.

    X (N, d), y (m, N). With a closed-form dF/dK the whole gradient is hand-written: every kernel
    derivative is an O(N^2 d) contraction with G * K (:func:`rbf_log_param_grads`), one K^-1 and
    one (N, N) product per evaluation, and fewer (m, N, N) buffers than autograd keeps alive.
    """
    if objective.value_and_dK is None:
        return chained_value_and_grad(objective, partial(params.gram, X), y, theta)
    log_ls, log_sf, log_sn = params.unpack(theta)
    with torch.no_grad():
        ls = torch.exp(log_ls)
        Kf = rbf_kernel(X, X, ls, torch.exp(log_sf))
        K = Kf.clone()
        K.diagonal(dim1=-2, dim2=-1).add_((torch.exp(log_sn) + params.noise_floor)[:, None])
        L, _ = robust_cholesky(K)
        del K
        F, G = objective.value_and_dK(L, y)
        del L
        g_sn = G.diagonal(dim1=-2, dim2=-1).sum(-1) * torch.exp(log_sn)
        g_ls, g_sf = rbf_log_param_grads(G.mul_(Kf), X, ls)  # G is symmetric, so rows = columns
    return F.sum(), torch.cat([g_ls.ravel(), g_sf, g_sn])


def optimise_hyper(X: torch.Tensor, Y: torch.Tensor, init: Hyper, *, objective: str | Objective = "loo",
                   ard: bool = _GP.ard, max_iter: int = _GP.max_iter, noise_floor: float = _GP.noise_floor,
                   independent: bool = False, rounds: int = 1, climb_tol: float = 0.01,
                   shared_starts: bool = False) -> tuple[Hyper, float]:
    """Hyperparameters of the batched RBF GP maximising ``objective`` (plus the weak priors).

    X (N, d) and Y (N, m) standardised tensors; ``objective`` "loo" (leave-one-out log predictive),
    "marginal", or an :class:`~mmgp.gp.objectives.Objective` such as
    :func:`~mmgp.gp.objectives.leave_block_out`. Returns the optimum and the objective per sample
    there (summed over outputs); ``init`` and NaN if no evaluation succeeded.

    ``independent``: one L-BFGS run per output instead of one run over all outputs' parameters.
    The outputs are independent GPs, but a joint run shares its line searches and its stopping,
    so an output whose climb is slow can stop far from its optimum; separate runs reach it and
    improve the other outputs too, in less time.

    ``rounds``: up to this many runs of ``max_iter`` iterations, each from the last one's optimum,
    another only while the last gained more than ``climb_tol`` per sample (a climb cut short far
    from its optimum: it stops with a large noise term holding what the GP should explain).

    ``shared_starts`` (with ``independent``): every output climbs a second time from the best
    output's optimum (:func:`restart_from_best_output`).
    """
    if independent and Y.shape[1] > 1:
        def climb(j: int, start: Hyper) -> tuple[Hyper, float]:
            return optimise_hyper(X, Y[:, j:j + 1], start, objective=objective, ard=ard, max_iter=max_iter,
                                  noise_floor=noise_floor, rounds=rounds, climb_tol=climb_tol)
        parts = [climb(j, init.output(j)) for j in range(Y.shape[1])]
        if shared_starts:
            parts = restart_from_best_output(parts, climb)
        return Hyper.stack([h for h, _ in parts]), float(sum(v for _, v in parts))
    obj = get_objective(objective)
    params = RBFParams(Y.shape[1], X.shape[1], ard=ard, noise_floor=noise_floor)
    climb = partial(maximise, partial(rbf_value_and_grad, params, obj, X, Y.T.contiguous()), n=X.shape[0],
                    bounds=params.bounds, priors=params.priors, max_iter=max_iter, rows=X.shape[0], device=X.device)
    best = climb(params.pack(init))
    if best is None:
        return init, float("nan")
    for _ in range(rounds - 1):
        more = climb(best.theta)
        gain = -math.inf if more is None else more.value - best.value
        if gain > 0:
            best = more
        if not gain > climb_tol:
            break
    return params.to_hyper(best.theta), best.value


def restart_from_best_output(parts: list[tuple[Hyper, float]],
                             climb: Callable[[int, Hyper], tuple[Hyper, float]]) -> list[tuple[Hyper, float]]:
    """Per-output optima ``parts`` [(Hyper with m = 1, objective per sample)], each output but the
    best one climbed again by ``climb(j, start)`` from the best output's lengthscales (unit signal,
    noise 1e-3 of the output's variance); the higher of an output's two optima is kept.

    Why: the outputs (a robot's joint torques) are functions of the same inputs and often share
    their geometry, while one output's own climb can settle in a basin that explains it by the
    wrong inputs; climbed from a neighbour's optimum it can find the geometry its own climb
    missed. Objectives per sample of standardised outputs on the same rows are comparable, so
    the output that reached the highest is the donor. Cost: one more refinement per output but
    one.
    """
    values = np.array([v for _, v in parts], dtype=float)
    if not np.isfinite(values).any():
        return parts
    donor = int(np.nanargmax(values))
    out = list(parts)
    for j, (_, value) in enumerate(parts):
        if j == donor:
            continue
        start = Hyper(parts[donor][0].lengthscale, np.ones(1), np.full(1, 1e-3))   # climbs do not mutate it
        h, v = climb(j, start)
        if v > value or (math.isnan(value) and math.isfinite(v)):
            out[j] = (h, v)
    return out


def fit_hyper_subsets(Xs: torch.Tensor, Ys: torch.Tensor, init: Hyper, *, warm: bool, procedure: HyperProcedure,
                      t: np.ndarray | None = None) -> tuple[Hyper, float]:
    """ExactGP's hyperparameter procedure, shared with the scalable GP.

    Xs (N, d), Ys (N, m) standardised; ``procedure`` the settings. Cold starts (``warm`` False)
    climb on a small coarse subset first, then refine on the fitting subset (in rounds, and from
    the best output's optimum when ``shared_starts``). With sample times ``t`` (N,) s, increasing,
    and ``block_s`` > 0, every subset is scored by leave-block-out on its own times
    (:func:`mmgp.gp.objectives.leave_block_out`) instead of ``objective``.
    """
    p = procedure
    rng = np.random.default_rng(p.seed)
    N = Xs.shape[0]
    idx = np.arange(N)
    if N > p.max_fit_points:
        idx = np.sort(rng.choice(N, p.max_fit_points, replace=False))
    block_s = float(p.block_s or 0.0)
    objective = ((lambda rows: leave_block_out(np.asarray(t)[rows], block_s)) if t is not None and block_s > 0
                 else (lambda rows: p.objective))
    opts = dict(ard=p.ard, noise_floor=p.noise_floor, independent=bool(p.independent_outputs))
    n_c = int(p.coarse_fit_points or 0)
    max_iter, rounds = p.max_iter, 1
    if not warm and n_c > 0 and len(idx) > 2 * n_c:
        coarse = np.sort(rng.choice(idx, n_c, replace=False))
        init, _ = optimise_hyper(Xs[coarse], Ys[coarse], init, objective=objective(coarse), max_iter=p.max_iter,
                                 **opts)
        max_iter, rounds = max(10, p.max_iter // 3), int(p.refine_rounds)
        opts["shared_starts"] = bool(p.shared_starts)
    return optimise_hyper(Xs[idx], Ys[idx], init, objective=objective(idx), max_iter=max_iter, rounds=rounds, **opts)


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
