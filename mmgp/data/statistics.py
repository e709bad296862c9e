"""Robust statistics shared by the package: the scale every robust rule measures residuals in."""
from __future__ import annotations

import numpy as np

#: median absolute deviation -> standard deviation at the normal
MAD_TO_SD = 1.4826


def mad_sd(x: np.ndarray, axis: int | None = 0, centre: bool = True) -> np.ndarray:
    """Robust standard deviation of ``x`` along ``axis``: 1.4826 x the median absolute deviation
    about the median (``centre``) or about zero; in ``x``'s units, the normal's sd for normal data."""
    x = np.asarray(x)
    med = np.median(x, axis=axis, keepdims=True) if centre else 0.0
    return MAD_TO_SD * np.median(np.abs(x - med), axis=axis)


def difference_noise_sd(x: np.ndarray, robust: bool = True) -> np.ndarray:
    """White-noise standard deviation of each column of ``x`` (T, n) (or (T,)), in ``x``'s units,
    from its second differences: a smooth signal's are ~0, white noise's have variance 6 sigma^2.
    ``robust``: their MAD (turning points and brief events do not count); else their RMS, for
    quantised signals whose second differences are mostly exactly 0 (an encoder at rest that
    ticks now and then: the MAD would say 0)."""
    x = np.asarray(x, dtype=np.float64)
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    s = mad_sd(d2) if robust else np.sqrt(np.mean(d2 ** 2, axis=0))
    return s / np.sqrt(6.0)
