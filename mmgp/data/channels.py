"""What a logged torque channel can resolve.

A drive that reports its torque from the motor current may report exactly zero below a
threshold (a dead band): a real arm's joints may read exactly 0.0 N*m on most samples and a few
tenths of a N*m otherwise. A model of such a channel learns
the zeros almost exactly, so every non-zero reading stands tens of standard deviations off; the
user is told rather than left to read those as pushes or effects.
"""
from __future__ import annotations

import numpy as np

#: A channel is called dead-banded when one exact reading covers at least this share of samples.
DEAD_BAND_SHARE = 0.5


def modal_reading(x: np.ndarray) -> tuple[float, float, int]:
    """The most frequent exact value of ``x`` (T,), the share of samples holding it, and how many
    distinct values ``x`` has."""
    values, counts = np.unique(x, return_counts=True)
    i = int(counts.argmax())
    return float(values[i]), float(counts[i] / len(x)), len(values)


def dead_banded(tau: np.ndarray) -> np.ndarray:
    """(n,) bool: the joints of ``tau`` (T, n) whose most frequent exact reading covers at least
    :data:`DEAD_BAND_SHARE` of the samples while other readings exist (a dead band or a stuck
    channel; a constant channel is not one)."""
    out = np.zeros(tau.shape[1], bool)
    for j in range(tau.shape[1]):
        _, share, distinct = modal_reading(tau[:, j])
        out[j] = share >= DEAD_BAND_SHARE and distinct >= 2
    return out


def dead_band_warnings(tau: np.ndarray, names: list) -> list[str]:
    """One warning per joint of ``tau`` (T, n) whose most frequent exact reading covers at least
    :data:`DEAD_BAND_SHARE` of the samples while other readings exist (a constant channel is not
    warned about here); ``names`` (n,) the joint names."""
    out = []
    for j in np.flatnonzero(dead_banded(tau)):
        value, share, _ = modal_reading(tau[:, j])
        v = value + 0.0                              # + 0.0: a channel stuck at -0.0 reads "0"
        off = np.abs(tau[tau[:, j] != value, j] - v)
        out.append(f"{names[j]}: the torque reads exactly {v:.6g} on {100 * share:.0f}% of the samples (its other "
                   f"readings lie {off.min():.3g} to {off.max():.3g} away, median {np.median(off):.3g}): a dead "
                   "band or a stuck channel; what is smaller than that on this joint cannot be seen, and its "
                   "readings do not vote on pushes in train's labels")
    return out
