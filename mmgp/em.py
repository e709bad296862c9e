"""Stochastic EM over dynamic modes and a disturbance mode, with per-mode exact GPs.

Hidden state of sample t: ``s_t = (k_t, d_t)``: dynamic mode ``k`` in ``0..K-1`` and a disturbance
flag ``d`` (when the disturbance mode is on). State index ``s = k + K * d``.

Emission (per joint independent, product over joints):
- ``d = 0``: the GP of mode k, ``N(y_t; mu_kt, sigma2_kt)``. For samples in mode k's support set
  the leave-one-out predictive is used (closed form), for the others the ordinary predictive;
  either way no sample is explained by a GP that has already seen it.
- ``d = 1``: ``N(y_t; mu_kt, sigma2_kt + Sigma_d)``, with ``Sigma_d`` (diagonal, per joint)
  re-estimated every sweep from the samples currently labelled disturbed. For K = 1 this is the
  source's disturbance mode ``N(mu, Sigma + Sigma_d)`` around the nominal mode; for K > 1 a
  push can happen in any mode, so the disturbance is centred on the sample's own mode.

Temporal prior: a Markov chain with ``p(k_t = k_{t-1}) = pi`` (the source's "stay" prior) and,
independently, a two-state chain on ``d`` (enter / leave a push). Both are re-estimated from
the sampled label sequences with weak Beta priors, unless fixed in the settings.

E-step (each sweep, likelihoods computed from the current labels):
- ``"ffbs"``: forward filtering / backward sampling draws the whole label sequence jointly from
  the chain's posterior given the per-sample likelihoods; marginals from forward-backward.
- ``"gibbs"``: single-site Gibbs as in the source, ``p(s_t | s_-t) ~ L_t(s) A(s_{t-1}, s)
  A(s, s_{t+1})``, scanned as two interleaved blocks (even then odd sites: given their
  neighbours they are conditionally independent, so the block update is exact Gibbs).
M-step: refit each mode's GP on its undisturbed samples (hyperparameters by the LOO objective,
warm-started, on a schedule), Sigma_d and the transition probabilities.
Final labels are posterior marginals averaged over the last sweeps.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .gp import ExactGP, Hyper, LOG_2PI


# ----------------------------------------------------------------------------------------------
# Markov chain pieces (pure numpy; tested against exact enumeration)
# ----------------------------------------------------------------------------------------------

def transition_matrix(n_modes: int, stay: float, p_enter: float | None = None,
                      p_leave: float | None = None) -> np.ndarray:
    """(S, S) transition matrix over states ``k + K*d``; S = K, or 2K with a disturbance chain."""
    K = n_modes
    Pk = np.full((K, K), (1.0 - stay) / (K - 1)) if K > 1 else np.ones((1, 1))
    if K > 1:
        np.fill_diagonal(Pk, stay)
    if p_enter is None:
        return Pk
    Pd = np.array([[1.0 - p_enter, p_enter], [p_leave, 1.0 - p_leave]])
    return np.kron(Pd, Pk)  # index k + K*d: outer factor d, inner factor k


def _log_normalise(logp: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    m = logp.max(axis=axis, keepdims=True)
    p = np.exp(logp - m)
    z = p.sum(axis=axis, keepdims=True)
    return p / z, (np.log(z) + m).squeeze(axis)


def forward_backward(loglik: np.ndarray, A: np.ndarray, init: np.ndarray,
                     starts: Sequence[int] = (0,)) -> tuple[np.ndarray, np.ndarray, float]:
    """Scaled forward-backward. loglik (T, S), A (S, S), init (S,); the chain restarts at each
    index in ``starts`` (separate logs). Returns filtered alpha (T, S), marginals (T, S) and the
    log marginal likelihood of the sequence."""
    T, S = loglik.shape
    is_start = np.zeros(T, bool)
    is_start[list(starts)] = True
    lik, shift = _log_normalise(loglik)           # per-row scaled likelihoods
    alpha = np.empty((T, S))
    logZ = float(shift.sum())
    for t in range(T):
        pred = init if is_start[t] else alpha[t - 1] @ A
        a = pred * lik[t]
        c = a.sum()
        alpha[t] = a / c
        logZ += math.log(c)
    beta = np.ones((T, S))
    for t in range(T - 2, -1, -1):
        if is_start[t + 1]:
            beta[t] = 1.0
            continue
        b = A @ (lik[t + 1] * beta[t + 1])
        beta[t] = b / b.sum()
    post = alpha * beta
    post /= post.sum(1, keepdims=True)
    return alpha, post, logZ


def ffbs_sample(alpha: np.ndarray, A: np.ndarray, rng: np.random.Generator,
                starts: Sequence[int] = (0,)) -> np.ndarray:
    """Backward sampling of a whole state sequence from filtered ``alpha`` (T, S)."""
    T, S = alpha.shape
    is_start = np.zeros(T + 1, bool)
    is_start[list(starts)] = True
    is_start[T] = True
    s = np.empty(T, int)
    u = rng.random(T)
    for t in range(T - 1, -1, -1):
        p = alpha[t] if is_start[t + 1] else alpha[t] * A[:, s[t + 1]]
        c = np.cumsum(p)
        s[t] = min(int(np.searchsorted(c, u[t] * c[-1], side="right")), S - 1)
    return s


def gibbs_conditionals(loglik: np.ndarray, A: np.ndarray, init: np.ndarray, states: np.ndarray,
                       sites: np.ndarray, starts: Sequence[int] = (0,)) -> np.ndarray:
    """p(s_t | s_-t) for each t in ``sites`` given the others' current ``states``: (len(sites), S)."""
    T = loglik.shape[0]
    is_start = np.zeros(T + 1, bool)
    is_start[list(starts)] = True
    is_start[T] = True
    logA = np.log(np.clip(A, 1e-300, None))
    logp = loglik[sites].copy()
    first = is_start[sites]
    logp[first] += np.log(np.clip(init, 1e-300, None))
    prev = np.where(first, 0, states[np.maximum(sites - 1, 0)])
    logp[~first] += logA[prev[~first]]
    has_next = ~is_start[sites + 1]
    nxt = states[np.minimum(sites + 1, T - 1)]
    logp[has_next] += logA[:, nxt[has_next]].T
    p, _ = _log_normalise(logp)
    return p


