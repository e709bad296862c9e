"""Numerics shared by every GP: float64 on a chosen device (and the default device of a block),
the memory a kernel matrix may take there, robust Cholesky, inverses.

Threads are not set here: :mod:`mmgp.threads` holds the one thread policy.
"""
from __future__ import annotations

import contextlib
import contextvars
import math
import os
from typing import Iterator

import numpy as np
import torch

DTYPE = torch.float64
LOG_2PI = math.log(2 * math.pi)


def gaussian_logpdf(y, mean, var):
    """Elementwise log density of ``y`` under N(``mean``, ``var``): numpy arrays or torch tensors
    (``var`` decides which log), broadcast together."""
    log = torch.log if isinstance(var, torch.Tensor) else np.log
    return -0.5 * (LOG_2PI + log(var) + (y - mean) ** 2 / var)


class GPNumericalError(RuntimeError):
    """The kernel matrix could not be factorised even with the largest allowed jitter."""


_DEFAULT_DEVICE: contextvars.ContextVar = contextvars.ContextVar("mmgp_default_device", default="cpu")


@contextlib.contextmanager
def default_device(device: str | torch.device | None) -> Iterator[None]:
    """Within the block, GPs whose ``device`` setting is None run on ``device`` ("cpu", "cuda",
    "cuda:1", "auto"; None leaves the current default). How a command's ``--device`` reaches GPs
    built deep inside a pipeline without each layer passing it on."""
    if device is None:
        yield
        return
    resolve_device(device)
    token = _DEFAULT_DEVICE.set(device)
    try:
        yield
    finally:
        _DEFAULT_DEVICE.reset(token)


def resolve_device(device: str | torch.device | None) -> torch.device:
    """The torch device of a setting: None is the block's default (:func:`default_device`, "cpu"
    outside one); "auto" is CUDA when available. Raises ValueError for another device type (mps,
    xpu, ...), for CUDA without a GPU and for a CUDA index beyond the GPUs there are."""
    if device is None:
        device = _DEFAULT_DEVICE.get()
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type not in ("cpu", "cuda"):  # torch names more (mps, xpu, meta, ...); the GPs run on these two
        raise ValueError(f"device {device!r} is not supported: expected cpu, cuda, cuda:N or auto")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but no CUDA device is available")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r} requested but there are {torch.cuda.device_count()} CUDA device(s)")
    return dev


def memory_budget(device: torch.device) -> float:
    """Bytes one factorisation may hold on ``device``: half the free GPU memory on CUDA, a third
    of the available RAM on a CPU (shared machines: other processes need the rest)."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return 0.5 * free
    return _available_ram() / 3.0


def _available_ram() -> float:
    """MemAvailable of /proc/meminfo (free + reclaimable cache), else free pages, else 8 GiB."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 8.0 * 2 ** 30


def exact_fits(n_rows: int, device: torch.device, n_matrices: int = 1) -> bool:
    """Whether ``n_matrices`` (N, N) float64 kernel matrices, with the factor and the workspace of
    their factorisation (3 matrices each), fit :func:`memory_budget` of ``device``."""
    return 3.0 * n_matrices * n_rows ** 2 * 8 <= memory_budget(device)


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
    jitter = 0.0
    for attempt in range(max_tries):
        jitter = 0.0 if attempt == 0 else base_jitter * (100.0 ** (attempt - 1))
        if jitter:
            # a jittered copy only when needed: no (N, N) identity beside a large K
            Kj = K.clone()
            Kj.diagonal(dim1=-2, dim2=-1).add_(jitter * scale)
        L, info = torch.linalg.cholesky_ex(Kj if jitter else K)
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
