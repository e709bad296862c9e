"""Numerics shared by every GP: float64 on a chosen device, robust Cholesky, inverses, threads."""
from __future__ import annotations

import math

import torch

DTYPE = torch.float64
LOG_2PI = math.log(2 * math.pi)


class GPNumericalError(RuntimeError):
    """The kernel matrix could not be factorised even with the largest allowed jitter."""


def resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but no CUDA device is available")
    return dev


def robust_cholesky(K: torch.Tensor, *, base_jitter: float = 1e-10, max_tries: int = 7) -> tuple[torch.Tensor, float]:
    """Cholesky of a batch of SPD matrices K (..., N, N), adding growing diagonal jitter on failure.

    Tries jitter 0, then base_jitter * 100^k (k = 0 .. max_tries - 2), relative to the mean
    diagonal. Returns (L, jitter used). Raises GPNumericalError when K holds NaN/inf or when
    even the largest jitter fails.
    """
    if not bool(torch.isfinite(K).all()):
        raise GPNumericalError(
            f"kernel matrix of size {K.shape[-1]} contains NaN or inf: the inputs, outputs or "
            "hyperparameters are not finite (check the log for NaN rows and the hyperparameters for overflow)")
    scale = K.diagonal(dim1=-2, dim2=-1).mean().detach().clamp_min(1e-300)
    eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
    jitter = 0.0
    for attempt in range(max_tries):
        jitter = 0.0 if attempt == 0 else base_jitter * (100.0 ** (attempt - 1))
        L, info = torch.linalg.cholesky_ex(K + jitter * scale * eye if jitter else K)
        if not bool((info > 0).any()):
            return L, jitter
    raise GPNumericalError(
        f"kernel matrix of size {K.shape[-1]} is not positive definite even with jitter {jitter:.1e} x "
        "mean diagonal: inputs are probably duplicated or badly scaled; try downsampling or a larger noise floor")


def inverse_from_cholesky(L: torch.Tensor) -> torch.Tensor:
    """K^-1 from its lower Cholesky factor L (..., N, N).

    Triangular solve then one product: on a busy shared CPU this was 5-15x faster than
    torch.cholesky_inverse (LAPACK potri), whose multithreaded path stalls when cores are taken.
    """
    eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device).expand_as(L)
    Li = torch.linalg.solve_triangular(L, eye, upper=False)
    return Li.transpose(-1, -2) @ Li


class _TorchThreads:
    """Temporarily cap torch's intra-op threads (restored on exit)."""

    def __init__(self, n: int | None):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n is not None and self.n < self.old:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)
