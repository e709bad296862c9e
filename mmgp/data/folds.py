"""Splits of a log into contiguous time blocks: neighbouring samples are near-copies of each
other, so every held-out figure and cross-validated objective in mmgp splits by time."""
from __future__ import annotations

import numpy as np

from .differentiation import SavitzkyGolay


def time_block_folds(T: int, n_folds: int = 5, gap: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Contiguous time blocks as (train_idx, test_idx) pairs.

    Neighbouring samples are nearly identical, so random splits leak; ``gap`` samples on each
    side of the test block are dropped from training to stop leakage through the smoother window.
    """
    if n_folds < 2 or n_folds > T:
        raise ValueError(f"n_folds must be in [2, {T}]")
    edges = np.linspace(0, T, n_folds + 1).round().astype(int)
    folds = []
    for k in range(n_folds):
        lo, hi = edges[k], edges[k + 1]
        test = np.arange(lo, hi)
        keep = np.ones(T, bool)
        keep[max(0, lo - gap):min(T, hi + gap)] = False
        folds.append((np.flatnonzero(keep), test))
    return folds


def default_gap(t: np.ndarray, window_s: float | None = None) -> int:
    """Samples to keep out of training on each side of a test block for a log sampled at ``t`` (T,) s
    whose derivatives were estimated with Savitzky-Golay windows of at most ``window_s`` seconds
    (None: the differentiator's default window, what ``mmgp compare`` estimates with).

    Two samples whose derivative estimates share no raw sample are at least one window apart
    (each estimate reads half a window on each side).
    """
    t = np.asarray(t, dtype=np.float64)
    dt = float(np.median(np.diff(t)))
    return int(SavitzkyGolay(window_s=window_s).window_samples(dt, len(t)))


def decorrelation_time(t: np.ndarray, X: np.ndarray) -> float:
    """Correlation time (s) of a sampled trajectory: the shortest lag at which the
    autocorrelation of X (T, d) at increasing times ``t`` (T,) s, columns standardised, averaged
    over columns and over the unbroken stretches of the log (a gap longer than twice the median
    period ends one), falls below 1/e; at most half the longest stretch. Constant columns are
    left out; 0.0 when no column varies.

    For x(t) = sin(w t) the autocorrelation is cos(w h), so the time is arccos(1/e) / w."""
    t, X = np.asarray(t, dtype=np.float64), np.asarray(X, dtype=np.float64).reshape(len(t), -1)
    sd = X.std(0)
    varied = sd > 1e-12 * (np.abs(X.mean(0)) + 1)
    if not varied.any() or len(t) < 3:
        return 0.0
    Z = (X[:, varied] - X[:, varied].mean(0)) / sd[varied]
    dt = float(np.median(np.diff(t)))
    pieces = np.split(np.arange(len(t)), np.flatnonzero(np.diff(t) > 2.0 * dt) + 1)
    longest = max(len(p) for p in pieces)
    num, pairs = np.zeros(longest), np.zeros(longest)
    for p in pieces:
        n = len(p)
        f = np.fft.rfft(Z[p], 2 * n, axis=0)              # zero-padded: no wrap-around
        num[:n] += np.fft.irfft(f * f.conj(), 2 * n, axis=0)[:n].sum(1)
        pairs[:n] += (n - np.arange(n)) * Z.shape[1]
    rho = num[:longest // 2 + 1] / pairs[:longest // 2 + 1]
    below = np.flatnonzero(rho < np.exp(-1.0))
    return float((below[0] if len(below) else longest // 2) * dt)


def spread_subset(idx: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``k`` of the time-ordered sample indices ``idx``, evenly spaced with a random
    offset. Random picks put near-copies side by side, and their shared noise makes a
    leave-one-out objective take noise for signal; evenly spaced picks keep them apart."""
    if len(idx) <= k:
        return idx
    step = len(idx) / k
    pos = np.floor(rng.uniform(0, step) + step * np.arange(k)).astype(int)
    return idx[np.minimum(pos, len(idx) - 1)]


def time_blocks(ts: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Partition sorted times into consecutive blocks spanning at most ``length`` seconds:
    member indices (n_blocks, B) padded with 0, and a validity mask (n_blocks, B)."""
    starts = [0]
    for i in range(1, len(ts)):
        if ts[i] - ts[starts[-1]] > length:
            starts.append(i)
    bounds = starts + [len(ts)]
    B = max(b - a for a, b in zip(bounds[:-1], bounds[1:]))
    idx = np.zeros((len(starts), B), int)
    valid = np.zeros((len(starts), B), bool)
    for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        idx[k, :b - a] = np.arange(a, b)
        valid[k, :b - a] = True
    return idx, valid


# Windows (s) longer than these fractions of the shortest log leave too little of it outside
# the window: an exclusion window as long as the log leaves every sample's likelihood to the
# prior alone, and every sample looks disturbed.
# The shortest push and mode shrink with the others, in proportion to their defaults (0.15 s and
# 4 s beside the 1 s exclusion window): a 24-sample push in a 0.04 s log is a push of that log.
WINDOW_FRACTIONS = {"exclusion_s": 0.2, "block_s": 0.4, "mode_smoothing_s": 0.8, "min_push_s": 0.03,
                    "min_mode_s": 0.8, "push_scan_s": 0.04}


def windows_for_duration(duration_s: float, **windows: float) -> dict:
    """The time windows (keyword: seconds, keys of ``WINDOW_FRACTIONS``) capped at their
    fraction of ``duration_s``, the shortest log's duration: only those that change are returned."""
    out = {}
    for key, value in windows.items():
        cap = WINDOW_FRACTIONS[key] * float(duration_s)
        if value > cap:
            out[key] = cap
    return out
