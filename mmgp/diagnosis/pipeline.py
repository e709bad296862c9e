"""Sim-vs-real diagnosis: which physical effects is the nominal model missing, where, how large.

Pipeline (``diagnose``):

1. *Locate*: residual ``r = tau - tau_rbd(q, dq, ddq)`` per joint; where it concentrates (near
   zero velocity, high load, position/acceleration ranges, time spans). Residual and every
   regressor column are low-passed alike (parallel filtering). A joint's equation is left out
   where its velocity is within noise of zero (``valid_mask``): stuck, static friction is
   set-valued, and fitting it would feed look-alike effects.
2. *Separate* pushes and modes before naming anything: a robust (Huber then Tukey IRLS) fit of
   the whole library gives sample weights with pushes at zero; effects are selected on those
   weights; the residual of the *selected* model is scanned for pushes (chi-square scan at a
   family-wise level over the log's independent samples; excursions shorter than the filter's
   resolution are not events). The multimodal learner (``mmgp.em.MultimodalSEM``, disturbance
   mode on, GP inputs ``[q, dq, ddq, tanh(dq/v_s)]``, on <= 500 samples of ``tau - tau_rbd``
   evenly spaced in time, leave-window-out likelihoods) then arbitrates (``separate="auto"``): a
   scanned span is kept when the learner also flags some of it, or when the scan's statistic
   peaks at >= ``em_gate_peak`` (5) times its threshold. Where a payload mode switch is found,
   the pushes are scanned again on the two-mode residual and gated by a two-mode learner
   (``n_modes=2``; one mode would call the rarer mode disturbed). Chosen on
   ``benchmarks/bench_diagnose.py`` (26 cases x 2 seeds, 3000 samples): the learner alone
   (``separate="em"``) flags pushes on control logs (a false ``external_disturbance`` on
   ``panda_control`` and ``actuator_control``), so it cannot lead; the union inherits that; the
   scan alone keeps one false push finding (``panda_loadfric_j2``) that the gate removes; a gate
   without the strong-span exemption dropped a true 1.2 s push (15x threshold) that the learner's
   GP had absorbed. ``separate`` = "scan", "em", "scan|em" (union), "none" select the others.
3. *Name*: every candidate effect of ``mmgp.effects`` is a few regressor columns. Forward selection
   on time-block cross-validation (20 blocks): an effect is added only while the best candidate's
   paired held-out gain is significant (one-sided signed-rank test over the blocks) at family-wise
   level ``alpha`` (Bonferroni over the candidates tried at that step); physical signs must hold;
   nested effects (load dependence in Coulomb friction) are only tried as extensions. No
   magnitude threshold.
4. *Model*: refit the nominal model plus the chosen effects (non-negative least squares), then a
   GP (``mmgp.gp.ExactGP``) on what is left; held-out normalised MSE per joint at three stages.
   Mode switches: one vs two payload modes per link (sticky two-state switching regression, HMM
   predictive from samples a filter memory earlier, on held-out blocks), same test.
5. *Tell*: findings per CONTRACT section 2/3, a Markdown report and residual plots.

Units: N*m, rad, s throughout; shapes (T, n) for T samples of n joints.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..physics import effects as fx
from ..data.logs import RobotLog
from ..data.outputs import jsonable

STAGES = ("nominal", "with_physics", "with_physics_and_gp")

_UNITS = {"tau_c": "N*m", "b": "N*m*s/rad", "beta": "", "inertia": "kg*m^2", "k": "N*m/rad",
          "q0": "rad", "offset": None, "mass": "kg", "com": "m"}
_LABEL = {"coulomb_friction": "Coulomb friction", "viscous_friction": "viscous friction",
          "load_dependent_friction": "load-dependent friction", "armature": "armature (rotor inertia)",
          "joint_spring": "a joint spring", "encoder_offset": "an encoder offset",
          "torque_offset": "a torque-sensor offset", "payload": "a payload"}


@dataclass
class DiagnoseConfig:
    """Settings of :func:`diagnose`.

    n_folds: time blocks for cross-validation (selection, uncertainty and the stage figures).
    rule: "bonferroni" (add an effect only while the best candidate's paired held-out gain is
        significant at family-wise level ``alpha`` over the candidates tried) or "1se".
    se_rule: the "k standard errors" of the "1se" rule (1.0 is the classic rule).
    effects: candidate effect names (CONTRACT section 3); None = all.
    payload_links: "auto" or a list of link indices (0-based, the link joint i moves).
    separate: "auto" (= "scan+em": robust scan, spans gated by mmgp.em.MultimodalSEM, see the
        module docstring), "scan" (robust scan only), "em" (the learner's flags only), "scan|em"
        (union), or "none".
    em_modes, em_points: dynamic modes of the learner (the re-scan after a payload mode switch
        uses at least 2) and the most samples it sees (evenly thinned in time).
    em_gate_peak: scanned spans peaking at this many times the scan threshold are kept without
        the learner's confirmation.
    gp: fit the third stage. gp_points: training points per fold for that GP; gp_hyper_points,
        gp_iter: subset size and L-BFGS iterations of its one hyperparameter optimisation.
    max_samples: longer logs are thinned evenly to this many samples (runtime bound).
    sign_noise_factor: v_s = this times the velocity noise (smooth sign of Coulomb friction).
    filter: low-pass residual and regressor columns alike (parallel filtering) at a cutoff set
        by the trajectory's bandwidth, so noise in estimated accelerations does not bias the fit.
    plots: write PNGs with ``write``.
    modes: test for a payload that switches between two values (mode_switch); mode_folds,
        mode_max_samples: time blocks and (thinned) samples of that test.
    load_with_friction: (when not load_from_log) the load is the nominal torque plus the robust
        fit's friction estimate, as the motor torque that the gears carry includes friction.
    state_check: also drop flagged spans whose residual the joints' own state explains (kNN);
        off by default: physics-first scanning and the rest mask already remove such misfit, and
        on 1-DOF logs with long pushes the neighbours themselves are pushed samples.
    load_from_log: load-dependent friction scales with the low-passed logged torque (True) or
        with the nominal model's torque (False, default: the logged torque contains the friction
        itself, so on joints whose torque is mostly friction |tau| * sign(dq) fits friction with
        beta ~ 1 -- an endogenous regressor).
    push_alpha: family-wise false-alarm level of the push scan over the log's independent samples.
    rest_factor: a joint's equation is left out where |dq| < rest_factor * v_s (the velocity is
        within noise of zero, widened by the filter's memory): at rest friction takes any value
        in [-tau_c, tau_c] (stiction), which no function of the state can fit.
    """

    n_folds: int = 20
    se_rule: float = 1.0
    rule: str = "bonferroni"
    alpha: float = 0.05
    effects: Sequence[str] | None = None
    payload_links: Sequence[int] | str = "auto"
    separate: str = "auto"
    gp: bool = True
    gp_points: int = 600
    gp_hyper_points: int = 300
    gp_iter: int = 25
    max_samples: int = 6000
    sign_noise_factor: float = 3.0
    plots: bool = True
    rest_factor: float = 1.0
    push_alpha: float = 0.001
    load_from_log: bool = False
    load_with_friction: bool = False
    state_check: bool = False
    modes: bool = True
    mode_folds: int = 10
    mode_max_samples: int = 1000
    max_steps: int | None = None
    filter: bool = True
    em_modes: int = 1
    em_points: int = 500
    em_gate_peak: float = 5.0
    seed: int = 0

    def __post_init__(self):
        if self.separate not in _SEPARATION_METHOD:
            raise ValueError(f"separate must be one of {sorted(_SEPARATION_METHOD)}, got {self.separate!r}")

    @classmethod
    def from_dict(cls, d: dict | None) -> "DiagnoseConfig":
        if d is None:
            return cls()
        if isinstance(d, cls):
            return d
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)


# --------------------------------------------------------------------------------------------
# Cross-validated forward selection on per-fold Gram matrices
# --------------------------------------------------------------------------------------------

class FoldGrams:
    """Sufficient statistics of weighted least squares per fold and joint.

    ``A``: (T, n, P) atom columns, ``r``: (T, n) residual, ``use``: (T,) bool samples to use,
    ``folds``: list of (train_idx, test_idx), ``W``: optional (T, n) non-negative weights per
    sample and joint. Stores per-fold train/test Grams (K, n, P, P), cross terms (K, n, P), sums
    of squares (K, n) and test-sample counts per joint ``nte`` (K, n).
    """

    def __init__(self, A: np.ndarray, r: np.ndarray, use: np.ndarray, folds, W: np.ndarray | None = None):
        T, n, P = A.shape
        K = len(folds)
        self.K, self.n, self.P = K, n, P
        # per-sample, per-joint weights (0 drops a joint's equation at that sample)
        sw = np.ones((T, n)) if W is None else np.sqrt(np.asarray(W, dtype=np.float64))
        # per joint, weighted and contiguous in time: the fold sums below slice rows only
        Aw = np.ascontiguousarray(np.transpose(A * sw[:, :, None], (1, 0, 2)))
        rw = np.ascontiguousarray((r * sw).T)

        def gram(idx):
            G = np.empty((n, P, P))
            c = np.empty((n, P))
            y = np.empty(n)
            m = np.empty(n)
            for j in range(n):
                Aj = Aw[j, idx]
                rj = rw[j, idx]
                G[j] = Aj.T @ Aj
                c[j] = Aj.T @ rj
                y[j] = rj @ rj
                m[j] = (sw[idx, j] > 0).sum()
            return G, c, y, m

        idx_all = np.flatnonzero(use)
        self.Gall, self.call, self.yall, self.nall = gram(idx_all)
        self.Gte = np.zeros((K, n, P, P))
        self.cte = np.zeros((K, n, P))
        self.yte = np.zeros((K, n))
        self.Gtr = np.zeros((K, n, P, P))
        self.ctr = np.zeros((K, n, P))
        self.ytr = np.zeros((K, n))
        self.nte = np.zeros((K, n))
        for k, (tr, te) in enumerate(folds):
            te_u = te[use[te]]
            self.Gte[k], self.cte[k], self.yte[k], self.nte[k] = gram(te_u)
            # train = all minus (test block and the gaps around it): only the short excluded
            # stretch is summed, so K folds cost about two full Gram matrices
            excl = np.ones(T, bool)
            excl[tr] = False
            Ge, ce, ye, _ = gram(np.flatnonzero(excl & use))
            self.Gtr[k], self.ctr[k], self.ytr[k] = self.Gall - Ge, self.call - ce, self.yall - ye

    @staticmethod
    def _solve(G, c):
        # tiny ridge relative to the diagonal: keeps exactly collinear atoms from blowing up
        d = np.diag(G).copy()
        reg = 1e-10 * (d.max() if d.size else 1.0) + 1e-300
        try:
            return np.linalg.solve(G + reg * np.eye(len(c)), c)
        except np.linalg.LinAlgError:
            return np.linalg.lstsq(G, c, rcond=None)[0]

    def fit(self, S: Sequence[int], w: np.ndarray, fold: int | None = None) -> np.ndarray:
        """Weighted LS coefficients of atoms ``S`` on all data or on a fold's training part."""
        S = list(S)
        if not S:
            return np.zeros(0)
        if fold is None:
            G, c = self.Gall, self.call
        else:
            G, c = self.Gtr[fold], self.ctr[fold]
        Gw = np.einsum("j,jpq->pq", w, G[:, S][:, :, S])
        cw = np.einsum("j,jp->p", w, c[:, S])
        return self._solve(Gw, cw)

    def cv_errors(self, S: Sequence[int], w: np.ndarray) -> np.ndarray:
        """Held-out sum of squared errors (K, n) of the model with atoms ``S``."""
        S = list(S)
        err = self.yte.copy()
        if not S:
            return err
        for k in range(self.K):
            th = self.fit(S, w, k)
            Gs = self.Gte[k][:, S][:, :, S]
            cs = self.cte[k][:, S]
            err[k] = self.yte[k] - 2 * cs @ th + np.einsum("p,jpq,q->j", th, Gs, th)
        return err

    def fold_coefficients(self, S: Sequence[int], w: np.ndarray) -> np.ndarray:
        return np.array([self.fit(S, w, k) for k in range(self.K)])


