"""Robust linear regression (Huber IRLS) of torques on regressor columns: per output, or one
coefficient vector shared by all outputs (a payload's inertial parameters load every joint)."""
from __future__ import annotations

import numpy as np


def fit_basis_coefficients(basis: np.ndarray, Y: np.ndarray, *, n_irls: int = 4,
                           huber: float = 1.345) -> np.ndarray:
    """Per-output linear coefficients (n, p) with Y[:, j] ~ basis[:, j, :] @ coef[j].

    basis (N, n, p), Y (N, n). Huber-weighted least squares (a few IRLS steps, scale from the
    MAD), because the samples a mode is fitted on may still hold undetected pushes. Columns are
    scaled to unit RMS and the solve is minimum-norm (``lstsq``), so rank-deficient regressors
    (parameters a joint cannot see) get zero coefficients instead of blowing up.
    """
    N, n, p = basis.shape
    coef = np.zeros((n, p))
    for j in range(n):
        Aj = basis[:, j, :]
        rms = np.sqrt((Aj ** 2).mean(0))
        cols = np.flatnonzero(rms > 1e-12 * (rms.max() + 1e-300))
        if len(cols) == 0:
            continue
        As = Aj[:, cols] / rms[cols]
        y = Y[:, j]
        w = np.ones(N)
        for _ in range(n_irls):
            sw = np.sqrt(w)
            c, *_ = np.linalg.lstsq(As * sw[:, None], y * sw, rcond=1e-7)
            r = y - As @ c
            scale = 1.4826 * np.median(np.abs(r - np.median(r))) + 1e-12
            w = np.minimum(1.0, huber * scale / np.maximum(np.abs(r), 1e-300))
        coef[j, cols] = c / rms[cols]
    return coef


def fit_shared_coefficients(basis: np.ndarray, Y: np.ndarray, *, n_irls: int = 5,
                            huber: float = 1.345) -> np.ndarray:
    """One coefficient vector for all outputs, returned as (n, p) with equal rows:
    Y[:, j] ~ basis[:, j, :] @ c for every j (e.g. a payload's 10 inertial parameters, which
    load every joint). Huber-weighted least squares over the stacked (N * n) rows, each output's
    rows scaled by its robust residual scale, re-estimated every IRLS step. basis (N, n, p)."""
    N, n, p = basis.shape
    A = basis.reshape(N * n, p)
    rms = np.sqrt((A ** 2).mean(0))
    cols = np.flatnonzero(rms > 1e-12 * (rms.max() + 1e-300))
    coef = np.zeros(p)
    if len(cols) == 0:
        return np.zeros((n, p))
    As = basis[:, :, cols] / rms[cols]                          # (N, n, k)
    scale = Y.std(0) + 1e-12                                    # first pass: the outputs' spread
    w = np.ones((N, n))
    for _ in range(n_irls):
        sw = np.sqrt(w) / scale
        c, *_ = np.linalg.lstsq((As * sw[:, :, None]).reshape(N * n, -1), (Y * sw).ravel(), rcond=1e-7)
        r = Y - As @ c
        scale = 1.4826 * np.median(np.abs(r - np.median(r, 0)), 0) + 1e-12
        w = np.minimum(1.0, huber * scale / np.maximum(np.abs(r), 1e-300))
    coef[cols] = c / rms[cols]
    return np.tile(coef, (n, 1))


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
