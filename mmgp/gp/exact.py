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
evaluation, see :func:`mmgp.gp.hyper.rbf_value_and_grad`), first on a small coarse subset, then on
the fitting subset. This fits faster than scikit-learn's GaussianProcessRegressor at lower
held-out error (benchmarks/bench_gp_speed.py). ``mmgp.gp.sparse.make_gp`` picks this GP or SGPR by size and memory.
"""
from __future__ import annotations

from dataclasses import fields

import numpy as np
import torch
from sklearn.base import BaseEstimator
from sklearn.utils.validation import check_is_fitted

from .hyper import Hyper, Standardiser, default_hyper, fit_hyper_subsets, optimise_hyper
from .settings import GP_DEFAULTS as _GP, HyperProcedure
from .kernels import rbf_cross_kernel, rbf_kernel
from ..threads import threads_for_rows
from .linalg import DTYPE, GPNumericalError, gaussian_logpdf, exact_fits, inverse_from_cholesky, resolve_device, robust_cholesky
from .objectives import leave_block_out, loo_from_inverse

#: kernel matrices of all outputs together up to this many bytes are factorised as one batch
#: (m, N, N) (fast for the EM's small supports); larger ones one output at a time
BATCHED_BYTES = 2 ** 28


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


class StandardisedRBFGP(BaseEstimator):
    """What the exact and the sparse RBF GP share: settings, standardisation, the hyperparameter
    procedure (:func:`mmgp.gp.hyper.fit_hyper_subsets`) and the conversions to data units.

    Subclasses implement ``_condition``, ``predict`` and ``loo_predictive``.
    """

    def __init__(self, *, ard: bool = _GP.ard, objective: str = _GP.objective, max_fit_points: int = _GP.max_fit_points,
                 max_iter: int = _GP.max_iter, noise_floor: float = _GP.noise_floor, device: str | None = None,
                 seed: int = _GP.seed, coarse_fit_points: int = _GP.coarse_fit_points,
                 independent_outputs: bool = _GP.independent_outputs, refine_rounds: int = _GP.refine_rounds,
                 shared_starts: bool = _GP.shared_starts, block_s: float = _GP.block_s, hyper: Hyper | None = None,
                 optimise: bool = _GP.optimise):
        self.ard = ard
        self.objective = objective
        self.max_fit_points = max_fit_points
        self.max_iter = max_iter
        self.noise_floor = noise_floor
        self.device = device
        self.seed = seed
        self.coarse_fit_points = coarse_fit_points
        self.independent_outputs = independent_outputs
        self.refine_rounds = refine_rounds
        self.shared_starts = shared_starts
        self.block_s = block_s
        self.hyper = hyper
        self.optimise = optimise

    def _procedure(self) -> HyperProcedure:
        """This GP's settings of the hyperparameter procedure."""
        return HyperProcedure(**{f.name: getattr(self, f.name) for f in fields(HyperProcedure)})

    def _fit_standardised(self, X, Y, t: np.ndarray | None = None):
        """Checked X (N, d), Y (N, m) and their standardised tensors; sets ``dev_``, the scalers,
        ``hyper_`` (``hyper`` or the default, optimised from there when ``optimise``; by
        leave-block-out with times ``t`` (N,) s and ``block_s`` > 0) and ``objective_value_``."""
        hyper = self.hyper
        X, Y, self._vector_output = check_xy(X, Y)
        self.dev_ = resolve_device(self.device)
        self.x_scaler_ = Standardiser().fit(X)
        self.y_scaler_ = Standardiser().fit(Y)
        Xs = torch.as_tensor(self.x_scaler_.transform(X), dtype=DTYPE, device=self.dev_)
        Ys = torch.as_tensor(self.y_scaler_.transform(Y), dtype=DTYPE, device=self.dev_)
        init = hyper if hyper is not None else default_hyper(X.shape[1], Y.shape[1])
        self.objective_value_ = float("nan")
        if self.optimise:
            if t is not None and np.shape(t) != (X.shape[0],):
                raise ValueError(f"t must be (N,) = ({X.shape[0]},), got {np.shape(t)}")
            init, self.objective_value_ = fit_hyper_subsets(Xs, Ys, init, warm=hyper is not None,
                                                                procedure=self._procedure(), t=t)
        self.hyper_ = init
        self.lengthscale_ = self.hyper_.lengthscale * self.x_scaler_.scale_[None, :]
        self.noise_std_ = np.sqrt(self.hyper_.noise_var) * self.y_scaler_.scale_
        return X, Y, Xs, Ys

    def _query(self, X) -> torch.Tensor:
        check_is_fitted(self, "hyper_")
        return torch.as_tensor(self.x_scaler_.transform(np.asarray(X, dtype=np.float64)), dtype=DTYPE,
                               device=self.dev_)

    def _data_units(self, mean_s: torch.Tensor, var_s: torch.Tensor | None):
        """Standardised mean and variance (M, m) -> data-unit mean and std, shaped like the fit's Y."""
        mean = mean_s.cpu().numpy() * self.y_scaler_.scale_ + self.y_scaler_.mean_
        out = (lambda a: a[:, 0]) if self._vector_output else (lambda a: a)
        if var_s is None:
            return out(mean)
        return out(mean), out(np.sqrt(var_s.cpu().numpy()) * self.y_scaler_.scale_)

    def block_hyper(self, X: np.ndarray, Y: np.ndarray, t: np.ndarray, block_s: float, *,
                    hyper: Hyper | None = None, max_iter: int | None = None, noise_floor: float | None = None) -> Hyper:
        """Hyperparameters (standardised units) maximising the leave-time-block-out log
        predictive (:func:`mmgp.gp.objectives.leave_block_out`, blocks of ``block_s`` s) of X
        (N, d) -> Y (N, m) sampled at times ``t`` (N,) s, climbed from ``hyper`` (None: the
        default start) for at most ``max_iter`` iterations (None: this GP's ``max_iter``; the noise
        floor None: its ``noise_floor``). Conditions this GP on X, Y for their standardisation
        (its ``hyper`` set to the start, ``optimise`` off): set its settings and refit it on what
        it should predict from."""
        start = hyper or default_hyper(X.shape[1], np.atleast_2d(Y.T).shape[0])
        self.set_params(hyper=start, optimise=False).fit(X, Y)
        out, _ = optimise_hyper(self.Xs_, self.Ys_, self.hyper_, objective=leave_block_out(t, block_s),
                                max_iter=self.max_iter if max_iter is None else max_iter,
                                noise_floor=self.noise_floor if noise_floor is None else noise_floor)
        return out

    def loo_log_predictive(self) -> float:
        """Sum over samples and outputs of the LOO log predictive density, in data units."""
        mean, std = self.loo_predictive()
        Y = self._training_outputs()
        if self._vector_output:
            mean, std = mean[:, None], std[:, None]
        return float(gaussian_logpdf(Y, mean, std ** 2).sum())

    def _training_outputs(self) -> np.ndarray:
        return self.Ys_.cpu().numpy() * self.y_scaler_.scale_ + self.y_scaler_.mean_