@dataclass
class PathStep:
    effects: list  # list[fx.Effect]
    cv_mean: float
    cv_folds: np.ndarray


class ForwardCVSelector:
    """Forward selection of effects with time-block CV and a multiplicity-corrected paired test.

    At each step every admissible candidate (one not yet chosen, whose physical signs hold on
    the full-data fit) is scored by the paired held-out differences ``d_k`` (weighted squared
    error of the current model minus that of the current model plus the candidate, fold k). A
    candidate qualifies when its paired t statistic exceeds the one-sided Student-t quantile at
    level ``alpha / m`` (Bonferroni over the ``m`` candidates tried at that step: the best of
    many noise columns would otherwise look significant by chance). The qualifying candidate
    with the largest mean gain is added; the search stops when none qualifies. ``rule="1se"``
    gives the classic one-standard-error rule on the path instead.

    ``fit(effects, keys, grams, w)``: ``effects`` the candidate list, ``keys`` the atom keys
    indexing the Gram matrices, ``w`` (n,) joint weights (inverse noise variance).
    Learned: ``path_`` (list of PathStep), ``chosen_step_``, ``selected_`` (effects),
    ``t_stats_`` (t statistic of each added effect, in order).
    """

    def __init__(self, se_rule: float = 1.0, max_steps: int | None = None, *, rule: str = "bonferroni",
                 alpha: float = 0.05, reach: float | None = None):
        self.reach = reach
        self.se_rule = se_rule
        self.max_steps = max_steps
        self.rule = rule
        self.alpha = alpha

    @staticmethod
    def _atoms(effs, keys_index):
        S = []
        for e in effs:
            for a in e.atoms():
                i = keys_index[a]
                if i not in S:
                    S.append(i)
        return S

    def _admissible(self, effs, S, th, keys):
        pos = {keys[i]: v for i, v in zip(S, th)}
        for e in effs:
            for a in e.nonneg:
                if pos[a] < 0:
                    return False
            reach = getattr(self, "reach", None)
            if isinstance(e, fx.Payload) and reach:
                # a payload is attached to the robot: its centre of mass lies within the robot's
                # reach of the link frame (else it is first-moment columns fitting something else)
                m = pos[("pl", e.index, 0)]
                h = np.array([pos[("pl", e.index, i)] for i in (1, 2, 3)])
                if m <= 0 or np.linalg.norm(h) > reach * m:
                    return False
        return True

    @staticmethod
    def paired_t(d: np.ndarray) -> float:
        """t statistic of the mean of paired fold differences ``d`` (K,)."""
        K = len(d)
        if K < 2:
            return 0.0
        sd = d.std(ddof=1)
        m = d.mean()
        if sd <= 1e-12 * (abs(m) + 1e-300):
            return float(np.sign(m)) * np.inf if m != 0 else 0.0
        return float(m / (sd / np.sqrt(K)))

    @staticmethod
    def paired_p(d: np.ndarray) -> float:
        """One-sided p-value of "the paired fold differences ``d`` (K,) are centred above zero":
        Wilcoxon signed-rank test (exact for small K). Distribution-free: a real effect's gain
        varies a lot between time blocks (fast motion in some, slow in others), which makes a
        t test weak, but it is positive in nearly every block."""
        from scipy.stats import wilcoxon

        d = np.asarray(d, dtype=np.float64)
        scale = np.abs(d).max() if d.size else 0.0
        d = d[np.abs(d) > 1e-12 * scale] if scale > 0 else d[:0]
        if len(d) < 2:
            return 1.0
        return float(wilcoxon(d, alternative="greater").pvalue)

    def fit(self, effects, keys, grams: FoldGrams, w: np.ndarray) -> "ForwardCVSelector":

        keys_index = {a: i for i, a in enumerate(keys)}
        chosen: list = []
        e0 = grams.cv_errors([], w) @ w
        path = [PathStep([], float(e0.mean()), e0)]
        tstats = []
        max_steps = self.max_steps or len(effects)
        best = path[0].cv_mean
        stale = 0
        K = grams.K
        while len(chosen) < max_steps:
            S0 = self._atoms(chosen, keys_index)
            cur = path[-1].cv_folds
            cand = []
            for e in effects:
                if e in chosen:
                    continue
                new = [keys_index[a] for a in e.atoms() if keys_index[a] not in S0]
                if not new:
                    continue  # nested in what is already chosen (e.g. Coulomb inside load-dependent)
                if any(not any(o.name == req and o.index == e.index for o in chosen) for req in e.requires):
                    continue
                effs = chosen + [e]
                S = S0 + new
                th = grams.fit(S, w)
                if not self._admissible(effs, S, th, keys):
                    continue
                ef = grams.cv_errors(S, w) @ w
                cand.append((float(ef.mean()), e, ef, self.paired_p(cur - ef)))
            if not cand:
                break
            if self.rule == "bonferroni":
                crit = self.alpha / len(cand)
                ok = [c for c in cand if c[3] < crit]
                if not ok:
                    break
                m, e, ef, tt = min(ok, key=lambda c: c[0])
                if e.supersedes:
                    # nested look-alikes (a spring contains an offset): keep the smaller effect
                    # when it qualifies on its own and the larger is not significantly better
                    for c in ok:
                        if c[1].index == e.index and c[1].name in e.supersedes and \
                                self.paired_p(c[2] - ef) >= crit:
                            m, e, ef, tt = c
                            break
                if isinstance(e, fx.Payload):
                    # a mass on joint i+1's axis loads the joints exactly as the same mass on
                    # link i does: among payloads the data cannot tell apart (held-out error
                    # within one standard error of the best one's gain: the classic 1-SE rule),
                    # report the most distal, where loads are attached
                    se = np.std(cur - ef, ddof=1) / np.sqrt(K)
                    for c in sorted(ok, key=lambda c: -c[1].index):
                        if isinstance(c[1], fx.Payload) and c[1].index > e.index and c[0] - m <= se:
                            m, e, ef, tt = c
                            break
            else:
                m, e, ef, tt = min(cand, key=lambda c: c[0])
            chosen = chosen + [e]
            tstats.append(tt)
            path.append(PathStep(list(chosen), m, ef))
            if self.rule != "bonferroni":
                if m < best:
                    best, stale = m, 0
                else:
                    stale += 1
                    if stale >= 2:  # two steps without improvement: the path has turned
                        break
        if self.rule == "bonferroni":
            chosen_step = len(path) - 1
        else:
            ib = int(np.argmin([p.cv_mean for p in path]))
            chosen_step = ib
            for i in range(ib + 1):
                d = path[i].cv_folds - path[ib].cv_folds
                se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
                if d.mean() <= self.se_rule * se:
                    chosen_step = i
                    break
        self.path_ = path
        self.chosen_step_ = chosen_step
        self.selected_ = list(path[chosen_step].effects)
        self.t_stats_ = tstats[:chosen_step]
        return self


