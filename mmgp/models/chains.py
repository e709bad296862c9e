"""Prototypes for seed-independent labels (issue 10), built around MultimodalSEM without changing it.

- :class:`RobustStartSEM`: the chain starts from an iteratively trimmed GP (hyperparameters and
  first labels from the samples the windowed GP explains best) instead of one GP on everything.
- :class:`ChainSet`: several chains, combined by selection on a criterion or by posterior
  averaging; reports how much the chains agreed.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .sem import MultimodalSEM


def _z_max(Y, mean, var) -> np.ndarray:
    """Largest absolute z-score over joints, (T,)."""
    return (np.abs(Y - mean) / np.sqrt(var)).max(1)


class RobustStartSEM(MultimodalSEM):
    """MultimodalSEM whose start is an iteratively trimmed fit.

    ``trim``: fractions of the samples kept in successive refits (smallest out-of-window z-score
    first); the last fit gives the first hyperparameters, and samples whose z-score, rescaled so
    the kept samples have unit mean square, exceeds ``start_cut`` start disturbed."""

    def __init__(self, n_modes: int = 1, *, trim=(0.8, 0.6), start_cut: float = 3.0, **kw):
        super().__init__(n_modes, **kw)
        self.trim = trim
        self.start_cut = start_cut

    def _initial_states(self, X, Y, rng) -> np.ndarray:
        states = super()._initial_states(X, Y, rng) if self.n_modes > 1 else np.zeros(len(Y), int)
        T = len(Y)
        mean, var, gp, _, _ = self._mode_likelihoods(X, Y, np.arange(T), None, True, rng)
        keep = np.arange(T)
        for frac in self.trim:
            z = _z_max(Y, mean, var)
            keep = np.sort(np.argsort(z, kind="stable")[: int(math.ceil(frac * T))])
            mean, var, gp, _, _ = self._mode_likelihoods(X, Y, keep, gp.hyper_, True, rng)
        self._init_hyper = gp.hyper_
        if self.disturbance:
            z = _z_max(Y, mean, var)
            scale = math.sqrt(max(float(np.mean(z[keep] ** 2)), 1e-12))
            dist = z / scale > self.start_cut
            states = (states % self.n_modes) + self.n_modes * dist
        return states


class ChainSet:
    """Several SEM chains on the same data, combined.

    ``n_chains`` chains of ``chain_class`` with seeds ``seed * 1000 + i``; ``combine``:
    "select" keeps the chain with the best ``criterion``, "average" averages the posteriors of
    all chains (mode columns matched to the first chain by overlap). ``criterion``:
    "log_marginal" (mean log p(Y) of the averaging sweeps). Learned: the chosen/averaged
    ``p_disturbed_``, ``disturbed_``, ``labels_``, ``p_mode_``, ``chains_``, ``scores_``,
    ``agreement_`` (smallest pairwise fraction of samples with the same disturbed label)."""

    def __init__(self, n_modes: int = 1, *, n_chains: int = 4, combine: str = "select",
                 criterion: str = "log_marginal", chain_class=MultimodalSEM, seed: int = 0, **kw):
        self.n_modes = n_modes
        self.n_chains = n_chains
        self.combine = combine
        self.criterion = criterion
        self.chain_class = chain_class
        self.seed = seed
        self.kw = kw

    def _score(self, sem, Y) -> float:
        if self.criterion == "log_marginal":
            tail = sem.trace_[-max(1, sem.average_last):]
            return float(np.mean([r.log_marginal for r in tail]))
        return robust_predictive_score(sem, Y)

    def fit(self, X, Y, **fit_kw) -> "ChainSet":
        t0 = time.perf_counter()
        self.chains_ = [self.chain_class(n_modes=self.n_modes, seed=self.seed * 1000 + i, **self.kw).fit(X, Y, **fit_kw)
                        for i in range(self.n_chains)]
        Y2 = np.asarray(Y, dtype=np.float64).reshape(len(Y), -1)
        self.scores_ = [self._score(c, Y2) for c in self.chains_]
        self.all_scores_ = {"log_marginal": [float(np.mean([r.log_marginal for r in c.trace_[-max(1, c.average_last):]]))
                                             for c in self.chains_],
                            "robust_pred": [robust_predictive_score(c, Y2) for c in self.chains_]}
        d = np.array([c.disturbed_ for c in self.chains_])
        self.agreement_ = float(min((d[i] == d[j]).mean() for i in range(len(d)) for j in range(i + 1, len(d)))) \
            if len(d) > 1 else 1.0
        if self.combine == "select":
            best = self.chains_[int(np.argmax(self.scores_))]
            self.p_disturbed_, self.p_mode_ = best.p_disturbed_, best.p_mode_
        else:
            self.p_disturbed_ = np.mean([c.p_disturbed_ for c in self.chains_], axis=0)
            self.p_mode_ = np.mean([_matched(self.chains_[0].p_mode_, c.p_mode_) for c in self.chains_], axis=0)
        self.disturbed_ = self.p_disturbed_ > 0.5
        self.labels_ = self.p_mode_.argmax(1)
        self.converged_ = all(c.converged_ for c in self.chains_)
        self.n_sweeps_ = int(sum(c.n_sweeps_ for c in self.chains_))
        self.log_marginal_ = max(self.scores_)
        self.seconds_ = time.perf_counter() - t0
        return self


def robust_predictive_score(sem, Y, eps: float = 0.3) -> float:
    """How well a chain's nominal model predicts every sample out of window, with a common
    robust tail: sum_t log[(1 - eps) N(y_t; mu_t, v_t) + eps B(y_t)], B a broad Gaussian around
    the data (4 x its per-joint spread), the same for every chain. mu_t, v_t: the last sweep's
    prediction of the sample's own mode. Unlike the chain's log marginal, a chain gains nothing by
    calling samples disturbed (the tail is fixed), only by predicting the rest tightly."""
    ls = sem.last_sweep_
    K = len(ls["means"])
    mode_of = ls["states"] % K
    T = len(Y)
    mu = np.stack(ls["means"])[mode_of, np.arange(T)]
    var = np.stack(ls["vars"])[mode_of, np.arange(T)]
    log2pi = math.log(2 * math.pi)
    ll_model = (-0.5 * (log2pi + np.log(var) + (Y - mu) ** 2 / var)).sum(1)
    c = np.median(Y, 0)
    wide = (4.0 * Y.std(0) + 1e-12) ** 2
    ll_tail = (-0.5 * (log2pi + np.log(wide) + (Y - c) ** 2 / wide)).sum(1)
    return float(np.logaddexp(math.log(1 - eps) + ll_model, math.log(eps) + ll_tail).sum())


def _matched(ref: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Columns of ``p`` (T, K) permuted to overlap ``ref`` (T, K) best (brute force over K!)."""
    from itertools import permutations

    K = ref.shape[1]
    best = max(permutations(range(K)), key=lambda perm: float((ref * p[:, list(perm)]).sum()))
    return p[:, list(best)]


