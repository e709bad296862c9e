"""The M-step of the stochastic EM, in its two halves around the E-step.

- :func:`mode_emissions`: refit each mode's model (robust basis mean + exact GP) on its
  undisturbed samples and score every sample under every state (the E-step's likelihoods).
- :func:`update_parameters`: from the new labels, the per-mode variance calibration, the
  disturbance spread ``Sigma_d`` and the transition probabilities.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple, Sequence

import numpy as np
from scipy.special import log_ndtr, logsumexp

from ..data.folds import decorrelation_time
from ..gp.exact import ExactGP
from ..gp.hyper import Hyper
from ..gp.linalg import gaussian_logpdf
from ..gp.sparse import make_gp
from ..gp.windowed import windowed_predictive
from ..physics.context import resting
from .estep import true_stretches
from .hmm import _transition_counts
from ..data.regression import fit_basis_coefficients, fit_shared_coefficients


#: leave-block-out blocks of the final GP span this many correlation times of its inputs
#: (:func:`honest_block_s`)
BLOCK_CORRELATION_TIMES = 4.0


def honest_block_s(t: np.ndarray, X: np.ndarray) -> float:
    """Block length (s) of the final GP's leave-block-out hyperparameter objective for inputs X
    (T, d) sampled at increasing times ``t`` (T,) s: :data:`BLOCK_CORRELATION_TIMES` correlation
    times of the inputs (:func:`mmgp.data.folds.decorrelation_time`).

    Why: in a densely sampled log a sample's neighbours in time are near-copies of it, so
    leave-one-out (and blocks shorter than the correlation time) scores interpolation along the
    trajectory and picks near-zero noise and short lengthscales that swing off it. Samples
    within one correlation time of a block's edge still have such neighbours outside it; with
    four correlation times at least half of every block is further than that from every sample
    the block is predicted from."""
    return BLOCK_CORRELATION_TIMES * decorrelation_time(t, X)


def evenly_spaced(idx: np.ndarray, m: int) -> np.ndarray:
    """At most ``m`` of the sorted indices ``idx``, spread evenly over them (every part of the log
    represented, and the same subset whatever the seed)."""
    idx = np.asarray(idx)
    if len(idx) <= m:
        return idx
    return idx[np.unique(np.linspace(0, len(idx) - 1, m).round().astype(int))]


@dataclass
class SweepParams:
    """What the M-step re-estimates: per-mode GP hyperparameters (K, None before the first fit),
    p(mode stays), p(enter / leave a push), ``sigma_d`` (n,) the disturbance variance per joint
    in N^2*m^2, ``calib`` (K, n) the per-mode predictive variance scale."""

    hypers: list
    stay: float
    p_enter: float
    p_leave: float
    sigma_d: np.ndarray
    calib: np.ndarray
    sigma_floor: np.ndarray | None = None   # (n,) Sigma_d's floor, N^2*m^2 (None before the first)
    stuck: list | None = None               # K (T,) bool: samples where a joint may be stuck (kept out of the GP)


@dataclass
class PushPrior:
    """Beta priors of the disturbance chain in time, not samples: pushes last ``push_len`` samples
    and come every ``gap_len`` samples a priori, worth ``n_pushes`` observed pushes; ``floor_z``:
    a push is at least this many predictive standard deviations (Sigma_d's floor), so a mode for
    samples barely off the model costs more than it explains."""

    push_len: float
    gap_len: float
    n_pushes: float
    floor_z: float
    min_len: float = 0.0     # shortest push, samples (shorter flagged stretches are unflagged)

    @classmethod
    def in_seconds(cls, t_axis: np.ndarray | None, push_s: float, gap_s: float, n_pushes: float,
                   floor_z: float, min_push_s: float = 0.0) -> "PushPrior":
        """Durations ``push_s``, ``gap_s``, ``min_push_s`` in s at the median sample period of
        ``t_axis`` (T,); without times, 5 and 20 samples (the per-sample priors of earlier
        versions) and no shortest push."""
        if t_axis is None or len(t_axis) < 2:
            return cls(5.0, 20.0, n_pushes, floor_z)
        dt = float(np.median(np.diff(t_axis)))
        return cls(max(push_s / dt, 2.0), max(gap_s / dt, 4.0), n_pushes, floor_z, min_push_s / dt)

    @property
    def p_enter(self) -> float:
        return 1.0 / self.gap_len

    @property
    def p_leave(self) -> float:
        return 1.0 / self.push_len


@dataclass
class Emissions:
    """Per-mode means and calibrated predictive variances (K arrays (T, n)), log-likelihoods
    (T, S), and per mode the friction band's half-width (K arrays (T, n), N*m, 0 where no joint
    rests; None without rest weights, see :meth:`ModeFitter.friction_band`)."""

    means: list
    vars: list
    loglik: np.ndarray
    bands: list | None = None
    once: np.ndarray | None = None    # (T, S) with every sample counted fully; None: no hold weights (= loglik)


@dataclass
class RestBand:
    """Where joints may be stuck and how to read their friction band (MultimodalGP ``rest_band``):
    ``weight`` (T, n) rest weights in [0, 1] (:func:`mmgp.physics.context.rest_weight`),
    ``sign_cols`` (n,) the columns of X holding each joint's smooth velocity sign,
    ``basis_branches`` the basis (T, n, p) with every joint's velocity sign set to +1 and to -1
    (None: the basis does not depend on the sign), ``dry_cols`` the basis columns of dry friction
    (their coefficients are friction levels: non-negative)."""

    weight: np.ndarray
    sign_cols: Sequence[int]
    basis_branches: tuple[np.ndarray, np.ndarray] | None = None
    dry_cols: Sequence[int] = ()


@dataclass(frozen=True)
class FitterSettings:
    """What one mode's model is fitted with, the EM's settings of the same names
    (:attr:`mmgp.labelling.settings.EMSettings.fitter`): GP support and hyperparameter-fitting sizes,
    the leave-window-out radius and objective block (s), whether the basis coefficients are
    shared by the joints, the GP's kind and keyword arguments."""

    max_support: int
    fit_points: int
    fit_iter: int
    exclusion_s: float
    block_s: float
    shared_basis: bool
    gp_method: str
    n_inducing: int
    gp_kwargs: dict

    @classmethod
    def of(cls, settings) -> "FitterSettings":
        """The fields read off ``settings`` (an object with attributes of these names)."""
        return cls(**{f.name: getattr(settings, f.name) for f in fields(cls)})