def lowpass_for(t: np.ndarray, dq: np.ndarray, *, power: float = 0.999, factor: float = 2.0):
    """Zero-phase Butterworth low-pass matched to the motion: cutoff ``factor`` times the frequency
    below which ``power`` of the velocity's *signal* power lies (the white-noise floor, the median
    power of the top half of the band, is subtracted first), capped below Nyquist.

    Filtering the torque residual and every regressor column with the same linear filter keeps
    the linear-in-parameters relation while removing the wide-band noise that differentiated
    accelerations and torque sensors add (errors in the regressors would bias the fit).
    Returns (filter function acting on axis 0, cutoff in Hz or None when no filtering applies).
    """
    from scipy.signal import butter, sosfiltfilt

    T = len(t)
    dt = float(np.median(np.diff(t)))
    fs = 1.0 / dt
    x = dq - dq.mean(0)
    # a Hann taper: without it the jump between the log's ends leaks a 1/f^2 tail over the band
    x = x * np.hanning(T)[:, None]
    P = np.abs(np.fft.rfft(x, axis=0)) ** 2
    f = np.fft.rfftfreq(T, dt)
    floor = np.median(P[f > 0.25 * fs], axis=0) if (f > 0.25 * fs).sum() > 5 else np.zeros(P.shape[1])
    P = np.clip(P - floor, 0, None)
    P = (P / np.maximum(P.sum(0), 1e-300)).sum(1)  # every joint counts alike
    cum = np.cumsum(P) / max(P.sum(), 1e-300)
    f_p = float(f[min(np.searchsorted(cum, power), len(f) - 1)])
    f_c = factor * max(f_p, 2.0 / (T * dt))
    if f_c >= 0.4 * fs or T < 60:
        return (lambda a: a), None
    sos = butter(4, f_c / (0.5 * fs), output="sos")
    # long even (mirror) padding of two cutoff periods: odd padding would pin the ends to a single
    # noisy sample; any padding is linear, so residual and columns stay consistent
    pad = int(min(T - 1, round(2.0 * fs / f_c)))
    return (lambda a: sosfiltfilt(sos, a, axis=0, padtype="even", padlen=pad)), f_c


def _joint_weights(e: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(n,) inverse residual variance per joint over valid samples (a GLS weighting)."""
    sig2 = (M * e ** 2).sum(0) / np.maximum(M.sum(0), 1)
    return 1.0 / (sig2 + 1e-12 * (sig2.max() + 1e-300))


def _folds(T: int, K: int, t: np.ndarray, f_c: float | None):
    from ..data.folds import time_block_folds

    # gap: the filter's memory (about 2 periods of the cutoff) plus the differentiator window
    gap_s = 0.05 + (2.0 / f_c if f_c else 0.0)
    gap = int(max(0, round(gap_s / max(float(np.median(np.diff(t))), 1e-9))))
    return time_block_folds(T, K, gap=min(gap, T // (4 * K)))


def valid_mask(dq: np.ndarray, v_s: np.ndarray, t: np.ndarray, f_c: float | None, *, factor: float = 1.0) -> np.ndarray:
    """(T, n) 1.0 where joint j's equation carries information a state function can fit, else 0.

    A joint whose velocity is within ``factor * v_s`` of zero (``v_s`` = 3 velocity-noise
    standard deviations) may be stuck: static friction then takes whatever value in
    [-tau_c, tau_c] balances the other torques, set-valued rather than a function of (q, dq, ddq).
    Those samples would otherwise be soaked up by look-alike effects (spring, armature, offset)
    or flagged as pushes. The mask is widened by the low-pass filter's memory (half a cutoff
    period each side), since filtering spreads those values over neighbouring samples.
    """
    T, n = dq.shape
    rest = np.abs(dq) < factor * np.asarray(v_s)[None, :]
    if f_c:
        dt = float(np.median(np.diff(t)))
        h = int(round(0.5 / (f_c * dt)))
        if h > 0:
            from scipy.ndimage import maximum_filter1d

            rest = maximum_filter1d(rest.astype(np.uint8), size=2 * h + 1, axis=0) > 0
    M = (~rest).astype(np.float64)
    # a joint that is (almost) never moving keeps its samples: nothing would be left to fit
    few = M.sum(0) < 0.1 * T
    M[:, few] = 1.0
    return M


# --------------------------------------------------------------------------------------------
# Mode switches: a two-state switching regression on what the selected physics leaves
# --------------------------------------------------------------------------------------------

def _hmm_filter(ll: np.ndarray, stay: float, smooth: bool = True):
    """Two-state forward(-backward) pass. ``ll`` (T, 2) log-likelihoods. Returns (posterior or
    filtered state probabilities (T, 2), one-step predictive probabilities (T, 2))."""
    T = ll.shape[0]
    P = np.array([[stay, 1 - stay], [1 - stay, stay]])
    alpha = np.empty((T, 2))
    pred = np.empty((T, 2))
    p = np.array([0.5, 0.5])
    lik = np.exp(ll - ll.max(1, keepdims=True))
    for i in range(T):
        pred[i] = p
        a = p * lik[i]
        a /= a.sum()
        alpha[i] = a
        p = a @ P
    if not smooth:
        return alpha, pred
    post = np.empty((T, 2))
    post[-1] = alpha[-1]
    for i in range(T - 2, -1, -1):
        b = post[i + 1] / np.maximum(pred[i + 1], 1e-300)
        g = alpha[i] * (P @ b)
        post[i] = g / g.sum()
    return post, pred


def _fit_switching(C: np.ndarray, e: np.ndarray, w: np.ndarray, V: np.ndarray, n_iter: int = 25):
    """EM for e_t = C_t theta_{s_t} + noise, s_t a sticky two-state Markov chain.

    ``C`` (T, n, p) columns, ``e`` (T, n) residual, ``w`` (n,) inverse noise variances, ``V``
    (T, n) sample weights. Returns (theta (2, p), stay probability, posterior (T, 2)). Started
    from a split of the time axis at the median of windowed single-state fits' first coefficient.
    """
    T, n, p = C.shape
    Wv = V * w[None, :]
    Gt = np.einsum("tj,tjp,tjq->tpq", Wv, C, C).reshape(T, p * p)
    ct = np.einsum("tj,tjp,tj->tp", Wv, C, e)

    def wls(g):
        return FoldGrams._solve((g @ Gt).reshape(p, p), g @ ct)

    # start: windowed fits of the first coefficient (mass), split at their median
    nw = 8
    edges = np.linspace(0, T, nw + 1).astype(int)
    loc = np.array([wls(((np.arange(T) >= a) & (np.arange(T) < b)).astype(float))[0] for a, b in zip(edges[:-1], edges[1:])])
    hi = np.zeros(T)
    for (a, b), v in zip(zip(edges[:-1], edges[1:]), loc):
        hi[a:b] = float(v > np.median(loc))
    post = np.stack([1 - hi, hi], 1)
    stay = 1 - 1.0 / max(T / 4, 2)
    th = np.zeros((2, p))
    for _ in range(n_iter):
        th = np.array([wls(post[:, k]) for k in range(2)])
        ll = np.stack([-0.5 * (Wv * (e - C @ th[k]) ** 2).sum(1) for k in range(2)], 1)
        post, _ = _hmm_filter(ll, stay)
        # expected switches from consecutive posteriors (a cheap, slightly low estimate)
        sw = np.abs(np.diff(post[:, 1])).sum()
        stay = float(np.clip(1 - (sw + 1) / T, 0.5, 1 - 1.0 / T))
    return th, stay, post


def mode_switch_test(C: np.ndarray, e: np.ndarray, w: np.ndarray, V: np.ndarray, folds, lag: int = 1) -> dict:
    """Held-out comparison of one versus two modes for the effect with columns ``C``.

    For each time-block fold both models are fitted on the training part; on the test block the
    two-mode model predicts each sample with its state probabilities given the test block's
    samples at least ``lag`` steps earlier (HMM ``lag``-step predictive), so the comparison stays
    out of sample. ``lag`` should span the residual's correlation time (the low-pass filter's
    memory): with a one-step predictive any latent-state model wins on a smooth residual just
    by tracking its autocorrelation.
    Returns {"d": (K,) held-out weighted SSE one-mode minus two-mode, "p": one-sided signed-rank
    p-value, and the all-data fit: "theta" (2, p), "post" (T, 2), "stay"}.
    """
    T, n, p = C.shape
    Wv = V * w[None, :]
    d = []
    for tr, te in folds:
        Ctr, etr, Wtr = C[tr], e[tr], Wv[tr]
        th1 = FoldGrams._solve(np.einsum("tj,tjp,tjq->pq", Wtr, Ctr, Ctr), np.einsum("tj,tjp,tj->p", Wtr, Ctr, etr))
        err1 = (Wv[te] * (e[te] - C[te] @ th1) ** 2).sum()
        th2, stay, _ = _fit_switching(C[tr], e[tr], w, V[tr], n_iter=15)
        ll = np.stack([-0.5 * (Wv[te] * (e[te] - C[te] @ th2[k]) ** 2).sum(1) for k in range(2)], 1)
        alpha, _ = _hmm_filter(ll, stay, smooth=False)
        Pl = np.linalg.matrix_power(np.array([[stay, 1 - stay], [1 - stay, stay]]), max(lag, 1))
        pred = np.full((len(te), 2), 0.5)
        if len(te) > lag:
            pred[lag:] = alpha[:-lag] @ Pl
        mu = pred[:, 0, None] * (C[te] @ th2[0]) + pred[:, 1, None] * (C[te] @ th2[1])
        err2 = (Wv[te] * (e[te] - mu) ** 2).sum()
        d.append(err1 - err2)
    d = np.array(d)
    th, stay, post = _fit_switching(C, e, w, V)
    return {"d": d, "p": ForwardCVSelector.paired_p(d), "theta": th, "post": post, "stay": stay}


# --------------------------------------------------------------------------------------------
# Separation of pushes
# --------------------------------------------------------------------------------------------

def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def scan_disturbances(e: np.ndarray, t: np.ndarray, *, f_c: float | None = None, alpha: float = 0.01,
                      valid: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Flag samples where the (low-passed) residual ``e`` (T, n) is too large to be noise.

    Each joint is scaled by a robust (MAD) noise level; the sum of squares over joints is
    chi-square(n) under "no push" (filtering makes the residual close to Gaussian). The threshold
    is the chi-square quantile at the Bonferroni level ``alpha / T_eff``, with ``T_eff`` the
    number of independent samples the filter leaves (``2 f_c`` per second). Flagged stretches are
    widened to where the statistic returns to its 99% noise band. Returns mask (T,) and summary.
    """
    from scipy.stats import chi2

    T, n = e.shape
    V = np.ones((T, n), bool) if valid is None else np.asarray(valid, bool)
    med = np.array([np.median(e[V[:, j], j]) if V[:, j].any() else 0.0 for j in range(n)])
    s = np.array([1.4826 * np.median(np.abs(e[V[:, j], j] - med[j])) if V[:, j].any() else 1.0
                  for j in range(n)]) + 1e-300
    z2 = ((((e - med) / s) ** 2) * V).sum(1)
    df = V.sum(1)
    dur = float(t[-1] - t[0]) if T > 1 else 1.0
    T_eff = max(1.0, min(T, 2.0 * f_c * dur)) if f_c else float(T)
    thr_df = np.array([chi2.ppf(1 - alpha / T_eff, d) if d > 0 else np.inf for d in range(n + 1)])
    thr = float(thr_df[n])
    core = z2 > thr_df[df]
    z2 = z2 * thr / thr_df[np.maximum(df, 1)]  # on the full-df scale for the widening and peaks
    if f_c:
        # within a cutoff period of the ends the zero-phase filter runs on padding, not data
        edge = (t - t[0] < 1.0 / f_c) | (t[-1] - t < 1.0 / f_c)
        core &= ~edge
    mask = core.copy()
    if core.any():
        band = z2 > chi2.ppf(0.99, n)
        for a, b in _runs(band):
            if core[a:b].any():
                mask[a:b] = True
        if f_c:
            # after a zero-phase low-pass at f_c any real event, however brief, stays above the
            # noise band for at least the filter's resolution (~ half a cutoff period); a shorter
            # excursion is a marginal crossing of heavy-tailed misfit, not a resolved push
            for a, b in _runs(mask):
                if t[b - 1] - t[a] < 0.5 / f_c:
                    mask[a:b] = False
    spans = [(float(t[a]), float(t[b - 1])) for a, b in _runs(mask)]
    peaks = [float(z2[a:b].max() / thr) for a, b in _runs(mask)]
    return mask, {"threshold": thr, "peaks": peaks, "effective_samples": T_eff, "spans": spans}