# ----------------------------------------------------------------------------------------------
# Benchmark hooks (benchmarks/bench_labels.py)
# ----------------------------------------------------------------------------------------------

def bench_methods(modes_auto: bool = False) -> dict:
    """Named methods for benchmarks/bench_labels.py: callables (case, prepared, seed) -> Outcome."""
    import sys

    bench = sys.modules.get("bench_labels") or sys.modules["__main__"]

    def make(factory):
        def run(case, prep, seed):
            cfg = bench.MmgpMethod().config(seed)
            kw = bench.sem_settings(cfg, prep.basis_kind)
            f = prep.feats
            t0 = time.perf_counter()
            m = factory(case.n_modes, kw).fit(f.X, f.Y, t=f.t, starts=f.starts, basis=f.basis)
            info = {"agreement": getattr(m, "agreement_", 1.0), "log_marginal": float(m.log_marginal_)}
            if hasattr(m, "chains_"):
                info["chains"] = {"scores": m.all_scores_, "quality": [
                    bench.score(case, bench.Outcome(c.disturbed_, None, c.labels_, 0.0)) for c in m.chains_]}
            return bench.Outcome(m.disturbed_.astype(bool), m.p_disturbed_, m.labels_, time.perf_counter() - t0, info)

        run.seeded = True
        return run

    return {
        "robust": make(lambda K, kw: RobustStartSEM(K, **kw)),
        "det": make(lambda K, kw: DeterministicSEM(K, **kw)),
        "band": make(lambda K, kw: FrictionBandSEM(K, **kw)),
        "physband": make(lambda K, kw: PhysicsBandSEM(K, **kw)),
        "prior": make(lambda K, kw: PriorSEM(K, **kw)),
        "prior50": make(lambda K, kw: StrongPriorSEM(K, **kw)),
        "prior50band": make(lambda K, kw: StrongPriorBandSEM(K, **kw)),
        "priorband": make(lambda K, kw: PriorBandSEM(K, **kw)),
        "prior_robust": make(lambda K, kw: PriorRobustSEM(K, **kw)),
        "prior_chains4": make(lambda K, kw: ChainSet(K, n_chains=4, criterion="robust_pred", chain_class=PriorSEM, **kw)),
        "prior_robust_chains4": make(lambda K, kw: ChainSet(K, n_chains=4, criterion="robust_pred",
                                                          chain_class=PriorRobustSEM, **kw)),
        "band_keep": make(lambda K, kw: FrictionBandSEM(K, exclude_rest=False, **kw)),
        "det_plain": make(lambda K, kw: DeterministicSEM(K, trim=(), start_cut=4.0, **kw)),
        "chains4": make(lambda K, kw: ChainSet(K, n_chains=4, **kw)),
        "chains6rp": make(lambda K, kw: ChainSet(K, n_chains=6, criterion="robust_pred", **kw)),
        "prb": make(lambda K, kw: StrongPriorRobustBandSEM(K, **kw)),
        "prb_chains6": make(lambda K, kw: ChainSet(K, n_chains=6, criterion="robust_pred",
                                                 chain_class=StrongPriorRobustBandSEM, **kw)),
        "pr_chains6": make(lambda K, kw: ChainSet(K, n_chains=6, criterion="robust_pred", chain_class=PriorRobustSEM, **kw)),
        "chains4avg": make(lambda K, kw: ChainSet(K, n_chains=4, combine="average", **kw)),
        "robust_chains4": make(lambda K, kw: ChainSet(K, n_chains=4, chain_class=RobustStartSEM, **kw)),
    }