# The EM's starts (fit ``start``): the start's basis fit without the joints' resting samples, or
# on every sample; neither is right on every log (docs/training.md, "Two starts").
START_NAMES = ("stuck-aware", "every-sample")


class Start(NamedTuple):
    """A start computed ahead (:meth:`mmgp.labelling.sem.MultimodalSEM.begin`): name, states (T,), the GP's hyper."""
    name: str
    states: np.ndarray
    hyper: object


class ModeFitter:
    """One mode's model on given member samples and every sample's predictive under it.

    X (T, d) inputs, Y (T, n) torques; ``settings`` a :class:`FitterSettings`;
    ``t_axis`` (T,) one increasing time axis over all logs (enables the leave-window-out
    likelihood); ``basis`` (T, n, p) optional regressors of a robust linear mean under the GP;
    ``band`` an optional :class:`RestBand`: a joint at rest may then hold any torque within its
    friction band (:meth:`friction_band`), one value per hold (``hold``, :func:`hold_weights`
    over the log starts ``starts``); ``rest`` is its weights (T, n) or None; ``muted`` (n,) bool
    the joints that do not vote on pushes; ``still`` (T,) bool the samples where the whole robot
    stands still: the leave-window-out then leaves a still sample's whole hold out
    (:func:`hold_windows`).
    Subsets (GP support, hyperparameter fitting points) are evenly spaced, and the GPs' own
    fitting subsets use seed 0: the seed plays no part in the fitted models.
    """

    def __init__(self, X: np.ndarray, Y: np.ndarray, settings: FitterSettings, *, t_axis: np.ndarray | None = None,
                 basis: np.ndarray | None = None, band: RestBand | None = None, starts: Sequence[int] = (0,),
                 muted: np.ndarray | None = None, still: np.ndarray | None = None):
        self.X, self.Y, self.settings, self.t_axis, self.basis = X, Y, settings, t_axis, basis
        # (T, 2) each sample's leave-out window in s on t_axis; None: t_axis +- exclusion_s
        self.windows = (None if still is None or t_axis is None
                        else hold_windows(t_axis, still, settings.exclusion_s, starts))
        self.rest = None if band is None else band.weight
        self.hold = None if band is None else hold_weights(band.weight, starts)
        self.sign_cols = None if band is None else list(band.sign_cols)
        self.basis_branches = None if band is None or basis is None else band.basis_branches
        self.dry_cols = [] if self.basis_branches is None else list(band.dry_cols)
        # (n,) bool: joints that do not vote on pushes (MultimodalSEM.fit ``muted``); None: none
        self.muted = None if muted is None or not np.any(muted) else np.asarray(muted, bool)

    def new_gp(self) -> ExactGP:
        s = self.settings
        kw = dict(max_fit_points=s.fit_points, max_iter=s.fit_iter, seed=0)
        kw.update(s.gp_kwargs)
        return ExactGP(**kw)

    def final_gp(self, members: np.ndarray, Y: np.ndarray, hyper: Hyper | None):
        """The GP a mode is returned with: conditioned on ``members`` of targets Y (T, n); exact
        or SGPR by :func:`mmgp.gp.sparse.make_gp` (``gp_method``). ``hyper`` None: the GP fits
        its own (its standard procedure on ``fit_points`` random members, one optimiser run
        per output, refined while the climb still gains: up to 3 x ``fit_iter // 3`` iterations,
        and once more from the best output's optimum, see :func:`mmgp.gp.hyper.restart_from_best_output`),
        with a time axis by leave-block-out on blocks of :func:`honest_block_s` (the GP's ``block_s``)."""
        s = self.settings
        kw = dict(max_fit_points=s.fit_points, max_iter=s.fit_iter, seed=0, n_inducing=s.n_inducing,
                  n_subset=s.n_inducing, independent_outputs=True, refine_rounds=3, shared_starts=True)
        kw.update(s.gp_kwargs)
        t = None
        if hyper is None and self.t_axis is not None:
            t = self.t_axis[members]
            kw["block_s"] = honest_block_s(t, self.X[members])
        gp = make_gp(len(members), method=s.gp_method, hyper=hyper, optimise=hyper is None, **kw)
        return gp.fit(self.X[members], Y[members], t=t)

    @property
    def stuck_aware(self) -> bool:
        """Whether the basis fit leaves some joint's resting samples out (:meth:`basis_coefficients`):
        only then does a start that counts them differ from one that does not."""
        return bool(self.dry_cols) and bool(resting(self.rest).any())

    def basis_coefficients(self, members: np.ndarray, stuck: bool = True) -> np.ndarray:
        """Robust basis coefficients (n, p) fitted on ``members``.

        With the friction band, a joint's resting samples are left out of its equations (a stuck
        joint's torque is anywhere in its band, not the basis at a near-zero smooth sign: counted,
        holds at one edge of the band bend a payload's gravity column into the friction; ``stuck``
        False counts them, the "every-sample" start of :data:`START_NAMES`) and the
        dry-friction coefficients are kept non-negative (friction dissipates): a column whose
        coefficient comes out negative is dropped and the rest refitted."""
        fit = fit_shared_coefficients if self.settings.shared_basis else fit_basis_coefficients
        B, Y = self.basis[members], self.Y[members]
        if not self.dry_cols:
            return fit(B, Y)
        mask = (~resting(self.rest[members])).astype(np.float64) if stuck else None
        B = B.copy()
        for _ in range(len(self.dry_cols) + 1):
            coef = fit(B, Y, mask=mask)
            negative = coef[:, self.dry_cols] < 0          # (n, dry)
            if not negative.any():
                break
            for j, c in zip(*np.nonzero(negative)):
                B[:, j, self.dry_cols[c]] = 0.0
                coef[j, self.dry_cols[c]] = 0.0
        return coef

    def predictive(self, members: np.ndarray, hyper: Hyper | None, optimise: bool,
                   stuck: bool = True) -> tuple[np.ndarray, np.ndarray, ExactGP, np.ndarray, np.ndarray | None]:
        """Mean and variance (T, n) of every sample under the model of ``members`` (out of
        sample: leave-window-out with a time axis, else LOO for the support), the GP, its
        support and the basis coefficients (None without a basis).

        With a basis, the mode's mean is ``basis @ coef`` (fitted on all members) and the GP
        models what is left; the linear part extrapolates like the physics it encodes."""
        if self.basis is not None:
            coef = self.basis_coefficients(members, stuck)
            offset = np.einsum("tjp,jp->tj", self.basis, coef)
            mean, var, gp, support = self._gp_predictive(self.Y - offset, members, hyper, optimise)
            return mean + offset, var, gp, support, coef
        return (*self._gp_predictive(self.Y, members, hyper, optimise), None)

    def friction_band(self, gp, coef: np.ndarray | None, support: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centre and half-width (T, n), N*m, of the torque band a joint at rest may hold, and
        the branches' predictive variance (T, n), N^2*m^2, that blurs its edges.

        A joint stuck by dry friction holds whatever torque within +-(its friction) balances the
        rest, so its torque is not a function of the state. The model itself learnt that friction
        on the sliding branches: at each resting sample (rest weight > 0.01) the GP is evaluated
        with the joint's velocity sign set to +1 and to -1; their mean is the band's centre (plus
        the basis mean), their mean variance (incl. noise) the blur, half their difference the
        half-width: the branches are where the model has data, while the sample's own state
        (sign near 0) may have none. With a mean basis that has dry-friction columns the
        half-width is the basis's dry friction alone: its coefficients are fitted where the
        joint slides and are never negative, so the band dissipates, while near rest the GP's
        own odd part learns to cancel the basis's step (a noisy velocity sign flips it there).
        Out of window like the mode's own predictions (``support``: the GP's samples): in-sample,
        a GP that has memorised a push at a pose visited once puts the band on the push, and the
        push is missed.
        Elsewhere: centre 0, width 0, variance 1.
        """
        T, n = self.Y.shape
        centre, half, bvar = np.zeros((T, n)), np.zeros((T, n)), np.ones((T, n))
        rows = [np.flatnonzero(self.rest[:, j] > 0.01) for j in range(n)]
        if not any(len(r) for r in rows):
            return centre, half, bvar
        # Each joint's two branches in one out-of-window prediction of its own output alone: the
        # branches' queries share their times, hence their windows' factorisations (mmgp.gp.windowed),
        # and the other outputs' predictions at joint j's branches would be thrown away.
        for j, idx in enumerate(rows):
            if not len(idx):
                continue
            queries = []
            for sign in (1.0, -1.0):
                Xs = self.X[idx].copy()
                Xs[:, self.sign_cols[j]] = sign
                queries.append(Xs)
            mean_j, var_j = self._out_of_window(gp, np.vstack(queries), np.concatenate([idx, idx]), support, output=j)
            branch = [mean_j[:len(idx), 0], mean_j[len(idx):, 0]]
            bv = [var_j[:len(idx), 0], var_j[len(idx):, 0]]
            if coef is not None:
                # the basis mean on each branch (its friction columns flip with the sign)
                plus, minus = self.basis_branches or (self.basis, self.basis)
                branch = [branch[0] + plus[idx, j] @ coef[j], branch[1] + minus[idx, j] @ coef[j]]
            centre[idx, j] = 0.5 * (branch[0] + branch[1])
            # with dry-friction columns, the basis's dry friction: the GP's branches would collapse
            # the band (docstring)
            dry = coef is not None and self.dry_cols
            step = (plus[idx, j] - minus[idx, j]) @ coef[j] if dry else branch[0] - branch[1]
            half[idx, j] = 0.5 * np.abs(step)
            bvar[idx, j] = 0.5 * (bv[0] + bv[1])
        return centre, half, bvar

    def _windowed(self) -> bool:
        """Predictions leave each sample's time window out (a time axis and both windows set)."""
        s = self.settings
        return self.t_axis is not None and s.exclusion_s > 0 and s.block_s > 0

    def _out_of_window(self, gp, Xq: np.ndarray, idx: np.ndarray, support: np.ndarray,
                       output: int) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance (incl. noise) (M, 1) of GP output ``output`` at inputs Xq of samples
        ``idx``: leaving each sample's time window out (as :meth:`_gp_predictive`), else the GP's
        ordinary predictive."""
        if self._windowed():
            mean, var = windowed_predictive(gp, Xq, self.t_axis[idx], self.t_axis[support],
                                            self.settings.exclusion_s, output=output,
                                            windows=None if self.windows is None else self.windows[idx])
            return mean.reshape(len(idx), 1), var.reshape(len(idx), 1)
        mean, std = gp.predict(Xq, include_noise=True)
        n = self.Y.shape[1]
        return (np.asarray(mean).reshape(len(idx), n)[:, [output]],
                np.asarray(std).reshape(len(idx), n)[:, [output]] ** 2)

    def _gp_predictive(self, Y, members, hyper, optimise):
        X, s = self.X, self.settings
        support = evenly_spaced(members, s.max_support)
        gp = self.new_gp()
        windowed = self._windowed()
        T, n = Y.shape
        if windowed and optimise:
            hyper = self._windowed_hyper(gp, Y, support, hyper)
            optimise = False
        gp.set_params(hyper=hyper, optimise=optimise).fit(X[support], Y[support])
        if windowed:
            mean, var = windowed_predictive(gp, X, self.t_axis, self.t_axis[support], s.exclusion_s,
                                            windows=self.windows)
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

    def _windowed_hyper(self, gp, Y, support, hyper) -> Hyper:
        # Condition once on the fitting subset to get the standardisation, then tune there.
        X, s = self.X, self.settings
        fit_idx = evenly_spaced(support, s.fit_points)
        # Warm-started refits on long logs (where refits dominate the cost) get half the
        # iterations of the first fit.
        iters = s.fit_iter if (hyper is None or len(Y) <= 2000) else max(10, s.fit_iter // 2)
        return gp.block_hyper(X[fit_idx], Y[fit_idx], self.t_axis[fit_idx], s.block_s, hyper=hyper, max_iter=iters)


def mode_emissions(fitter: ModeFitter, states: np.ndarray, params: SweepParams, n_modes: int,
                   disturbance: bool, optimise: bool) -> Emissions:
    """Refit every mode on its undisturbed samples under ``states`` (T,) and score all samples:
    loglik (T, S), column ``k`` mode k's GP, column ``K + k`` a push in mode k. Updates
    ``params.hypers`` to the fitted GPs' hyperparameters."""
    Y = fitter.Y
    T, n = Y.shape
    K = n_modes
    S = 2 * K if disturbance else K
    loglik = np.empty((T, S))
    once = np.empty((T, S)) if fitter.hold is not None else None
    mode_of = states % K
    dist = states >= K if disturbance else np.zeros(T, bool)
    mus, vars_, bands, blurs = [], [], [], []
    for k in range(K):
        members = np.flatnonzero((mode_of == k) & ~dist)
        if params.stuck is not None and (~params.stuck[k][members]).sum() >= 0.25 * len(members):
            # A stuck joint's torque is no function of the state: the GP learns from the rest.
            members = members[~params.stuck[k][members]]
        if len(members) < max(5, n):
            # An emptied mode is re-seeded from samples spread over the log so K stays K.
            members = evenly_spaced(np.arange(T), max(5, n))
        mean, var, gp, support, coef = fitter.predictive(members, params.hypers[k], optimise)
        params.hypers[k] = gp.hyper_
        var = var * params.calib[k]
        mus.append(mean)
        vars_.append(var)
        lu = gaussian_logpdf(Y, mean, var)      # (T, n) per joint, untouched
        band = None
        if fitter.rest is not None:
            centre, half, bvar = fitter.friction_band(gp, coef, support)
            blur = bvar * params.calib[k]
            bands.append(half)
            blurs.append(blur)
            band = (Y - centre, half, blur, fitter.rest)
            lu = at_rest_logpdf(lu, *band)
        lp = None
        if disturbance:
            # A push acts on one link: the chain mixture (push_loglik) over which link, each
            # loaded joint from the scale mixture (pushed_logpdf), at rest still in its band.
            lp = pushed_logpdf(Y, mean, var, params.sigma_d, params.sigma_floor, band)
        cols = [k, K + k] if disturbance else [k]
        loglik[:, cols] = _mode_columns(lu, lp, fitter.hold, fitter.muted)
        if once is not None:
            once[:, cols] = _mode_columns(lu, lp, None, fitter.muted)
    if fitter.rest is not None:
        params.stuck = [stuck_samples(fitter.rest, half, blur) for half, blur in zip(bands, blurs)]
    return Emissions(mus, vars_, loglik, bands if fitter.rest is not None else None, once)


