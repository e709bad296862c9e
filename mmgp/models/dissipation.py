"""Friction dissipates: the learnt undisturbed model must not inject energy, and when it does,
the EM is run again from a start that obeys the physics (issue 29).

Reversing every joint velocity (q and ddq kept) leaves the rigid-body torque unchanged (its
velocity terms are quadratic in dq), so the part of the undisturbed model that is odd in dq,

    f_odd(q, dq, ddq) = (f(q, dq, ddq) - f(q, -dq, ddq)) / 2,

is its friction, and friction opposes the motion: f_odd_j * dq_j >= 0 on every joint. A model
whose odd part has the other sign where a joint slides says that friction pushes the joint along,
which happens when the EM has taken a push that opposed the motion for friction and called the
clean motion in that direction disturbed (a basin the labels then stay in).

:func:`energy_check` measures how much of a fitted model's friction injects energy;
:func:`fit_dissipative` runs the default start, checks it, and only where it injects energy runs
the EM again from labels swapped where it does, keeping the model that does not (the evidence of
every run is kept in the record).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..physics.context import smooth_sign_scale

# Restarts from swapped labels while the friction still injects energy (each is one more EM run).
MAX_RESTARTS = 2
# A sliding sample injects energy when its friction's sign is wrong by more than this many
# posterior standard deviations (one-sided: a dissipative model crosses it on ~2% of samples).
Z_INJECT = 2.0


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


def odd_part(gp, coef, X: np.ndarray, basis: np.ndarray | None, rev: VelocityReversal) -> tuple[np.ndarray, np.ndarray]:
    """The model's part odd in the joint velocities at inputs X (T, d) (and basis (T, n, p) when
    ``coef`` (n, p) is given) and its posterior standard deviation, both (T, n) in N*m. The
    deviation treats the two GP predictions as independent (it overstates the spread where
    they are correlated, so the check errs towards calling a model dissipative)."""
    mu_a, sd_a = gp.predict(X, include_noise=False)
    mu_b, sd_b = gp.predict(rev.flip(X), include_noise=False)
    T = len(X)
    odd = 0.5 * (np.asarray(mu_a).reshape(T, -1) - np.asarray(mu_b).reshape(T, -1))
    sd = 0.5 * np.sqrt(np.asarray(sd_a).reshape(T, -1) ** 2 + np.asarray(sd_b).reshape(T, -1) ** 2)
    if coef is not None:
        flipped = rev.flip_basis(basis)
        odd = odd + 0.5 * np.einsum("tjp,jp->tj", basis - flipped, coef)
    return odd, sd


def energy_check(sem, X: np.ndarray, basis: np.ndarray | None, rev: VelocityReversal) -> dict:
    """Per mode and joint, over the mode's undisturbed samples where the joint slides (|dq| above
    its smooth-sign scale): ``injected`` the share of them whose friction torque has the motion's
    sign by more than :data:`Z_INJECT` standard deviations, ``work_share`` the friction work
    done on the joint there divided by the total |work| (0: all dissipated, 1: all injected).
    ``worst`` the largest ``injected``; ``physical`` whether no joint of any mode exceeds twice
    the share a dissipative model shows by chance (~2.3%, doubled: the predictions are correlated)."""
    dq = X[:, list(rev.dq_cols)]
    sliding = np.abs(dq) > smooth_sign_scale(dq)
    labels, clean = sem.labels_, ~sem.disturbed_
    injected = np.zeros((len(sem.gps_), dq.shape[1]))
    work = np.zeros_like(injected)
    for k, gp in enumerate(sem.gps_):
        rows = np.flatnonzero((labels == k) & clean & sliding.any(1))
        if not len(rows):
            continue
        odd, sd = odd_part(gp, sem.coef_[k], X[rows], None if basis is None else basis[rows], rev)
        s = np.sign(dq[rows])
        for j in range(dq.shape[1]):
            on = sliding[rows, j]
            if not on.any():
                continue
            z = odd[on, j] * s[on, j] / np.maximum(sd[on, j], 1e-12)
            injected[k, j] = float(np.mean(z < -Z_INJECT))
            power = odd[on, j] * dq[rows[on], j]
            work[k, j] = float(np.clip(-power, 0, None).sum() / max(np.abs(power).sum(), 1e-300))
    worst = float(injected.max()) if injected.size else 0.0
    return {"injected": injected.round(4).tolist(), "work_share": work.round(4).tolist(), "worst": worst,
            "physical": worst <= 2 * _chance_share()}


def _chance_share() -> float:
    from scipy.stats import norm

    return float(norm.cdf(-Z_INJECT))


def injecting_samples(sem, X: np.ndarray, basis: np.ndarray | None, rev: VelocityReversal) -> np.ndarray:
    """(T,) bool: samples where some joint slides and the model of the sample's mode has friction
    there that injects energy by more than :data:`Z_INJECT` standard deviations."""
    dq = X[:, list(rev.dq_cols)]
    sliding = np.abs(dq) > smooth_sign_scale(dq)
    out = np.zeros(len(X), bool)
    for k, gp in enumerate(sem.gps_):
        rows = np.flatnonzero((sem.labels_ == k) & sliding.any(1))
        if not len(rows):
            continue
        odd, sd = odd_part(gp, sem.coef_[k], X[rows], None if basis is None else basis[rows], rev)
        z = odd * np.sign(dq[rows]) / np.maximum(sd, 1e-12)
        out[rows] = ((z < -Z_INJECT) & sliding[rows]).any(1)
    return out


def fit_dissipative(make_sem: Callable, X: np.ndarray, Y: np.ndarray, rev: VelocityReversal, *, first=None,
                    restarts: int = MAX_RESTARTS, **fit_kw):
    """Fit ``make_sem()`` (a MultimodalSEM; ``fit_kw`` its fit's keywords) from its own start, or
    take ``first`` already fitted. While the model's friction injects energy
    (:func:`energy_check`), at most ``restarts`` times: fit again from its labels with the
    disturbed and undisturbed labels swapped where its friction injects energy
    (:func:`injecting_samples`: where a push that opposed the motion was taken for friction, the
    clean motion was called disturbed). Returns the model with the highest log marginal
    likelihood among those that do not inject energy (among all of them where none qualifies)
    and a record of each fit (its check and log marginal likelihood) and the choice."""
    basis = fit_kw.get("basis")
    X = np.asarray(X, dtype=np.float64)
    if first is None:
        first = make_sem().fit(X, Y, **fit_kw)
    fits = [first]
    checks = [energy_check(first, X, basis, rev)]
    while (first.disturbance and len(first.trace_) and not checks[-1]["physical"]
           and len(fits) <= restarts):
        last = fits[-1]
        flip = injecting_samples(last, X, basis, rev)
        if not flip.any():
            break
        states = last.labels_ + last.n_modes * (last.disturbed_ ^ flip)
        fits.append(make_sem().fit(X, Y, init_states=states, **fit_kw))
        checks.append(energy_check(fits[-1], X, basis, rev))
    evidence = [float(m.log_marginal_) for m in fits]
    pool = [i for i, c in enumerate(checks) if c["physical"]] or list(range(len(fits)))
    best = max(pool, key=lambda i: evidence[i])
    record = {"fits": [{"log_marginal": e, **c} for e, c in zip(evidence, checks)], "chosen": best,
              "physical": checks[best]["physical"]}
    others = [evidence[i] for i in range(len(fits)) if i != best]
    if others:
        record["runner_up_gap"] = evidence[best] - max(others)
    return fits[best], record
