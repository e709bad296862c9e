"""Scalable GP for logs of 10^4-10^5 samples: SGPR (Titsias 2009) with k-means inducing inputs.

Chosen on evidence (benchmarks/bench_real_gp.py, same hyperparameters for both options): SGPR
with 1,000 inducing inputs over all samples vs an exact GP on a random 3,000-sample subset
("subset of data", ``method="subset"``). The subset can win where lengthscales are shorter than
the inducing inputs resolve; SGPR stays the default because it uses every sample and its error
keeps falling with M; both beat scikit-learn's exact GP on a smaller subset (figures:
benchmarks/README.md).

Model, per output j (a loop over outputs, to keep memory at O(M^2 + M * chunk)):
inducing inputs Z (M, d) are k-means centres of the standardised inputs (shared by all outputs);
with Kuu = k(Z, Z), Kuf = k(Z, X), noise variance s2, the collapsed variational posterior
(Titsias' SGPR, identical in mean to DTC / projected process) is

    Sigma  = (Kuu + Kuf Kfu / s2)^-1
    mean*  = K*u Sigma Kuf y / s2
    var*   = k** - K*u Kuu^-1 Ku* + K*u Sigma Ku*          (+ s2 with include_noise)

computed through L = chol(Kuu), A = L^-1 Kuf / s (M, N), B = I + A A^T, LB = chol(B):
O(N M^2) time per output; A is never held whole: A A^T and A y are summed over chunks of
samples, so memory is O(M^2 + M * chunk) whatever N (the same code on a GPU for 10^5+ samples).

Hyperparameters: the exact GP's LOO objective (``mmgp.gp.hyper.optimise_hyper``) on a random subset of
``max_fit_points`` samples, the same procedure as ``ExactGP`` (so ``hyper_`` means the same thing
and can be passed between the two).

``loo_predictive`` is the exact closed-form LOO of the approximate (Nystrom / DTC) model, whose
prior covariance is Qff + s2 I with Qff = Kfu Kuu^-1 Kuf: with A as above,
(Qff + s2 I)^-1 = (I - A^T B^-1 A) / s2, so its diagonal and (Qff + s2 I)^-1 y cost O(N M^2).
It is not the LOO of the exact GP: Qff underestimates the prior variance away from Z, so these
LOO variances are somewhat optimistic where inducing points are sparse.
"""
from __future__ import annotations

import numpy as np
import torch

from sklearn.utils.validation import check_is_fitted

from ..threads import threads_for_rows
from .exact import ExactGP, StandardisedRBFGP
from .settings import GP_DEFAULTS as _GP
from .hyper import Hyper
from .kernels import rbf_kernel
from .linalg import DTYPE, exact_fits, resolve_device, robust_cholesky

#: "auto" conditions an exact GP on every sample up to this many (memory permitting), an SGPR
#: above: up to it, the exact GP on every row was the more accurate at about the SGPR's time
#: (benchmarks/README.md, "Training that scales")
EXACT_MAX_SAMPLES = 16000
#: GP kinds a caller may ask for
GP_METHODS = ("auto", "exact", "sgpr", "subset")
#: bytes of one chunk of the (M, chunk) cross-kernel during SGPR conditioning and prediction
CHUNK_BYTES = 2 ** 27


def kmeans_inducing(Xs: np.ndarray, n_inducing: int, seed: int = 0) -> np.ndarray:
    """Inducing inputs (M, d): k-means centres of the standardised inputs Xs (N, d).

    Centres follow the data density, so inducing points sit where the trajectory spends time;
    duplicated centres (empty clusters) are dropped. Beyond 20 M samples the centres are fitted
    on a random 20 M of them (the density is as well described; k-means cost stays O(M^2 d)).
    """
    from sklearn.cluster import KMeans

    M = min(n_inducing, Xs.shape[0])
    if M == Xs.shape[0]:
        return Xs.copy()
    if Xs.shape[0] > 20 * M:
        Xs = Xs[np.sort(np.random.default_rng(seed).choice(Xs.shape[0], 20 * M, replace=False))]
    km = KMeans(n_clusters=M, n_init=1, max_iter=50, random_state=seed).fit(Xs)
    return np.unique(km.cluster_centers_, axis=0)


