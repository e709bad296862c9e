"""Separating pushes from physics: which samples an external force disturbed.

Two detectors and how they combine:

* :func:`scan_disturbances`: a chi-square scan of the (low-passed) residual that the selected
  physics leaves, at a family-wise false-alarm level over the log's independent samples.
* :func:`em_separate`: the multimodal learner (``mmgp.labelling.sem.MultimodalSEM``, disturbance mode
  on), which explains the state-dependent part of the residual by a GP rather than by the effect
  library.
* :func:`gate_spans`: a scanned span is kept when the learner also flags some of it, or when the
  scan's statistic peaks far above its threshold (the learner's GP can absorb part of a long
  push).

:func:`valid_mask` says which equations carry information at all (a joint at rest is left out).
"""
from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ..data.statistics import mad_sd
from ..labelling.estep import runs_shorter_than, true_stretches

#: the ``separate`` setting of the Diagnoser: method name -> what it does (as reported)
SEPARATION_METHODS = {
    "auto": "robust chi-square scan, each span confirmed by MultimodalSEM (p_disturbed > 0.5 in it)",
    "scan": "robust chi-square scan",
    "em": "MultimodalSEM (p_disturbed > 0.5)",
    "none": "none",
}


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges [a, b) of the True stretches of ``mask`` (T,)."""
    return true_stretches(mask)


def spans_of(mask: np.ndarray, t: np.ndarray) -> list[tuple[float, float]]:
    """(start, end) times in s of the True stretches of ``mask``."""
    return [(float(t[a]), float(t[b - 1])) for a, b in runs(mask)]


def rest_runs(rest: np.ndarray, min_len: int) -> np.ndarray:
    """(T, n) bool: the runs of ``rest`` (T, n) along time lasting at least ``min_len`` samples;
    shorter runs are dropped."""
    kept = rest.copy()
    for j in range(rest.shape[1]):
        kept[runs_shorter_than(rest[:, j], min_len), j] = False
    return kept


def valid_mask(dq: np.ndarray, v_s: np.ndarray, t: np.ndarray, f_c: float | None, *, factor: float = 1.0,
               min_rest_periods: float = 0.1) -> np.ndarray:
    """(T, n) 1.0 where joint j's equation carries information a state function can fit, else 0.

    A joint whose velocity is within ``factor * v_s`` of zero (``v_s`` = 3 velocity-noise
    standard deviations) may be stuck: static friction then takes whatever value in
    [-tau_c, tau_c] balances the other torques, set-valued rather than a function of (q, dq, ddq).
    Those samples would otherwise be soaked up by look-alike effects (spring, armature, offset)
    or flagged as pushes. The mask is widened by the low-pass filter's memory (half a cutoff
    period each side), since filtering spreads those values over neighbouring samples.

    A joint that only passes through zero velocity (a reversal: a few milliseconds within the
    band) is not at rest: its friction follows the sliding law through the turn, and after the
    filter so short a stretch weighs little. With a filter, only stays of at least
    ``min_rest_periods`` cutoff periods (a tenth; 0: every stay, the push scans' mask) count as
    rest (``rest_runs``). Widening every reversal by the filter's memory would drop most of a
    fast excitation's equations, and with them the reversals that tell Coulomb friction from
    offsets and gravity.
    """
    T, n = dq.shape
    rest = np.abs(dq) < factor * np.asarray(v_s)[None, :]
    if f_c:
        dt = float(np.median(np.diff(t)))
        rest = rest_runs(rest, int(round(min_rest_periods / (f_c * dt))))
        h = int(round(0.5 / (f_c * dt)))
        if h > 0:
            from scipy.ndimage import maximum_filter1d

            rest = maximum_filter1d(rest.astype(np.uint8), size=2 * h + 1, axis=0) > 0
    M = (~rest).astype(np.float64)
    # a joint that is (almost) never moving keeps its samples: nothing would be left to fit
    few = M.sum(0) < 0.1 * T
    M[:, few] = 1.0
    return M


def _chi2_statistic(e: np.ndarray, V: np.ndarray, R: np.ndarray, band) -> tuple[np.ndarray, np.ndarray]:
    """Sum over valid joints ``V`` of the squared residual beyond ``band`` (:func:`beyond_band`,
    after the median of the equations ``R`` is taken off) in robust (MAD) noise units of ``R``,
    and the number of valid joints, per sample."""
    n = e.shape[1]
    med = np.array([np.median(e[R[:, j], j]) if R[:, j].any() else 0.0 for j in range(n)])
    s = np.array([mad_sd(e[R[:, j], j]) if R[:, j].any() else 1.0 for j in range(n)]) + 1e-300
    return (((beyond_band(e - med, band) / s) ** 2) * V).sum(1), V.sum(1)


def hold_interiors(M_scan: np.ndarray, t: np.ndarray, f_c: float | None) -> np.ndarray:
    """(T,) bool: the samples where the whole robot holds still, less a filter memory at each end.

    A hold is a stretch in which no joint's equation is scanned (``M_scan`` (T, n) 0: each joint
    at rest or within the filter's memory of rest); its first and last filter memory (half a
    cutoff period, past the memory ``M_scan`` already adds) still carry the low-passed motion
    around it. Inside, every joint is at rest or pushed: a stuck joint holds any torque within
    its friction band, so what a push shows there is the torque beyond the band
    (:func:`beyond_band`)."""
    still = ~(np.asarray(M_scan) > 0).any(1)
    h = int(round(0.5 / (f_c * float(np.median(np.diff(t)))))) if f_c and len(t) > 1 else 0
    inner = np.zeros(len(t), bool)
    for a, b in runs(still):
        inner[a + 2 * h:max(b - 2 * h, a + 2 * h)] = True
    return inner


def beyond_band(e: np.ndarray, band: np.ndarray) -> np.ndarray:
    """(T, n) the part of the residual ``e`` (T, n) beyond the friction band ``[-band, band]``
    (``band`` (T, n) or (n,) >= 0, N*m): zero inside it (a stuck joint can hold it)."""
    return np.sign(e) * np.maximum(np.abs(e) - band, 0.0)


def _drop_unresolved(mask: np.ndarray, t: np.ndarray, f_c: float) -> np.ndarray:
    """After a zero-phase low-pass at f_c any real event, however brief, stays above the noise
    band for at least the filter's resolution (~ half a cutoff period); a shorter excursion is a
    marginal crossing of heavy-tailed misfit, not a resolved push."""
    out = mask.copy()
    for a, b in runs(mask):
        if t[b - 1] - t[a] < 0.5 / f_c:
            out[a:b] = False
    return out


def scan_disturbances(e: np.ndarray, t: np.ndarray, *, f_c: float | None = None, alpha: float = 0.01,
                      valid: np.ndarray | None = None, reference: np.ndarray | None = None,
                      band: np.ndarray | float = 0.0) -> tuple[np.ndarray, dict]:
    """Flag samples where the (low-passed) residual ``e`` (T, n) N*m is too large to be noise.

    Each joint is scaled by a robust (MAD) noise level; the sum of squares over joints is
    chi-square(n) under "no push" (filtering makes the residual close to Gaussian). The threshold
    is the chi-square quantile at the Bonferroni level ``alpha / T_eff``, with ``T_eff`` the
    number of independent samples the filter leaves (``2 f_c`` per second). Flagged stretches are
    widened to where the statistic returns to its 99% noise band. ``valid`` (T, n) bool: joint
    equations to use; ``reference`` (T, n) bool: the equations the noise level is taken on
    (default ``valid``); ``band`` (T, n) N*m >= 0: a residual within it is no evidence (a stuck
    joint's friction band; :func:`beyond_band`). Returns the mask (T,) and {"threshold", "peaks"
    (per span, in units of the threshold), "effective_samples", "spans" (s)}.
    """
    from scipy.stats import chi2

    T, n = e.shape
    V = np.ones((T, n), bool) if valid is None else np.asarray(valid, bool)
    R = V if reference is None else np.asarray(reference, bool)
    z2, df = _chi2_statistic(e, V, R, band)
    dur = float(t[-1] - t[0]) if T > 1 else 1.0
    T_eff = max(1.0, min(T, 2.0 * f_c * dur)) if f_c else float(T)
    thr_df = np.array([chi2.ppf(1 - alpha / T_eff, d) if d > 0 else np.inf for d in range(n + 1)])
    thr = float(thr_df[n])
    core = z2 > thr_df[df]
    z2 = z2 * thr / thr_df[np.maximum(df, 1)]  # on the full-df scale for the widening and peaks
    if f_c:
        # within a cutoff period of the ends the zero-phase filter runs on padding, not data
        core &= ~((t - t[0] < 1.0 / f_c) | (t[-1] - t < 1.0 / f_c))
    mask = core.copy()
    if core.any():
        for a, b in runs(z2 > chi2.ppf(0.99, n)):
            if core[a:b].any():
                mask[a:b] = True
        if f_c:
            mask = _drop_unresolved(mask, t, f_c)
    peaks = [float(z2[a:b].max() / thr) for a, b in runs(mask)]
    return mask, {"threshold": thr, "peaks": peaks, "effective_samples": T_eff, "spans": spans_of(mask, t)}


def em_separate(resid: np.ndarray, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, t: np.ndarray, *,
                n_modes: int = 1, max_points: int = 500, seed: int = 0, **sem_kw) -> dict:
    """The multimodal learner's separation: ``MultimodalSEM`` (disturbance mode on) on the
    nominal residual ``resid = tau - tau_rbd`` (T, n), N*m, with GP inputs
    ``[q, dq, ddq, tanh(dq / v_s)]`` (v_s as in training, :func:`mmgp.physics.context.smooth_sign_scale`: without
    the smooth sign a GP cannot follow the friction jump at velocity reversals and would take it
    for pushes), on at most ``max_points`` samples evenly spaced in time (``t`` in s is passed, so
    likelihoods leave a window out and a long push is not explained by itself; where the whole
    robot stands still, the whole hold: a push that holds the arm still is one observation,
    :func:`mmgp.labelling.mstep.hold_windows`).

    Returns {"p_disturbed": (T,) posterior push probability interpolated in time to every sample,
    "mode": (T,) int mode labels (nearest subsample), "sigma_d": (n,), "n_modes", "n_points",
    "seconds", "n_sweeps"}. ``sem_kw`` overrides MultimodalSEM settings.
    """
    from ..physics.context import rest_weight, resting, smooth_sign_scale
    from ..labelling.features import StateFeatures
    from ..labelling.sem import MultimodalSEM

    T, n = resid.shape
    idx = np.unique(np.linspace(0, T - 1, min(T, max_points)).round().astype(int))
    vs = smooth_sign_scale(dq)
    # the friction input without the fade at rest: the learner has no band for a stuck joint
    X = StateFeatures("none", friction_scale=vs, sign_fades=False)(q[idx], dq[idx], ddq[idx], resid[idx]).X
    still = resting(rest_weight(dq[idx], vs)).all(1)
    # a small learner: hyperparameter refits are >60% of its cost, and the labels settle in a few
    # sweeps (about 10 s on a 7-DOF log on one core). Otherwise training's inference (its trimmed
    # start, push-size floor, abstention and shortest push), since the robust fit of the effect
    # library starts from its flags: a lighter learner without them flagged most of a push-free
    # log as pushed, and on a pushed log the load-dependent friction was then missed.
    # No shortest mode: diagnosis judges each mode by its own held-out gain. Its sweep budget stops
    # it before convergence by design: its labels are its last sweeps' average, not a budget's
    # best sweep (benchmarks/README.md, "an EM that cycles ends at its best sweep").
    kw = dict(max_support=min(250, len(idx)), fit_points=min(200, len(idx)), fit_iter=15, max_sweeps=8,
              min_sweeps=4, average_last=3, final_support=min(250, len(idx)), estep="mpm", min_mode_s=0.0,
              unconverged="average")
    kw.update(sem_kw)
    t0 = time.perf_counter()
    sem = MultimodalSEM(n_modes=n_modes, disturbance=True, seed=seed, **kw).fit(X, resid[idx], t=t[idx], still=still)
    p = np.interp(t, t[idx], sem.p_disturbed_)
    near = np.clip(np.searchsorted(t[idx], t), 0, len(idx) - 1)
    return {"p_disturbed": p, "mode": sem.labels_[near].astype(int), "sigma_d": np.asarray(sem.sigma_d_),
            "n_modes": n_modes, "n_points": int(len(idx)), "seconds": time.perf_counter() - t0,
            "n_sweeps": int(sem.n_sweeps_)}


def em_summary(em: dict) -> dict:
    """What the separation reports about a learner run."""
    return {"em_points": em["n_points"], "em_seconds": float(em["seconds"]),
            "em_sweeps": em["n_sweeps"], "em_flagged_fraction": float((em["p_disturbed"] > 0.5).mean()),
            "em_sigma_d": [float(x) for x in em["sigma_d"]], "em_modes": em["n_modes"]}


def gate_spans(scan: np.ndarray, p_disturbed: np.ndarray, peaks: Sequence[float] | None = None,
               strong: float = np.inf) -> tuple[np.ndarray, dict]:
    """The scan's flags ``scan`` (T,) bool, gated by the learner's ``p_disturbed`` (T,).

    A scanned span stays if its scan statistic peaks at ``strong`` times the threshold or more
    (``peaks``: one per span of ``scan``, in units of the threshold), or if the learner also
    calls some of it disturbed (p > 0.5). Strong spans need no confirmation: the learner's GP can
    absorb part of a long push and miss it (benchmark: a 1.2 s push at 15x the threshold).
    Returns the gated mask and {"spans_dropped_by_em"}.
    """
    em = np.asarray(p_disturbed) > 0.5
    out = scan.copy()
    dropped = 0
    spans = runs(scan)
    pk = np.zeros(len(spans)) if peaks is None else np.asarray(peaks, dtype=np.float64)
    for (a, b), peak in zip(spans, pk):
        if peak < strong and not em[a:b].any():
            out[a:b] = False
            dropped += 1
    return out, {"spans_dropped_by_em": dropped}
