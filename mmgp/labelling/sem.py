"""EM over dynamic modes and a disturbance mode, with per-mode exact GPs.

Hidden state of sample t: ``s_t = (k_t, d_t)``: dynamic mode ``k`` in ``0..K-1`` and a disturbance
flag ``d`` (when the disturbance mode is on). State index ``s = k + K * d``.

Emission (per joint independent, product over joints):
- ``d = 0``: the GP of mode k, ``N(y_t; mu_kt, sigma2_kt)``. For samples in mode k's support set
  the leave-one-out predictive is used (closed form), for the others the ordinary predictive;
  either way no sample is explained by a GP that has already seen it.
- ``d = 1``: ``N(y_t; mu_kt, sigma2_kt + Sigma_d)``, with ``Sigma_d`` (diagonal, per joint)
  re-estimated every sweep from the samples currently labelled disturbed. For K = 1 this is the
  source's disturbance mode ``N(mu, Sigma + Sigma_d)`` around the nominal mode; for K > 1 a
  push can happen in any mode, so the disturbance is centred on the sample's own mode. On
  several joints (in chain order, base first) a push acts on one link k, loading joints 1..k
  only: the emission is a mixture over k of "joints 1..k pushed, k+1..n as in d = 0", and each
  pushed joint a scale mixture of ``Sigma_d`` (x 1, 0.1, 0.01, floored) so that proximal and
  light pushes are not measured against the spread of the hardest distal shoves
  (:func:`.mstep.push_loglik`, :func:`.mstep.pushed_logpdf`).

With a ``basis`` (T, n, p) (e.g. a robot's inertial-parameter regressor), mode k's mean is
``basis @ coef_k`` plus its GP, the coefficients re-fitted robustly on the mode's undisturbed
samples every sweep (per joint, or one vector shared by all joints with ``shared_basis``).

Temporal prior: a Markov chain with ``p(k_t = k_{t-1}) = pi`` (the source's "stay" prior) and,
independently, a two-state chain on ``d`` (enter / leave a push), re-estimated with Beta priors;
the push chain's are durations in seconds (``push_s``, ``gap_s``, worth ``push_prior_n`` pushes).

Start (no labels given): one GP on every sample, refitted on the ``start_trim`` fractions of the
samples it explains best (pushes inflate a GP's noise); samples whose robust z-score under the
last fit exceeds ``start_z`` start disturbed; for K > 1, modes from k-means on smoothed residuals.

E-step (each sweep, likelihoods from the current labels): ``"mpm"`` (default) each sample's most
probable state under the posterior marginals (forward-backward; with the deterministic start and
evenly spaced GP subsets the fit does not depend on the seed); ``"ffbs"`` draws the whole label
sequence jointly (forward filtering / backward sampling); ``"gibbs"`` single-site Gibbs as in the
source, scanned as two interleaved blocks (even then odd sites, exact given their neighbours).
M-step: refit each mode's GP on its undisturbed samples (hyperparameters by the LOO objective,
warm-started, on a schedule), Sigma_d and the transition probabilities.
Final labels: posterior marginals averaged over the last sweeps; nothing flagged when the
disturbance states do not pay their BIC price (``0.5 log T`` per parameter) in log evidence.

Pieces: :mod:`.mstep` (mode models, emissions, parameter updates), :mod:`.estep` (label
sampling), :mod:`.convergence` (when to stop); this module runs the sweeps and keeps the result.
"""
from __future__ import annotations

import copy
import math
import time
from typing import Callable, Sequence

import numpy as np

from ..data.statistics import mad_sd
from ..physics.context import resting
from ..progress import report
from ..threads import limit_threads
from .convergence import ConvergenceMonitor, SweepRecord
from .estep import (chain_matrix, disturbed_given_modes, e_step, longest_runs_s, merge_short_runs,
                    runs_shorter_than)
from .hmm import forward_backward
from .mstep import (START_NAMES, ModeFitter, PushPrior, RestBand, Start, SweepParams, evenly_spaced,
                    mode_emissions, update_parameters)
from ..data.regression import basis_rank
from .scan import scan_probability, sustained_offset_scan
from .settings import EMSettings