def gibbs_sweep(loglik: np.ndarray, A: np.ndarray, init: np.ndarray, states: np.ndarray,
                rng: np.random.Generator, starts: Sequence[int] = (0,)) -> tuple[np.ndarray, np.ndarray]:
    """One single-site Gibbs sweep as two exact blocks (even sites, then odd). Returns new states
    and the conditional probabilities used (T, S), a Rao-Blackwellised marginal estimate."""
    T, S = loglik.shape
    states = states.copy()
    probs = np.empty((T, S))
    for parity in (0, 1):
        sites = np.arange(parity, T, 2)
        p = gibbs_conditionals(loglik, A, init, states, sites, starts)
        c = np.cumsum(p, 1)
        states[sites] = np.minimum((c < rng.random(len(sites))[:, None]).sum(1), S - 1)
        probs[sites] = p
    return states, probs


def sequence_log_prior(states: np.ndarray, A: np.ndarray, init: np.ndarray, starts: Sequence[int] = (0,)) -> float:
    T = len(states)
    is_start = np.zeros(T, bool)
    is_start[list(starts)] = True
    lp = float(np.log(init[states[is_start]]).sum())
    idx = np.flatnonzero(~is_start)
    return lp + float(np.log(A[states[idx - 1], states[idx]]).sum())


# ----------------------------------------------------------------------------------------------
# The estimator
# ----------------------------------------------------------------------------------------------

@dataclass
class SweepRecord:
    sweep: int
    log_joint: float          # log p(Y, s) at the sampled labels
    log_marginal: float       # log p(Y) under the chain, given the sweep's likelihoods
    changed: float            # fraction of samples whose state changed
    n_disturbed: int
    mode_sizes: list
    seconds: float