def _mode_columns(lu: np.ndarray, lp: np.ndarray | None, weight: np.ndarray | None,
                  muted: np.ndarray | None) -> np.ndarray:
    """A mode's undisturbed and (with ``lp``) pushed log-likelihood columns (T, 1 or 2) from
    each joint's densities lu, lp (T, n), weighted by ``weight`` (T, n) (None: 1); the
    ``muted`` joints (n,) bool vote neither way."""
    if weight is not None:
        lu = lu * weight
    if lp is None:
        return lu.sum(1)[:, None]
    lp = lp * weight if weight is not None else lp.copy()
    if muted is not None:
        lp[:, muted] = lu[:, muted]
    return np.stack([lu.sum(1), push_loglik(lu, lp)], axis=1)


# Scales of Sigma_d in the pushed component of a multi-joint log (see :func:`pushed_logpdf`).
PUSH_SCALES = (1.0, 0.1, 0.01)


def pushed_logpdf(Y: np.ndarray, mean: np.ndarray, var: np.ndarray, sigma_d: np.ndarray,
                  floor: np.ndarray | None = None, band: tuple | None = None) -> np.ndarray:
    """Per-joint log density (T, n) of a pushed sample: N(mean, var + Sigma_d) on one joint
    (n = 1); on several joints an equal-weight scale mixture over ``PUSH_SCALES`` of Sigma_d, each
    scaled spread at least ``floor`` (n,) N^2*m^2. Why a mixture: Sigma_d pools every push of
    the log, and a push on a distal link loads the proximal joints through long lever arms, so
    Sigma_d there is set by the hardest shoves; a proximal or light push, a few predictive
    standard deviations off, then fits "untouched" better than "pushed".

    ``band`` (offset from the band's centre, half-width, variance, rest weight; each (T, n)), as
    :func:`at_rest_logpdf` takes them: a joint pushed while it rests still holds any torque in
    its friction band, so its pushed torque is the band blurred by the push's spread as well
    (never denser than the untouched band inside it: only torque beyond the band is evidence)."""
    def spread(extra):
        lg = gaussian_logpdf(Y, mean, var + extra)
        if band is None:
            return lg
        e, half, bvar, rest = band
        return at_rest_logpdf(lg, e, half, bvar + extra, rest)

    if Y.shape[1] == 1:
        return spread(sigma_d)
    parts = [spread(sigma_d * f if floor is None else np.maximum(sigma_d * f, floor)) for f in PUSH_SCALES]
    return logsumexp(np.stack(parts), 0) - np.log(len(PUSH_SCALES))


