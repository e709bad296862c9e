"""A push is a sustained offset: the residual scan that pools evidence over a push's duration.

The disturbance state of the chain judges each sample alone against a wide zero-mean spread
(at least ``push_floor_z`` predictive standard deviations), so a light push that holds the
torque 1-3 standard deviations off for half a second is never favoured sample by sample,
however long it lasts. Averaged over ``w`` samples, the standardised residual of
such a push stands 1-3 x sqrt(w) of the average's own spread off, while model error averages
out. The average's spread is measured, not assumed (robustly, on the samples the labels call
undisturbed), so residuals that are correlated in time do not pass for pushes.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.stats import norm

from ..data.statistics import mad_sd

# Residuals are clipped at this many standard deviations before averaging: the scan looks for
# many moderate deviations in a row; a few large ones (a friction reversal's blip, which the
# shortest-push rule unflags) are the chain's to judge, and must not make a 0.2 s "push".
CLIP_Z = 3.0


def masked_moving_average(z: np.ndarray, ok: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred running mean over ``window`` samples of ``z`` (T, n) using only samples with ``ok``
    (T,) or (T, n) True; returns the means (T, n) (0 where no sample counts) and the fraction of
    each window that counted ((T,) or (T, n), as ``ok``). Samples outside the array count as absent."""
    ok2 = ok[:, None] if ok.ndim == 1 else ok
    num = uniform_filter1d(np.where(ok2, z, 0.0), window, axis=0, mode="constant")
    frac = uniform_filter1d(ok.astype(np.float64), window, axis=0, mode="constant")
    frac2 = frac[:, None] if ok.ndim == 1 else frac
    mean = np.where(frac2 > 0, num / np.maximum(frac2, 1e-12), 0.0)
    return mean, frac


def sustained_offset_scan(z: np.ndarray, ok: np.ndarray, window: int, z_max: float,
                          starts: Sequence[int] = (0,)) -> tuple[np.ndarray, np.ndarray]:
    """Samples whose running-mean residual stands more than ``z_max`` robust standard deviations
    off on some joint.

    z (T, n): residuals standardised by each sample's predictive standard deviation; ok (T,) or
    (T, n): samples the labels call undisturbed, per joint where some joint's samples do not
    count (only these are averaged, scaled and flagged); window:
    samples averaged (centred); starts: first sample of each log (windows stay inside a log).
    Residuals are clipped at +-``CLIP_Z`` first. The running mean counts where at least half its
    window is ``ok``; its centre and spread per joint are the median and the robust standard
    deviation (:func:`mmgp.data.statistics.mad_sd`) over windows that are wholly ``ok``. Returns (flags (T,) bool, the largest joint's scaled deviation (T,))."""
    T, n = z.shape
    ok = np.broadcast_to(ok[:, None] if ok.ndim == 1 else ok, (T, n))
    z = np.clip(z, -CLIP_Z, CLIP_Z)
    window = max(int(window), 1)
    avg = np.zeros_like(z)
    frac = np.zeros((T, n))
    bounds = sorted(set(int(s) for s in starts) | {0}) + [T]
    for a, b in zip(bounds[:-1], bounds[1:]):
        avg[a:b], frac[a:b] = masked_moving_average(z[a:b], ok[a:b], window)
    ref = ok & (frac > 1.0 - 1e-9)
    dev = np.zeros((T, n))
    for j in range(n):
        if ref[:, j].sum() < 10 * window:
            continue        # too few reference windows on this joint: it cannot be judged
        centre = np.median(avg[ref[:, j], j])
        spread = mad_sd(avg[ref[:, j], j])
        dev[:, j] = np.where(ok[:, j] & (frac[:, j] >= 0.5), np.abs(avg[:, j] - centre) / max(spread, 1e-12), 0.0)
    stat = dev.max(1)
    return stat > z_max, stat


def scan_probability(stat: np.ndarray, n_tests: float) -> np.ndarray:
    """p(disturbed) of a scanned sample from its statistic (T,): one minus the chance that one of
    ``n_tests`` independent Gaussian windows-and-joints strays that far (Bonferroni), at least 0."""
    return np.clip(1.0 - n_tests * 2.0 * norm.sf(stat), 0.0, 1.0)
