"""Hyperparameter objectives, each a function of the kernel matrix and the targets.

All are log densities to be *maximised*, batched over outputs: K (m, N, N) including the noise,
y (m, N), value (m,). An :class:`Objective` bundles

* ``value(K, y)``: written with differentiable torch operations, so autograd gives its gradient;
* ``value_and_dK(L, y)`` (where a closed form exists): the value and ``G = dF/dK`` (m, N, N) from
  the Cholesky factor ``L`` of K. A caller then only needs ``dK/dtheta`` (hand-written or by
  autograd) to finish the chain rule, which avoids backpropagating through the factorisation.

Objectives: the leave-one-out log predictive (:data:`LOO`, Rasmussen & Williams, GPML 5.4.2), the
log marginal likelihood (:data:`MARGINAL`) and the leave-time-block-out log predictive
(:func:`leave_block_out`, for densely logged samples whose neighbours are near-copies).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from .linalg import LOG_2PI, gaussian_logpdf, inverse_from_cholesky, robust_cholesky


@dataclass(frozen=True)
class Objective:
    """A named objective: ``value(K, y) -> (m,)``, optionally ``value_and_dK(L, y) -> (F, G)``."""

    name: str
    value: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    value_and_dK: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None


def loo_from_inverse(Kinv: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form LOO predictive. Kinv (m, N, N), y (m, N) -> mean (m, N), var (m, N)."""
    alpha = (Kinv @ y.unsqueeze(-1)).squeeze(-1)
    diag = Kinv.diagonal(dim1=-2, dim2=-1)
    return y - alpha / diag, 1.0 / diag


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


