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