def link_components(lu: np.ndarray, lp: np.ndarray) -> np.ndarray:
    """(T, n) log densities of "the push acts on link k" for k = 1..n (column k - 1): joints
    1..k pushed (``lp`` (T, n)), joints k+1..n untouched (``lu`` (T, n)). Joints are in chain
    order, base first: a wrench on link k produces torque J_k^T F on joints 1..k only."""
    head = np.cumsum(lp, 1)
    tail = np.zeros_like(lu)
    tail[:, :-1] = np.cumsum(lu[:, :0:-1], 1)[:, ::-1]
    return head + tail


def push_loglik(lu: np.ndarray, lp: np.ndarray) -> np.ndarray:
    """(T,) log-likelihood of the disturbance state from per-joint log densities (T, n) of
    "untouched" ``lu`` and "pushed" ``lp``: a mixture over the pushed link, equal weights
    (:func:`link_components`); O(T n)."""
    n = lu.shape[1]
    if n == 1:
        return lp[:, 0]
    return logsumexp(link_components(lu, lp), 1) - np.log(n)


def hold_weights(rest: np.ndarray, starts: Sequence[int] = (0,)) -> np.ndarray:
    """(T, n) evidence weights: 1 / L on each of the L samples of an unbroken stretch in which a
    joint rests (rest weight > 0.5; a stretch ends where a log starts, ``starts``), 1 elsewhere.

    Why: a stuck joint holds one torque, set by its history, for the whole hold: its samples are
    one draw (from the band, or from a push) plus noise, not L independent draws. Both hypotheses
    with that latent value integrated out differ by the one draw's density ratio (the noise
    terms cancel), which the mean of the L per-sample log densities approximates. Counted L
    times, a hold a little more likely pushed than stuck (its torque near the band's middle,
    where N(0, Sigma_d) is denser than the band) was flagged whole, on logs without a push."""
    out = np.ones(rest.shape)
    for j in range(rest.shape[1]):
        for a, b in true_stretches(resting(rest[:, j]), starts):
            out[a:b, j] = 1.0 / (b - a)
    return out


