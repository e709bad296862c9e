"""Hyperparameter objectives: leave-one-out log predictive, log marginal likelihood and (in
mmgp.gp.windowed) leave-block-out; each a function of the kernel matrix and the targets."""
from __future__ import annotations

import torch

from .linalg import LOG_2PI, inverse_from_cholesky, robust_cholesky


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
