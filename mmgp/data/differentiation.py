"""Differentiation and resampling of logged signals.

Velocities and accelerations are estimated from positions with local polynomial (Savitzky-Golay)
fits, evaluated on the actual, possibly jittered, time stamps: the sample rate sets the window,
so a log at 20 Hz and a log at 1 kHz both get a window of about the same duration in seconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

from ..errors import InputError
from .logs import RobotLog


@dataclass(frozen=True)
class SavitzkyGolay:
    """Savitzky-Golay differentiator.

    ``window_s``: window length in seconds (None: ``max(5 samples, 0.05 s)``, odd, capped so it
    fits the log); ``order``: polynomial order (3 keeps accelerations unbiased at turning points).
    ``cv``: with ``window_s`` None, choose each column's window by leave-one-out cross-validation
    of the smoother on the signal being differentiated (see :func:`loo_window`), between the
    default above and ``max_window_s``.
    Non-uniform time stamps are resampled to the median step, differentiated, and interpolated back.
    """

    window_s: float | None = None
    order: int = 3
    cv: bool = False
    max_window_s: float = 0.5

    def window_samples(self, dt: float, T: int) -> int:
        w_s = self.window_s if self.window_s is not None else max(5 * dt, 0.05)
        w = int(round(w_s / dt))
        w = max(w, self.order + 2)
        w = min(w, T if T % 2 == 1 else T - 1)
        if w % 2 == 0:
            w += 1
        if w > T:
            w -= 2
        return w

    def _uniform(self, t: np.ndarray, x: np.ndarray):
        """(uniform times, x on them, step, whether t was uniform already)."""
        dt = float(np.median(np.diff(t)))
        if np.allclose(np.diff(t), dt, rtol=1e-3, atol=1e-9):
            return t, x, dt, True
        tu = t[0] + dt * np.arange(int(np.floor((t[-1] - t[0]) / dt)) + 1)
        return tu, np.stack([np.interp(tu, t, x[:, j]) for j in range(x.shape[1])], axis=1), dt, False

    def _windows(self, xu: np.ndarray, dt: float) -> list[int]:
        w = self.window_samples(dt, xu.shape[0])
        if w <= self.order:
            raise InputError(f"too few samples ({xu.shape[0]}) to differentiate with a polynomial of order {self.order}")
        if not (self.cv and self.window_s is None):
            return [w] * xu.shape[1]
        w_max = max(w, SavitzkyGolay(self.max_window_s, self.order).window_samples(dt, xu.shape[0]))
        return [loo_window(xu[:, j], self.order, w, w_max) for j in range(xu.shape[1])]

    def windows(self, t: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(n,) window length in samples (odd) used on each column of ``x`` (T, n) sampled at
        ``t``: derivatives within half a window of either end come from the edge fit, extrapolated."""
        _, xu, dt, _ = self._uniform(np.asarray(t, dtype=np.float64), np.asarray(x, dtype=np.float64))
        return np.array(self._windows(xu, dt))

    def __call__(self, t: np.ndarray, x: np.ndarray, deriv: int) -> np.ndarray:
        """Derivative ``deriv`` (1 or 2) of ``x`` (T, n) sampled at ``t`` (T,); same shape."""
        return self.derivatives(t, x, (deriv,))[0]

    def derivatives(self, t: np.ndarray, x: np.ndarray, derivs=(1, 2)) -> list[np.ndarray]:
        """Derivatives ``derivs`` (each 1 or 2) of ``x`` (T, n) sampled at ``t`` (T,), each (T, n).
        The windows depend on ``x`` alone, so they are chosen once for all of them."""
        t = np.asarray(t, dtype=np.float64)
        x = np.asarray(x, dtype=np.float64)
        tu, xu, dt, uniform = self._uniform(t, x)
        windows = self._windows(xu, dt)
        out = []
        for deriv in derivs:
            if len(set(windows)) == 1 and not (self.cv and self.window_s is None):
                d = savgol_filter(xu, windows[0], self.order, deriv=deriv, delta=dt, axis=0, mode="interp")
            else:
                d = np.stack([savgol_filter(xu[:, j], wj, self.order, deriv=deriv, delta=dt, mode="interp")
                              for j, wj in enumerate(windows)], axis=1)
            out.append(d if uniform else np.stack([np.interp(t, tu, d[:, j]) for j in range(x.shape[1])], axis=1))
        return out