def state_explained(e: np.ndarray, mask: np.ndarray, q, dq, ddq, *, k: int = 15) -> np.ndarray:
    """Per flagged span, the fraction of its residual energy that the joint's own state explains.

    Each joint's residual in a span is predicted from the unflagged samples nearest in that
    joint's (q, dq, ddq) (k-nearest neighbours on standardised values). A model misfit (friction
    at velocity reversals, say) repeats wherever the state repeats, so it is explained; an
    external push is not. Returns one fraction per span of ``mask`` (order of ``_runs``).
    """
    from sklearn.neighbors import KNeighborsRegressor

    T, n = e.shape
    s2 = e[~mask].var(0) + 1e-300
    pred = np.zeros_like(e)
    free = np.flatnonzero(~mask)
    flagged = np.flatnonzero(mask)
    if len(free) < 2 * k or not len(flagged):
        return np.zeros(len(_runs(mask)))
    for j in range(n):
        X = np.stack([q[:, j], dq[:, j], ddq[:, j]], 1)
        X = (X - X[free].mean(0)) / (X[free].std(0) + 1e-12)
        knn = KNeighborsRegressor(n_neighbors=k).fit(X[free], e[free, j])
        pred[flagged, j] = knn.predict(X[flagged])
    out = []
    for a, b in _runs(mask):
        tot = ((e[a:b] ** 2) / s2).sum()
        left = (((e[a:b] - pred[a:b]) ** 2) / s2).sum()
        out.append(float(1 - left / max(tot, 1e-300)))
    return np.array(out)


def em_separate(resid: np.ndarray, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, t: np.ndarray, *,
                n_modes: int = 1, max_points: int = 500, seed: int = 0, **sem_kw) -> dict:
    """The multimodal learner's separation: ``mmgp.em.MultimodalSEM`` (disturbance mode on) on
    the nominal residual ``resid = tau - tau_rbd`` (T, n), N*m, with GP inputs
    ``[q, dq, ddq, tanh(dq / v_s)]`` (v_s as in training, ``mmgp.model.friction_velocity_scale``:
    without the smooth sign a GP cannot follow the friction jump at velocity reversals and would
    take it for pushes), on at most ``max_points`` samples evenly spaced in time (``t`` in s is
    passed, so likelihoods leave a window out and a long push is not explained by itself).

    Returns {"p_disturbed": (T,) posterior push probability interpolated in time to every sample,
    "mode": (T,) int mode labels (nearest subsample), "sigma_d": (n,), "n_points", "seconds",
    "n_sweeps"}. ``sem_kw`` overrides MultimodalSEM settings.
    """
    from ..models.sem import MultimodalSEM
    from ..models.features import friction_velocity_scale

    T, n = resid.shape
    idx = np.unique(np.linspace(0, T - 1, min(T, max_points)).round().astype(int))
    vs = friction_velocity_scale(dq)
    X = np.concatenate([q, dq, ddq, np.tanh(dq / vs)], axis=1)[idx]
    # a small learner: hyperparameter refits are >60% of its cost, and the labels settle in a few
    # sweeps (about 10 s on a 7-DOF log on one core)
    kw = dict(max_support=min(250, len(idx)), fit_points=min(200, len(idx)), fit_iter=15, max_sweeps=8,
              min_sweeps=4, average_last=3, final_support=min(250, len(idx)))
    kw.update(sem_kw)
    t0 = time.perf_counter()
    sem = MultimodalSEM(n_modes=n_modes, disturbance=True, seed=seed, **kw).fit(X, resid[idx], t=t[idx])
    p = np.interp(t, t[idx], sem.p_disturbed_)
    near = np.clip(np.searchsorted(t[idx], t), 0, len(idx) - 1)
    return {"p_disturbed": p, "mode": sem.labels_[near].astype(int), "sigma_d": np.asarray(sem.sigma_d_),
            "n_points": int(len(idx)), "seconds": time.perf_counter() - t0, "n_sweeps": int(sem.n_sweeps_)}


_SEPARATION_METHOD = {
    "auto": "robust chi-square scan, each span confirmed by MultimodalSEM (p_disturbed > 0.5 in it)",
    "scan+em": "robust chi-square scan, each span confirmed by MultimodalSEM (p_disturbed > 0.5 in it)",
    "scan|em": "robust chi-square scan or MultimodalSEM (union)",
    "scan": "robust chi-square scan",
    "em": "MultimodalSEM (p_disturbed > 0.5)",
    "none": "none",
}


def _combine(scan: np.ndarray, p_disturbed: np.ndarray, how: str, peaks: Sequence[float] | None = None,
             strong: float = np.inf) -> tuple[np.ndarray, dict]:
    """Join the scan's flags ``scan`` (T,) bool with the learner's ``p_disturbed`` (T,).

    "gate": a scanned span stays if its scan statistic peaks at ``strong`` times the threshold or
    more (``peaks``: one per span of ``scan``, in units of the threshold), or if the learner,
    which explains the state-dependent part of the residual by a GP (friction, missing inertia)
    rather than by the effect library, also calls some of it disturbed. Strong spans need no
    confirmation: the learner's GP can absorb part of a long push and miss it (benchmark: a
    1.2 s push at 15x the threshold). "union": either flags a sample.
    """
    em = np.asarray(p_disturbed) > 0.5
    if how == "union":
        out = scan | em
        return out, {"spans_added_by_em": len(_runs(out)) - len(_runs(scan))}
    out = scan.copy()
    dropped = 0
    runs = _runs(scan)
    pk = np.zeros(len(runs)) if peaks is None else np.asarray(peaks, dtype=np.float64)
    for (a, b), peak in zip(runs, pk):
        if peak < strong and not em[a:b].any():
            out[a:b] = False
            dropped += 1
    return out, {"spans_dropped_by_em": dropped}