# ----------------------------------------------------------------------------------------------
# Deterministic E-step (prototype: MultimodalSEM's sampler swapped for a decoder)
# ----------------------------------------------------------------------------------------------

def smoothed_marginals(alpha: np.ndarray, A: np.ndarray, starts=(0,)) -> np.ndarray:
    """p(s_t | y_1:T) (T, S) from filtered ``alpha`` (T, S) alone, by the backward recursion
    p(s_t | y) = sum_s' p(s_t | s_{t+1} = s', y_1:t) p(s_{t+1} = s' | y)."""
    T, S = alpha.shape
    is_start = np.zeros(T + 1, bool)
    is_start[list(starts)] = True
    is_start[T] = True
    post = np.empty((T, S))
    for t in range(T - 1, -1, -1):
        if is_start[t + 1]:
            post[t] = alpha[t]
            continue
        joint = alpha[t][:, None] * A                      # (s_t, s_{t+1}) up to a column constant
        cond = joint / np.maximum(joint.sum(0, keepdims=True), 1e-300)
        post[t] = cond @ post[t + 1]
    return post / post.sum(1, keepdims=True)


def mpm_decode(alpha, A, rng, starts=(0,)) -> np.ndarray:
    """Drop-in for ``ffbs_sample``: the most probable state of each sample (no randomness)."""
    return smoothed_marginals(alpha, A, starts).argmax(1)