def loo_window(x: np.ndarray, order: int, w_min: int, w_max: int, n_candidates: int = 12) -> int:
    """Odd window in [w_min, w_max] samples minimising the leave-one-out squared error of the
    order-``order`` Savitzky-Golay smoother of ``x`` (T,).

    The smoother is linear with centre weight c0, so the LOO residual is (x - x_hat) / (1 - c0)
    exactly (interior samples; the same interior is scored for every candidate). Noise sets the
    window: a noisy logged velocity gets a long one, a fine encoder position a short one, which a
    rate-based rule cannot know (a 7-DOF log at 100 Hz: 0.05 s windows gave accelerations noisy
    enough to hide 1 N*m pushes).
    """
    T = len(x)
    w_min = max(order + 2 + (order % 2 == 0), w_min | 1)
    w_max = min(w_max | 1, (T // 3) | 1)
    if w_max <= w_min:
        return w_min
    cands = np.unique((np.geomspace(w_min, w_max, n_candidates).round().astype(int)) | 1)
    cands = cands[(cands >= w_min) & (cands <= w_max)]
    edge = int(cands.max()) // 2
    best, best_score = int(cands[0]), np.inf
    for w in cands:
        c0 = savgol_coeffs(int(w), order)[int(w) // 2]
        r = (x - savgol_filter(x, int(w), order, mode="interp")) / (1.0 - c0)
        score = float(np.mean(r[edge:T - edge] ** 2))
        if score < best_score:
            best, best_score = int(w), score
    return best


def complete_derivatives(log: RobotLog, differentiator: SavitzkyGolay | None = None) -> RobotLog:
    """Fill in ``dq``/``ddq`` when the log lacks them. ``ddq`` comes from ``q`` directly
    (one smoothing pass), not from a differentiated ``dq``, unless only ``dq`` was logged."""
    diff = differentiator or SavitzkyGolay()
    dq, ddq = log.dq, log.ddq
    dq_est = ddq_est = False
    if dq is None and ddq is None and hasattr(diff, "derivatives"):
        dq, ddq = diff.derivatives(log.t, log.q, (1, 2))  # one window search for both
        dq_est = ddq_est = True
    if dq is None:
        dq = diff(log.t, log.q, 1)
        dq_est = True
    if ddq is None:
        ddq = diff(log.t, log.q, 2) if dq_est else diff(log.t, dq, 1)
        ddq_est = True
    return log.replace(dq=dq, ddq=ddq, dq_estimated=log.dq_estimated or dq_est,
                       ddq_estimated=log.ddq_estimated or ddq_est)


def downsample(log: RobotLog, rate_hz: float) -> RobotLog:
    """Keep about ``rate_hz`` samples per second by picking the sample nearest each new tick.

    Picking (rather than averaging) keeps every kept row a real measurement; derivatives should
    be completed *before* downsampling so they benefit from the full rate.
    """
    if rate_hz <= 0:
        raise InputError(f"target rate must be positive, got {rate_hz}")
    t = log.t
    ticks = np.arange(t[0], t[-1] + 1e-12, 1.0 / rate_hz)
    right = np.clip(np.searchsorted(t, ticks), 0, len(t) - 1)
    left = np.clip(right - 1, 0, len(t) - 1)
    nearest = np.where(np.abs(t[left] - ticks) <= np.abs(t[right] - ticks), left, right)
    return log.subset(np.unique(nearest))