def _em_summary(em_info: dict) -> dict:
    return {"em_points": em_info["n_points"], "em_seconds": float(em_info["seconds"]),
            "em_sweeps": em_info["n_sweeps"], "em_flagged_fraction": float((em_info["p_disturbed"] > 0.5).mean()),
            "em_sigma_d": [float(x) for x in em_info["sigma_d"]]}


# --------------------------------------------------------------------------------------------
# The result
# --------------------------------------------------------------------------------------------

def _fmt_num(x: float, s: float | None = None) -> str:
    if s is None or not np.isfinite(s):
        return f"{x:.3g}"
    return f"{x:.3g} +/- {s:.2g}"


@dataclass
class DiagnosisResult:
    """Findings (CONTRACT section 2), held-out fit per stage, residual locations.

    ``findings``: list of dicts with ``effect``, ``joint`` or ``link``, ``params``, ``evidence``,
    ``explanation``; ``fit``: {stage: {"nmse": {joint: value}, "mean_nmse": value}};
    ``location``: per joint, where the nominal residual concentrates.
    """

    findings: list
    fit: dict
    location: dict
    joint_names: list
    info: dict = field(default_factory=dict)
    _plot_data: dict | None = field(default=None, repr=False)
    #: per analysed sample: {"t", "mode" (int), "disturbed" (0/1)} when modes or pushes were found
    labels: dict | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {"findings": self.findings, "fit": self.fit, "location": self.location, "info": self.info}

    def to_json(self, indent: int = 2) -> str:
        return json.dumps(jsonable(self.to_dict()), indent=indent)

    def report_markdown(self) -> str:
        lines = ["# Sim-vs-real diagnosis", ""]
        effects = [f for f in self.findings if f["effect"] not in ("external_disturbance", "mode_switch")]
        if not effects:
            lines.append("Nothing is missing: no candidate effect improves the held-out (time-block "
                         "cross-validated) error significantly over the nominal model.")
        else:
            lines.append("## Findings")
            lines.append("")
            for f in self.findings:
                lines.append(f"- {f['explanation']}")
        other = [f for f in self.findings if f["effect"] in ("external_disturbance", "mode_switch")]
        if other and not effects:
            lines.append("")
            for f in other:
                lines.append(f"- {f['explanation']}")
        lines += ["", "## Held-out normalised MSE per joint (time-block cross-validation)", "",
                  "| joint | " + " | ".join(STAGES) + " |", "|---|" + "---|" * len(STAGES)]
        for jn in self.joint_names:
            row = [f"{self.fit[s]['nmse'].get(jn, float('nan')):.4g}" if s in self.fit else "-" for s in STAGES]
            lines.append(f"| {jn} | " + " | ".join(row) + " |")
        lines += ["", "## Where the nominal residual concentrates", ""]
        for jn, loc in self.location.items():
            lines.append(f"- {jn}: residual RMS {loc['rms']:.3g} N*m ({100 * loc['fraction_of_torque_rms']:.1f}% "
                         f"of the torque RMS); largest in {loc['where']} ({loc['ratio']:.2f}x the overall RMS)")
        lines += ["", "## Method", "",
                  f"Candidates: {self.info.get('n_candidates')} effects. Forward selection on {self.info.get('n_folds')} "
                  "time blocks: an effect is added while its paired held-out gain is significant (signed-rank "
                  "test, Bonferroni over the candidates of each step); parameters by "
                  "non-negative least squares on all undisturbed samples, standard deviations by block "
                  "jackknife over the folds. Coulomb friction uses tanh(dq/v_s), v_s = "
                  f"{self.info.get('sign_noise_factor')} x velocity noise: "
                  + ", ".join(f"{v:.3g}" for v in self.info.get("v_s", [])) + " rad/s.", ""]
        if self.info.get("plots"):
            lines += ["## Plots", ""] + [f"![{p}]({p})" for p in self.info["plots"]]
        return "\n".join(lines) + "\n"

    def write(self, out_dir) -> Path:
        """Write ``findings.json``, ``report.md``, residual plots and (when modes or pushes were
        found) ``labels.parquet`` (t, mode, disturbed per analysed sample) into ``out_dir``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        if self._plot_data is not None:
            self.info["plots"] = _plot(self._plot_data, out)
        (out / "findings.json").write_text(self.to_json())
        if self.labels is not None:
            import pandas as pd

            from ..data.outputs import write_table

            write_table(out / "labels.parquet", pd.DataFrame(self.labels))
        (out / "report.md").write_text(self.report_markdown())
        return out


def _plot(d: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    T = d["q"].shape[0]
    idx = np.linspace(0, T - 1, min(T, 3000)).astype(int)
    for j, jn in enumerate(d["joint_names"]):
        fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharey="row")
        for row, (res, lab) in enumerate(((d["r_before"], "nominal"), (d["r_after"], "with physics"))):
            for col, (x, xl) in enumerate(((d["dq"], "dq [rad/s]"), (d["q"], "q [rad]"), (d["tau"], "tau [N*m]"))):
                ax = axes[row, col]
                ax.plot(x[idx, j], res[idx, j], ".", ms=1.5, alpha=0.5, rasterized=True)
                ax.axhline(0, color="k", lw=0.5)
                ax.set_xlabel(xl)
                if col == 0:
                    ax.set_ylabel(f"residual, {lab} [N*m]")
        fig.suptitle(f"{jn}: residual before / after the found effects")
        fig.tight_layout()
        name = f"residual_{j}_{jn}.png".replace("/", "_")
        fig.savefig(out / name, dpi=80)
        plt.close(fig)
        names.append(name)
    return names


# --------------------------------------------------------------------------------------------
# Locate
# --------------------------------------------------------------------------------------------

def locate(r: np.ndarray, q, dq, ddq, tau_rbd, t, v_s, joint_names) -> dict:
    """Where the residual ``r`` (T, n) concentrates, per joint: the region (of five candidates:
    near-zero velocity, high load, a position quintile, high acceleration, a time fifth) whose
    residual RMS is largest relative to the joint's overall residual RMS."""
    out = {}
    T = r.shape[0]
    for j, jn in enumerate(joint_names):
        rj = r[:, j]
        rms = float(np.sqrt(np.mean(rj ** 2))) + 1e-300
        regions = {}
        slow = np.abs(dq[:, j]) < 2 * v_s[j]
        if 20 <= slow.sum() <= T - 20:
            regions["near zero velocity (|dq| < 2 v_s)"] = slow
        hi = np.abs(tau_rbd[:, j]) > np.quantile(np.abs(tau_rbd[:, j]), 0.8)
        regions["high load (top 20% |tau_rbd|)"] = hi
        acc = np.abs(ddq[:, j]) > np.quantile(np.abs(ddq[:, j]), 0.8)
        regions["high acceleration (top 20% |ddq|)"] = acc
        qe = np.quantile(q[:, j], [0, .2, .4, .6, .8, 1])
        for a, b in zip(qe[:-1], qe[1:]):
            regions[f"q in [{a:.2f}, {b:.2f}] rad"] = (q[:, j] >= a) & (q[:, j] <= b)
        te = np.linspace(0, T, 6).astype(int)
        for a, b in zip(te[:-1], te[1:]):
            m = np.zeros(T, bool)
            m[a:b] = True
            regions[f"t in [{t[a]:.1f}, {t[b - 1]:.1f}] s"] = m
        ratios = {k: float(np.sqrt(np.mean(rj[m] ** 2)) / rms) for k, m in regions.items() if m.any()}
        where = max(ratios, key=ratios.get)
        out[jn] = {"rms": rms, "fraction_of_torque_rms": rms / (float(np.sqrt(np.mean(tau_rbd[:, j] ** 2))) + 1e-12),
                   "where": where, "ratio": ratios[where], "regions": ratios}
    return out


# --------------------------------------------------------------------------------------------
# The diagnosis
# --------------------------------------------------------------------------------------------

def _nnls_gram(G: np.ndarray, c: np.ndarray, nonneg: np.ndarray) -> np.ndarray:
    """min th' G th - 2 c' th with th[nonneg] >= 0, via a Cholesky factor and lsq_linear."""
    from scipy.optimize import lsq_linear

    P = len(c)
    if P == 0:
        return np.zeros(0)
    reg = 1e-10 * max(np.diag(G).max(), 1e-300)
    L = np.linalg.cholesky(G + reg * np.eye(P))
    b = np.linalg.solve(L, c)
    lo = np.where(nonneg, 0.0, -np.inf)
    return lsq_linear(L.T, b, bounds=(lo, np.full(P, np.inf)), method="bvls").x


def _joint_label(jn: str, j: int) -> str:
    return f"joint {j} ({jn})"