def hold_windows(t: np.ndarray, still: np.ndarray, radius: float, starts: Sequence[int] = (0,)) -> np.ndarray:
    """(T, 2) leave-out windows [start, end] in s: ``t`` (T,) +- ``radius``, widened for a
    sample in a hold (an unbroken stretch of ``still`` (T,) bool, ending where a log starts,
    ``starts``) to cover the whole hold.

    Why: held still, the robot shows one torque for the whole hold (set by friction or by the
    hand that holds it), so a hold is one observation (:func:`hold_weights`). A hold longer than
    the window, at a pose the log visits only then, was otherwise predicted from itself: a push
    that held the arm for 1.8 s was explained by the rest of the same push."""
    t = np.asarray(t, dtype=np.float64)
    out = np.stack([t - radius, t + radius], 1)
    for a, b in true_stretches(still, starts):
        out[a:b, 0] = np.minimum(out[a:b, 0], t[a])
        out[a:b, 1] = np.maximum(out[a:b, 1], t[b - 1])
    return out


def stuck_samples(rest: np.ndarray, half: np.ndarray, blur: np.ndarray) -> np.ndarray:
    """(T,) samples where some joint rests (weight > 0.5) with a friction band wider than the
    spread that blurs its edges (half-width^2 > ``blur``, the sliding branches' predictive
    variance, :meth:`ModeFitter.friction_band`): its torque there may be anything in the band.
    The branches' spread, not the sample's own predictive: at a hold the GP's own spread grows
    with the hold's scatter across the band, so judged by it the holds stayed in the GP and
    taught it the band's scatter as a function of the state."""
    return (resting(rest) & (half ** 2 > blur)).any(1)


