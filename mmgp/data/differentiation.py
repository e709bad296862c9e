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
    rate-based rule cannot know.
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


#: a logged velocity is judged for delay where, at its best lag, it follows the position's
#: derivative this closely (correlation): below, it is mostly noise or not a derivative at all
#: (``mmgp.physics.plausibility.velocity_warnings`` tells those)
DELAY_MIN_CORRELATION = 0.9
#: the longest delay looked for (s); contiguous blocks the delay is estimated on, each alone
DELAY_MAX_S = 0.5
DELAY_BLOCKS = 10
#: family-wise level of "delayed by more than one sample" over a log's joints
DELAY_ALPHA = 0.05


def _peak_lag(a: np.ndarray, b: np.ndarray, L: int) -> tuple[float, float]:
    """(lag, correlation) of the largest Pearson correlation of ``b[t + k]`` with ``a[t]`` over
    their overlap, for k within +-L samples; the lag refined between samples by a parabola
    through the peak."""
    a, b = a - a.mean(), b - b.mean()
    N, m = len(a), 2 * len(a)
    cc = np.fft.irfft(np.conj(np.fft.rfft(a, m)) * np.fft.rfft(b, m), m)   # sum_t a[t] b[t + k]
    lags = np.arange(-L, L + 1)
    sxy = np.r_[cc[-L:], cc[:L + 1]]
    A1, A2, B1, B2 = (np.r_[0.0, np.cumsum(x)] for x in (a, a * a, b, b * b))
    k, cnt = np.abs(lags), N - np.abs(lags)
    # the overlap: a[0:N-k] with b[k:N] for k >= 0, a[k:N] with b[0:N-k] for k < 0
    lo_a, lo_b = np.where(lags >= 0, 0, k), np.where(lags >= 0, k, 0)
    sx, sxx = A1[lo_a + cnt] - A1[lo_a], A2[lo_a + cnt] - A2[lo_a]
    sy, syy = B1[lo_b + cnt] - B1[lo_b], B2[lo_b + cnt] - B2[lo_b]
    cov, vx, vy = sxy / cnt - sx * sy / cnt ** 2, sxx / cnt - (sx / cnt) ** 2, syy / cnt - (sy / cnt) ** 2
    ok = (vx > 0) & (vy > 0)
    if not ok.any():
        return 0.0, 0.0
    c = np.where(ok, cov / np.sqrt(np.where(ok, vx * vy, 1.0)), -np.inf)
    i = int(np.argmax(c))
    if 0 < i < 2 * L and np.isfinite(c[i - 1]) and np.isfinite(c[i + 1]):
        den = c[i - 1] - 2 * c[i] + c[i + 1]
        return float(lags[i] + (0.5 * (c[i - 1] - c[i + 1]) / den if den < 0 else 0.0)), float(c[i])
    return float(lags[i]), float(c[i])


def position_difference(t: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, int]:
    """(central difference of ``q`` (T, n) over about 20 ms, (T - 2h, n) aligned with samples
    h..T-h-1; h): the position's derivative a logged velocity is checked against."""
    dt = float(np.median(np.diff(t)))
    h = max(1, int(round(0.01 / max(dt, 1e-12))))
    return (q[2 * h:] - q[:-2 * h]) / (t[2 * h:] - t[:-2 * h])[:, None], h