def diagnose(log: RobotLog, robot, *, config: DiagnoseConfig | dict | None = None,
             out_dir=None, labels_disturbed: np.ndarray | None = None) -> DiagnosisResult:
    """Diagnose what the nominal model of ``robot`` misses in ``log``.

    ``log``: RobotLog (dq/ddq estimated when absent); ``robot``: mmgp RobotModel or a
    pinocchio.Model with the log's joints. ``labels_disturbed`` (T,) optional known push flags
    (skip the separation). Returns a :class:`DiagnosisResult`; with ``out_dir`` also writes it.
    """
    from threadpoolctl import threadpool_limits

    # the linear algebra here is many small products; multi-threaded BLAS only adds contention
    # (on a busy 2-core machine a 21000 x 90 Gram took 1-3 s threaded and 0.03 s on one thread)
    with threadpool_limits(limits=1, user_api="blas"):
        return _diagnose(log, robot, config=config, out_dir=out_dir, labels_disturbed=labels_disturbed)


def _diagnose(log: RobotLog, robot, *, config=None, out_dir=None, labels_disturbed=None) -> DiagnosisResult:
    cfg = DiagnoseConfig.from_dict(config)
    t0 = time.perf_counter()
    from ..data.differentiation import complete_derivatives

    if log.dq is None or log.ddq is None:
        log = complete_derivatives(log)
    if log.dq_estimated or log.ddq_estimated:
        # polynomial differentiators are poor within a window of the ends; the parallel filter
        # would spread those errors over a cutoff period, so the ends are dropped first
        dt0 = float(np.median(np.diff(log.t)))
        cut = int(np.ceil(0.06 / dt0)) + 2
        if log.n_samples > 10 * cut:
            keep = np.arange(cut, log.n_samples - cut)
            log = log.subset(keep)
            if labels_disturbed is not None:
                labels_disturbed = np.asarray(labels_disturbed)[keep]
    T_full = log.n_samples
    if T_full > cfg.max_samples:
        # derivatives were taken at the full rate; thinning only bounds the runtime
        keep = np.unique(np.linspace(0, T_full - 1, cfg.max_samples).round().astype(int))
        log = log.subset(keep)
        if labels_disturbed is not None:
            labels_disturbed = np.asarray(labels_disturbed)[keep]
    q, dq, ddq, tau, t = log.q, log.dq, log.ddq, log.tau, log.t
    T, n = q.shape
    names = list(getattr(robot, "joint_names", None) or log.joint_names or
                 [str(fx._pin_model(robot).names[j]) for j in range(1, n + 1)])
    vs = fx.smooth_sign_scale(dq, k=cfg.sign_noise_factor)
    ctx = fx.build_context(robot, q, dq, ddq, v_s=vs, joint_names=names)
    timings = {"context_s": time.perf_counter() - t0}
    r_raw = tau - ctx.tau_rbd
    lp, f_c = lowpass_for(t, dq) if cfg.filter else ((lambda x: x), None)
    r = lp(r_raw)

    library = fx.effect_library(ctx, effects=cfg.effects, payload_links=cfg.payload_links)
    pm = fx._pin_model(robot)
    reach = float(sum(np.linalg.norm(pm.jointPlacements[j].translation) for j in range(1, pm.njoints)))
    reach = reach if reach > 0 else None
    payloads = [e for e in library if isinstance(e, fx.Payload)]
    M = valid_mask(dq, vs, t, f_c, factor=cfg.rest_factor)


    def atoms():
        keys, A = fx.build_atoms(library, ctx)
        return keys, lp(A)

    # full-library fit: noise weights, payload com guesses, and the whitened residual for the scan
    def full_fit(use, iters: int = 10, redescend: int = 5):
        """Robust M-estimate of the whole library by IRLS: Huber weights (knee at 1.345 robust
        sigmas per joint) to convergence, then ``redescend`` Tukey-bisquare steps (4.685 sigmas)
        from there. Pushes get weight zero, so they stand out in the residual instead of dragging
        the fit (least squares spreads a push over every column; Huber still lets a long push
        outweigh a small effect). The last weights go to ``huber["h"]`` (T, n)."""
        Au, ru, Mu = A[use], r[use], M[use]

        def solve(h):
            sw = np.sqrt(h)
            Aw = (Au * sw[:, :, None]).reshape(-1, Au.shape[2])
            G = Aw.T @ Aw
            return FoldGrams._solve(G + 1e-8 * np.diag(np.diag(G)), Aw.T @ (ru * sw).reshape(-1))

        h = Mu.copy()
        th = solve(h)
        for phase, n_it in (("huber", iters), ("tukey", redescend)):
            for _ in range(n_it):
                e = ru - Au @ th
                sc = np.array([1.4826 * np.median(np.abs(e[Mu[:, j] > 0, j])) if (Mu[:, j] > 0).any() else 1.0
                               for j in range(e.shape[1])]) + 1e-300
                if phase == "huber":
                    h = Mu * np.minimum(1.0, 1.345 * sc / np.maximum(np.abs(e), 1e-300))
                else:
                    u = np.abs(e) / (4.685 * sc)
                    h = Mu * np.where(u < 1, (1 - u ** 2) ** 2, 0.0)
                th_new = solve(h)
                done = np.allclose(th_new, th, rtol=1e-4, atol=1e-12)
                th = th_new
                if done:
                    break
        huber["h"] = np.zeros_like(r)
        huber["h"][use] = h
        return th

    huber: dict = {"h": np.ones_like(r)}

    use = np.ones(T, bool)
    keys, A = atoms()
    th = full_fit(use)
    if payloads:
        for _ in range(2):
            for e in payloads:
                m = th[keys.index(("pl", e.index, 0))]
                h = np.array([th[keys.index(("pl", e.index, i))] for i in (1, 2, 3)])
                c = h / m if m > 0 else np.zeros(3)
                ctx.payload_com[e.index] = c if np.linalg.norm(c) < 1.0 else np.zeros(3)
            keys, A = atoms()
            th = full_fit(use)

    # separate pushes
    sep_info: dict = {"method": "labels" if labels_disturbed is not None else _SEPARATION_METHOD.get(cfg.separate, cfg.separate)}
    em_info = None
    em_cache: dict = {}

    def get_em(n_modes: int | None = None) -> dict:
        k = cfg.em_modes if n_modes is None else n_modes
        if k not in em_cache:
            em_cache[k] = em_separate(r_raw, q, dq, ddq, t, n_modes=k, max_points=cfg.em_points, seed=cfg.seed)
            sep_info.update(_em_summary(em_cache[k]), em_modes=k)
        em_cache["res"] = em_cache[k]
        return em_cache[k]

    if labels_disturbed is not None:
        disturbed = np.asarray(labels_disturbed) == 1
    elif cfg.separate == "none":
        disturbed = np.zeros(T, bool)
    elif cfg.separate == "em":
        # the learner alone: its flags, at its own (thinned) resolution
        em_info = get_em()
        disturbed = em_info["p_disturbed"] > 0.5
        sep_info["spans"] = [(float(t[a]), float(t[b - 1])) for a, b in _runs(disturbed)]
        if disturbed.any():
            th = full_fit(~disturbed)
    else:
        # physics first, pushes from what it leaves: select effects on the Huber-weighted data
        # (pushes carry small weights there), then scan the residual of the *selected* model.
        # Scanning the full library's residual instead would see an over-fitted, too-quiet
        # residual wherever the log has few independent samples (slow trajectories).
        folds0 = _folds(T, cfg.n_folds, t, f_c)
        w0 = _joint_weights(r - A @ th, M)
        g0 = FoldGrams(A, r, np.ones(T, bool), folds0, W=M * huber["h"])
        sel0 = ForwardCVSelector(se_rule=cfg.se_rule, max_steps=cfg.max_steps, rule=cfg.rule,
                                 alpha=cfg.alpha, reach=reach).fit(library, keys, g0, w0)
        S0 = ForwardCVSelector._atoms(sel0.selected_, {a: i for i, a in enumerate(keys)})
        e0 = r - (A[:, :, S0] @ g0.fit(S0, w0) if S0 else 0.0)
        disturbed, sep_info_scan = scan_disturbances(e0, t, f_c=f_c, valid=M > 0, alpha=cfg.push_alpha)
        sep_info.update(sep_info_scan)
        if cfg.separate == "scan|em" or (cfg.separate in ("auto", "scan+em") and disturbed.any()):
            # as a gate the learner can only drop spans: with none scanned it is not needed
            em_info = get_em()
            disturbed, comb = _combine(disturbed, em_info["p_disturbed"], "union" if cfg.separate == "scan|em" else "gate",
                                       peaks=sep_info_scan["peaks"], strong=cfg.em_gate_peak)
            sep_info.update(comb)
            sep_info["spans"] = [(float(t[a]), float(t[b - 1])) for a, b in _runs(disturbed)]
        if disturbed.any() and cfg.state_check:
            # keep only spans the state does not explain better than not (pushes, not misfit)
            frac = state_explained(e0, disturbed, q, dq, ddq)
            runs = _runs(disturbed)
            for (a, b), fr in zip(runs, frac):
                if fr > 0.5:
                    disturbed[a:b] = False
            sep_info["spans"] = [(float(t[a]), float(t[b - 1])) for a, b in _runs(disturbed)]
            sep_info["state_explained"] = [float(x) for x in frac]
        if disturbed.any():
            th = full_fit(~disturbed)
    use = ~disturbed
    if cfg.load_from_log:
        # the gears carry the motor torque (friction and all), which the nominal torque misses
        # by exactly the effects being looked for; low-passed, the logged torque is nearly
        # noise-free. Only now: before the pushes are known, the logged torque carries them too.
        ctx.tau_load = lp(tau)
        keys, A = atoms()
        th = full_fit(use)
    elif cfg.load_with_friction:
        # the motor torque the gears carry includes the friction itself; add the robust fit's
        # (non-negative) Coulomb and viscous estimate to the nominal torque. A state function,
        # unlike the logged torque, so no endogeneity; where friction dominates, |load| * sign
        # is collinear with the Coulomb column and load dependence brings no held-out gain.
        kk = {a: i for i, a in enumerate(keys)}
        fr = np.zeros_like(tau)
        for j in range(n):
            if ("sign", j) in kk:
                fr[:, j] += max(th[kk[("sign", j)]], 0.0) * np.tanh(dq[:, j] / vs[j])
            if ("dq", j) in kk:
                fr[:, j] += max(th[kk[("dq", j)]], 0.0) * dq[:, j]
        ctx.tau_load = ctx.tau_rbd + fr
        keys, A = atoms()
        th = full_fit(use)
    timings["separate_s"] = time.perf_counter() - t0 - timings["context_s"]

    w = _joint_weights((r - A @ th)[use], M[use])
    K = cfg.n_folds
    folds = _folds(T, K, t, f_c)
    grams = FoldGrams(A, r, use, folds, W=M)
    sel = ForwardCVSelector(se_rule=cfg.se_rule, max_steps=cfg.max_steps, rule=cfg.rule,
                            alpha=cfg.alpha, reach=reach).fit(library, keys, grams, w)
    chosen = sel.selected_
    timings["select_s"] = time.perf_counter() - t0 - sum(timings.values())

    # final fit with point-mass inertia of payloads re-estimated
    kidx = {a: i for i, a in enumerate(keys)}
    S = ForwardCVSelector._atoms(chosen, kidx)
    nonneg = np.array([any(keys[i] in e.nonneg for e in chosen) for i in S], bool)

    def final(S):
        Gw = np.einsum("j,jpq->pq", w, grams.Gall[:, S][:, :, S])
        cw = np.einsum("j,jp->p", w, grams.call[:, S])
        return _nnls_gram(Gw, cw, nonneg)

    thS = final(S)
    for _ in range(3):
        moved = False
        for e in chosen:
            if isinstance(e, fx.Payload):
                m = thS[S.index(kidx[("pl", e.index, 0)])]
                h = np.array([thS[S.index(kidx[("pl", e.index, i)])] for i in (1, 2, 3)])
                if m > 0:
                    ctx.payload_com[e.index] = h / m
                    moved = True
        if not moved:
            break
        keys, A = atoms()
        grams = FoldGrams(A, r, use, folds, W=M)
        thS = final(S)
    # block jackknife over the folds: honest under time-correlated residuals
    thK = np.array([_nnls_gram(np.einsum("j,jpq->pq", w, grams.Gtr[k][:, S][:, :, S]),
                               np.einsum("j,jp->p", w, grams.ctr[k][:, S]), nonneg) for k in range(K)]) if S else np.zeros((K, 0))
    dev = thK - thK.mean(0)
    cov_m = (K - 1) / K * dev.T @ dev
    coef = {keys[i]: float(v) for i, v in zip(S, thS)}
    cov = {(keys[a], keys[b]): float(cov_m[ia, ib]) for ia, a in enumerate(S) for ib, b in enumerate(S)}

    # per-joint held-out error of each stage
    def stage_err(Ssub):
        return grams.cv_errors(Ssub, w)  # (K, n)

    err_nom = stage_err([])
    err_phys = stage_err(S)
    findings = []
    reported = [e for e in chosen if not any(o is not e and o.index == e.index and e.name in o.supersedes and
                                             not isinstance(o, fx.Payload) for o in chosen)]
    for step, e in enumerate(chosen):
        if e not in reported:
            continue
        others = [o for o in chosen if o is not e]
        S_wo = ForwardCVSelector._atoms(others, kidx)
        # an effect nested in a reported one (Coulomb in load-dependent) goes with it
        S_wo = [i for i in S_wo if keys[i] not in e.atoms()]
        err_wo = stage_err(S_wo)
        per_joint = 1 - err_phys.sum(0) / np.maximum(err_wo.sum(0), 1e-300)
        d = (err_wo - err_phys) @ w
        z = float(d.mean() / (d.std(ddof=1) / np.sqrt(K) + 1e-300))
        aff = e.affected_joints(ctx)
        jmain = max(aff, key=lambda j: per_joint[j]) if aff else int(np.argmax(per_joint))
        p, s = e.params(coef, cov)
        ev = {"cv_error_reduction": float(per_joint[jmain]),
              "cv_error_reduction_joint": names[jmain],
              "cv_error_reduction_per_joint": {names[j]: float(per_joint[j]) for j in aff},
              "cv_improvement_in_se": z, "p_value_without_it": ForwardCVSelector.paired_p(d),
              "selection_step": chosen.index(e) + 1, "params_std": s,
              "criterion": (f"{K}-fold time-block CV, paired t-test at family-wise level {cfg.alpha:g}"
                            if cfg.rule == "bonferroni" else f"{K}-fold time-block CV, {cfg.se_rule:g}-SE rule")}
        f = {"effect": e.name, **e.where(ctx), "params": p, "evidence": ev}
        if isinstance(e, fx.Payload):
            f["params"] = {"link": ctx.link_names[e.index], **p}
        f["explanation"] = _explain(e, p, s, ev, names, jmain, ctx)
        findings.append(f)

    # third stage: GP on what physics leaves
    fit = {}
    denom = np.array([np.sum((tau[use, j] - tau[use, j].mean()) ** 2) / use.sum() for j in range(n)]) + 1e-300
    nte = grams.nte.sum(0)
    for stage, err in (("nominal", err_nom), ("with_physics", err_phys)):
        nm = err.sum(0) / nte / denom
        fit[stage] = {"nmse": {names[j]: float(nm[j]) for j in range(n)}, "mean_nmse": float(nm.mean())}
    if cfg.gp:
        from ..gp.exact import ExactGP

        X = np.concatenate([q, dq, ddq], axis=1)
        rng = np.random.default_rng(cfg.seed)
        sq = np.zeros(n)
        hyper = None
        for k, (tr, te) in enumerate(folds):
            tr, te = tr[use[tr]], te[use[te]]
            th_k = grams.fit(S, w, k) if S else np.zeros(0)
            res_tr = r[tr] - (A[tr][:, :, S] @ th_k if S else 0)
            res_te = r[te] - (A[te][:, :, S] @ th_k if S else 0)
            sub = np.sort(rng.choice(tr, min(cfg.gp_points, len(tr)), replace=False))
            pos = np.searchsorted(tr, sub)
            if hyper is None:
                # hyperparameters (23 numbers per joint) are optimised once, on the first fold's
                # training part; every fold then conditions on its own training points only. The
                # optimisation is >95% of the GP cost, so this keeps the stage to a few seconds.
                gp = ExactGP(max_fit_points=min(cfg.gp_hyper_points, len(sub)), max_iter=cfg.gp_iter,
                             coarse_fit_points=0, seed=cfg.seed).fit(X[sub], res_tr[pos])
                hyper = gp.hyper_
            else:
                gp = ExactGP(seed=cfg.seed).fit(X[sub], res_tr[pos], hyper=hyper, optimise=False)
            mu = gp.predict(X[te], return_std=False)
            sq += (M[te] * (res_te - mu) ** 2).sum(0)
        nm = sq / nte / denom
        fit["with_physics_and_gp"] = {"nmse": {names[j]: float(nm[j]) for j in range(n)}, "mean_nmse": float(nm.mean())}
        timings["gp_s"] = time.perf_counter() - t0 - sum(timings.values())
    fit["folds"] = K
    fit["samples_used"] = int(use.sum())
    fit["samples_excluded_as_disturbed"] = int((~use).sum())

    # mode switches: does a payload that changes over time (two sticky states) predict the
    # held-out residual better than one fixed payload?
    mode_info = None
    if cfg.modes and payloads:
        tm0 = time.perf_counter()
        e_all = r - (A[:, :, S] @ thS if S else 0.0)
        step = max(1, int(np.floor(1.0 / (4.0 * f_c * float(np.median(np.diff(t)))))) if f_c else 1)
        step = max(step, int(np.ceil(T / cfg.mode_max_samples)))
        idx = np.arange(0, T, step)
        folds_m = _folds(len(idx), cfg.mode_folds, t[idx], f_c)
        # predict a held-out sample from samples a filter memory (one cutoff period) earlier
        lag = int(np.ceil((1.0 / f_c) / (step * float(np.median(np.diff(t)))))) if f_c else 1
        # screen: two-mode fit of every link on all (thinned) samples; the held-out test then runs
        # for the two links with the largest in-sample gain (Bonferroni still counts every link)
        screen = []
        Wv = M[idx] * w[None, :]
        for e in payloads:
            cols = [kidx[("pl", e.index, i)] for i in range(4)]
            Cm, em = A[idx][:, :, cols], e_all[idx]
            th1 = FoldGrams._solve(np.einsum("tj,tjp,tjq->pq", Wv, Cm, Cm), np.einsum("tj,tjp,tj->p", Wv, Cm, em))
            th2, _, post = _fit_switching(Cm, em, w, M[idx], n_iter=10)
            mu = post[:, 0, None] * (Cm @ th2[0]) + post[:, 1, None] * (Cm @ th2[1])
            screen.append(((Wv * (em - Cm @ th1) ** 2).sum() - (Wv * (em - mu) ** 2).sum(), e, cols))
        tests = []
        for _, e, cols in sorted(screen, key=lambda x: -x[0])[:2]:
            tests.append((e, mode_switch_test(A[idx][:, :, cols], e_all[idx], w, M[idx], folds_m, lag=lag)))
        n_tested = len(payloads)
        def base_of(e):
            if e in chosen:
                return np.array([thS[S.index(kidx[("pl", e.index, i)])] for i in range(4)])
            return np.zeros(4)

        # physical: both modes' masses non-negative, centres of mass within reach
        def admissible(e, rm):
            for k in range(2):
                th_k = base_of(e) + rm["theta"][k]
                if th_k[0] < 0 or (th_k[0] > 0 and reach and np.linalg.norm(th_k[1:]) > reach * th_k[0]):
                    return False
            return True

        best = [(e, rm) for e, rm in tests if rm["p"] < cfg.alpha / n_tested and admissible(e, rm)]
        if best:
            e, rm = max(best, key=lambda x: x[1]["d"].mean())
            se = np.std(rm["d"], ddof=1) / np.sqrt(len(rm["d"]))
            for e2, rm2 in sorted(best, key=lambda x: -x[0].index):
                # as for payloads: of links the data cannot tell apart, the most distal
                if e2.index > e.index and rm["d"].mean() - rm2["d"].mean() <= se:
                    e, rm = e2, rm2
                    break
            post = rm["post"]
            lab_d = post.argmax(1)
            lab = lab_d[np.minimum(np.round(np.arange(T) / step).astype(int), len(idx) - 1)]
            base = base_of(e)
            per_mode = []
            for k in range(2):
                th_k = base + rm["theta"][k]
                mk = float(th_k[0])
                per_mode.append({"link": ctx.link_names[e.index], "mass": mk,
                                 "com": [float(x) for x in (th_k[1:] / mk if mk > 0 else np.full(3, np.nan))],
                                 "fraction": float((lab == k).mean())})
            order = np.argsort([pm["mass"] for pm in per_mode])
            per_mode = [per_mode[i] for i in order]
            lab = np.argsort(order)[lab]
            sw_t = [float(t[i]) for i in np.flatnonzero(np.diff(lab) != 0) + 1]
            mode_info = {"effect": e, "labels": lab, "test": rm}
            findings.append({
                "effect": "mode_switch", "joint": None,
                "params": {"n_modes": 2, "per_mode": per_mode, "switch_times_s": sw_t[:100]},
                "evidence": {"held_out_gain_per_fold": rm["d"].tolist(), "p_value": rm["p"],
                             "criterion": f"{cfg.mode_folds}-fold time-block CV of one vs two payload modes "
                                          "(HMM predictive from a filter memory earlier, held-out blocks), signed-rank test, "
                                          f"family-wise level {cfg.alpha:g} over {n_tested} links"},
                "explanation": (f"the dynamics switch between two modes ({len(sw_t)} switch(es)): a payload on "
                                f"{per_mode[0]['link']} of {per_mode[0]['mass']:.3g} kg "
                                f"({100 * per_mode[0]['fraction']:.0f}% of the time) and {per_mode[1]['mass']:.3g} kg "
                                f"({100 * per_mode[1]['fraction']:.0f}%); two modes cut the held-out error in "
                                f"{int((rm['d'] > 0).sum())} of {len(rm['d'])} time blocks.")})
            # the single payload on that link is the modes' average: the mode finding replaces it
            findings[:] = [f for f in findings if not (f["effect"] == "payload" and f.get("link") == ctx.link_names[e.index])]
            if labels_disturbed is None and cfg.separate in ("auto", "scan", "scan+em", "scan|em"):
                # pushes are looked for again once the modes explain their part of the residual
                mu = np.zeros_like(r)
                cols = [kidx[("pl", e.index, i)] for i in range(4)]
                for k in range(2):
                    kk = order[k]
                    mu += (lab == k)[:, None] * (A[:, :, cols] @ rm["theta"][kk])
                # within the filter's memory of a switch the filtered residual mixes both modes
                near = np.zeros(T, bool)
                h = int(round(0.5 / (f_c * float(np.median(np.diff(t)))))) if f_c else 0
                for i in np.flatnonzero(np.diff(lab) != 0) + 1:
                    near[max(0, i - h - step):i + h + step] = True
                disturbed, sep2 = scan_disturbances(e_all - mu, t, f_c=f_c, valid=(M > 0) & ~near[:, None],
                                                    alpha=cfg.push_alpha)
                sep_info.update(sep2)
                if cfg.separate == "scan|em" or (cfg.separate in ("auto", "scan+em") and disturbed.any()):
                    # with one mode the learner would call the rarer mode's samples disturbed and
                    # confirm everything; with two it learns both (99.9% agreement with the
                    # simulator's modes on panda_modes) and confirms only what neither explains
                    em_info = get_em(max(2, cfg.em_modes))
                    disturbed, comb = _combine(disturbed, em_info["p_disturbed"],
                                               "union" if cfg.separate == "scan|em" else "gate",
                                               peaks=sep2["peaks"], strong=cfg.em_gate_peak)
                    sep_info.update(comb)
                    sep_info["spans"] = [(float(t[a]), float(t[b - 1])) for a, b in _runs(disturbed)]
        timings["modes_s"] = time.perf_counter() - tm0

    if disturbed.any():
        spans = sep_info.get("spans", [(float(t[a]), float(t[b - 1])) for a, b in _runs(disturbed)])
        findings.append({"effect": "external_disturbance", "joint": None,
                         "params": {"n_samples": int(disturbed.sum()), "fraction": float(disturbed.mean()),
                                    "spans_s": spans[:50]},
                         "evidence": {"method": sep_info.get("method"), "threshold": sep_info.get("threshold"),
                                      **({"em_p_disturbed_max_per_span": [float(em_cache["res"]["p_disturbed"][a:b].max())
                                                                          for a, b in _runs(disturbed)][:50]}
                                         if "res" in em_cache else {})},
                         "explanation": f"{len(spans)} span(s) of unmodelled external force ({int(disturbed.sum())} "
                                        f"samples, {100 * disturbed.mean():.1f}% of the log) were found and left out "
                                        "of the effect fitting."})

    r_after = r - (A[:, :, S] @ thS if S else 0)
    loc = locate(r[use], q[use], dq[use], ddq[use], ctx.tau_rbd[use], t[use], vs, names)
    timings["total_s"] = time.perf_counter() - t0
    info = {"n_samples": int(T), "n_samples_in_log": int(T_full), "n_candidates": len(library),
            "n_folds": K, "lowpass_hz": f_c, "sign_noise_factor": cfg.sign_noise_factor, "v_s": vs.tolist(),
            "selection_path": [{"effects": [f"{e.name}@{e.where(ctx)}" for e in p.effects[-1:]],
                                "cv": p.cv_mean} for p in sel.path_],
            "chosen_step": sel.chosen_step_, "separation": {k: v for k, v in sep_info.items() if k != "spans"},
            "timings": timings}
    plot = None
    if cfg.plots:
        plot = {"q": q[use], "dq": dq[use], "tau": tau[use], "r_before": r[use], "r_after": r_after[use],
                "joint_names": names}
    labels = None
    if disturbed.any() or mode_info is not None:
        labels = {"t": t.copy(), "mode": (mode_info["labels"] if mode_info is not None else np.zeros(T, int)).astype(int),
                  "disturbed": disturbed.astype(int)}
    res = DiagnosisResult(findings=findings, fit=fit, location=loc, joint_names=names, info=info, _plot_data=plot,
                          labels=labels)
    if out_dir is not None:
        res.write(out_dir)
    return res