class SparseGP(StandardisedRBFGP):
    """SGPR with k-means inducing inputs; the ``ExactGP`` API for large N.

    Parameters: as ``ExactGP`` (ard, objective, max_fit_points, max_iter, noise_floor, device,
    seed, coarse_fit_points, independent_outputs, refine_rounds, shared_starts), plus
    ``n_inducing`` (M, default 1000; cost O(N M^2 m), memory O(M^2 + M * chunk)), ``method``
    ("sgpr", default, or "subset": an ``ExactGP`` conditioned on ``n_subset`` random samples,
    exposed as ``exact_`` with the rows in ``subset_``; it standardises the subset itself and
    takes the hyperparameters, in standardised units, from the fit on the full data).

    Learned: ``hyper_`` (standardised units, same meaning as ExactGP's), ``Z_`` (M, d)
    standardised inducing inputs, ``inducing_`` (M, d) the same in data units,
    ``lengthscale_`` (m, d) and ``noise_std_`` (m,) in data units, ``objective_value_``
    (per-sample LOO objective of the exact GP on the fitting subset).
    """

    def __init__(self, *, ard: bool = _GP.ard, objective: str = _GP.objective, max_fit_points: int = _GP.max_fit_points,
                 max_iter: int = _GP.max_iter, noise_floor: float = _GP.noise_floor, device: str | None = None,
                 seed: int = _GP.seed, coarse_fit_points: int = _GP.coarse_fit_points,
                 independent_outputs: bool = _GP.independent_outputs, n_inducing: int = 1000,
                 method: str = "sgpr", n_subset: int = 3000, refine_rounds: int = _GP.refine_rounds,
                 shared_starts: bool = _GP.shared_starts, block_s: float = _GP.block_s, hyper: Hyper | None = None,
                 optimise: bool = _GP.optimise):
        super().__init__(ard=ard, objective=objective, max_fit_points=max_fit_points, max_iter=max_iter,
                         noise_floor=noise_floor, device=device, seed=seed, coarse_fit_points=coarse_fit_points,
                         independent_outputs=independent_outputs, refine_rounds=refine_rounds,
                         shared_starts=shared_starts, block_s=block_s, hyper=hyper, optimise=optimise)
        self.method = method
        self.n_subset = n_subset
        self.n_inducing = n_inducing

    def fit(self, X: np.ndarray, Y: np.ndarray, *, inducing: np.ndarray | None = None,
            t: np.ndarray | None = None) -> "SparseGP":
        """X (N, d), Y (N, m) or (N,). ``inducing`` (M, d) in data units replaces the k-means
        inputs (e.g. a saved model's ``inducing_``); ``t`` (N,) s as in :meth:`ExactGP.fit`."""
        if self.method not in ("sgpr", "subset"):
            raise ValueError(f"method must be 'sgpr' or 'subset', got {self.method!r}")
        # Same procedure as ExactGP: the exact GP's hyperparameters on a subset.
        X, Y, Xs, Ys = self._fit_standardised(X, Y, t)
        if self.method == "subset":
            rng = np.random.default_rng(self.seed + 1)
            self.subset_ = np.sort(rng.choice(len(X), min(self.n_subset, len(X)), replace=False))
            self.exact_ = ExactGP(device=self.device, hyper=self.hyper_, optimise=False).fit(X[self.subset_],
                                                                                            Y[self.subset_])
            self._X, self._Y = X, Y
            return self
        if inducing is None:
            self.Z_ = kmeans_inducing(Xs.cpu().numpy(), self.n_inducing, self.seed)
        else:
            self.Z_ = self.x_scaler_.transform(np.asarray(inducing, dtype=np.float64))
        self.inducing_ = self.Z_ * self.x_scaler_.scale_ + self.x_scaler_.mean_
        self._condition(Xs, Ys)
        return self

    def _chunks(self, Xs: torch.Tensor) -> list[torch.Tensor]:
        return list(torch.split(Xs, max(64, int(CHUNK_BYTES // (8 * self.Z_.shape[0])))))

    def _condition(self, Xs: torch.Tensor, Ys: torch.Tensor) -> None:
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        Z = torch.as_tensor(self.Z_, dtype=DTYPE, device=self.dev_)
        M = Z.shape[0]
        eye = torch.eye(M, dtype=DTYPE, device=self.dev_)
        self.L_, self.LB_, self.w_, self.jitter_ = [], [], [], 0.0
        with threads_for_rows(max(M, Xs.shape[0]), self.dev_):
            for j in range(Ys.shape[1]):
                L, jit = robust_cholesky(rbf_kernel(Z, Z, ls[j:j + 1], sf[j:j + 1])[0], base_jitter=1e-8)
                AAt = torch.zeros((M, M), dtype=DTYPE, device=self.dev_)
                Ay = torch.zeros(M, dtype=DTYPE, device=self.dev_)
                for Xc, yc in zip(self._chunks(Xs), self._chunks(Ys[:, j])):
                    A = self._scaled_cross(L, Z, Xc, j, ls, sf, sn)                 # (M, chunk)
                    AAt += A @ A.T
                    Ay += A @ yc
                LB, jit_b = robust_cholesky(eye + AAt)
                c = torch.linalg.solve_triangular(LB, Ay[:, None], upper=False)[:, 0] / torch.sqrt(sn[j])
                # mean weights: mean* = K*u w with w = L^-T LB^-T c
                w = torch.linalg.solve_triangular(L.T, torch.linalg.solve_triangular(LB.T, c[:, None], upper=True),
                                                  upper=True)[:, 0]
                self.L_.append(L)
                self.LB_.append(LB)
                self.w_.append(w)
                self.jitter_ = max(self.jitter_, jit, jit_b)
        self._Xs, self.Ys_ = Xs, Ys
        self._loo_s = None

    def _scaled_cross(self, L, Z, Xc, j, ls, sf, sn) -> torch.Tensor:
        """A = L^-1 K(Z, Xc) / s for output j: (M, chunk)."""
        return torch.linalg.solve_triangular(L, rbf_kernel(Z, Xc, ls[j:j + 1], sf[j:j + 1])[0],
                                             upper=False) / torch.sqrt(sn[j])

    def _dtc_loo(self) -> tuple[torch.Tensor, torch.Tensor]:
        """LOO mean and variance (N, m), standardised, of the DTC model: (Qff + s2 I)^-1 =
        (I - A^T B^-1 A) / s2, chunk by chunk with V = LB^-1 A."""
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        Z = torch.as_tensor(self.Z_, dtype=DTYPE, device=self.dev_)
        means, vars_ = [], []
        with threads_for_rows(max(Z.shape[0], self._Xs.shape[0]), self.dev_):
            for j in range(self.Ys_.shape[1]):
                y = self.Ys_[:, j]
                Ay = sum(self._scaled_cross(self.L_[j], Z, Xc, j, ls, sf, sn) @ yc
                         for Xc, yc in zip(self._chunks(self._Xs), self._chunks(y)))
                Vy = torch.linalg.solve_triangular(self.LB_[j], Ay[:, None], upper=False)[:, 0]
                m_j, v_j = [], []
                for Xc, yc in zip(self._chunks(self._Xs), self._chunks(y)):
                    V = torch.linalg.solve_triangular(self.LB_[j], self._scaled_cross(self.L_[j], Z, Xc, j, ls, sf, sn),
                                                      upper=False)
                    diag = (1.0 - (V * V).sum(0)) / sn[j]
                    alpha = (yc - V.T @ Vy) / sn[j]
                    m_j.append(yc - alpha / diag)
                    v_j.append(1.0 / diag)
                means.append(torch.cat(m_j))
                vars_.append(torch.cat(v_j))
        return torch.stack(means, 1), torch.stack(vars_, 1)

    def predict(self, X: np.ndarray, *, include_noise: bool = False, return_std: bool = True):
        """Posterior mean (M, m) and std (M, m) at X (M, d), in data units (SGPR predictive)."""
        Xq = self._query(X)
        if self.method == "subset":
            return self._subset_shape(self.exact_.predict(X, include_noise=include_noise, return_std=return_std))
        with threads_for_rows(max(self.Z_.shape[0], self._Xs.shape[0]), self.dev_):
            return self._predict_sgpr(Xq, include_noise, return_std)

    def _predict_sgpr(self, Xq: torch.Tensor, include_noise: bool, return_std: bool):
        ls, sf, sn = self.hyper_.to_torch(self.dev_)
        Z = torch.as_tensor(self.Z_, dtype=DTYPE, device=self.dev_)
        means, vars_ = [], []
        for j in range(len(self.w_)):
            m_j, v_j = [], []
            for Xc in self._chunks(Xq):
                Ksu = rbf_kernel(Xc, Z, ls[j:j + 1], sf[j:j + 1])[0]                # (Q, M)
                m_j.append(Ksu @ self.w_[j])
                if return_std:
                    V1 = torch.linalg.solve_triangular(self.L_[j], Ksu.T, upper=False)
                    V2 = torch.linalg.solve_triangular(self.LB_[j], V1, upper=False)
                    var = (sf[j] - (V1 * V1).sum(0) + (V2 * V2).sum(0)).clamp_min(1e-12)
                    v_j.append(var + sn[j] if include_noise else var)
            means.append(torch.cat(m_j))
            if return_std:
                vars_.append(torch.cat(v_j))
        return self._data_units(torch.stack(means, 1), torch.stack(vars_, 1) if return_std else None)

    def loo_predictive(self) -> tuple[np.ndarray, np.ndarray]:
        """LOO mean and std (N, m) of the training outputs.

        "sgpr": closed form under the DTC approximate model (computed on first call). "subset":
        exact closed-form LOO for the rows in the conditioning subset; the other rows are not
        conditioned on, so their ordinary predictive (with noise) already leaves them out.
        """
        check_is_fitted(self, "hyper_")
        if self.method == "subset":
            mean, std = self.exact_.predict(self._X, include_noise=True)
            lm, ls = self.exact_.loo_predictive()
            mean, std = np.array(mean), np.array(std)
            mean[self.subset_], std[self.subset_] = lm, ls
            return self._subset_shape((mean, std))
        if self._loo_s is None:
            self._loo_s = self._dtc_loo()
        return self._data_units(*self._loo_s)

    def _subset_shape(self, arrays):
        # exact_ was fitted on 2-D outputs; give vectors back where the fit got a vector
        if not self._vector_output:
            return arrays
        return arrays[:, 0] if isinstance(arrays, np.ndarray) else tuple(a[:, 0] for a in arrays)

    def _training_outputs(self) -> np.ndarray:
        return self._Y if self.method == "subset" else super()._training_outputs()


_SPARSE_ONLY = ("n_inducing", "method", "n_subset")


def gp_kind(gp) -> str:
    """"exact", "sgpr" or "subset": what a fitted GP of :func:`make_gp` is."""
    return gp.method if isinstance(gp, SparseGP) else "exact"


def choose_gp_method(n_samples: int, method: str = "auto", device=None, *,
                     exact_threshold: int = EXACT_MAX_SAMPLES) -> str:
    """The GP kind for ``n_samples`` training samples: ``method`` itself unless "auto"; "auto" is
    "exact" (every sample, exact) up to ``exact_threshold`` samples when one output's kernel
    matrix and its factor fit the free memory of ``device`` (:func:`mmgp.gp.linalg.exact_fits`),
    else "sgpr" (every sample, O(N M^2) time, O(M^2 + M chunk) memory). "subset" (subset of
    data) is never chosen by "auto": it was less accurate than SGPR at the same size on real arms
    (benchmarks/README.md, "Training that scales")."""
    if method not in GP_METHODS:
        raise ValueError(f"GP method must be one of {', '.join(GP_METHODS)}, got {method!r}")
    if method != "auto":
        return method
    if n_samples <= exact_threshold and exact_fits(n_samples, resolve_device(device)):
        return "exact"
    return "sgpr"


def make_gp(n_samples: int, *, method: str = "auto", exact_threshold: int = EXACT_MAX_SAMPLES, **kw):
    """The GP :func:`choose_gp_method` picks for ``n_samples``: ``ExactGP(**kw)`` or
    ``SparseGP(method=..., **kw)``. Sparse-only settings (``n_inducing``, ``n_subset``) are
    dropped for the exact GP, so one set of keyword arguments serves all."""
    kind = choose_gp_method(n_samples, method, kw.get("device"), exact_threshold=exact_threshold)
    if kind == "exact":
        return ExactGP(**{k: v for k, v in kw.items() if k not in _SPARSE_ONLY})
    return SparseGP(method=kind, **kw)