class ExactGP(StandardisedRBFGP):
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
        happens far from the optimum, where a small subset points the same way at a fraction of
        the cost.
        0 disables it.
    noise_floor : smallest noise variance, as a fraction of each output's variance.
    block_s : with sample times given to ``fit`` (``t``), hyperparameters maximise the
        leave-time-block-out log predictive, blocks of this many seconds
        (:func:`mmgp.gp.objectives.leave_block_out`), instead of ``objective``; 0 (default): ``objective``.
    independent_outputs : one optimiser run per output (see
        :func:`mmgp.gp.hyper.optimise_hyper`); default False, one run over all outputs.
    refine_rounds : after a coarse climb, up to this many refinement runs of ``max_iter // 3``
        iterations on the fitting subset, another only while the last one still gained (see
        :func:`mmgp.gp.hyper.optimise_hyper`'s ``rounds``); default 1.
    shared_starts : with ``independent_outputs``, after a coarse climb every output's refinement
        is repeated from the best output's optimum and the better one kept (see
        :func:`mmgp.gp.hyper.restart_from_best_output`); default False.
    device : torch device ("cpu", "cuda", "auto"); None (default): the block's default
        (:func:`mmgp.gp.linalg.default_device`), "cpu" outside one.
    hyper : hyperparameters (:class:`mmgp.gp.hyper.Hyper`, standardised units) the fit starts
        from (a warm start), or keeps with ``optimise=False``; None (default): the default start.
    optimise : whether ``fit`` optimises the hyperparameters (default True); False keeps ``hyper``
        (or the default start) as they are.

    Memory: while the kernel matrices of all outputs take at most :data:`BATCHED_BYTES` they are
    factorised together (m, N, N); larger fits keep one output's (N, N) factor at a time, made
    when first predicted (``per_output_``), so an exact GP on 10^4+ samples needs O(N^2), not
    O(m N^2), memory, and a fit that is only saved never pays the O(N^3).

    Learned: ``hyper_`` (standardised units), ``lengthscale_`` (m, d) and ``noise_std_`` (m,) in
    data units, ``objective_value_`` (per-sample objective on the fitting subset), ``per_output_``.
    """

    def fit(self, X: np.ndarray, Y: np.ndarray, *, weights: np.ndarray | None = None,
            t: np.ndarray | None = None) -> "ExactGP":
        """X (N, d), Y (N, m) or (N,). ``t`` (N,) s, increasing: sample times for the
        leave-block-out objective (``block_s``). ``weights`` (m, N): what :meth:`solved_weights`
        returned for the same X, Y and ``hyper`` (``optimise=False``); a large fit
        (``per_output_``) then predicts its mean without factorising, which is what costs
        O(N^3) per output."""
        _, _, Xs, Ys = self._fit_standardised(X, Y, t)
        self._condition(Xs, Ys)
        if weights is not None and self.per_output_:
            if np.shape(weights) != (Ys.shape[1], Ys.shape[0]):
                raise ValueError(f"weights must be (m, N) = {(Ys.shape[1], Ys.shape[0])}, got {np.shape(weights)}")
            self._alpha = list(torch.as_tensor(np.asarray(weights, dtype=np.float64), dtype=DTYPE, device=self.dev_))
        return self

    def solved_weights(self) -> np.ndarray | None:
        """``K^-1 y`` (m, N) per output in standardised units, or None while an output's are not
        solved yet (a large fit solves them when first predicted)."""
        check_is_fitted(self, "hyper_")
        if not self.per_output_:
            return self.alpha_.cpu().numpy()
        if any(a is None for a in self._alpha):
            return None
        return torch.stack(self._alpha).cpu().numpy()

    def _condition(self, Xs: torch.Tensor, Ys: torch.Tensor) -> None:
        self.Xs_, self.Ys_ = Xs, Ys
        N, m = Ys.shape
        self.per_output_ = m * N * N * 8 > BATCHED_BYTES
        if self.per_output_:
            # One output at a time, factorised when first predicted: memory O(N^2) instead of
            # O(m N^2), and a model that is only saved (training) never pays the O(N^3).
            if not exact_fits(N, self.dev_):
                raise GPNumericalError(
                    f"an exact GP on {N} samples needs {3 * N * N * 8 / 2 ** 30:.1f} GiB on {self.dev_}, more "
                    "than is free: use the sparse GP (mmgp.gp.sparse.make_gp)")
            self.L_, self.jitter_ = None, 0.0
            self._alpha = [None] * m
            return
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        K = rbf_kernel(Xs, Xs, ls, sf) + sn[:, None, None] * torch.eye(N, dtype=DTYPE, device=self.dev_)
        with threads_for_rows(N, self.dev_):
            self.L_, self.jitter_ = robust_cholesky(K)
            self.alpha_ = torch.cholesky_solve(Ys.T.unsqueeze(-1), self.L_).squeeze(-1)  # (m, N)

    def _factor(self, j: int) -> torch.Tensor:
        """Output j's Cholesky factor (N, N) (per-output mode); caches its weights K^-1 y."""
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        with threads_for_rows(self.Xs_.shape[0], self.dev_):
            K = rbf_kernel(self.Xs_, self.Xs_, ls[j:j + 1], sf[j:j + 1])[0]
            K.diagonal().add_(sn[j])
            L, jitter = robust_cholesky(K)
            del K
            self._alpha[j] = torch.cholesky_solve(self.Ys_[:, j:j + 1], L)[:, 0]
        self.jitter_ = max(self.jitter_, jitter)
        return L

    def predict(self, X: np.ndarray, *, include_noise: bool = False, return_std: bool = True):
        """Posterior mean (M, m) and std (M, m) at X (M, d), in data units.

        ``include_noise`` adds the observation noise (predictive of a new measurement).
        """
        Xq = self._query(X)
        with threads_for_rows(self.Xs_.shape[0], self.dev_):
            if self.per_output_:
                return self._predict_per_output(Xq, include_noise, return_std)
            return self._predict_batched(Xq, include_noise, return_std)

    def _predict_batched(self, Xq: torch.Tensor, include_noise: bool, return_std: bool):
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
        return self._data_units(torch.cat(mean_s), torch.cat(var_s) if return_std else None)

    def _predict_per_output(self, Xq: torch.Tensor, include_noise: bool, return_std: bool):
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        N = self.Xs_.shape[0]
        chunk_size = max(64, int(4e6 // N))
        if not return_std:
            return self._data_units(self._mean_per_output(Xq, chunk_size), None)
        means, vars_ = [], []
        for j in range(len(self._alpha)):
            L = self._factor(j)
            m_j, v_j = [], []
            for chunk in torch.split(Xq, chunk_size):
                Ks = rbf_kernel(self.Xs_, chunk, ls[j:j + 1], sf[j:j + 1])[0]          # (N, Q)
                m_j.append(Ks.T @ self._alpha[j])
                V = torch.linalg.solve_triangular(L, Ks, upper=False)
                v_j.append((sf[j] - (V * V).sum(0)).clamp_min(1e-12) + (sn[j] if include_noise else 0.0))
            del L
            means.append(torch.cat(m_j))
            vars_.append(torch.cat(v_j))
        return self._data_units(torch.stack(means, 1), torch.stack(vars_, 1))

    def _mean_per_output(self, Xq: torch.Tensor, chunk_size: int) -> torch.Tensor:
        """Standardised posterior means (M, m) of a large fit, output by output, solving an output's
        weights where they are not yet solved (:func:`rbf_cross_kernel`: the mean alone)."""
        ls, sf, _ = self.hyper_.to_torch(self.dev_)
        means = []
        for j in range(len(self._alpha)):
            if self._alpha[j] is None:
                self._factor(j)  # caches the weights; the factor itself is not needed here
            means.append(torch.cat([rbf_cross_kernel(chunk, self.Xs_, ls[j], sf[j]) @ self._alpha[j]
                                    for chunk in torch.split(Xq, chunk_size)]))
        return torch.stack(means, 1)

    def loo_predictive(self) -> tuple[np.ndarray, np.ndarray]:
        """Leave-one-out predictive mean and std (N, m) of the training outputs (closed form)."""
        check_is_fitted(self, "hyper_")
        if not self.per_output_:
            mu, var = loo_from_inverse(inverse_from_cholesky(self.L_), self.Ys_.T)
            return self._data_units(mu.T, var.T)
        mus, vars_ = [], []
        for j in range(len(self._alpha)):
            Kinv = inverse_from_cholesky(self._factor(j))
            mu, var = loo_from_inverse(Kinv[None], self.Ys_[:, j][None])
            del Kinv
            mus.append(mu[0])
            vars_.append(var[0])
        return self._data_units(torch.stack(mus, 1), torch.stack(vars_, 1))
