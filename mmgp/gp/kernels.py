"""Kernels, batched over outputs: each output (joint) has its own hyperparameters."""
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
    return signal_var[:, None, None] * torch.exp(-0.5 * sq.clamp_min(0.0))
