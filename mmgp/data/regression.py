"""Robust linear regression of torques on regressor columns: the one implementation in mmgp.

``robust_regression`` fits outputs ``Y`` (N, n) on columns ``A`` (N, n, p) by iteratively
reweighted least squares (IRLS): Huber steps (knee at ``HUBER_K`` robust scales) and then,
optionally, Tukey-bisquare steps (``TUKEY_K``), whose weights fall to zero, so gross outliers
(pushes) stop pulling the fit at all. Coefficients are either one vector shared by all outputs
(a payload's or an effect library's parameters load every joint) or one vector per output.

Users: the EM's mode means (``fit_basis_coefficients``, ``fit_shared_coefficients``, a few Huber
steps with minimum-norm solves) and the diagnosis's whole-library fit (Huber to convergence,
then Tukey, on masked equations, solved through the Gram matrix because the library has ~100
columns over ~40,000 stacked equations).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .statistics import mad_sd

HUBER_K = 1.345   # 95% efficiency at the normal
TUKEY_K = 4.685   # 95% efficiency at the normal
_EPS = 1e-12      # floor of a robust scale (N*m): keeps noise-free data finite


@dataclass
class RobustFit:
    """``coef``: (p,) shared or (n, p) per output; ``weights``: (N, n) robustness weights (times
    the mask) of the last solve; ``scale``: (n,) robust residual scale per output (MAD)."""

    coef: np.ndarray
    weights: np.ndarray
    scale: np.ndarray


def solve_gram(G: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Solution of ``G x = c`` for a Gram matrix ``G`` (p, p), with a ridge of 1e-10 times its
    largest diagonal entry: exactly collinear columns then share their coefficient instead of
    blowing up. Falls back to least squares if ``G`` is still singular. A stack ``G`` (K, p, p),
    ``c`` (K, p) is solved system by system, each with its own ridge (K, p)."""
    G, c = np.asarray(G), np.asarray(c)
    if G.ndim == 3:
        if not G.shape[0]:
            return np.zeros(c.shape)
        d = np.diagonal(G, axis1=1, axis2=2)
        reg = 1e-10 * (d.max(1) if d.shape[1] else 1.0) + 1e-300
        try:
            return np.linalg.solve(G + reg[:, None, None] * np.eye(c.shape[1]), c[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            return np.stack([solve_gram(g, b) for g, b in zip(G, c)])
    d = np.diag(G).copy()
    reg = 1e-10 * (d.max() if d.size else 1.0) + 1e-300
    try:
        return np.linalg.solve(G + reg * np.eye(len(c)), c)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(G, c, rcond=None)[0]


def _huber(r: np.ndarray, knee: np.ndarray) -> np.ndarray:
    return np.minimum(1.0, knee / np.maximum(np.abs(r), 1e-300))


def _tukey(r: np.ndarray, knee: np.ndarray) -> np.ndarray:
    u = np.abs(r) / knee
    return np.where(u < 1, (1 - u ** 2) ** 2, 0.0)


def _robust_scale(r: np.ndarray, mask: np.ndarray | None, centre: bool) -> np.ndarray:
    """(n,) MAD of each output's residual over its unmasked rows, about the median (``centre``)
    or about zero; 1 for an output without rows."""
    if mask is None:
        return mad_sd(r, 0, centre) + _EPS
    out = np.ones(r.shape[1])
    for j in range(r.shape[1]):
        v = r[mask[:, j] > 0, j]
        if v.size:
            out[j] = mad_sd(v, 0, centre)
    return out + _EPS


class _MinNormSolver:
    """Weighted least squares by ``lstsq`` on columns scaled to unit RMS (minimum norm,
    ``rcond`` 1e-7): a column the data cannot see gets coefficient zero, not a blow-up."""

    def __init__(self, A: np.ndarray):
        N, m, p = A.shape
        rms = np.sqrt((A.reshape(N * m, p) ** 2).mean(0))
        self.p = p
        self.cols = np.flatnonzero(rms > 1e-12 * (rms.max() + 1e-300))
        self.rms = rms[self.cols]
        self.As = A[:, :, self.cols] / self.rms

    def __call__(self, Y: np.ndarray, sw: np.ndarray) -> np.ndarray:
        N, m = Y.shape
        c, *_ = np.linalg.lstsq((self.As * sw[:, :, None]).reshape(N * m, -1), (Y * sw).ravel(), rcond=1e-7)
        return c

    def predict(self, c: np.ndarray) -> np.ndarray:
        N, m, k = self.As.shape
        return (self.As.reshape(N * m, k) @ c).reshape(N, m)

    def coefficients(self, c: np.ndarray) -> np.ndarray:
        out = np.zeros(self.p)
        out[self.cols] = c / self.rms
        return out


class _GramSolver:
    """Weighted least squares through the normal equations with a relative ridge of 1e-8 of each
    column's own weighted sum of squares (scale-free, so columns in N*m and in N*m per kg mix):
    one p x p solve per step, far cheaper than an SVD of a tall stacked system."""

    def __init__(self, A: np.ndarray):
        self.A = A
        self.cols = np.arange(A.shape[2])

    def __call__(self, Y: np.ndarray, sw: np.ndarray) -> np.ndarray:
        Aw = (self.A * sw[:, :, None]).reshape(-1, self.A.shape[2])
        G = Aw.T @ Aw
        return solve_gram(G + 1e-8 * np.diag(np.diag(G)), Aw.T @ (Y * sw).reshape(-1))

    def predict(self, c: np.ndarray) -> np.ndarray:
        return self.A @ c

    def coefficients(self, c: np.ndarray) -> np.ndarray:
        return c


def _irls_shared(A, Y, mask, *, huber_steps, tukey_steps, tol, whiten, centre, solver, huber_k, init=None) -> RobustFit:
    N, m, p = A.shape
    solve = _MinNormSolver(A) if solver == "lstsq" else _GramSolver(A)
    if len(solve.cols) == 0:
        return RobustFit(np.zeros(p), np.ones((N, m)) if mask is None else mask.astype(float), np.ones(m))
    h = np.ones((N, m)) if mask is None else np.asarray(mask, dtype=np.float64).copy()
    # whitened: each output's rows divided by its residual scale, so outputs in different units
    # or with different noise count alike; the first pass uses the outputs' own spread
    scale = Y.std(0) + _EPS if whiten else np.ones(m)
    h0 = h if init is None else h * init
    c = solve(Y, np.sqrt(h0) / scale if whiten else np.sqrt(h0))
    for psi, k, n_steps in ((_huber, huber_k, huber_steps), (_tukey, TUKEY_K, tukey_steps)):
        for _ in range(n_steps):
            r = Y - solve.predict(c)
            scale = _robust_scale(r, mask, centre)
            h = psi(r, k * scale) if mask is None else mask * psi(r, k * scale)
            c_new = solve(Y, np.sqrt(h) / scale if whiten else np.sqrt(h))
            done = tol is not None and np.allclose(c_new, c, rtol=tol, atol=1e-12)
            c = c_new
            if done:
                break
    return RobustFit(solve.coefficients(c), h, scale)


def robust_regression(A: np.ndarray, Y: np.ndarray, *, shared: bool = True, mask: np.ndarray | None = None,
                      huber_steps: int = 4, tukey_steps: int = 0, tol: float | None = None,
                      whiten: bool = False, centre: bool = True, solver: str = "lstsq",
                      huber_k: float = HUBER_K, init: np.ndarray | None = None) -> RobustFit:
    """Robust (IRLS) fit of ``Y`` (N, n) on columns ``A`` (N, n, p).

    shared: one coefficient vector (p,) for all outputs (``Y[:, j] ~ A[:, j] @ c``), else one per
        output ((n, p), each output fitted on its own).
    mask: (N, n) 0/1 weights of the equations (0 leaves an output's equation out at that row).
    huber_steps, tukey_steps: reweighting steps after the first (unweighted) solve: Huber
        weights, then Tukey-bisquare weights from where Huber ended; each phase stops early when
        the coefficients move by less than ``tol`` (relative; None: run every step).
        ``huber_k``: the Huber knee in robust scales.
    whiten: divide each output's rows by its current robust scale (shared fits only matter).
    centre: measure each output's scale about its residual median (an unmodelled constant does
        not inflate it) or about zero.
    solver: "lstsq" (minimum-norm on unit-RMS columns, for rank-deficient regressors) or "gram"
        (ridge-regularised normal equations, for many stacked rows).
    init: (N, n) weights in [0, 1] of the first solve only (shared fits): where IRLS starts. A
        start that already leaves most outliers out (e.g. another detector's flags) keeps the
        reweighting from settling on a fit the outliers dragged, when they are many (long pushes).
    """
    A = np.asarray(A, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    kw = dict(huber_steps=huber_steps, tukey_steps=tukey_steps, tol=tol, whiten=whiten, centre=centre,
              solver=solver, huber_k=huber_k)
    if shared:
        return _irls_shared(A, Y, mask, init=init, **kw)
    fits = [_irls_shared(A[:, j:j + 1], Y[:, j:j + 1], None if mask is None else mask[:, j:j + 1], **kw)
            for j in range(Y.shape[1])]
    return RobustFit(np.stack([f.coef for f in fits]), np.concatenate([f.weights for f in fits], 1),
                     np.concatenate([f.scale for f in fits]))


def fit_basis_coefficients(basis: np.ndarray, Y: np.ndarray, *, n_irls: int = 4,
                           huber: float = 1.345, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-output linear coefficients (n, p) with Y[:, j] ~ basis[:, j, :] @ coef[j].

    basis (N, n, p), Y (N, n). Huber-weighted least squares (``n_irls`` solves, scale from the
    MAD), because the samples a mode is fitted on may still hold undetected pushes. Columns are
    scaled to unit RMS and the solve is minimum-norm, so rank-deficient regressors (parameters a
    joint cannot see) get zero coefficients instead of blowing up. ``mask`` (N, n) 0/1: the
    equations used (None: all).
    """
    return robust_regression(basis, Y, shared=False, mask=mask, huber_steps=n_irls - 1, huber_k=huber).coef


def fit_shared_coefficients(basis: np.ndarray, Y: np.ndarray, *, n_irls: int = 5,
                            huber: float = 1.345, mask: np.ndarray | None = None) -> np.ndarray:
    """One coefficient vector for all outputs, returned as (n, p) with equal rows:
    Y[:, j] ~ basis[:, j, :] @ c for every j (e.g. a payload's 10 inertial parameters, which
    load every joint). Huber-weighted least squares over the stacked (N * n) rows, each output's
    rows scaled by its robust residual scale, re-estimated every IRLS step. basis (N, n, p);
    ``mask`` (N, n) 0/1: the equations used (None: all)."""
    coef = robust_regression(basis, Y, shared=True, whiten=True, mask=mask, huber_steps=n_irls - 1, huber_k=huber).coef
    return np.tile(coef, (Y.shape[1], 1))


def basis_rank(basis: np.ndarray, max_rows: int = 1000, seed: int = 0, shared: bool = False) -> int:
    """Number of identifiable basis coefficients (N, n, p): the sum over outputs of each output's
    regressor rank, or with ``shared`` coefficients the rank of the stacked (N * n, p) rows."""
    rng = np.random.default_rng(seed)
    rows = basis if len(basis) <= max_rows else basis[rng.choice(len(basis), max_rows, replace=False)]
    if shared:
        return int(np.linalg.matrix_rank(rows.reshape(-1, basis.shape[2])))
    total = 0
    for j in range(basis.shape[1]):
        Aj = rows[:, j, :]
        rms = np.sqrt((Aj ** 2).mean(0))
        cols = rms > 1e-12 * (rms.max() + 1e-300)
        if cols.any():
            total += int(np.linalg.matrix_rank(Aj[:, cols] / rms[cols], tol=None))
    return total