__all__ = ["MultimodalSEM", "SweepRecord", "longest_runs_s", "select_n_modes"]


class MultimodalSEM:
    """EM for multimodal GP inverse dynamics with a disturbance mode.

    ``n_modes`` K (>= 1) dynamic modes; ``settings`` an :class:`.settings.EMSettings` (None: the
    defaults), then ``overrides`` of its fields by name; ``seed`` the draws of the "ffbs" and
    "gibbs" E-steps (unused by "mpm"); ``progress`` takes each sweep's :class:`SweepRecord`.
    """

    def __init__(self, n_modes: int, settings: EMSettings | None = None, *, seed: int = 0,
                 progress: Callable[[SweepRecord], None] | None = None, **overrides):
        if n_modes < 1:
            raise ValueError(f"expected n_modes >= 1, got {n_modes!r}")
        self.n_modes, self.seed, self.progress = n_modes, seed, progress
        self.settings = (settings or EMSettings()).replace(**overrides)

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, X: np.ndarray, Y: np.ndarray, *, t: np.ndarray | None = None, starts: Sequence[int] = (0,),
            init_states: np.ndarray | None = None, basis: np.ndarray | None = None,
            rest: RestBand | None = None, muted: np.ndarray | None = None, still: np.ndarray | None = None,
            sweeps: bool | None = None, start: str = "stuck-aware") -> "MultimodalSEM":
        """X (T, d) inputs, Y (T, n) torques, t (T,) sample times in s (per log; enables the
        leave-window-out likelihood). ``starts``: first index of each separate log. ``basis``
        (T, n, p): optional per-output linear regressors (e.g. the rigid-body inertial-parameter
        regressor); each mode then has the mean ``basis @ coef_[k]`` (coef (n, p)) under its GP.
        ``rest``: a :class:`.mstep.RestBand` for the friction band at rest (None: no band).
        ``muted``: (n,) bool, joints whose torque channel cannot tell a push (a dead band,
        :func:`mmgp.data.channels.dead_banded`): no vote for or against a push, nor in the start or scan.
        ``still``: (T,) bool, where the whole robot stands still; with ``t``, a still sample's
        likelihood leaves its whole hold out (:func:`.mstep.hold_windows`).
        ``start`` (without ``init_states``): one of :data:`START_NAMES`, or a :class:`Start`.

        Learned: ``p_mode_`` (T, K), ``p_disturbed_`` (T,), ``labels_`` (T,), ``disturbed_`` (T,),
        ``gps_`` (K ExactGPs), ``sigma_d_`` (n,), ``stay_prob_``, ``p_enter_``, ``p_leave_``,
        ``trace_`` (list of SweepRecord), ``converged_``, ``n_sweeps_``, ``timings_``, ``coef_`` (K
        (n, p) or None), ``members_`` (K index arrays the modes learnt from), ``basis_rank_``,
        ``last_sweep_`` (the last sweep's per-mode means/variances (T, n), log-likelihoods (T, S),
        calibration, sigma_d, states, in the sweep's mode order; None without sweeps),
        ``longest_stretch_s_`` (K,): each mode's longest stretch before merging (``min_mode_s``);
        ``abandoned_`` (``abandon_short_modes``); ``start_`` (None from ``init_states``), ``start_states_``
        (T,), ``other_start_``: whether the other of :data:`START_NAMES` fits the basis differently.

        One mode without the disturbance mode: no sweeps (one GP on every sample,
        :meth:`_fit_single`) unless ``sweeps=True`` (their log marginal scores K = 1 against K > 1).
        """
        if getattr(start, "name", start) not in START_NAMES:
            raise ValueError(f"start must be one of {START_NAMES}, got {start!r}")
        if sweeps is None:
            sweeps = not (self.n_modes == 1 and not self.settings.disturbance and init_states is None)
        if not sweeps:
            return self._fit_single(X, Y, t=t, starts=starts, basis=basis)
        # Each sweep is many small factorisations, which must run on one thread (mmgp.threads).
        with limit_threads(1):
            return self._fit(X, Y, t=t, starts=starts, init_states=init_states, basis=basis, rest=rest,
                             muted=muted, still=still, start=start)

    def _fit_single(self, X, Y, *, t, starts, basis=None) -> "MultimodalSEM":
        """One GP on every sample, by :func:`mmgp.gp.sparse.make_gp`, hyperparameters by its own
        procedure (``objective`` on ``fit_points`` random samples)."""
        t0 = time.perf_counter()
        report(f"one GP on all {len(Y)} samples")
        fitter, _ = self._prepare(X, Y, t, starts, basis)
        T, n = fitter.Y.shape
        self.labels_ = np.zeros(T, int)
        self.p_mode_ = np.ones((T, 1))
        self.p_disturbed_ = np.zeros(T)
        self.disturbed_ = np.zeros(T, bool)
        self.sigma_d_ = np.zeros(n)
        self.friction_band_ = np.zeros((1, n))
        self.stay_prob_ = 1.0
        self.p_enter_ = self.p_leave_ = 0.0
        self.trace_, self.converged_, self.n_sweeps_, self.last_sweep_ = [], True, 0, None
        self.abandoned_, self.labels_sweep_ = False, None
        self.start_, self.other_start_ = None, False
        self.longest_stretch_s_ = longest_runs_s(self.labels_, fitter.t_axis, 1, starts)
        self.log_marginal_ = float("nan")
        self.disturbance_gain_ = 0.0
        self._final_gps(fitter, [0], [None])
        total = time.perf_counter() - t0
        self.timings_ = {"init_s": 0.0, "gp_s": total, "estep_s": 0.0, "total_s": total}
        return self

    def _fit(self, X, Y, *, t, starts, init_states, basis=None, rest=None, muted=None, still=None,
             start="stuck-aware") -> "MultimodalSEM":
        t0 = time.perf_counter()
        s = self.settings
        fitter, starts = self._prepare(X, Y, t, starts, basis, rest, muted, still)
        T, n = fitter.Y.shape
        K = self.n_modes
        S = 2 * K if s.disturbance else K
        rng = np.random.default_rng(self.seed)
        prior = PushPrior.in_seconds(fitter.t_axis, s.push_s, s.gap_s, s.push_prior_n, s.push_floor_z, s.min_push_s)
        init_hyper = None
        self.other_start_ = fitter.stuck_aware
        if init_states is not None:
            states, self.start_ = np.asarray(init_states, int).copy(), None
        else:
            begun = (start if isinstance(start, Start) else
                     Start(start, *self._initial_states(fitter, start == "stuck-aware")))
            states, init_hyper, self.start_ = begun.states.copy(), begun.hyper, begun.name
        self.start_states_ = states.copy()
        params = SweepParams(hypers=[init_hyper] * K, stay=0.95 if s.stay_prob is None else s.stay_prob,
                             p_enter=prior.p_enter, p_leave=prior.p_leave, sigma_d=fitter.Y.var(0) + 1e-12,
                             calib=np.ones((K, n)))
        init_p = np.full(S, 1.0 / S)
        # Hyperparameter refits dominate a sweep's cost on long logs; short logs refit often.
        refit_at = {0, 1, 2, 4, 8, 16, 32} if T <= 2000 else {0, 2, 5}
        monitor = ConvergenceMonitor(min_sweeps=s.min_sweeps, max_sweeps=s.max_sweeps, tol_changed=s.tol_changed,
                                     patience=s.patience, average_last=s.average_last)
        timings = {"init_s": time.perf_counter() - t0, "gp_s": 0.0, "estep_s": 0.0}
        sweep = 0
        self.abandoned_, short = False, 0
        # A mode's shortest stretch in samples (0: no such rule without times or with one mode).
        dt = float(np.median(np.diff(fitter.t_axis))) if fitter.t_axis is not None else math.inf
        min_mode_len = s.min_mode_s / dt if K > 1 else 0.0
        scan_len = s.push_scan_s / dt          # the scan's window in samples (0: no scan)
        while True:
            ts = time.perf_counter()
            optimise = (sweep in refit_at) and not monitor.averaging
            em = mode_emissions(fitter, states, params, K, s.disturbance, optimise)
            te = time.perf_counter()
            timings["gp_s"] += te - ts
            A = chain_matrix(K, s.disturbance, params.stay, params.p_enter, params.p_leave)
            step = e_step(em.loglik, A, init_p, states, s.estep, rng, starts)
            timings["estep_s"] += time.perf_counter() - te
            changed = float((step.states != states).mean())
            states = step.states
            update_parameters(fitter.Y, states, em, params, n_modes=K, disturbance=s.disturbance, calibrate=s.calibrate,
                              learn_stay=s.stay_prob is None, starts=starts, prior=prior, rest=fitter.rest)
            # Kept for diagnostics (what the last sweep saw); references, no copies.
            self.last_sweep_ = {"means": em.means, "vars": em.vars, "bands": em.bands,
                                "loglik": em.loglik, "once": em.once, "calib": params.calib.copy(),
                                "sigma_d": np.array(params.sigma_d), "states": states}
            n_dist = int((states >= K).sum()) if s.disturbance else 0
            rec = SweepRecord(sweep, step.log_joint, step.log_marginal, changed, n_dist,
                              np.bincount(states % K, minlength=K).tolist(), time.perf_counter() - ts)
            if self.progress is not None:
                self.progress(rec)
            else:  # nobody takes the sweeps: a stage report each (the diagnosis's learner)
                report(f"EM sweep {sweep}: {changed:.1%} of the labels changed ({rec.seconds:.1f} s)")
            if monitor.update(rec, step.probs, (copy.deepcopy(params), self.last_sweep_), refit=optimise):
                break
            fleeting = sweep + 1 >= s.min_sweeps and self._fleeting(step.probs, K, fitter.t_axis, starts)
            short = short + 1 if fleeting else 0
            if short >= s.patience:
                monitor.abandon(step.probs)
                self.abandoned_ = True
                break
            sweep += 1
        if not monitor.converged and not self.abandoned_ and s.unconverged == "best":
            params, self.last_sweep_ = monitor.fall_back()
        self._finish(fitter, monitor, params, starts, prior.min_len, min_mode_len, scan_len)
        self.n_sweeps_ = sweep
        timings["total_s"] = time.perf_counter() - t0
        self.timings_ = timings
        return self

    def begin(self, X, Y, *, t=None, starts=(0,), basis=None, rest=None, muted=None, still=None,
              start: str = "stuck-aware") -> Start:
        """The start ``start`` the EM would begin from (``fit``'s arguments), without the sweeps;
        ``fit(..., start=<this>)`` begins there without computing it again."""
        with limit_threads(1):
            fitter, _ = self._prepare(X, Y, t, starts, basis, rest, muted, still)
            return Start(start, *self._initial_states(fitter, start == "stuck-aware"))

    def _fleeting(self, probs: np.ndarray, K: int, t: np.ndarray | None, starts) -> bool:
        """``abandon_short_modes``: some mode of this sweep's most probable labels (marginals
        ``probs`` (T, S)) holds nowhere for ``min_mode_s`` in one stretch, the test
        :func:`select_n_modes` rejects a candidate by (on the averaged labels, before merging)."""
        if not self.settings.abandon_short_modes or K < 2 or t is None:
            return False
        p_mode = probs[:, :K] + (probs[:, K:2 * K] if self.settings.disturbance else 0.0)
        return float(longest_runs_s(p_mode.argmax(1), t, K, starts).min()) < self.settings.min_mode_s

    def _prepare(self, X, Y, t, starts, basis, rest=None, muted=None, still=None) -> tuple[ModeFitter, list[int]]:
        """Checked float64 arrays, the joined time axis and the basis rank, as a ModeFitter."""
        X = np.asarray(X, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if Y.ndim == 1:
            Y = Y[:, None]
        T, n = Y.shape
        starts = sorted(set(int(s) for s in starts) | {0})
        self.basis_rank_ = 0
        if basis is not None:
            basis = np.asarray(basis, dtype=np.float64)
            if basis.ndim != 3 or basis.shape[:2] != (T, n):
                raise ValueError(f"basis must be (T, n, p) = ({T}, {n}, p), got {basis.shape}")
            self.basis_rank_ = basis_rank(basis, seed=0, shared=self.settings.shared_basis)
        axis = None
        if t is not None:
            # One increasing time axis over all logs, with gaps wider than any window between them.
            t = np.asarray(t, dtype=np.float64)
            axis = t.copy()
            bounds = list(starts) + [T]
            offset = 0.0
            for a, b in zip(bounds[:-1], bounds[1:]):
                axis[a:b] = t[a:b] - t[a] + offset
                offset = axis[b - 1] + 10.0 * max(self.settings.exclusion_s, 1.0)
        if T < 5 * self.n_modes:
            raise ValueError(f"{T} samples are too few for {self.n_modes} modes")
        if rest is not None and (np.shape(rest.weight) != (T, n) or len(rest.sign_cols) != n):
            raise ValueError(f"rest weights must be (T, n) = ({T}, {n}) with n sign columns")
        if still is not None and np.shape(still) != (T,):
            raise ValueError(f"still must be (T,) = ({T},), got {np.shape(still)}")
        return (ModeFitter(X, Y, self.settings.fitter, t_axis=axis, basis=basis, band=rest, starts=starts,
                           muted=muted, still=still), starts)

    def _initial_states(self, fitter: ModeFitter, stuck: bool = True) -> tuple[np.ndarray, object]:
        """Start without labels (deterministic): one GP on everything, refitted (with the
        disturbance mode) on the ``start_trim`` fractions of the samples with the smallest
        largest-joint z-score; samples
        whose robust z-score (median / MAD per joint, per initial mode) exceeds ``start_z`` start
        disturbed; for K > 1, modes from k-means on time-smoothed residuals (modes persist in
        time). ``stuck`` False: the basis is fitted on the resting samples too (the "every-sample"
        start). Returns the states (T,) and the last GP's hyperparameters (the first warm start)."""
        Y = fitter.Y
        T, n = Y.shape
        K = self.n_modes
        report(f"EM start: one GP on all {T} samples")
        mean, var, gp, _, _ = fitter.predictive(np.arange(T), None, True, stuck)
        # Trimming is against pushes; without a disturbance mode every sample belongs to a mode.
        for frac in (self.settings.start_trim if self.settings.disturbance else ()):
            report(f"EM start: GP refit on the {frac:.0%} most typical samples")
            z = (np.abs(Y - mean) / np.sqrt(var)).max(1)
            keep = np.sort(np.argsort(z, kind="stable")[:int(math.ceil(frac * T))])
            mean, var, gp, _, _ = fitter.predictive(keep, gp.hyper_, True, stuck)
        if K > 1:
            report(f"EM start: {K} initial modes from the smoothed residuals")
        modes = self._initial_modes(fitter, Y - mean) if K > 1 else np.zeros(T, int)
        states = modes.copy()
        if self.settings.disturbance:
            r = (Y - mean) / np.sqrt(var)
            z = np.zeros_like(r)
            for k in range(K):
                sel = modes == k
                if sel.any():
                    z[sel] = np.abs(r[sel] - np.median(r[sel], 0)) / (mad_sd(r[sel]) + 1e-12)
            if fitter.muted is not None:
                z[:, fitter.muted] = 0.0
            states[(z > self.settings.start_z).any(1)] += K
        return states, gp.hyper_

    def _initial_modes(self, fitter: ModeFitter, raw: np.ndarray) -> np.ndarray:
        """K-means (fixed seed) on residuals ``raw`` (T, n) smoothed over ``mode_smoothing_s``."""
        from scipy.ndimage import median_filter
        from sklearn.cluster import KMeans

        T = len(raw)
        # Modes persist far longer than pushes: a running median over a few seconds keeps a
        # mode's offset and suppresses pushes, which would otherwise dominate the clustering.
        if fitter.t_axis is not None:
            dt = float(np.median(np.diff(fitter.t_axis)))
            w = int(round(self.settings.mode_smoothing_s / max(dt, 1e-9)))
        else:
            w = T // 25
        w = int(min(max(w, 3), max(3, T // 4)))
        smooth = median_filter(raw, size=(w, 1), mode="nearest")
        smooth = smooth / (smooth.std(0) + 1e-12)
        return KMeans(n_clusters=self.n_modes, n_init=10, random_state=0).fit(smooth).labels_

    def _finish(self, fitter: ModeFitter, monitor: ConvergenceMonitor, params: SweepParams, starts,
                min_push_len: float = 0.0, min_mode_len: float = 0.0, scan_len: float = 0.0) -> None:
        """Labels from the averaged marginals, nominal mode first, and the final GPs; flagged
        stretches shorter than ``min_push_len`` samples are unflagged (p_disturbed 0), stretches
        of one mode shorter than ``min_mode_len`` samples take a neighbouring stretch's mode."""
        K, T, n = self.n_modes, *fitter.Y.shape
        report("EM end: labels and the final GPs")
        post = monitor.posterior()
        p_mode = np.clip(post[:, :K] + (post[:, K:] if self.settings.disturbance else 0.0), 0.0, 1.0)
        p_dist = np.clip(post[:, K:].sum(1), 0.0, 1.0) if self.settings.disturbance else np.zeros(T)
        self.disturbance_gain_ = self._disturbance_gain(params, starts) if self.settings.disturbance else 0.0
        abstained = self.settings.disturbance and self.settings.abstain and self.disturbance_gain_ <= 0.0
        if abstained:
            p_dist = np.zeros(T)
        # A mode lasts: shorter stretches take a neighbouring stretch's mode (one-hot below).
        unmerged = p_mode.argmax(1)
        modes = merge_short_runs(unmerged, min_mode_len, starts) if min_mode_len > 1 else unmerged
        moved = modes != unmerged
        if self.settings.disturbance and not abstained and moved.any():
            # With the other mode ruled out, a moved sample is its new mode's, undisturbed or
            # pushed, as the chain weighs them (a push can look like the other payload for
            # a fraction of a second; counted clean it would be missed).
            p_dist[moved] = disturbed_given_modes(self.last_sweep_["loglik"], modes, K, params.p_enter,
                                                  params.p_leave, starts)[moved]
        if self.settings.disturbance and fitter.hold is not None:
            p_dist = self._holds_on_their_own(fitter, modes, p_dist, params)
        p_dist = np.where(runs_shorter_than(p_dist > 0.5, min_push_len, starts), 0.0, p_dist)
        if self.settings.disturbance:
            # After the shortest-push rule (its blips are model error, part of the scan's
            # reference), and the rule again on what the scan adds.
            p_dist = self._scan_sustained(fitter, modes, p_dist, starts, scan_len)
            p_dist = np.where(runs_shorter_than(p_dist > 0.5, min_push_len, starts), 0.0, p_dist)
        # Mode 0 is the nominal mode: the one holding the most undisturbed probability mass.
        order = np.argsort(-(p_mode * (1 - p_dist)[:, None]).sum(0), kind="stable")
        rank = np.argsort(order)
        # How long each mode holds before any merging (merging can join a flicker into long stretches).
        self.longest_stretch_s_ = longest_runs_s(rank[unmerged], fitter.t_axis, K, starts)
        p_mode[moved] = np.eye(K)[modes[moved]]
        self.p_mode_ = p_mode[:, order]
        self.p_disturbed_ = p_dist
        self.labels_ = rank[modes]
        self.disturbed_ = self.p_disturbed_ > 0.5
        self.sigma_d_ = params.sigma_d if self.settings.disturbance else np.zeros(n)
        bands = self.last_sweep_["bands"]
        # the median band half-width over each mode's resting samples (weight > 0.5), N*m
        self.friction_band_ = np.zeros((K, n)) if bands is None else np.array(
            [[np.median(bands[k][resting(fitter.rest[:, j]), j]) if resting(fitter.rest[:, j]).any() else 0.0
              for j in range(n)] for k in order])
        self.stay_prob_ = float(params.stay)
        self.p_enter_ = float(params.p_enter) if self.settings.disturbance else 0.0
        self.p_leave_ = float(params.p_leave) if self.settings.disturbance else 0.0
        self.trace_ = monitor.trace
        self.converged_ = monitor.converged
        best = monitor.best[0] if monitor.fell_back else None
        self.labels_sweep_ = None if best is None else best.sweep
        self.log_marginal_ = (best or monitor.trace[-1]).log_marginal
        self._final_gps(fitter, order, params.hypers, params.stuck)

    def _scan_sustained(self, fitter: ModeFitter, modes: np.ndarray, p_dist: np.ndarray, starts,
                        scan_len: float) -> np.ndarray:
        """p_dist (T,) raised to the scan's probability where :func:`.scan.sustained_offset_scan`
        finds a sustained offset among the undisturbed samples (residuals under each sample's
        mode ``modes`` (T,) as the last sweep predicted them). Its own test, also where the chain
        abstained: it judges averages against their measured spread, not single samples.
        ``scan_len``: the window in samples (0 without times or with ``push_scan_s`` 0: no scan)."""
        if scan_len <= 0:
            self.scan_flagged_ = 0
            return p_dist
        last = self.last_sweep_
        T = len(modes)
        mean = np.stack(last["means"])[modes, np.arange(T)]
        var = np.stack(last["vars"])[modes, np.arange(T)]
        z = (fitter.Y - mean) / np.sqrt(var)
        ok = np.repeat((p_dist <= 0.5)[:, None], z.shape[1], 1)
        if fitter.muted is not None:
            ok[:, fitter.muted] = False
        if last["bands"] is not None:
            # Where a joint may be stuck, its held torque is an offset that lasts as long as
            # the hold: not evidence of a push unless it leaves the band (the chain's test).
            half = np.stack(last["bands"])[modes, np.arange(T)]
            ok &= fitter.rest * half ** 2 <= var
        window = max(int(round(scan_len)), 1)
        flags, stat = sustained_offset_scan(z, ok, window, self.settings.push_scan_z, starts)
        self.scan_flagged_ = int(flags.sum())
        p_scan = scan_probability(stat, T / window * z.shape[1])
        return np.where(flags, np.maximum(p_dist, p_scan), p_dist)

    def _holds_on_their_own(self, fitter: ModeFitter, modes: np.ndarray, p_dist: np.ndarray,
                            params: SweepParams) -> np.ndarray:
        """p_disturbed (T,) where the whole robot rests (every joint's rest weight > 0.5): each
        sample's own evidence (its mode's band or model against a push, the sample counted
        whole) at the chain's stationary share of pushes p_enter / (p_enter + p_leave), in place
        of the chain's marginal; elsewhere ``p_dist``.

        Why: held still by friction, the robot shows one torque for the whole hold, so the
        chain counts a hold once (:func:`.mstep.hold_weights`), and so weakly that the stay prior
        carried a neighbouring push's state into it, a sample at a time. A stuck
        joint's torque is evidence of a push only where it leaves the band, and that is
        decided sample by sample: a push that builds up inside a hold is flagged from where it
        leaves the band on."""
        K = self.n_modes
        once = self.last_sweep_["once"]
        T = len(p_dist)
        still = (fitter.rest > 0.5).all(1)
        pi = params.p_enter / max(params.p_enter + params.p_leave, 1e-300)
        log_odds = once[np.arange(T), K + modes] - once[np.arange(T), modes] + math.log(max(pi, 1e-300) / max(1 - pi, 1e-300))
        return np.where(still, 1.0 / (1.0 + np.exp(-np.clip(log_odds, -700, 700))), p_dist)

    def _disturbance_gain(self, params: SweepParams, starts) -> float:
        """log p(Y) of the last sweep's chain minus that of the same chain without disturbance
        states (modes only), minus the disturbance parameters' BIC price (p_enter, p_leave,
        Sigma_d: 2 + n, at 0.5 log T each). Positive: the disturbance mode earns its keep."""
        from .estep import chain_matrix

        loglik = self.last_sweep_["loglik"]
        T, S = loglik.shape
        K = self.n_modes
        n = len(params.sigma_d)
        A_full = chain_matrix(K, True, params.stay, params.p_enter, params.p_leave)
        A_modes = chain_matrix(K, False, params.stay, 0.0, 1.0)
        full = forward_backward(loglik, A_full, np.full(S, 1.0 / S), starts)[2]
        modes_only = forward_backward(loglik[:, :K], A_modes, np.full(K, 1.0 / K), starts)[2]
        return float(full - modes_only - 0.5 * math.log(T) * (2 + n))

    def _final_gps(self, fitter: ModeFitter, order, hypers, stuck=None) -> None:
        # Final GPs conditioned on the final labels, hyperparameters kept from the last refit.
        # support_Y_ holds the GP's targets: torques minus the basis part when there is one.
        X, Y = fitter.X, fitter.Y
        n = Y.shape[1]
        # members_: per mode, the samples its mean coefficients and GP learnt from (before the
        # support's subsampling; mmgp.evaluation.heldout conditions its fold GPs on these)
        self.gps_, self.support_X_, self.support_Y_, self.coef_, self.members_ = [], [], [], [], []
        for i, k in enumerate(order):
            members = np.flatnonzero((self.labels_ == i) & ~self.disturbed_)
            if stuck is not None and (~stuck[k][members]).sum() >= 0.25 * len(members):
                members = members[~stuck[k][members]]      # as in the sweeps (mstep.mode_emissions)
            if len(members) < max(5, n):
                members = np.flatnonzero(self.labels_ == i)
            if len(members) < max(5, n):
                # A mode no sample ended in (e.g. K = 3 tried on a 2-mode log) keeps the samples
                # most likely in it, so its GP is defined (on no data its mean and scale are NaN).
                members = np.sort(np.argsort(-self.p_mode_[:, i], kind="stable")[:max(5, n)])
            coef = None
            Yk = Y
            if fitter.basis is not None:
                coef = fitter.basis_coefficients(members)
                Yk = Y - np.einsum("tjp,jp->tj", fitter.basis, coef)
            self.coef_.append(coef)
            self.members_.append(members)
            if self.settings.final_support is not None:
                members = evenly_spaced(members, self.settings.final_support)
            self.gps_.append(fitter.final_gp(members, Yk, hypers[k]))
            self.support_X_.append(X[members])
            self.support_Y_.append(Yk[members])

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
        return self.n_modes * per_mode + (self.n_modes > 1) + (2 + n if self.settings.disturbance else 0)


def select_n_modes(X, Y, candidates: Sequence[int] = (1, 2, 3), *, t=None, starts=(0,), basis=None, rest=None,
                   muted=None, **kw) -> tuple[MultimodalSEM, dict]:
    """Choose K: the candidates are tried in increasing order; K is kept while it raises a
    BIC-style score on the chain's log marginal likelihood of the final sweep (itself built from
    out-of-sample GP predictions), score = log p(Y) - 0.5 log(T) * n_params, and every one of
    its modes holds for at least ``min_mode_s`` seconds (an :class:`.settings.EMSettings` field, ``kw``'s, default
    4) in one stretch (not tested without ``t``).
    The first K that fails either test ends the search.

    Why the duration test: a dynamic mode (a payload on or off) lasts far longer than a push
    (0.2-3 s). On logs without a mode change, the extra modes the score alone picked were pushes
    and stuck-joint stretches that a GP of their own fits better than the disturbance state
    does; none of them held longer than 3 s (independent 1-DOF validation logs: 0.6-3.0 s),
    while true payload stretches last 5-30 s."""
    T, n = np.asarray(Y).reshape(len(Y), -1).shape
    d = np.asarray(X).shape[1]
    scores, longest, models = {}, {}, {}
    best = None
    for K in sorted(candidates):
        report(f"mode selection: EM with {K} mode(s)")
        m = MultimodalSEM(n_modes=K, abandon_short_modes=K > 1, **kw).fit(X, Y, t=t, starts=starts, basis=basis,
                                                                          rest=rest, muted=muted, sweeps=True)
        scores[K] = m.log_marginal_ - 0.5 * math.log(T) * m.n_parameters(d, n)
        longest[K] = m.longest_stretch_s_.round(3).tolist()
        models[K] = m
        lasting = K == 1 or t is None or (min(longest[K]) >= m.settings.min_mode_s and not m.abandoned_)
        if best is not None and (scores[K] <= scores[best] or not lasting):
            break
        best = K
    return models[best], {"scores": scores, "longest_run_s": longest, "min_mode_s": models[best].settings.min_mode_s,
                          "abandoned": {K: bool(m.abandoned_) for K, m in models.items()}, "chosen": best}
