"""What a recording makes the robot do: reference trajectories and random push schedules.

Every ``reference(t)`` returned here maps a time (s) to ``(q, dq, ddq)``, each (n,) in rad, rad/s,
rad/s^2, as :func:`mmgp.sim.simulate` expects. Random draws come from the ``rng`` passed in, in a
fixed order, so a recording depends only on its seed.
"""
from __future__ import annotations

import numpy as np


def push_schedule(rng, t_end: float, *, gap: tuple, dur: tuple, first: tuple) -> list[tuple[float, float]]:
    """(t0, duration) in s of pushes separated by random gaps, all ending before ``t_end``.

    The first starts at U(*first), durations are U(*dur), gaps U(*gap)."""
    out = []
    t = rng.uniform(*first)
    while True:
        d = rng.uniform(*dur)
        if t + d > t_end:
            break
        out.append((t, d))
        t += d + rng.uniform(*gap)
    return out


def sines_reference(centre, a, w, ph, amp, max_speed):
    """``reference(t)`` of per-joint sums of sines ``a sin(w t + ph)`` around ``centre`` (n,).

    ``a``, ``w`` (rad/s), ``ph`` (rad) are (n, h); the weights ``a`` are rescaled to peak
    ``|q - centre| = amp`` (n,) and then shrunk where the peak speed would exceed ``max_speed``."""
    a = a * (amp / a.sum(axis=1))[:, None]
    a = a * np.minimum(1.0, max_speed / (a * w).sum(axis=1))[:, None]

    def reference(t):
        arg = w * t + ph
        return (centre + (a * np.sin(arg)).sum(1), (a * w * np.cos(arg)).sum(1),
                -(a * w * w * np.sin(arg)).sum(1))

    return reference


def sinusoid_reference(rng, lower, upper, *, n_harm: int = 4, f_range=(0.04, 0.25), max_speed=0.8,
                       fill=0.7):
    """Sum of ``n_harm`` sinusoids per joint of frequencies U(*f_range) Hz, centred in the limits
    ``lower``, ``upper`` (n,), with peak |q - centre| <= fill * half-range (capped at 1.2 rad) and
    peak speed <= max_speed. Returns ``reference(t)``."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    n = lower.size
    w = 2 * np.pi * rng.uniform(*f_range, size=(n, n_harm))
    a = rng.uniform(0.3, 1.0, size=(n, n_harm))
    ph = rng.uniform(0, 2 * np.pi, size=(n, n_harm))
    return sines_reference(0.5 * (lower + upper), a, w, ph, np.minimum(fill * 0.5 * (upper - lower), 1.2),
                           max_speed)


def fourier_reference(rng, lower, upper, period: float, *, n_harm: int = 3, fill: float = 0.3,
                      max_amp: float = 0.9, max_speed: float = 0.7, decay: float = 1.0):
    """Periodic exciting trajectory (base period ``period`` s, repeats exactly): harmonics
    k = 1..n_harm per joint with weights U(0.3, 1) / k^decay and random phases, centred in the
    limits, peak |q - centre| = min(fill * range, max_amp), peak speed <= max_speed.
    Returns ``reference(t)`` -> (q, dq, ddq)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    n = lower.size
    k = np.arange(1, n_harm + 1)
    w = 2 * np.pi * k / period
    a = rng.uniform(0.3, 1.0, (n, n_harm)) / k ** decay
    ph = rng.uniform(0, 2 * np.pi, (n, n_harm))
    return sines_reference(0.5 * (lower + upper), a, w, ph, np.minimum(fill * (upper - lower), max_amp), max_speed)