class MultimodalSEM:
    """Stochastic EM for multimodal GP inverse dynamics with a disturbance mode.

    Parameters
    ----------
    n_modes : number of dynamic modes K (>= 1).
    disturbance : include the disturbance mode.
    estep : "ffbs" (default; see benchmarks/bench_estep.py) or "gibbs".
    stay_prob : fixed p(k_t = k_{t-1}); None learns it (Beta prior, mean 0.95).
    max_sweeps, min_sweeps : sweep limits; convergence when the sampled labels change in fewer
        than ``tol_changed`` of the samples and the log joint stops rising, over ``patience`` sweeps.
    average_last : sweeps after convergence whose posterior marginals are averaged.
    max_support : at most this many undisturbed samples condition each mode's GP (random subset;
        the others are predicted out of sample); bounds each sweep at O(max_support^3).
    fit_points, fit_iter : hyperparameter fitting subset size and L-BFGS iterations.
    gp_kwargs : passed to ExactGP (e.g. ard, objective, device).
    """

    def __init__(self, n_modes: int = 1, *, disturbance: bool = True, estep: str = "ffbs",
                 stay_prob: float | None = None, max_sweeps: int = 40, min_sweeps: int = 6,
                 tol_changed: float = 0.01, patience: int = 3, average_last: int = 5,
                 max_support: int = 1000, fit_points: int = 600, fit_iter: int = 50,
                 gp_kwargs: dict | None = None, seed: int = 0,
                 progress: Callable[[SweepRecord], None] | None = None):
        if n_modes < 1:
            raise ValueError("n_modes must be >= 1")
        if estep not in ("ffbs", "gibbs"):
            raise ValueError(f"estep must be 'ffbs' or 'gibbs', got {estep!r}")
        self.n_modes = n_modes
        self.disturbance = disturbance
        self.estep = estep
        self.stay_prob = stay_prob
        self.max_sweeps = max_sweeps
        self.min_sweeps = min_sweeps
        self.tol_changed = tol_changed
        self.patience = patience
        self.average_last = average_last
        self.max_support = max_support
        self.fit_points = fit_points
        self.fit_iter = fit_iter
        self.gp_kwargs = gp_kwargs or {}
        self.seed = seed
        self.progress = progress

    # -- helpers -------------------------------------------------------------------------------
    def _new_gp(self) -> ExactGP:
        kw = dict(max_fit_points=self.fit_points, max_iter=self.fit_iter, seed=self.seed)
        kw.update(self.gp_kwargs)
        return ExactGP(**kw)

    def _mode_likelihoods(self, X, Y, members: np.ndarray, hyper: Hyper | None, optimise: bool,
                          rng) -> tuple[np.ndarray, np.ndarray, ExactGP, np.ndarray]:
        """Mean and variance (T, n) of every sample under a GP on ``members`` (LOO for support)."""
        support = members
        if len(support) > self.max_support:
            support = np.sort(rng.choice(support, self.max_support, replace=False))
        gp = self._new_gp()
        gp.fit(X[support], Y[support], hyper=hyper, optimise=optimise)
        T, n = Y.shape
        mean = np.empty((T, n))
        std = np.empty((T, n))
        other = np.setdiff1d(np.arange(T), support, assume_unique=True)
        if len(other):
            m_o, s_o = gp.predict(X[other], include_noise=True)
            mean[other], std[other] = m_o.reshape(-1, n), s_o.reshape(-1, n)
        m_l, s_l = gp.loo_predictive()
        mean[support], std[support] = m_l.reshape(-1, n), s_l.reshape(-1, n)
        return mean, std ** 2, gp, support

    def _initial_states(self, X, Y, rng) -> np.ndarray:
        """Start without labels: one GP on everything; robust outliers of its LOO residuals start
        disturbed; for K > 1, modes from k-means on time-smoothed residuals (modes persist in time)."""
        T, n = Y.shape
        K = self.n_modes
        all_idx = np.arange(T)
        mean, var, gp, _ = self._mode_likelihoods(X, Y, all_idx, None, True, rng)
        self._init_hyper = gp.hyper_
        r = (Y - mean) / np.sqrt(var)
        states = np.zeros(T, int)
        if self.disturbance:
            mad = np.median(np.abs(r - np.median(r, 0)), 0) * 1.4826 + 1e-12
            z = np.abs(r - np.median(r, 0)) / mad
            states[(z > 4.0).any(1)] = K  # k=0, d=1
        if K > 1:
            from scipy.ndimage import uniform_filter1d
            from sklearn.cluster import KMeans

            raw = Y - mean
            w = max(3, T // 50)
            smooth = uniform_filter1d(raw, size=w, axis=0, mode="nearest")
            smooth = smooth / (smooth.std(0) + 1e-12)
            km = KMeans(n_clusters=K, n_init=10, random_state=self.seed).fit(smooth)
            states = km.labels_ + K * (states >= K)
        return states

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, X: np.ndarray, Y: np.ndarray, *, starts: Sequence[int] = (0,),
            init_states: np.ndarray | None = None) -> "MultimodalSEM":
        """X (T, d) inputs, Y (T, n) torques. ``starts``: first index of each separate log.

        Learned: ``p_mode_`` (T, K), ``p_disturbed_`` (T,), ``labels_`` (T,), ``disturbed_`` (T,),
        ``gps_`` (K ExactGPs), ``sigma_d_`` (n,), ``stay_prob_``, ``p_enter_``, ``p_leave_``,
        ``trace_`` (list of SweepRecord), ``converged_``, ``n_sweeps_``, ``timings_``.
        """
        t0 = time.perf_counter()
        X = np.asarray(X, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if Y.ndim == 1:
            Y = Y[:, None]
        T, n = Y.shape
        K = self.n_modes
        S = 2 * K if self.disturbance else K
        rng = np.random.default_rng(self.seed)
        starts = sorted(set(int(s) for s in starts) | {0})
        if T < 5 * K:
            raise ValueError(f"{T} samples are too few for {K} modes")

        states = (np.asarray(init_states, int).copy() if init_states is not None
                  else self._initial_states(X, Y, rng))
        hypers: list[Hyper | None] = [getattr(self, "_init_hyper", None)] * K
        stay = self.stay_prob if self.stay_prob is not None else 0.95
        p_enter, p_leave = 0.05, 0.2
        sigma_d = Y.var(0) + 1e-12
        init_p = np.full(S, 1.0 / S)
        refit_at = {0, 1, 2, 4, 8, 16, 32}
        trace: list[SweepRecord] = []
        post_sum = np.zeros((T, S))
        n_avg = 0
        converged = False
        quiet = 0
        best_joint = -np.inf
        sweep = 0
        self.gps_ = [None] * K
        timings = {"init_s": time.perf_counter() - t0, "gp_s": 0.0, "estep_s": 0.0}
        averaging = False
        while True:
            ts = time.perf_counter()
            loglik = np.empty((T, S))
            mode_of = states % K
            dist = states >= K if self.disturbance else np.zeros(T, bool)
            mus, vars_ = [], []
            for k in range(K):
                members = np.flatnonzero((mode_of == k) & ~dist)
                if len(members) < max(5, n):
                    # An emptied mode is re-seeded from random samples so K stays K.
                    members = np.sort(rng.choice(T, max(5, n), replace=False))
                optimise = (sweep in refit_at) and not averaging
                mean, var, gp, _ = self._mode_likelihoods(X, Y, members, hypers[k], optimise, rng)
                hypers[k] = gp.hyper_
                self.gps_[k] = gp
                mus.append(mean)
                vars_.append(var)
                loglik[:, k] = (-0.5 * (LOG_2PI + np.log(var) + (Y - mean) ** 2 / var)).sum(1)
                if self.disturbance:
                    vd = var + sigma_d
                    loglik[:, K + k] = (-0.5 * (LOG_2PI + np.log(vd) + (Y - mean) ** 2 / vd)).sum(1)
            timings["gp_s"] += time.perf_counter() - ts
            te = time.perf_counter()
            A = transition_matrix(K, stay, p_enter if self.disturbance else None,
                                  p_leave if self.disturbance else None)
            alpha, post, log_marg = forward_backward(loglik, A, init_p, starts)
            if self.estep == "ffbs":
                new_states = ffbs_sample(alpha, A, rng, starts)
                probs = post
            else:
                new_states, probs = gibbs_sweep(loglik, A, init_p, states, rng, starts)
            timings["estep_s"] += time.perf_counter() - te
            changed = float((new_states != states).mean())
            states = new_states
            log_joint = float(loglik[np.arange(T), states].sum() + sequence_log_prior(states, A, init_p, starts))

            # M-step for the disturbance spread and the chain.
            mode_of = states % K
            dist = states >= K if self.disturbance else np.zeros(T, bool)
            if self.disturbance:
                mu_s = np.stack(mus)[mode_of, np.arange(T)]
                var_s = np.stack(vars_)[mode_of, np.arange(T)]
                if dist.sum() >= 3:
                    excess = ((Y - mu_s) ** 2 - var_s)[dist].mean(0)
                    sigma_d = np.maximum(excess, 4.0 * np.median(var_s, 0))
                trans = _transition_counts(states, K, starts)
                p_enter = (trans["enter"] + 1.0) / (trans["undisturbed"] + 20.0)
                p_leave = (trans["leave"] + 2.0) / (trans["disturbed"] + 10.0)
            if self.stay_prob is None and K > 1:
                trans = _transition_counts(states, K, starts)
                stay = (trans["stay"] + 19.0) / (trans["pairs"] + 20.0)

            rec = SweepRecord(sweep, log_joint, float(log_marg), changed, int(dist.sum()),
                              np.bincount(mode_of, minlength=K).tolist(), time.perf_counter() - ts)
            trace.append(rec)
            if self.progress is not None:
                self.progress(rec)
            if averaging:
                post_sum += probs
                n_avg += 1
                if n_avg >= self.average_last:
                    break
            else:
                improving = log_joint > best_joint + 1e-3 * abs(best_joint) if np.isfinite(best_joint) else True
                best_joint = max(best_joint, log_joint)
                quiet = quiet + 1 if (changed < self.tol_changed and not improving) or changed == 0.0 else 0
                if sweep + 1 >= self.min_sweeps and quiet >= self.patience:
                    converged = True
                    averaging = True
                elif sweep + 1 >= self.max_sweeps:
                    averaging = True
            sweep += 1

        post = post_sum / max(n_avg, 1)
        p_mode = post[:, :K] + (post[:, K:] if self.disturbance else 0.0)
        p_dist = post[:, K:].sum(1) if self.disturbance else np.zeros(T)
        # Mode 0 is the nominal mode: the one holding the most undisturbed probability mass.
        order = np.argsort(-(p_mode * (1 - p_dist)[:, None]).sum(0), kind="stable")
        self.p_mode_ = p_mode[:, order]
        self.p_disturbed_ = p_dist
        self.labels_ = self.p_mode_.argmax(1)
        self.disturbed_ = self.p_disturbed_ > 0.5
        self.sigma_d_ = sigma_d if self.disturbance else np.zeros(n)
        self.stay_prob_ = float(stay)
        self.p_enter_ = float(p_enter) if self.disturbance else 0.0
        self.p_leave_ = float(p_leave) if self.disturbance else 0.0
        self.trace_ = trace
        self.converged_ = converged
        self.n_sweeps_ = sweep
        self.log_marginal_ = trace[-1].log_marginal
        # Final GPs conditioned on the final labels, hyperparameters kept from the last refit.
        self.gps_, self.support_X_, self.support_Y_ = [], [], []
        for i, k in enumerate(order):
            members = np.flatnonzero((self.labels_ == i) & ~self.disturbed_)
            if len(members) < max(5, n):
                members = np.flatnonzero(self.labels_ == i)
            if len(members) > self.max_support:
                members = np.sort(rng.choice(members, self.max_support, replace=False))
            gp = self._new_gp().fit(X[members], Y[members], hyper=hypers[k], optimise=False)
            self.gps_.append(gp)
            self.support_X_.append(X[members])
            self.support_Y_.append(Y[members])
        timings["total_s"] = time.perf_counter() - t0
        self.timings_ = timings
        return self

    def predict(self, X: np.ndarray, mode: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (T, n) of the torque in ``mode`` (0 = nominal) at inputs X (T, d)."""
        if not 0 <= mode < len(self.gps_):
            raise ValueError(f"mode must be in 0..{len(self.gps_) - 1}")
        return self.gps_[mode].predict(X, include_noise=True)

    def n_parameters(self, d: int, n: int) -> int:
        per_mode = n * (d + 2) + 1
        return self.n_modes * per_mode + (self.n_modes > 1) + (2 + n if self.disturbance else 0)


def _transition_counts(states: np.ndarray, K: int, starts: Sequence[int]) -> dict:
    T = len(states)
    is_start = np.zeros(T, bool)
    is_start[list(starts)] = True
    idx = np.flatnonzero(~is_start)
    a, b = states[idx - 1], states[idx]
    ka, kb, da, db = a % K, b % K, a >= K, b >= K
    return {"pairs": len(idx), "stay": int((ka == kb).sum()),
            "undisturbed": int((~da).sum()), "enter": int((~da & db).sum()),
            "disturbed": int(da.sum()), "leave": int((da & ~db).sum())}


def select_n_modes(X, Y, candidates: Sequence[int] = (1, 2, 3), *, starts=(0,), **kw) -> tuple[MultimodalSEM, dict]:
    """Choose K by a BIC-style score on the chain's log marginal likelihood of the final sweep
    (itself built from out-of-sample GP predictions): score = log p(Y) - 0.5 log(T) * n_params."""
    T, n = np.asarray(Y).reshape(len(Y), -1).shape
    d = np.asarray(X).shape[1]
    scores, models = {}, {}
    for K in candidates:
        m = MultimodalSEM(n_modes=K, **kw).fit(X, Y, starts=starts)
        scores[K] = m.log_marginal_ - 0.5 * math.log(T) * m.n_parameters(d, n)
        models[K] = m
    best = max(scores, key=scores.get)
    return models[best], {"scores": scores, "chosen": best}