def loo_value_and_dK(L: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """LOO log predictive (m,) and its gradient w.r.t. K, G (m, N, N), from L = chol(K).

    With P = K^-1, c = diag P, alpha = P y: F = sum_i 0.5 log c_i - alpha_i^2 / (2 c_i) - 0.5 log 2 pi,
    and G = -P diag(a) P - sym(P b alpha^T) with a = dF/dc, b = dF/dalpha (GPML eq. 5.13 rewritten).
    """
    N = y.shape[-1]
    P = inverse_from_cholesky(L)
    alpha = (P @ y.unsqueeze(-1)).squeeze(-1)
    c = P.diagonal(dim1=-2, dim2=-1)
    F = (0.5 * torch.log(c) - 0.5 * alpha ** 2 / c).sum(-1) - 0.5 * N * LOG_2PI
    a = 0.5 / c + 0.5 * alpha ** 2 / c ** 2              # dF/d[P]_ii
    b = -alpha / c                                       # dF/dalpha_i
    Pb = P @ b.unsqueeze(-1)
    G = (P * a.unsqueeze(-2)) @ P
    G.neg_()
    G -= 0.5 * (Pb @ alpha.unsqueeze(-2) + alpha.unsqueeze(-1) @ Pb.transpose(-1, -2))
    return F, G


def marginal_value_and_dK(L: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log marginal likelihood (m,) and G = dF/dK = (alpha alpha^T - K^-1) / 2 (m, N, N), from L = chol(K)."""
    N = y.shape[-1]
    P = inverse_from_cholesky(L)
    alpha = (P @ y.unsqueeze(-1)).squeeze(-1)
    F = -0.5 * (y * alpha).sum(-1) - torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1) - 0.5 * N * LOG_2PI
    G = P.mul_(-0.5)
    G += 0.5 * alpha.unsqueeze(-1) * alpha.unsqueeze(-2)
    return F, G


def block_loo_log_predictive(K: torch.Tensor, y: torch.Tensor, idx: np.ndarray, valid: np.ndarray) -> torch.Tensor:
    """Sum over samples of log p(y_i | all samples outside i's block), per output (m,).

    Exact leave-block-out: for block W, y_W | rest ~ N(y_W - P_WW^-1 [P y]_W, P_WW^-1), P = K^-1;
    each sample contributes its marginal. K (m, N, N) incl. noise, y (m, N); ``idx`` (n_blocks, B)
    member indices padded with 0 and ``valid`` (n_blocks, B) marking real members.
    """
    L, _ = robust_cholesky(K)
    _, _, _, vt, _, _, r, var = _block_parts(L, y, idx, valid)
    return (gaussian_logpdf(r, 0.0, var) * vt).sum((-1, -2))


def _block_parts(L: torch.Tensor, y: torch.Tensor, idx: np.ndarray, valid: np.ndarray):
    """The blocks' pieces from L = chol(K): P = K^-1, alpha = P y, the index and validity
    tensors, C = P_WW^-1 per block (padding: identity), alpha_W (zero on padding), r = C alpha_W
    (y_W less its leave-block-out mean) and var = diag C."""
    P = torch.cholesky_inverse(L)
    alpha = (P @ y.unsqueeze(-1)).squeeze(-1)
    it = torch.as_tensor(idx, device=L.device)
    vt = torch.as_tensor(valid, dtype=L.dtype, device=L.device)
    mask2 = vt[:, :, None] * vt[:, None, :]
    eye = torch.eye(idx.shape[1], dtype=L.dtype, device=L.device)
    C = torch.cholesky_inverse(torch.linalg.cholesky(P[:, it[:, :, None], it[:, None, :]] * mask2 + eye * (1 - mask2)))
    aW = alpha[:, it] * vt                                                   # (m, nb, B)
    r = (C @ aW.unsqueeze(-1)).squeeze(-1)
    return P, alpha, it, vt, C, aW, r, C.diagonal(dim1=-2, dim2=-1)


def block_loo_value_and_dK(L: torch.Tensor, y: torch.Tensor, idx: np.ndarray,
                           valid: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Leave-block-out log predictive (m,) and G = dF/dK (m, N, N), from L = chol(K); ``idx``,
    ``valid`` as in :func:`block_loo_log_predictive`.

    With P = K^-1, alpha = P y and per block W: C = P_WW^-1, r = C alpha_W, F_W = sum_i
    log N(r_i; 0, C_ii). With a = dF/dC_ii, b = dF/dr: dF/dC = diag(a) + b alpha_W^T,
    dF/dP_WW = -C (dF/dC) C (from C = P_WW^-1) and dF/dalpha_W = C b; then, with D the blocks'
    dF/dP_WW on P's diagonal blocks and g the dF/dalpha: dF/dP = D + g y^T, and
    G = -P (dF/dP) P = -P D P - (P g) alpha^T, symmetrised. Cost: a few (N, N) products, like
    :func:`loo_value_and_dK`, against backpropagating through two factorisations.
    """
    m, N = y.shape
    P, alpha, it, vt, C, aW, r, var = _block_parts(L, y, idx, valid)
    F = (gaussian_logpdf(r, 0.0, var) * vt).sum((-1, -2))
    a = (0.5 * r ** 2 / var ** 2 - 0.5 / var) * vt                         # padding: 0
    b = -r / var * vt
    dC = torch.diag_embed(a) + b.unsqueeze(-1) * aW.unsqueeze(-2)
    # scattered by adding: padded members index sample 0 but carry zeros (a, b, aW vanish there)
    D = torch.zeros(m, N * N, dtype=P.dtype, device=P.device)
    D.index_add_(1, (it[:, :, None] * N + it[:, None, :]).reshape(-1), (-(C @ dC @ C)).reshape(m, -1))
    D = D.view(m, N, N)
    g = torch.zeros_like(y).index_add_(1, it.reshape(-1), ((C @ b.unsqueeze(-1)).squeeze(-1) * vt).reshape(m, -1))
    G = P @ D @ P
    G += (P @ g.unsqueeze(-1)) @ alpha.unsqueeze(-2)
    G = -0.5 * (G + G.transpose(-1, -2))
    return F, G


LOO = Objective("loo", loo_log_predictive, loo_value_and_dK)
MARGINAL = Objective("marginal", log_marginal_likelihood, marginal_value_and_dK)


def leave_block_out(ts: np.ndarray, length: float) -> Objective:
    """Leave-block-out log predictive for samples at sorted times ``ts`` (N,) s, in consecutive
    blocks spanning at most ``length`` s (:func:`mmgp.data.folds.time_blocks`), with its closed-form
    dF/dK (:func:`block_loo_value_and_dK`)."""
    from ..data.folds import time_blocks

    idx, valid = time_blocks(np.asarray(ts, dtype=np.float64), float(length))
    return Objective(f"leave-block-out({length:g} s)", lambda K, y: block_loo_log_predictive(K, y, idx, valid),
                     lambda L, y: block_loo_value_and_dK(L, y, idx, valid))


def get_objective(objective: str | Objective) -> Objective:
    """An :class:`Objective` from itself or its name ("loo", "marginal")."""
    if isinstance(objective, Objective):
        return objective
    named = {LOO.name: LOO, MARGINAL.name: MARGINAL}
    if objective not in named:
        raise ValueError(f"objective must be 'loo' or 'marginal', got {objective!r}")
    return named[objective]