class DeterministicSEM(RobustStartSEM):
    """RobustStartSEM with hard EM: every sweep's labels are the posterior's most probable states,
    so the chain's answer depends on the seed only through support subsets of long logs."""

    def fit(self, X, Y, **kw):
        from . import sem as sem_module

        sampler = sem_module.ffbs_sample
        sem_module.ffbs_sample = mpm_decode
        try:
            return super().fit(X, Y, **kw)
        finally:
            sem_module.ffbs_sample = sampler


# ----------------------------------------------------------------------------------------------
# Friction band (prototype): at rest the friction torque can be anywhere between its branches
# ----------------------------------------------------------------------------------------------

class FrictionBandSEM(RobustStartSEM):
    """Samples whose sliding direction is uncertain (|dq| within ``band`` velocity scales of 0)
    are scored against the band between the GP's friction branches, and kept out of the GPs'
    supports (their torque is set-valued: stuck anywhere in the dry-friction band).

    Needs the inputs laid out as mmgp.models.features builds them: [q, dq, ddq, tanh(dq / v_s)]
    (n columns each). The smooth sign of a velocity known to +-``band`` v_s lies in
    [tanh(dq / v_s - band), tanh(dq / v_s + band)]; the emission uses the GP mean at ``band_grid``
    values of it and projects the torque onto their range (profile likelihood over the sign)."""

    def __init__(self, n_modes: int = 1, *, band: float = 2.0, band_grid: int = 5, exclude_rest: bool = True,
                 trim=(), start_cut: float = 4.0, **kw):
        super().__init__(n_modes, trim=trim, start_cut=start_cut, **kw)
        self.band = band
        self.band_grid = band_grid
        self.exclude_rest = exclude_rest

    def fit(self, X, Y, **kw):
        from .features import friction_velocity_scale

        X = np.asarray(X, dtype=np.float64)
        n = np.asarray(Y).reshape(len(Y), -1).shape[1]
        if X.shape[1] < 4 * n:
            raise ValueError("FrictionBandSEM needs the friction inputs tanh(dq / v_s)")
        dq = X[:, n:2 * n]
        z = dq / friction_velocity_scale(dq)
        self._sign_lo, self._sign_hi = np.tanh(z - self.band), np.tanh(z + self.band)
        self._rest = (self._sign_hi - self._sign_lo) > 0.5
        self._n_out = n
        return super().fit(X, Y, **kw)

    def _gp_likelihoods(self, X, Y, members, hyper, optimise, rng):
        rest_any = self._rest.any(1)
        moving = members[~rest_any[members]]
        if self.exclude_rest and len(moving) >= max(20, len(members) // 5):
            members = moving
        mean, var, gp, support = super()._gp_likelihoods(X, Y, members, hyper, optimise, rng)
        R = np.flatnonzero(rest_any)
        if not len(R):
            return mean, var, gp, support
        n = self._n_out
        lo, hi, rest = self._sign_lo[R], self._sign_hi[R], self._rest[R]
        cands = []
        for g in np.linspace(0.0, 1.0, self.band_grid):
            Xg = X[R].copy()
            Xg[:, 3 * n:4 * n] = np.where(rest, lo + g * (hi - lo), Xg[:, 3 * n:4 * n])
            if self._t_axis is not None and self.exclusion_s > 0:
                from ..gp.windowed import windowed_predictive

                m_g, _ = windowed_predictive(gp, Xg, self._t_axis[R], self._t_axis[support], self.exclusion_s)
            else:
                m_g, _ = gp.predict(Xg, include_noise=True)
            cands.append(np.asarray(m_g).reshape(len(R), n))
        cands = np.stack(cands)
        # Profile over the sign: the torque projected onto the band is the emission's mean.
        mean[R] = np.clip(Y[R], cands.min(0), cands.max(0))
        return mean, var, gp, support


# ----------------------------------------------------------------------------------------------
# Physical friction mean fitted robustly on every moving sample (prototype)
# ----------------------------------------------------------------------------------------------

def bisquare_coefficients(basis: np.ndarray, Y: np.ndarray, *, shared: bool, n_irls: int = 8,
                          c: float = 4.685) -> np.ndarray:
    """Coefficients (n, p) of Y ~ basis @ coef by Tukey-bisquare IRLS (redescending: pushes on up
    to ~40% of the samples get zero weight instead of Huber's bounded pull), started from the
    Huber fit. ``shared``: one vector for all outputs."""
    from .robust import fit_basis_coefficients, fit_shared_coefficients

    N, n, p = basis.shape
    coef = fit_shared_coefficients(basis, Y) if shared else fit_basis_coefficients(basis, Y)
    rms = np.sqrt((basis.reshape(-1, p) ** 2).mean(0))
    live = rms > 1e-12 * rms.max()
    coef[:, ~live] = 0.0
    basis = basis[:, :, live]
    rms = rms[live]
    coef_live = coef[:, live]
    for _ in range(n_irls):
        r = Y - np.einsum("tjp,jp->tj", basis, coef_live)
        scale = 1.4826 * np.median(np.abs(r - np.median(r, 0)), 0) + 1e-12
        u = r / (c * scale)
        w = np.where(np.abs(u) < 1, (1 - u ** 2) ** 2, 0.0)
        if shared:
            sw = np.sqrt(w) / scale
            A = (basis / rms * sw[:, :, None]).reshape(N * n, -1)
            sol, *_ = np.linalg.lstsq(A, (Y * sw).ravel(), rcond=1e-7)
            coef_live = np.tile(sol / rms, (n, 1))
        else:
            for j in range(n):
                sw = np.sqrt(w[:, j])
                sol, *_ = np.linalg.lstsq(basis[:, j, :] / rms * sw[:, None], Y[:, j] * sw, rcond=1e-7)
                coef_live[j] = sol / rms
    coef[:, live] = coef_live
    return coef


class PhysicsBandSEM(MultimodalSEM):
    """K = 1 prototype: the mean is the given basis plus Coulomb and viscous friction columns
    [tanh(dq_j / v_s), dq_j], fitted once by bisquare IRLS on every moving sample (labels play no
    part, so a friction branch the chain calls disturbed is still learned); the GP models what is
    left on moving samples; samples of uncertain sliding direction are scored against the
    Coulomb band [c s_lo, c s_hi] (profile likelihood over the sign)."""

    def __init__(self, n_modes: int = 1, *, band: float = 2.0, **kw):
        super().__init__(n_modes, **kw)
        self.band = band

    def fit(self, X, Y, *, basis=None, **kw):
        from .features import friction_velocity_scale

        if self.n_modes != 1:
            raise ValueError("prototype for one mode")
        X = np.asarray(X, dtype=np.float64)
        Y2 = np.asarray(Y, dtype=np.float64).reshape(len(Y), -1)
        T, n = Y2.shape
        dq = X[:, n:2 * n]
        z = dq / friction_velocity_scale(dq)
        lo, hi = np.tanh(z - self.band), np.tanh(z + self.band)
        self._rest = (hi - lo) > 0.5
        # Friction columns per joint, and an offset and single-link gravity (1, sin q, cos q) so that
        # a log without a robot model does not pass gravity off as friction.
        q = X[:, :n]
        fric = np.zeros((T, n, 5 * n))
        for j in range(n):
            fric[:, j, j] = np.tanh(z[:, j])
            fric[:, j, n + j] = dq[:, j]
            fric[:, j, 2 * n + j] = 1.0
            fric[:, j, 3 * n + j] = np.sin(q[:, j])
            fric[:, j, 4 * n + j] = np.cos(q[:, j])
        self._p0 = 0 if basis is None else basis.shape[2]
        full = fric if basis is None else np.concatenate([np.asarray(basis, dtype=np.float64), fric], axis=2)
        moving = ~self._rest.any(1)
        if moving.sum() < max(20, T // 5):
            moving = np.ones(T, bool)
        self._coef_fixed = bisquare_coefficients(full[moving], Y2[moving], shared=self.shared_basis)
        self._band_lo, self._band_hi = lo, hi
        return super().fit(X, Y, basis=full, **kw)

    def _fit_basis(self, basis, Y):
        return self._coef_fixed

    def _mode_likelihoods(self, X, Y, members, hyper, optimise, rng):
        coef = self._coef_fixed
        basis = self._basis
        n = Y.shape[1]
        p0 = self._p0
        coulomb = coef[np.arange(n), p0 + np.arange(n)]                        # (n,)
        offset = np.einsum("tjp,jp->tj", basis, coef)
        moving = members[~self._rest.any(1)[members]]
        if len(moving) >= max(20, len(members) // 5):
            members = moving
        mean, var, gp, support = self._gp_likelihoods(X, Y - offset, members, hyper, optimise, rng)
        mean = mean + offset
        # Rest samples: the Coulomb term is anywhere in [c s_lo, c s_hi]; project the torque on it.
        s_now = basis[:, np.arange(n), p0 + np.arange(n)]
        base = mean - coulomb * s_now
        a, b = coulomb * self._band_lo, coulomb * self._band_hi
        band_lo, band_hi = np.minimum(a, b), np.maximum(a, b)
        rest = self._rest
        mean = np.where(rest, base + np.clip(Y - base, band_lo, band_hi), mean)
        return mean, var, gp, support, coef


# ----------------------------------------------------------------------------------------------
# Push priors in seconds and a push-size floor (prototype scaffolding: MultimodalSEM's inline
# M-step is reached through two module-level names it looks up at call time)
# ----------------------------------------------------------------------------------------------

class _FloorNumpy:
    """numpy for sem.py, except that its one ``np.maximum`` (sigma_d's floor of 4 x the median
    predictive variance) floors at ``z2`` x that median instead."""

    def __init__(self, z2: float):
        self._z2 = z2

    def __getattr__(self, name):
        return getattr(np, name)

    def maximum(self, a, b):
        return np.maximum(a, b * (self._z2 / 4.0))


class PushPriors:
    """Mixin: pushes last ``push_s`` s and come every ``gap_s`` s a priori, whatever the sampling
    rate (``n_prior`` pseudo-pushes added to the transition counts; MultimodalSEM's own prior is
    per sample: p_enter 0.05, i.e. a push every 0.2 s at 100 Hz), and the push spread sigma_d is
    at least ``push_z`` predictive standard deviations."""

    push_s = 1.0
    gap_s = 5.0
    n_prior = 3.0
    push_z = 5.0

    def fit(self, X, Y, **kw):
        from . import sem as sem_module

        t = kw.get("t")
        dt = float(np.median(np.diff(np.asarray(t)))) if t is not None and len(t) > 1 else 0.05
        counts, numpy_ = sem_module._transition_counts, sem_module.np
        n0, push, gap = self.n_prior, self.push_s / dt, self.gap_s / dt

        def with_prior(states, K, starts):
            c = dict(counts(states, K, starts))
            c["disturbed"] += n0 * push
            c["leave"] += n0
            c["undisturbed"] += n0 * gap
            c["enter"] += n0
            return c

        sem_module._transition_counts = with_prior
        sem_module.np = _FloorNumpy(self.push_z ** 2)
        try:
            return super().fit(X, Y, **kw)
        finally:
            sem_module._transition_counts, sem_module.np = counts, numpy_


class PriorSEM(PushPriors, MultimodalSEM):
    pass


class PriorBandSEM(PushPriors, FrictionBandSEM):
    pass


class PriorRobustSEM(PushPriors, RobustStartSEM):
    pass


class StrongPriorSEM(PriorSEM):
    """PriorSEM with the push timing prior worth 50 pushes (durations and gaps then follow the
    prior unless a log holds far more evidence)."""

    n_prior = 50.0


class StrongPriorBandSEM(PriorBandSEM):
    n_prior = 50.0


class StrongPriorRobustBandSEM(StrongPriorBandSEM):
    """Push priors in seconds (50 pseudo-pushes), the friction band at rest, the trimmed start."""

    def __init__(self, n_modes: int = 1, **kw):
        kw.setdefault("trim", (0.8, 0.6))
        kw.setdefault("start_cut", 3.0)
        super().__init__(n_modes, **kw)