def band_logpdf(e: np.ndarray, half: np.ndarray, var: np.ndarray) -> np.ndarray:
    """log density of e = u + noise, u uniform on [-half, half], noise N(0, var) (all (T, n)):
    log([Phi((e + half) / s) - Phi((e - half) / s)] / (2 half)), s = sqrt(var); the Gaussian
    where the band is narrower than 1e-3 s. Computed on the tail side for accuracy."""
    s = np.sqrt(var)
    h = np.maximum(half, 1e-3 * s)
    a, b = (e + h) / s, (e - h) / s
    right = b > 0                      # both in the right tail: Phi(a) - Phi(b) = Phi(-b) - Phi(-a)
    hi, lo = np.where(right, -b, a), np.where(right, -a, b)
    la, lb = log_ndtr(hi), log_ndtr(lo)
    band = la + np.log1p(-np.exp(np.minimum(lb - la, -1e-300))) - np.log(2.0 * h)
    return np.where(half < 1e-3 * s, gaussian_logpdf(e, 0.0, var), band)


def at_rest_logpdf(lu: np.ndarray, e: np.ndarray, half: np.ndarray, var: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Undisturbed log density (T, n) where joints may rest: with weight ``rest`` the torque lies
    in the friction band (offset ``e`` from its centre, ``half`` its half-width:
    :func:`band_logpdf`), otherwise it is the model's Gaussian (log density ``lu``)."""
    w = np.clip(rest, 1e-300, 1.0)
    return np.logaddexp(np.log1p(-np.minimum(w, 1.0 - 1e-16)) + lu, np.log(w) + band_logpdf(e, half, var))


def update_parameters(Y: np.ndarray, states: np.ndarray, em: Emissions, params: SweepParams, *,
                      n_modes: int, disturbance: bool, calibrate: bool, learn_stay: bool,
                      starts: Sequence[int], prior: PushPrior, rest: np.ndarray | None = None) -> None:
    """The M-step after the E-step, in place on ``params``: calibration (resting samples, by the
    rest weights ``rest`` (T, n), weigh less), Sigma_d (at least ``prior.floor_z`` squared times
    the median predictive variance), transitions (Beta priors: p_enter and p_leave from
    ``prior``, stay mean 0.95)."""
    T = len(Y)
    K = n_modes
    mode_of = states % K
    dist = states >= K if disturbance else np.zeros(T, bool)
    if calibrate:
        # Out-of-window predictions in states the log visits once are overconfident; a
        # per-mode, per-joint variance scale fitted on the undisturbed samples (never below 1)
        # keeps them from being taken for pushes.
        for k in range(K):
            sel = (mode_of == k) & ~dist
            if sel.sum() >= 10:
                z2 = ((Y - em.means[k]) ** 2 / (em.vars[k] / params.calib[k]))[sel]
                # The mean, not a robust median: the overconfident states are the few visited
                # once, which a median passes over. Resting samples weigh by how much they
                # move: their spread is the friction band's, not the model's.
                w = np.ones_like(z2) if rest is None else 1.0 - rest[sel]
                params.calib[k] = np.clip((w * z2).sum(0) / np.maximum(w.sum(0), 1e-9), 1.0, 1e4)
    if disturbance:
        mu_s = np.stack(em.means)[mode_of, np.arange(T)]
        var_s = np.stack(em.vars)[mode_of, np.arange(T)]
        if dist.sum() >= 3:
            excess = ((Y - mu_s) ** 2 - var_s)[dist].mean(0)
            params.sigma_floor = prior.floor_z ** 2 * np.median(var_s, 0)
            params.sigma_d = np.maximum(excess, params.sigma_floor)
        trans = _transition_counts(states, K, starts)
        n0 = prior.n_pushes
        params.p_enter = (trans["enter"] + n0) / (trans["undisturbed"] + n0 * prior.gap_len)
        params.p_leave = (trans["leave"] + n0) / (trans["disturbed"] + n0 * prior.push_len)
    if learn_stay and K > 1:
        trans = _transition_counts(states, K, starts)
        params.stay = (trans["stay"] + 19.0) / (trans["pairs"] + 20.0)
