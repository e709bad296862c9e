"""Zero-phase low-pass filtering matched to a trajectory's bandwidth.

Filtering a torque residual and every regressor column with the same linear filter keeps a
linear-in-parameters relation intact while removing the wide-band noise that differentiated
accelerations and torque sensors add (noise in the regressors would bias a least-squares fit).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

#: family-wise level at which a bin of the velocity's periodogram counts as rising above its
#: white-noise floor (the fallback of :func:`lowpass_for`)
SIGNAL_ALPHA = 0.01


def identity(a: np.ndarray) -> np.ndarray:
    """The filter that leaves its input unchanged (no low-pass applies)."""
    return a


def _band_edge(P: np.ndarray, f: np.ndarray, power: float) -> float:
    """The frequency (Hz) below which ``power`` of the summed per-joint power ``P`` (F, n) lies,
    every joint counting alike (the highest frequency when ``P`` holds nothing)."""
    P = (P / np.maximum(P.sum(0), 1e-300)).sum(1)
    cum = np.cumsum(P) / max(P.sum(), 1e-300)
    return float(f[min(np.searchsorted(cum, power), len(f) - 1)])


def lowpass_for(t: np.ndarray, dq: np.ndarray, *, power: float = 0.999,
                factor: float = 2.0) -> tuple[Callable[[np.ndarray], np.ndarray], float | None]:
    """Zero-phase Butterworth low-pass matched to the motion.

    ``t`` (T,) s, ``dq`` (T, n) rad/s. The cutoff is ``factor`` times the frequency below which
    ``power`` of the velocity's *signal* power lies (the white-noise floor, the median power of
    the top half of the band, is subtracted first), capped below Nyquist. Where that puts the
    cutoff at the rate's limit, the signal power is taken again from the bins alone that rise
    above what white noise reaches over the band (level :data:`SIGNAL_ALPHA`).
    Returns (filter acting on axis 0 of any (T, ...) array, cutoff in Hz or None when no
    filtering applies: a cutoff at >= 0.4 times the sample rate, or fewer than 60 samples).
    """
    from scipy.signal import butter, sosfiltfilt

    T = len(t)
    dt = float(np.median(np.diff(t)))
    fs = 1.0 / dt
    x = dq - dq.mean(0)
    # a Hann taper: without it the jump between the log's ends leaks a 1/f^2 tail over the band
    x = x * np.hanning(T)[:, None]
    P = np.abs(np.fft.rfft(x, axis=0)) ** 2
    f = np.fft.rfftfreq(T, dt)
    floor = np.median(P[f > 0.25 * fs], axis=0) if (f > 0.25 * fs).sum() > 5 else np.zeros(P.shape[1])
    f_c = factor * max(_band_edge(np.clip(P - floor, 0, None), f, power), 2.0 / (T * dt))
    if f_c >= 0.4 * fs:
        # the clipped excess of white noise (half its power, spread to Nyquist) can outweigh a
        # motion near the velocity's noise (an arm holding a pose, moved only by pushes): then only
        # the bins above what noise reaches over the band are taken for motion (a white-noise bin's
        # power is exponential, its mean the median / ln 2)
        reach = floor / np.log(2.0) * np.log(len(f) / SIGNAL_ALPHA)
        f_c = factor * max(_band_edge(np.where(P > reach, P - floor, 0.0), f, power), 2.0 / (T * dt))
    if f_c >= 0.4 * fs or T < 60:
        return identity, None
    sos = butter(4, f_c / (0.5 * fs), output="sos")
    # long even (mirror) padding of two cutoff periods: odd padding would pin the ends to a single
    # noisy sample; any padding is linear, so residual and columns stay consistent
    pad = int(min(T - 1, round(2.0 * fs / f_c)))
    return (lambda a: sosfiltfilt(sos, a, axis=0, padtype="even", padlen=pad)), f_c
