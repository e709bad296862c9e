"""Friction dissipates: the learnt undisturbed model must not inject energy, and when it does,
the EM is run again from a start that obeys the physics.

Reversing every joint velocity (q and ddq kept) leaves the rigid-body torque unchanged (its
velocity terms are quadratic in dq), so the part of the undisturbed model that is odd in dq,

    f_odd(q, dq, ddq) = (f(q, dq, ddq) - f(q, -dq, ddq)) / 2,

is its friction, and friction opposes the motion: f_odd_j * dq_j >= 0 on every joint. A model
whose odd part has the other sign where a joint slides says that friction pushes the joint along,
which happens when the EM has taken a push that opposed the motion for friction and called the
clean motion in that direction disturbed (a basin the labels then stay in).

:func:`energy_check` measures how much of a fitted model's friction injects energy;
:func:`fit_dissipative` runs the EM from its start (and from the other start where the two
differ: :data:`mmgp.labelling.mstep.START_NAMES`), checks each fit, and only where none dissipates runs
the EM again from labels swapped where it injects energy, keeping the dissipative model with the
highest evidence (the evidence of every run is kept in the record).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..physics.context import smooth_sign_scale
from ..progress import report
from ..gp.exact import ExactGP
from .mstep import START_NAMES, evenly_spaced

# Restarts from swapped labels while the friction still injects energy (each is one more EM run).
MAX_RESTARTS = 2
# Sliding samples per mode the check looks at (evenly spaced), and the support of the GP its
# variances come from (:func:`_variance_gp`): the check then costs seconds on 20,000 samples.
CHECK_POINTS = 4000
VARIANCE_SUPPORT = 1000
# A sliding sample injects energy when its friction's sign is wrong by more than this many
# predictive standard deviations (one-sided: a dissipative model crosses it on ~2.3% of samples).
Z_INJECT = 2.0
# Family-wise level of the check: a model is called injecting when, on some mode and joint, its
# friction stays deeper in the wrong sign than a dissipative model's would at this level
# (:func:`depth_p_value`, Bonferroni over the modes and joints judged).
ALPHA = 0.05


@dataclass
class VelocityReversal:
    """How to reverse the joint velocities in a model's inputs: ``dq_cols`` (n,) the columns of X
    holding dq (their values also decide where a joint slides), ``flip_cols`` every column of X
    that changes sign with dq (dq and its smooth sign), ``odd_basis`` the number of trailing basis
    columns that change sign with dq (dry-friction columns; the rigid-body regressor's are even)."""

    dq_cols: Sequence[int]
    flip_cols: Sequence[int]
    odd_basis: int = 0

    def flip(self, X: np.ndarray) -> np.ndarray:
        out = np.array(X, dtype=np.float64, copy=True)
        out[:, list(self.flip_cols)] *= -1.0
        return out

    def flip_basis(self, basis: np.ndarray | None) -> np.ndarray | None:
        if basis is None or not self.odd_basis:
            return basis
        out = np.array(basis, dtype=np.float64, copy=True)
        out[..., -self.odd_basis:] *= -1.0
        return out


def odd_part(gp, coef, X: np.ndarray, basis: np.ndarray | None, rev: VelocityReversal) -> np.ndarray:
    """The model's part odd in the joint velocities (T, n) in N*m at inputs X (T, d) (and basis
    (T, n, p) when ``coef`` (n, p) is given): two mean predictions, no variances (those of a GP on
    a whole mode's samples cost O(T * support^2))."""
    T = len(X)
    mu_a = np.asarray(gp.predict(X, return_std=False)).reshape(T, -1)
    mu_b = np.asarray(gp.predict(rev.flip(X), return_std=False)).reshape(T, -1)
    odd = 0.5 * (mu_a - mu_b)
    if coef is not None:
        odd = odd + 0.5 * np.einsum("tjp,jp->tj", basis - rev.flip_basis(basis), coef)
    return odd


def _variance_gp(sem, k: int):
    """The GP whose latent variance bounds mode ``k``'s: the mode's own where its support is at
    most :data:`VARIANCE_SUPPORT` samples, else an exact GP with the same hyperparameters on that
    many of them, evenly spaced (conditioned on fewer samples, its variance is at least the
    full GP's, so the check errs towards calling a model dissipative; the full GP's costs
    O(samples * support^2))."""
    gp = sem.gps_[k]
    Xs, Ys = sem.support_X_[k], sem.support_Y_[k]
    if isinstance(gp, ExactGP) and len(Xs) <= VARIANCE_SUPPORT:
        return gp
    sub = evenly_spaced(np.arange(len(Xs)), VARIANCE_SUPPORT)
    small = ExactGP(ard=gp.ard, independent_outputs=True, seed=0, device=str(gp.dev_), hyper=gp.hyper_, optimise=False)
    return small.fit(Xs[sub], Ys[sub])


def _odd_z(sem, k: int, rows: np.ndarray, X: np.ndarray, basis, rev: VelocityReversal, dq: np.ndarray,
           with_noise: bool = True):
    """(odd part (M, n), its z-score with the motion's sign (M, n)) of mode ``k`` at samples
    ``rows``. The spread is that of the mean of the two predictions (taken as independent) plus,
    ``with_noise``, the mode's noise variance: the GP's noise term holds what the model cannot
    explain, model error included, and the latent variance alone (from a support of 1,000
    samples) ignores that error: on frictionless arms it called a model with no friction
    injecting (benchmarks/README.md, "The friction check on frictionless arms")."""
    Xr = X[rows]
    odd = odd_part(sem.gps_[k], sem.coef_[k], Xr, None if basis is None else basis[rows], rev)
    var_gp = _variance_gp(sem, k)
    M = len(rows)
    _, sd_a = var_gp.predict(Xr, include_noise=False)
    _, sd_an = var_gp.predict(Xr, include_noise=True)
    _, sd_b = var_gp.predict(rev.flip(Xr), include_noise=False)
    sd_a, sd_an, sd_b = (np.asarray(v).reshape(M, -1) for v in (sd_a, sd_an, sd_b))
    noise_var = np.maximum(sd_an ** 2 - sd_a ** 2, 0.0) if with_noise else 0.0
    sd = np.sqrt(0.25 * (sd_a ** 2 + sd_b ** 2) + noise_var)
    return odd, odd * np.sign(dq[rows]) / np.maximum(sd, 1e-12)


def energy_check(sem, X: np.ndarray, basis: np.ndarray | None, rev: VelocityReversal,
                 max_points: int = CHECK_POINTS) -> dict:
    """Per mode and joint, over the mode's undisturbed samples where the joint slides (|dq| above
    its smooth-sign scale; at most ``max_points`` of them, evenly spaced): ``injected`` the share
    whose friction torque has the motion's sign by more than :data:`Z_INJECT` standard
    deviations, ``n_eff`` the effective number of independent samples behind that share (the
    odd part is a smooth function along the trajectory, so its crossings come in runs),
    ``work_share`` the friction work done on the joint there divided by the total |work| (0: all
    dissipated, 1: all injected), ``p_depth`` the probability that a dissipative model's friction
    stays as deep in the wrong sign (:func:`depth_p_value`). ``worst`` the largest ``injected``
    (what the report shows); ``p_value`` the smallest ``p_depth``, Bonferroni-corrected over the
    modes and joints judged; ``physical``: ``p_value`` >= :data:`ALPHA`."""
    dq, sliding = _sliding(X, rev)
    labels, clean = sem.labels_, ~sem.disturbed_
    injected = np.zeros((len(sem.gps_), dq.shape[1]))
    work, n_eff = np.zeros_like(injected), np.zeros_like(injected)
    p_depth = np.ones_like(injected)
    for k in range(len(sem.gps_)):
        rows = evenly_spaced(np.flatnonzero((labels == k) & clean & sliding.any(1)), max_points)
        if not len(rows):
            continue
        odd, z = _odd_z(sem, k, rows, X, basis, rev, dq)
        for j in range(dq.shape[1]):
            on = sliding[rows, j]
            if not on.any():
                continue
            injected[k, j] = float(np.mean(z[on, j] < -Z_INJECT))
            n_eff[k, j] = effective_sample_size(z[on, j])
            p_depth[k, j] = depth_p_value(z[on, j], n_eff[k, j])
            power = odd[on, j] * dq[rows[on], j]
            work[k, j] = float(np.clip(-power, 0, None).sum() / max(np.abs(power).sum(), 1e-300))
    judged = max(int((n_eff > 0).sum()), 1)          # every judged (mode, joint) has n_eff >= 1
    p = float(min(1.0, p_depth.min() * judged))
    return {"injected": injected.round(4).tolist(), "n_eff": n_eff.round(1).tolist(), "p_depth": p_depth.tolist(),
            "work_share": work.round(4).tolist(), "worst": float(injected.max()) if injected.size else 0.0,
            "p_value": p, "physical": p >= ALPHA}


def effective_sample_size(x: np.ndarray) -> float:
    """Effective number of independent samples in the series ``x`` (M,): M / (1 + 2 sum of its
    autocorrelations), the sum truncated where consecutive pairs of autocorrelations stop being
    positive (Geyer's initial positive sequence). An AR(1) series with coefficient rho gives
    M (1 - rho) / (1 + rho) for large M; a constant series (no information on its correlation)
    counts as one sample."""
    x = np.asarray(x, dtype=np.float64)
    M = len(x)
    if M < 2:
        return float(M)
    x = x - x.mean()
    energy = float(x @ x)
    if energy <= 1e-300:
        return 1.0
    f = np.fft.rfft(x, 2 * M)
    rho = np.fft.irfft(f * np.conj(f))[:M] / energy
    pairs = rho[: 2 * (M // 2)].reshape(-1, 2).sum(1)
    stop = np.flatnonzero(pairs <= 0)
    tau = 2.0 * pairs[: stop[0] if len(stop) else len(pairs)].sum() - 1.0
    return float(np.clip(M / max(tau, 1.0), 1.0, M))


def depth_p_value(z: np.ndarray, n_eff: float) -> float:
    """How likely a dissipative model's odd part stays as deep in the wrong sign as ``z`` (M,)
    does, ``z`` the z-scores with the motion's sign along the trajectory (time order), each at
    least N(0, 1) under dissipation, ``n_eff`` their effective number of independent samples.

    The depth is the lowest median of ``z`` over a window of W = max(3, M / n_eff) consecutive
    samples (one effective sample's worth, and at least three: a lone glitch at a log's edge,
    where the velocity is poorly estimated, is not evidence of friction). A window's median is
    at least N(0, 1) under dissipation (correlated samples: a spread of at most one), and the
    sliding windows hold about 2 M / W independent ones, so the deepest is that deep with
    probability 1 - (1 - Phi(depth))^(2 M / W)."""
    from numpy.lib.stride_tricks import sliding_window_view
    from scipy.stats import norm

    z = np.asarray(z, dtype=np.float64)
    M = len(z)
    if M == 0 or n_eff <= 0:
        return 1.0
    W = int(min(M, max(3, np.ceil(M / n_eff))))
    depth = float(np.median(sliding_window_view(z, W), axis=1).min())
    windows = max(1.0, 2.0 * M / W)
    return float(-np.expm1(windows * norm.logsf(depth)))


def _sliding(X: np.ndarray, rev: VelocityReversal) -> tuple[np.ndarray, np.ndarray]:
    """The joint velocities (T, n) of inputs X and where each joint slides (|dq| above its
    smooth-sign scale), (T, n) bool."""
    dq = X[:, list(rev.dq_cols)]
    return dq, np.abs(dq) > smooth_sign_scale(dq)


def injecting_samples(sem, X: np.ndarray, basis: np.ndarray | None, rev: VelocityReversal) -> np.ndarray:
    """(T,) bool: samples where some joint slides and the model of the sample's mode has friction
    there that injects energy by more than :data:`Z_INJECT` latent standard deviations (without
    the noise term: the refit's start takes every sample whose friction the model holds to have
    the wrong sign, while the verdict, :func:`energy_check`, asks whether that is beyond what the
    model cannot explain)."""
    dq, sliding = _sliding(X, rev)
    out = np.zeros(len(X), bool)
    for k in range(len(sem.gps_)):
        rows = np.flatnonzero((sem.labels_ == k) & sliding.any(1))
        if len(rows):
            _, z = _odd_z(sem, k, rows, X, basis, rev, dq, with_noise=False)
            out[rows] = ((z < -Z_INJECT) & sliding[rows]).any(1)
    return out


def fit_dissipative(make_sem: Callable, X: np.ndarray, Y: np.ndarray, rev: VelocityReversal, *, first=None,
                    restarts: int = MAX_RESTARTS, **fit_kw):
    """Fit ``make_sem()`` (a MultimodalSEM; ``fit_kw`` its fit's keywords) from its own start, or
    take ``first`` already fitted, and, where the other start of
    :data:`mmgp.labelling.mstep.START_NAMES` begins from other labels, from that one too.
    While no fit's friction dissipates (:func:`energy_check`), at most ``restarts`` times: fit
    again from the last fit's labels with the disturbed and undisturbed labels swapped where its
    friction injects energy (:func:`injecting_samples`: where a push that opposed the motion was
    taken for friction, the clean motion was called disturbed). Returns the model with the
    highest log marginal likelihood among those that do not inject energy (where none qualifies,
    the one whose check's p-value is largest) and a record of each fit (its start, check and log
    marginal likelihood), the choice, the runner-up's gap in log evidence and
    ``other_start_same_labels`` (None: no other start; True: its labels were the first's, not run)."""
    basis = fit_kw.get("basis")
    X = np.asarray(X, dtype=np.float64)
    if first is None:
        first = make_sem().fit(X, Y, **fit_kw)
    fits, same_start = [first], None
    swept = first.settings.disturbance and len(first.trace_)      # labels learnt by sweeps (else nothing to redo)
    if swept and first.other_start_ and first.start_ in START_NAMES:
        other = make_sem().begin(X, Y, start=next(n for n in START_NAMES if n != first.start_), **fit_kw)
        same_start = bool(np.array_equal(other.states, first.start_states_))
        if not same_start:     # the same start labels: the same sweeps, up to the start's warm start
            report(f"EM again from the {other.name} start: the labels may settle elsewhere; the evidence decides")
            fits.append(make_sem().fit(X, Y, start=other, **fit_kw))
    report("friction check: does the learnt friction dissipate?")
    checks = [energy_check(fit, X, basis, rev) for fit in fits]
    n_starts = len(fits)
    while swept and not any(c["physical"] for c in checks) and len(fits) < n_starts + restarts:
        last = fits[-1]
        flip = injecting_samples(last, X, basis, rev)
        if not flip.any():
            break
        states = last.labels_ + last.n_modes * (last.disturbed_ ^ flip)
        report(f"friction check: refit {len(fits) - n_starts + 1} of at most {restarts}, labels swapped where "
               "friction injects energy")
        fits.append(make_sem().fit(X, Y, init_states=states, **fit_kw))
        checks.append(energy_check(fits[-1], X, basis, rev))
    evidence = [float(m.log_marginal_) for m in fits]
    pool = [i for i, c in enumerate(checks) if c["physical"]] or [int(np.argmax([c["p_value"] for c in checks]))]
    best = max(pool, key=lambda i: evidence[i])
    record = {"fits": [{"start": m.start_ or "swapped labels", "log_marginal": e, **c}
                       for m, e, c in zip(fits, evidence, checks)], "chosen": best,
              "physical": checks[best]["physical"], "other_start_same_labels": same_start}
    others = [evidence[i] for i in range(len(fits)) if i != best]
    if others:
        record["runner_up_gap"] = evidence[best] - max(others)
    return fits[best], record