def _explain(e, p, s, ev, names, jmain, ctx) -> str:
    red = 100 * ev["cv_error_reduction"]
    tail = (f"adding it cuts the held-out error on joint {jmain} ({names[jmain]}) by {red:.0f}%"
            if red > 0 else "it is kept by the selection rule although its own held-out gain is small")
    if isinstance(e, fx.Payload):
        com = ", ".join(f"{c:.3f}" for c in p["com"])
        return (f"link {ctx.link_names[e.index]}: {_LABEL[e.name]} of {_fmt_num(p['mass'], s['mass'])} kg at "
                f"[{com}] m (link frame) is missing from the model; {tail}.")
    parts = []
    for k in e.param_names:
        unit = _UNITS.get(k)
        if k == "offset":
            unit = "rad" if e.name == "encoder_offset" else "N*m"
        parts.append(f"{k} = {_fmt_num(p[k], s[k])}{(' ' + unit) if unit else ''}")
    j = e.index
    if e.name in ("coulomb_friction", "viscous_friction", "armature") and len(parts) == 1:
        what = f"{_LABEL[e.name]} of {parts[0].split(' = ')[1]}"
    else:
        what = f"{_LABEL[e.name]} ({', '.join(parts)})"
    return f"joint {j} ({names[j]}): {what} is missing from the model; {tail}."
