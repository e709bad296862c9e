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

With a ``basis`` (T, n, p) (e.g. a robot's inertial-parameter regressor), mode k's mean is
``basis @ coef_k`` plus its GP, the coefficients re-fitted robustly on the mode's undisturbed
samples every sweep (per joint, or one vector shared by all joints with ``shared_basis``).

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
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..gp.exact import ExactGP
from ..gp.hyper import Hyper, default_hyper, optimise_hyper
from ..gp.linalg import LOG_2PI
from ..gp.objectives import leave_block_out
from ..gp.windowed import windowed_predictive
from .hmm import (_transition_counts, ffbs_sample, forward_backward, gibbs_sweep, sequence_log_prior,
                  transition_matrix)
from .robust import basis_rank, fit_basis_coefficients, fit_shared_coefficients


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
    max_sweeps, min_sweeps : sweep limits; convergence when, over the last ``patience`` sweeps,
        the sampled labels change in fewer than ``tol_changed`` of the samples on average and
        either the mean log joint stops rising compared with the ``patience`` sweeps before or
        fewer than a fifth of ``tol_changed`` change.
    average_last : sweeps after convergence whose posterior marginals are averaged.
    max_support : at most this many undisturbed samples condition each mode's GP during the sweeps
        (random subset; the others are predicted out of sample): each sweep costs
        O(max_support^2 * T) per joint.
    final_support : the returned GPs (used by predict/export) condition on up to this many.
    fit_points, fit_iter : hyperparameter fitting subset size and L-BFGS iterations.
    exclusion_s, block_s : leave-window-out radius of the E-step likelihood and the block length
        of the hyperparameter objective, seconds (need ``t`` in ``fit``).
    mode_smoothing_s : running-median length of the residuals clustered into initial modes.
    calibrate : scale each mode's predictive variance per joint by its undisturbed mean z^2.
    shared_basis : with a ``basis`` in ``fit``, one coefficient vector for all joints (a
        payload) instead of one per joint.
    gp_kwargs : passed to ExactGP (e.g. ard, objective, device).
    """

    def __init__(self, n_modes: int = 1, *, disturbance: bool = True, estep: str = "ffbs",
                 stay_prob: float | None = None, max_sweeps: int = 40, min_sweeps: int = 6,
                 tol_changed: float = 0.05, patience: int = 3, average_last: int = 5,
                 max_support: int = 500, fit_points: int = 500, fit_iter: int = 50,
                 final_support: int = 2000,
                 exclusion_s: float = 1.0, block_s: float = 2.0, mode_smoothing_s: float = 4.0,
                 calibrate: bool = True, shared_basis: bool = False, gp_kwargs: dict | None = None, seed: int = 0,
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
        self.final_support = final_support
        self.fit_points = fit_points
        self.fit_iter = fit_iter
        self.exclusion_s = exclusion_s
        self.block_s = block_s
        self.mode_smoothing_s = mode_smoothing_s
        self.calibrate = calibrate
        self.shared_basis = shared_basis
        self.gp_kwargs = gp_kwargs or {}
        self.seed = seed
        self.progress = progress

    # -- helpers -------------------------------------------------------------------------------
    def _new_gp(self) -> ExactGP:
        kw = dict(max_fit_points=self.fit_points, max_iter=self.fit_iter, seed=self.seed)
        kw.update(self.gp_kwargs)
        return ExactGP(**kw)

    def _mode_likelihoods(self, X, Y, members: np.ndarray, hyper: Hyper | None, optimise: bool,
                          rng) -> tuple[np.ndarray, np.ndarray, ExactGP, np.ndarray, np.ndarray | None]:
        """Mean and variance (T, n) of every sample under mode ``members``' model (LOO for
        support), the GP, its support and the basis coefficients (None without a basis).

        With a basis, the mode's mean is ``basis @ coef`` (fitted on all members) and the GP
        models what is left; the linear part extrapolates like the physics it encodes."""
        basis = getattr(self, "_basis", None)
        if basis is not None:
            coef = self._fit_basis(basis[members], Y[members])
            offset = np.einsum("tjp,jp->tj", basis, coef)
            mean, var, gp, support = self._gp_likelihoods(X, Y - offset, members, hyper, optimise, rng)
            return mean + offset, var, gp, support, coef
        return (*self._gp_likelihoods(X, Y, members, hyper, optimise, rng), None)

    def _fit_basis(self, basis, Y):
        return fit_shared_coefficients(basis, Y) if self.shared_basis else fit_basis_coefficients(basis, Y)

    def _gp_likelihoods(self, X, Y, members, hyper, optimise, rng):
        support = members
        if len(support) > self.max_support:
            support = np.sort(rng.choice(support, self.max_support, replace=False))
        gp = self._new_gp()
        windowed = self._t_axis is not None and self.exclusion_s > 0 and self.block_s > 0
        T = len(Y)
        if windowed and optimise:
            # Condition once on the fitting subset to get the standardisation, then tune there.
            fit_idx = support
            if len(fit_idx) > self.fit_points:
                fit_idx = np.sort(rng.choice(support, self.fit_points, replace=False))
            gp.fit(X[fit_idx], Y[fit_idx], hyper=hyper or default_hyper(X.shape[1], Y.shape[1]), optimise=False)
            # Warm-started refits on long logs (where refits dominate the cost) get half the
            # iterations of the first fit.
            iters = self.fit_iter if (hyper is None or T <= 2000) else max(10, self.fit_iter // 2)
            hyper, _ = optimise_hyper(gp.Xs_, gp.Ys_, gp.hyper_, max_iter=iters,
                                      objective=leave_block_out(self._t_axis[fit_idx], self.block_s))
            optimise = False
        gp.fit(X[support], Y[support], hyper=hyper, optimise=optimise)
        T, n = Y.shape
        if windowed:
            mean, var = windowed_predictive(gp, X, self._t_axis, self._t_axis[support], self.exclusion_s)
            return mean.reshape(T, n), var.reshape(T, n), gp, support
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
        mean, var, gp, _, _ = self._mode_likelihoods(X, Y, all_idx, None, True, rng)
        self._init_hyper = gp.hyper_
        r = (Y - mean) / np.sqrt(var)
        states = np.zeros(T, int)
        if self.disturbance:
            mad = np.median(np.abs(r - np.median(r, 0)), 0) * 1.4826 + 1e-12
            z = np.abs(r - np.median(r, 0)) / mad
            states[(z > 4.0).any(1)] = K  # k=0, d=1
        if K > 1:
            from scipy.ndimage import median_filter
            from sklearn.cluster import KMeans

            # Modes persist far longer than pushes: a running median over a few seconds keeps a
            # mode's offset and suppresses pushes, which would otherwise dominate the clustering.
            raw = Y - mean
            if self._t_axis is not None:
                dt = float(np.median(np.diff(self._t_axis)))
                w = int(round(self.mode_smoothing_s / max(dt, 1e-9)))
            else:
                w = T // 25
            w = int(min(max(w, 3), max(3, T // 4)))
            smooth = median_filter(raw, size=(w, 1), mode="nearest")
            smooth = smooth / (smooth.std(0) + 1e-12)
            km = KMeans(n_clusters=K, n_init=10, random_state=self.seed).fit(smooth)
            states = km.labels_ + K * (states >= K)
        return states

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, X: np.ndarray, Y: np.ndarray, *, t: np.ndarray | None = None, starts: Sequence[int] = (0,),
            init_states: np.ndarray | None = None, basis: np.ndarray | None = None) -> "MultimodalSEM":
        """X (T, d) inputs, Y (T, n) torques, t (T,) sample times in s (per log; enables the
        leave-window-out likelihood). ``starts``: first index of each separate log. ``basis``
        (T, n, p): optional per-output linear regressors (e.g. the rigid-body inertial-parameter
        regressor); each mode then has the mean ``basis @ coef_[k]`` (coef (n, p)) under its GP.

        Learned: ``p_mode_`` (T, K), ``p_disturbed_`` (T,), ``labels_`` (T,), ``disturbed_`` (T,),
        ``gps_`` (K ExactGPs), ``sigma_d_`` (n,), ``stay_prob_``, ``p_enter_``, ``p_leave_``,
        ``trace_`` (list of SweepRecord), ``converged_``, ``n_sweeps_``, ``timings_``,
        ``coef_`` (K basis coefficient arrays (n, p), or None each), ``basis_rank_``, and
        ``last_sweep_`` (the last sweep's per-mode means/variances (T, n), log-likelihoods (T, S),
        calibration, sigma_d and states: for diagnosing where errors sit). Mode order in
        ``last_sweep_`` is the sweep's internal one, not the final nominal-first order.
        """
        import torch

        # Each sweep is many small factorisations; with several threads, OpenMP spin-waiting
        # made them 10-100x slower whenever another process competed for the cores (a 5,000
        # sample 7-DOF sweep: 50-90 s on two threads under load, 3-7 s on one), and one thread
        # loses little when the machine is idle.
        prev_threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return self._fit(X, Y, t=t, starts=starts, init_states=init_states, basis=basis)
        finally:
            torch.set_num_threads(prev_threads)

    def _fit(self, X, Y, *, t, starts, init_states, basis=None) -> "MultimodalSEM":
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
        self._t_axis = None
        self._basis = None
        self.basis_rank_ = 0
        if basis is not None:
            basis = np.asarray(basis, dtype=np.float64)
            if basis.ndim != 3 or basis.shape[:2] != (T, n):
                raise ValueError(f"basis must be (T, n, p) = ({T}, {n}, p), got {basis.shape}")
            self._basis = basis
            self.basis_rank_ = basis_rank(basis, seed=self.seed, shared=self.shared_basis)
        if t is not None:
            # One increasing time axis over all logs, with gaps wider than any window between them.
            t = np.asarray(t, dtype=np.float64)
            axis = t.copy()
            bounds = list(starts) + [T]
            offset = 0.0
            for a, b in zip(bounds[:-1], bounds[1:]):
                axis[a:b] = t[a:b] - t[a] + offset
                offset = axis[b - 1] + 10.0 * max(self.exclusion_s, 1.0)
            self._t_axis = axis
        if T < 5 * K:
            raise ValueError(f"{T} samples are too few for {K} modes")

        states = (np.asarray(init_states, int).copy() if init_states is not None
                  else self._initial_states(X, Y, rng))
        hypers: list[Hyper | None] = [getattr(self, "_init_hyper", None)] * K
        stay = self.stay_prob if self.stay_prob is not None else 0.95
        p_enter, p_leave = 0.05, 0.2
        sigma_d = Y.var(0) + 1e-12
        init_p = np.full(S, 1.0 / S)
        calib = np.ones((K, n))
        # Hyperparameter refits dominate a sweep's cost on long logs; short logs refit often.
        refit_at = {0, 1, 2, 4, 8, 16, 32} if T <= 2000 else {0, 2, 5}
        trace: list[SweepRecord] = []
        post_sum = np.zeros((T, S))
        n_avg = 0
        converged = False
        quiet = 0
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
                mean, var, gp, _, _ = self._mode_likelihoods(X, Y, members, hypers[k], optimise, rng)
                hypers[k] = gp.hyper_
                self.gps_[k] = gp
                var = var * calib[k]
                mus.append(mean)
                vars_.append(var)
                loglik[:, k] = (-0.5 * (LOG_2PI + np.log(var) + (Y - mean) ** 2 / var)).sum(1)
                if self.disturbance:
                    vd = var + sigma_d
                    ll_push = -0.5 * (LOG_2PI + np.log(vd) + (Y - mean) ** 2 / vd)
                    if n > 1:
                        # A push on one link loads only some joints: per joint, a 50/50 mixture of
                        # "untouched" and "pushed", so unaffected joints cost at most log 2 each.
                        ll_free = -0.5 * (LOG_2PI + np.log(var) + (Y - mean) ** 2 / var)
                        ll_push = np.logaddexp(ll_free, ll_push) - np.log(2.0)
                    loglik[:, K + k] = ll_push.sum(1)
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
            if self.calibrate:
                # Out-of-window predictions in states the log visits once are overconfident; a
                # per-mode, per-joint variance scale fitted on the undisturbed samples (mean
                # squared z-score, never below 1) keeps them from being taken for pushes.
                for k in range(K):
                    sel = (mode_of == k) & ~dist
                    if sel.sum() >= 10:
                        z2 = ((Y - mus[k]) ** 2 / (vars_[k] / calib[k]))[sel]
                        # The mean, not a robust median/0.455: on the Panda both gave recall ~0.59,
                        # and the median let the replica's once-visited states through (worst
                        # unperturbed-correct 0.915 vs 0.954).
                        calib[k] = np.clip(z2.mean(0), 1.0, 1e4)
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

            # Kept for diagnostics (what the last sweep saw); references, no copies.
            self.last_sweep_ = {"means": mus, "vars": vars_, "loglik": loglik, "calib": calib.copy(),
                                "sigma_d": np.array(sigma_d), "states": states}
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
                # Sampled labels keep flickering at the margins, so convergence is judged on the
                # trend: the mean log joint of the last `patience` sweeps no longer beats the
                # mean of the `patience` before by more than a small tolerance, and few labels move.
                lj = [r.log_joint for r in trace]
                w = self.patience
                if len(lj) >= 2 * w:
                    now, before = np.mean(lj[-w:]), np.mean(lj[-2 * w:-w])
                    flat = now - before <= 1e-3 * abs(before) + 1.0
                    moved = np.mean([r.changed for r in trace[-w:]])
                    # Once under a fifth of the tolerance move, the sampled log joint only
                    # wanders with the draws (+-500 nats on a 5,000-sample 7-DOF log, where
                    # 20 more sweeps moved 0.5% of the labels), so it is not waited for.
                    quiet = 1 if (moved < self.tol_changed and (flat or moved < 0.2 * self.tol_changed)) else 0
                if sweep + 1 >= self.min_sweeps and quiet:
                    converged = True
                    averaging = True
                elif sweep + 1 >= self.max_sweeps:
                    averaging = True
            sweep += 1

        post = post_sum / max(n_avg, 1)
        p_mode = np.clip(post[:, :K] + (post[:, K:] if self.disturbance else 0.0), 0.0, 1.0)
        p_dist = np.clip(post[:, K:].sum(1), 0.0, 1.0) if self.disturbance else np.zeros(T)
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
        # support_Y_ holds the GP's targets: torques minus the basis part when there is one.
        self.gps_, self.support_X_, self.support_Y_, self.coef_ = [], [], [], []
        for i, k in enumerate(order):
            members = np.flatnonzero((self.labels_ == i) & ~self.disturbed_)
            if len(members) < max(5, n):
                members = np.flatnonzero(self.labels_ == i)
            coef = None
            Yk = Y
            if self._basis is not None:
                coef = self._fit_basis(self._basis[members], Y[members])
                Yk = Y - np.einsum("tjp,jp->tj", self._basis, coef)
            self.coef_.append(coef)
            if len(members) > self.final_support:
                members = np.sort(rng.choice(members, self.final_support, replace=False))
            gp = self._new_gp().fit(X[members], Yk[members], hyper=hypers[k], optimise=False)
            self.gps_.append(gp)
            self.support_X_.append(X[members])
            self.support_Y_.append(Yk[members])
        timings["total_s"] = time.perf_counter() - t0
        self.timings_ = timings
        return self

    def predict(self, X: np.ndarray, mode: int = 0, basis: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (T, n) of the torque in ``mode`` (0 = nominal) at inputs X (T, d);
        ``basis`` (T, n, p) is required when the model was fitted with one."""
        if not 0 <= mode < len(self.gps_):
            raise ValueError(f"mode must be in 0..{len(self.gps_) - 1}")
        mean, std = self.gps_[mode].predict(X, include_noise=True)
        coef = self.coef_[mode]
        if coef is not None:
            if basis is None:
                raise ValueError("this model has a basis mean: pass basis (T, n, p)")
            mean = mean.reshape(len(X), -1) + np.einsum("tjp,jp->tj", np.asarray(basis, dtype=np.float64), coef)
        return mean, std

    def n_parameters(self, d: int, n: int) -> int:
        per_mode = n * (d + 2) + 1 + getattr(self, "basis_rank_", 0)
        return self.n_modes * per_mode + (self.n_modes > 1) + (2 + n if self.disturbance else 0)


def select_n_modes(X, Y, candidates: Sequence[int] = (1, 2, 3), *, t=None, starts=(0,), basis=None,
                   **kw) -> tuple[MultimodalSEM, dict]:
    """Choose K by a BIC-style score on the chain's log marginal likelihood of the final sweep
    (itself built from out-of-sample GP predictions): score = log p(Y) - 0.5 log(T) * n_params."""
    T, n = np.asarray(Y).reshape(len(Y), -1).shape
    d = np.asarray(X).shape[1]
    scores, models = {}, {}
    for K in candidates:
        m = MultimodalSEM(n_modes=K, **kw).fit(X, Y, t=t, starts=starts, basis=basis)
        scores[K] = m.log_marginal_ - 0.5 * math.log(T) * m.n_parameters(d, n)
        models[K] = m
    best = max(scores, key=scores.get)
    return models[best], {"scores": scores, "chosen": best}