def _block_lags(t: np.ndarray, q: np.ndarray, dq: np.ndarray) -> list[np.ndarray]:
    """Per column of ``dq``, the lags (samples) of its largest cross-correlation with the
    position's derivative on each of :data:`DELAY_BLOCKS` contiguous blocks where it follows it
    closely (:data:`DELAY_MIN_CORRELATION`); empty arrays where the blocks are too short."""
    fd, h = position_difference(t, q)
    v = dq[h:len(dq) - h]
    dt = float(np.median(np.diff(t)))
    edges = np.linspace(0, len(fd), DELAY_BLOCKS + 1).astype(int)
    L = min(int(round(DELAY_MAX_S / max(dt, 1e-12))), int(np.diff(edges).min()) // 4)
    if L < 2:
        return [np.zeros(0)] * q.shape[1]
    out = []
    for j in range(q.shape[1]):
        peaks = [_peak_lag(fd[a:b, j], v[a:b, j], L) for a, b in zip(edges[:-1], edges[1:])]
        out.append(np.array([lag for lag, c in peaks if c >= DELAY_MIN_CORRELATION]))
    return out


def velocity_delay(t: np.ndarray, q: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How many samples each column of a logged velocity ``dq`` (T, n) lags the derivative of the
    logged position ``q`` (T, n) (:func:`position_difference`): (delay (n,), its standard error
    (n,)), the mean and standard error of the lag of their largest cross-correlation (within
    :data:`DELAY_MAX_S`) over :data:`DELAY_BLOCKS` contiguous blocks. Blocks where the velocity
    does not follow the position's derivative closely (:data:`DELAY_MIN_CORRELATION`) do not
    count; a column with fewer than 3 such blocks gets delay 0 and an infinite standard error
    (not judged).

    A velocity that is the position's derivative at the same instant peaks at lag 0 (a backward
    difference half a sample later); one from a causal filter of the drive (a velocity estimate
    smoothed for its controller) peaks later by its phase delay."""
    lags = _block_lags(t, q, dq)
    judged = [len(x) >= 3 for x in lags]
    delay = np.array([x.mean() if ok else 0.0 for x, ok in zip(lags, judged)])
    se = np.array([x.std(ddof=1) / np.sqrt(len(x)) if ok else np.inf for x, ok in zip(lags, judged)])
    return delay, se


def delayed_joints(t: np.ndarray, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """(n,) delay in samples of each joint whose logged velocity lags its position by more than
    one sample at the one-sided level :data:`DELAY_ALPHA` over the joints (Student's t on the
    blocks' lags, with as many degrees of freedom as blocks counted less one), else 0. One
    sample, because a backward difference already lags half of one."""
    from scipy.stats import t as student

    level = 1.0 - DELAY_ALPHA / max(q.shape[1], 1)
    out = np.zeros(q.shape[1])
    for j, x in enumerate(_block_lags(t, q, dq)):
        if len(x) >= 3 and x.mean() - student.ppf(level, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x)) > 1.0:
            out[j] = x.mean()
    return out


def undelay_velocities(log: RobotLog, differentiator: SavitzkyGolay | None = None) -> RobotLog:
    """``log`` with each logged velocity that lags its position by more than one sample
    (:func:`delayed_joints`) replaced by the position's derivative, and its acceleration by the
    position's second derivative; the delays (s) of the joints replaced in
    ``metadata["velocity_delay_s"]`` (absent when none is). A delayed velocity is not the joint's
    velocity at the sample's instant: friction would oppose the motion of 0.1 s before (its sign
    late at every reversal) and a joint already stopped would read as sliding."""
    if log.dq is None or log.dq_estimated or log.n_samples < 20:
        return log
    delay = delayed_joints(log.t, log.q, log.dq)
    late = delay > 0
    if not late.any():
        return log
    diff = differentiator or SavitzkyGolay()
    v, a = (diff.derivatives(log.t, log.q, (1, 2)) if hasattr(diff, "derivatives")
            else (diff(log.t, log.q, 1), diff(log.t, log.q, 2)))
    dq, ddq = log.dq.copy(), (diff(log.t, log.dq, 1) if log.ddq is None else log.ddq.copy())
    dq[:, late], ddq[:, late] = v[:, late], a[:, late]
    dt = float(np.median(np.diff(log.t)))
    names = log.joint_names or [f"joint {k}" for k in range(log.n_joints)]
    meta = dict(log.metadata, velocity_delay_s={names[k]: float(delay[k] * dt) for k in np.flatnonzero(late)})
    return log.replace(dq=dq, ddq=ddq, metadata=meta, dq_estimated=True, ddq_estimated=True)


def complete_derivatives(log: RobotLog, differentiator: SavitzkyGolay | None = None) -> RobotLog:
    """Fill in ``dq``/``ddq`` when the log lacks them, and replace logged velocities that lag
    their position (:func:`undelay_velocities`). ``ddq`` comes from ``q`` directly (one smoothing
    pass), not from a differentiated ``dq``, unless only ``dq`` was logged."""
    diff = differentiator or SavitzkyGolay()
    log = undelay_velocities(log, diff)
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


