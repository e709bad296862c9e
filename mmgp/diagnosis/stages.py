"""The stages of a diagnosis, each a function of explicit inputs returning its own result.

Data flow (``Diagnoser.fit`` runs them in this order):

``prepare_log`` -> ``build_problem`` (nominal residual, low-pass, valid equations, candidates)
-> ``fit_library`` (robust fit of every candidate: weights with pushes at zero)
-> ``separate_pushes`` (scan of what the physics selected on those weights leaves, gated by
the learner) -> ``fit_library`` again without the pushes -> ``select_effects`` -> ``fit_physics``
(non-negative refit of the chosen effects, jackknife covariance) -> ``effect_findings``,
``stage_errors``, ``gp_stage_errors`` -> ``modes.find_mode_switch`` -> ``rescan_pushes``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..data.filtering import identity, lowpass_for
from ..data.logs import RobotLog
from ..data.statistics import difference_noise_sd
from ..data.regression import robust_regression
from ..physics.context import Context, build_context, pin_model, smooth_sign_scale
from ..physics.effects import Effect, build_atoms, effect_classes, effect_library
from ..physics.identification import base_parameters
from . import separation as sep
from .fitting import PhysicsFit
from .selection import FoldGrams, atom_indices, carried_folds, signed_rank_p


@dataclass(frozen=True)
class Problem:
    """What every stage reads: the (thinned) log's arrays, (T, n); ``r_raw`` = tau - tau_rbd and
    ``r`` its low-passed copy (N*m); ``lowpass`` the filter applied to ``r`` and to every column,
    ``f_c`` its cutoff (Hz, None: none); ``M`` (T, n) valid equations; ``M_scan`` (T, n) where
    pushes are looked for: ``M`` less every passage through zero velocity and the filter's memory
    around it, since there the friction law's transition, which tanh(dq / v_s) only approximates,
    leaves a misfit that is no external force (a friction law that turns over more slowly than
    the smooth sign leaves "pushes" at every reversal); ``folds`` time blocks;
    ``library`` the candidate effects; ``ctx`` the nominal Context; ``n_samples_in_log``;
    ``smear_s`` how far (s) estimated derivatives spread a sudden change (0 when logged)."""

    t: np.ndarray
    tau: np.ndarray
    ctx: Context
    r_raw: np.ndarray
    r: np.ndarray
    lowpass: Callable[[np.ndarray], np.ndarray]
    f_c: float | None
    M: np.ndarray
    M_scan: np.ndarray
    folds: list
    library: list
    n_samples_in_log: int
    smear_s: float = 0.0

    def atoms(self, ctx: Context) -> tuple[list, np.ndarray]:
        """Atom keys and low-passed columns (T, n, P) of the library in ``ctx``."""
        return self.lowpass_atoms(self.library, ctx)

    def lowpass_atoms(self, effects, ctx: Context) -> tuple[list, np.ndarray]:
        """Atom keys and low-passed columns (T, n, P) of ``effects`` in ``ctx``."""
        keys, A = build_atoms(effects, ctx)
        return keys, self.lowpass(A)


def _edge_samples(differentiator, log: RobotLog) -> int:
    """Half the longest window (samples) the differentiator uses on ``log`` (before it fills in
    the derivatives): estimated derivatives that close to either end come from an extrapolated
    edge fit, and a sudden change is smeared that far. A part that does not tell its windows
    (no ``windows(t, x)``) counts as the former fixed 0.05 s window."""
    signal = log.q if log.dq is None else log.dq  # what complete_derivatives differentiates
    dt = float(np.median(np.diff(log.t)))
    windows = getattr(differentiator, "windows", None)
    longest = int(np.max(windows(log.t, signal))) if windows is not None else int(round(0.05 / dt)) | 1
    return (longest - 1) // 2


def prepare_log(log: RobotLog, differentiator, max_samples: int) -> tuple[RobotLog, int, float]:
    """The log with derivatives (estimated by ``differentiator`` where not logged), its ends
    trimmed when estimated, thinned evenly to at most ``max_samples``; its length before
    thinning; and how far (s) the estimated derivatives smear a sudden change (0 when logged)."""
    from ..data.differentiation import complete_derivatives

    before = log
    log = complete_derivatives(log, differentiator)
    edge = 0
    if log.dq_estimated or log.ddq_estimated:
        # a lagging logged velocity was replaced by the position's derivative: q was differentiated
        edge = _edge_samples(differentiator, before.replace(dq=None) if "velocity_delay_s" in log.metadata else before)
    dt = float(np.median(np.diff(log.t)))
    if edge:
        # the parallel filter would spread the extrapolated ends over a cutoff period, so they are
        # dropped first, with a margin (the 0.035 s that made 0.06 s for a fixed 0.05 s window)
        cut = edge + int(np.ceil(0.035 / dt)) + 2
        if log.n_samples > 10 * cut:
            log = log.subset(np.arange(cut, log.n_samples - cut))
    n_full = log.n_samples
    if n_full > max_samples:
        # derivatives were taken at the full rate; thinning only bounds the runtime
        log = log.subset(np.unique(np.linspace(0, n_full - 1, max_samples).round().astype(int)))
    return log, n_full, edge * dt


def build_problem(log: RobotLog, robot, n_samples_in_log: int, smear_s: float, *, effects, payload_links,
                  sign_noise_factor: float, lowpass: bool, rest_factor: float, n_folds: int) -> Problem:
    """Nominal model along the log, residual, filter, valid equations, folds and candidates."""
    q, dq, t = log.q, log.dq, log.t
    names = list(getattr(robot, "joint_names", None) or log.joint_names or
                 [str(pin_model(robot).names[j]) for j in range(1, q.shape[1] + 1)])
    vs = smooth_sign_scale(dq, k=sign_noise_factor, speed_frac=0.0)
    ctx = build_context(robot, q, dq, log.ddq, v_s=vs, joint_names=names)
    library = effect_library(ctx, effects=effects, payload_links=payload_links)
    if any(cls.scope == "model" for cls in effect_classes(effects)):
        Y = rigid_regressor(ctx.regressor, library)
        ctx = ctx.with_base(base_parameters(Y, ctx.link_names))
        library = effect_library(ctx, effects=effects, payload_links=payload_links)
    r_raw = log.tau - ctx.tau_rbd
    lp, f_c = lowpass_for(t, dq) if lowpass else (identity, None)
    M = sep.valid_mask(dq, vs, t, f_c, factor=rest_factor)
    return Problem(t=t, tau=log.tau, ctx=ctx, r_raw=r_raw, r=lp(r_raw), lowpass=lp, f_c=f_c, M=M,
                   M_scan=sep.valid_mask(dq, vs, t, f_c, factor=rest_factor, min_rest_periods=0.0),
                   folds=carried_folds(M, n_folds, t, f_c),
                   library=library,
                   n_samples_in_log=n_samples_in_log, smear_s=smear_s)


def rigid_regressor(Y: np.ndarray, library) -> np.ndarray:
    """The inertial regressor ``Y`` (T, n, 10 B) the re-identified body is made of: the links that
    carry a payload candidate left out (zero columns). CONTRACT section 3 names a mass on the
    distal link a ``payload``; were the body free there too, it would absorb every payload (and
    on a log whose URDF is right, a payload is all it would find)."""
    Y = Y.copy()
    for e in library:
        if e.name == "payload":
            Y[:, :, 10 * e.index:10 * e.index + 10] = 0.0
    return Y


@dataclass(frozen=True)
class LibraryFit:
    """Robust fit of every candidate: ``coef`` (P,) over ``keys``, ``A`` (T, n, P) low-passed
    columns in ``ctx``, ``weights`` (T, n) robustness weights times valid equations (zero on
    samples not used)."""

    ctx: Context
    keys: list
    A: np.ndarray
    coef: np.ndarray
    weights: np.ndarray


def _robust_fit(prob: Problem, A: np.ndarray, use: np.ndarray, init: np.ndarray | None = None):
    # Huber weights to convergence, then Tukey-bisquare steps from there: pushes get weight zero,
    # so they stand out in the residual instead of dragging the fit (least squares spreads a
    # push over every column; Huber still lets a long push outweigh a small effect)
    fit = robust_regression(A[use], prob.r[use], mask=prob.M[use], huber_steps=10, tukey_steps=5, tol=1e-4,
                            centre=False, solver="gram", init=None if init is None else init[use])
    weights = np.zeros_like(prob.r)
    weights[use] = fit.weights if init is None else fit.weights * init[use]
    return fit.coef, weights


def fit_library(prob: Problem, ctx: Context, use: np.ndarray, *, relinearise: int = 0,
                init: np.ndarray | None = None) -> LibraryFit:
    """Robust fit of the whole library on samples ``use`` (T,) bool, with ``relinearise`` rounds
    of moving linearised effects (payload centres of mass) to the fit and refitting; ``init``
    (T,) weights in [0, 1] (one minus the learner's push probability) where the reweighting
    starts, and which scale the robust weights: a sample the learner holds disturbed counts
    little in choosing effects (whether it is reported as a push is the scan's and the gate's
    decision)."""
    keys, A = prob.atoms(ctx)
    init = None if init is None else np.repeat(np.asarray(init, dtype=np.float64)[:, None], ctx.n, axis=1)
    coef, weights = _robust_fit(prob, A, use, init)
    if any(e.linearised for e in prob.library):
        for _ in range(relinearise):
            fitted = dict(zip(keys, coef))
            for e in prob.library:
                ctx = e.relinearise(fitted, ctx)
            keys, A = prob.atoms(ctx)
            coef, weights = _robust_fit(prob, A, use, init)
    return LibraryFit(ctx, keys, A, coef, weights)


def joint_weights(e: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(n,) inverse residual variance per joint of residual ``e`` over valid equations ``M``
    (a GLS weighting of the joints)."""
    sig2 = (M * e ** 2).sum(0) / np.maximum(M.sum(0), 1)
    return 1.0 / (sig2 + 1e-12 * (sig2.max() + 1e-300))


def nominal_weights(prob: Problem, use: np.ndarray | None = None) -> np.ndarray:
    """(n,) each joint's weight where effects are compared and chosen (the
    selection and fit): the inverse variance of its nominal residual over valid equations of
    samples ``use`` (default all), fixed before any effect is fitted, so every joint's error
    relative to the nominal model counts alike. Weights from a fitted model's own residual favour
    the joints it fits best: a re-identified body's base parameters then look significant where
    a payload is all there is, and a joint the nominal model fits worst gets almost no weight, so
    the body shared by every joint is set by the others
    (benchmarks/README.md, "sixth session: tuning history")."""
    use = np.ones(len(prob.t), bool) if use is None else use
    e, M = prob.r[use], prob.M[use]
    # about its mean: a constant level is no scatter. An arm holding a pose has a nominal residual
    # that is nearly all level (a payload's static torque); its mean square would give the joints
    # that carry the payload almost no weight beside those at noise
    mean = (M * e).sum(0) / np.maximum(M.sum(0), 1)
    return joint_weights(e - mean, M)


def candidates(prob: Problem, start) -> list:
    """The effects the selection may add: the library less what the model starts from, less
    the rigid body (decided before the selection, by ``reidentify``) and less the couplings
    (searched in their own family, ``coupling``)."""
    return [e for e in prob.library if e not in start and e.scope != "model" and not e.own_family]


@dataclass(frozen=True)
class Separation:
    """Pushed samples ``disturbed`` (T,) bool, what the separation reports (``info``), and the
    learner's last run (``em``, None when it did not run)."""

    disturbed: np.ndarray
    info: dict
    em: dict | None


def run_learner(prob: Problem, n_modes: int, *, max_points: int, seed: int, previous: dict | None = None,
                resid: np.ndarray | None = None) -> dict:
    """The learner's separation on ``resid`` (T, n) (default the nominal residual; the
    re-identified body's when it is re-identified), reusing ``previous`` when it ran with as
    many modes on the same residual (its ``"residual"`` entry, added here)."""
    r = prob.r_raw if resid is None else resid
    if previous is not None and previous["n_modes"] == n_modes and np.array_equal(previous.get("residual"), r):
        return previous
    ctx = prob.ctx
    em = sep.em_separate(r, ctx.q, ctx.dq, ctx.ddq, prob.t, n_modes=n_modes, max_points=max_points, seed=seed)
    return {**em, "residual": r}


def start_residual(prob: Problem, lib: LibraryFit, start) -> np.ndarray:
    """(T, n) unfiltered residual of the effects the model starts from (the re-identified body),
    at the library fit's coefficients: what the learner sees."""
    if not start:
        return prob.r_raw
    keys, A = build_atoms(start, lib.ctx)
    coef = dict(zip(lib.keys, lib.coef))
    return prob.r_raw - A @ np.array([coef[k] for k in keys])


def friction_band(coef: dict, ctx: Context) -> np.ndarray:
    """(T, n) the dry-friction band each joint can hold while stuck, N*m, from the fitted atoms
    ``coef`` (atom key -> value): Coulomb ``("sign", j)`` plus the load-dependent part
    ``("load", j)`` times the joint's load. Zero on a joint without chosen dry friction."""
    T, n = ctx.q.shape
    band = np.zeros((T, n))
    for j in range(n):
        band[:, j] = coef.get(("sign", j), 0.0) + coef.get(("load", j), 0.0) * np.abs(ctx.load[:, j])
    return band


def band_uncertainty(prob: Problem, e: np.ndarray, valid: np.ndarray, level: float = 0.95) -> np.ndarray:
    """(n,) N*m: how much wider each joint's dry-friction band may be than the model's, at
    ``level`` (one-sided): the upper confidence bound of a Coulomb level fitted with a constant
    to the residual ``e`` (T, n) on the joint's scanned equations ``valid`` (T, n), its standard
    error from the filter's independent samples (``2 f_c`` per second). A joint that slides one
    way only cannot tell friction from an offset: its bound is infinite."""
    from scipy.stats import norm

    from ..physics.effects import CoulombFriction

    n = e.shape[1]
    _, A = prob.lowpass_atoms([CoulombFriction(j) for j in range(n)], prob.ctx)
    sign = A[:, np.arange(n), np.arange(n)]          # (T, n) each joint's own Coulomb column
    dur = float(prob.t[-1] - prob.t[0]) if len(prob.t) > 1 else 1.0
    out = np.full(n, np.inf)
    for j in range(n):
        m = valid[:, j]
        if m.sum() < 3:
            continue
        X = np.stack([sign[m, j], np.ones(m.sum())], axis=1)
        G = X.T @ X
        if np.linalg.cond(G) > 1e12:
            continue
        c = np.linalg.solve(G, X.T @ e[m, j])
        r = e[m, j] - X @ c
        n_eff = min(m.sum(), 2.0 * prob.f_c * dur * m.mean()) if prob.f_c else m.sum()
        var = (r @ r) / max(m.sum() - 2, 1) * np.linalg.inv(G)[0, 0] * m.sum() / max(n_eff, 1.0)
        out[j] = max(c[0], 0.0) + norm.ppf(level) * np.sqrt(var)
    return out


def scan(prob: Problem, e: np.ndarray, band: np.ndarray, *, push_alpha: float,
         exclude: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """:func:`.separation.scan_disturbances` of the residual ``e`` (T, n) on the scanned
    equations (``prob.M_scan``) and on the whole-robot holds (:func:`.separation.hold_interiors`),
    where only the torque beyond each joint's friction ``band`` (T, n) counts; the noise level is
    the scanned equations'. ``exclude`` (T,) bool: samples left out (near mode switches)."""
    valid = prob.M_scan > 0
    hold = sep.hold_interiors(prob.M_scan, prob.t, prob.f_c)
    band = band + band_uncertainty(prob, e, valid)[None, :]
    if exclude is not None:
        valid, hold = valid & ~exclude[:, None], hold & ~exclude
    return sep.scan_disturbances(e, prob.t, f_c=prob.f_c, valid=valid | hold[:, None], reference=valid,
                                 band=band * hold[:, None], alpha=push_alpha)


def separate_pushes(prob: Problem, lib: LibraryFit, selector, *, method: str, push_alpha: float, em_modes: int,
                    em_points: int, em_gate_peak: float, seed: int, start=(), em: dict | None = None) -> Separation:
    """Which samples an external force disturbed (``method``: see ``SEPARATION_METHODS``).

    Physics first, pushes from what it leaves: effects are selected on the robust fit's weights
    (pushes carry small weights there), then the residual of the *selected* model is scanned.
    Scanning the full library's residual instead would see an over-fitted, too-quiet residual
    wherever the log has few independent samples (slow trajectories). ``start``: effects the
    model holds from the outset (the re-identified body); ``em``: a learner run on the nominal
    residual to reuse (it is run again on the re-identified body's residual when there is one).
    """
    T = len(prob.t)
    info = {"method": sep.SEPARATION_METHODS[method]}
    if method == "none":
        return Separation(np.zeros(T, bool), info, None)
    resid = start_residual(prob, lib, start)
    em = em if not start else None
    if method == "em":
        # the learner alone: its flags, at its own (thinned) resolution
        em = run_learner(prob, em_modes, max_points=em_points, seed=seed, resid=resid, previous=em)
        return Separation(em["p_disturbed"] > 0.5, {**info, **sep.em_summary(em)}, em)
    w0 = joint_weights(prob.r - lib.A @ lib.coef, prob.M)
    g0 = FoldGrams(lib.A, prob.r, np.ones(T, bool), prob.folds, W=lib.weights)
    chosen = selector.fit(candidates(prob, start), lib.keys, g0, w0, lib.ctx, start=start).selected_
    S0 = atom_indices(chosen, {a: i for i, a in enumerate(lib.keys)})
    coef0 = g0.fit(S0, w0) if S0 else np.zeros(0)
    e0 = prob.r - (lib.A[:, :, S0] @ coef0 if S0 else 0.0)
    band = friction_band({lib.keys[i]: c for i, c in zip(S0, coef0)}, lib.ctx)
    disturbed, found = scan(prob, e0, band, push_alpha=push_alpha)
    info = {**info, **found}
    if method == "auto" and disturbed.any():
        # as a gate the learner can only drop spans: with none scanned it is not needed
        em = run_learner(prob, em_modes, max_points=em_points, seed=seed, resid=resid, previous=em)
        disturbed, gate = sep.gate_spans(disturbed, em["p_disturbed"], peaks=found["peaks"], strong=em_gate_peak)
        info = {**info, **sep.em_summary(em), **gate}
    return Separation(disturbed, info, em)


def _nmse(sq: np.ndarray, nte: np.ndarray, denom: np.ndarray, names: list) -> dict:
    nm = sq / nte / denom
    return {"nmse": {names[j]: float(nm[j]) for j in range(len(names))}, "mean_nmse": float(nm.mean())}


def torque_variance(prob: Problem, use: np.ndarray) -> np.ndarray:
    """(n,) variance of each joint's logged torque over samples ``use`` (N*m)^2: the normaliser
    of the held-out errors."""
    tau = prob.tau[use]
    return np.array([np.sum((tau[:, j] - tau[:, j].mean()) ** 2) / use.sum() for j in range(tau.shape[1])]) + 1e-300


def still_joints(prob: Problem, use: np.ndarray) -> list:
    """Names of the joints held still on samples ``use`` (T,) bool: the joint's velocity varies
    there by no more than ``MOTION_NOISE_RATIO`` times its noise variance, and the nominal model's
    torque by less than the torque sensor's noise variance (each noise from second differences,
    ``difference_noise_sd``), so the logged torque varies by its noise alone, whatever the model.
    An arm holding a pose: the torque's level is what its data show, not a variation a model
    could predict better than the torque's mean. (A joint that moves while its torque stays
    within noise, a wrist on a log of noise, is not still.)"""
    from ..physics.plausibility import MOTION_NOISE_RATIO

    if use.sum() < 2:
        return []
    ctx = prob.ctx
    torque_noise, speed_noise = difference_noise_sd(prob.tau) ** 2, difference_noise_sd(ctx.dq) ** 2
    spread, speed = ctx.tau_rbd[use].var(axis=0), ctx.dq[use].var(axis=0)
    return [j for k, j in enumerate(ctx.joint_names)
            if spread[k] <= torque_noise[k] and speed[k] <= MOTION_NOISE_RATIO * speed_noise[k]]


def honest_grams(prob: Problem, phys: PhysicsFit, use: np.ndarray) -> FoldGrams:
    """Test-block sums of the chosen atoms over every valid equation of samples ``use`` (no
    robustness weights): held-out figures count every sample the separation kept."""
    return FoldGrams(phys.A[:, :, phys.S], prob.r, use, prob.folds, W=prob.M)


def stage_errors(prob: Problem, phys: PhysicsFit, use: np.ndarray, denom: np.ndarray, still=()) -> dict:
    """Held-out normalised MSE per joint of the nominal model and of nominal + found physics
    (fitted per fold with the selection's robust weights, scored on every kept sample): fold-wise
    squared error over the torque's variance ``denom`` (n,). With joints named in ``still``
    (``still_joints``), also ``still_worse_p`` (:func:`still_worse_p`)."""
    names, g = phys.ctx.joint_names, honest_grams(prob, phys, use)
    nte = g.nte.sum(0)
    thetas = [phys.grams.fit(phys.S, phys.w, k) for k in range(g.K)]
    nominal, found = g.test_errors([], None), g.test_errors(range(len(phys.S)), thetas)
    out = {"nominal": _nmse(nominal.sum(0), nte, denom, names),
           "with_physics": _nmse(found.sum(0), nte, denom, names)}
    if still:
        out["still_worse_p"] = still_worse_p(prob, use, nominal, found, [names.index(j) for j in still], names)
    return out


def mean_fold_errors(prob: Problem, use: np.ndarray) -> np.ndarray:
    """(K, n) held-out squared errors of the torque's mean as the model: each test block of the
    (low-passed, as the residual) torque against its fold's training mean, over the valid
    equations (``prob.M``) of samples ``use``, as ``honest_grams`` scores every model."""
    lp, W = prob.lowpass(prob.tau), prob.M
    out = np.zeros((len(prob.folds), lp.shape[1]))
    for k, (tr, te) in enumerate(prob.folds):
        tr, te = tr[use[tr]], te[use[te]]
        centre = (W[tr] * lp[tr]).sum(0) / np.maximum(W[tr].sum(0), 1e-300)
        out[k] = (W[te] * (lp[te] - centre) ** 2).sum(0)
    return out


def still_worse_p(prob: Problem, use: np.ndarray, nominal: np.ndarray, found: np.ndarray, joints: list,
                  names: list) -> dict:
    """{joint name: p} for each of ``joints`` (indices): the one-sided signed-rank p-value over
    the time blocks (``selection.signed_rank_p``) that the found physics' held-out errors
    ``found`` (K, n) exceed the reference's, the worse in total of the nominal model's
    (``nominal`` (K, n)) and the torque's mean (``mean_fold_errors``), as
    ``plausibility.fit_warnings`` judges a still joint. On a joint whose torque
    varies by its noise alone every model's held-out error is the noise's plus its error in the
    torque's level, so "worse" is a question of how sure, which the blocks answer."""
    mean = mean_fold_errors(prob, use)
    out = {}
    for j in joints:
        ref = nominal[:, j] if nominal[:, j].sum() > mean[:, j].sum() else mean[:, j]
        out[names[j]] = signed_rank_p(found[:, j] - ref)
    return out


def gp_stage_errors(prob: Problem, phys: PhysicsFit, use: np.ndarray, denom: np.ndarray, *, points: int,
                    hyper_points: int, n_iter: int, seed: int) -> dict:
    """Held-out normalised MSE per joint of nominal + physics + a GP (``ExactGP`` on
    [q, dq, ddq]) fitted per fold to what the fold's physics fit leaves."""
    from ..gp.exact import ExactGP
    from ..labelling.features import StateFeatures

    ctx, S, A, r, M = phys.ctx, phys.S, phys.A, prob.r, prob.M
    X = StateFeatures("none")(ctx.q, ctx.dq, ctx.ddq, r).X
    rng = np.random.default_rng(seed)
    sq = np.zeros(ctx.n)
    hyper = None
    # it learns where the robust fit trusted every joint's equation: a push the separation
    # missed would otherwise become part of the function it predicts
    # (a joint's equation left out at rest carries weight zero and does not count)
    trusted = use if phys.weights is None else use & np.all((phys.weights > 0.5) | (M == 0), axis=1)
    if any(trusted[tr].sum() < 10 for tr, _ in prob.folds):
        trusted = use
    for k, (tr, te) in enumerate(prob.folds):
        tr, te = tr[trusted[tr]], te[use[te]]
        th_k = phys.grams.fit(S, phys.w, k) if S else np.zeros(0)
        res_tr = r[tr] - (A[tr][:, :, S] @ th_k if S else 0)
        res_te = r[te] - (A[te][:, :, S] @ th_k if S else 0)
        sub = np.sort(rng.choice(tr, min(points, len(tr)), replace=False))
        pos = np.searchsorted(tr, sub)
        if hyper is None:
            # hyperparameters (23 numbers per joint) are optimised once, on the first fold's
            # training part; every fold then conditions on its own training points only. The
            # optimisation is >95% of the GP cost, so this keeps the stage to a few seconds.
            gp = ExactGP(max_fit_points=min(hyper_points, len(sub)), max_iter=n_iter, coarse_fit_points=0,
                         seed=seed).fit(X[sub], res_tr[pos])
            hyper = gp.hyper_
        else:
            gp = ExactGP(seed=seed, hyper=hyper, optimise=False).fit(X[sub], res_tr[pos])
        mu = gp.predict(X[te], return_std=False)
        sq += (M[te] * (res_te - mu) ** 2).sum(0)
    return _nmse(sq, (M * use[:, None] > 0).sum(0), denom, ctx.joint_names)


def rescan_pushes(prob: Problem, ms, phys: PhysicsFit, previous: Separation, resid: np.ndarray, *, method: str,
                  push_alpha: float, em_modes: int, em_points: int, em_gate_peak: float, seed: int) -> Separation:
    """Pushes looked for again once the mode switch ``ms`` explains its part of the residual
    (``resid`` (T, n): the fitted physics' unfiltered residual, :func:`raw_residual`).

    The learner gating them then runs with at least two modes: with one it would call the rarer
    mode's samples disturbed and confirm everything; with two it learns both and confirms only
    what neither explains.
    """
    from .modes import mode_prediction, near_switches

    index = {a: i for i, a in enumerate(phys.keys)}
    C = phys.A[:, :, [index[a] for a in ms.effect.atoms()]]
    e = phys.residual(prob.r) - mode_prediction(ms, C)
    near = near_switches(ms, prob.t, prob.f_c, margin_s=prob.smear_s)
    disturbed, found = scan(prob, e, friction_band(phys.coefficients(), phys.ctx), push_alpha=push_alpha, exclude=near)
    info, em = {**previous.info, **found}, previous.em
    if method == "auto" and disturbed.any():
        # the learner of the mode switch, on the same residual, is reused
        em = run_learner(prob, max(2, em_modes), max_points=em_points, seed=seed, previous=em, resid=resid)
        disturbed, gate = sep.gate_spans(disturbed, em["p_disturbed"], peaks=found["peaks"], strong=em_gate_peak)
        info = {**info, **sep.em_summary(em), **gate}
    return Separation(disturbed, info, em)


def confirm_pushes(prob: Problem, phys: PhysicsFit, previous: Separation, near: np.ndarray, *,
                   push_alpha: float) -> Separation:
    """The pushes ``previous`` found, each span kept only where the final model's residual
    (the modes' own bodies in it) still shows it: a stretch that one mode's point-mass payload
    left unexplained but the mode's body explains was not a push. ``near`` (T,) bool: samples
    within a filter memory of a mode switch (left out of the scan)."""
    flagged, _ = scan(prob, phys.residual(prob.r), friction_band(phys.coefficients(), phys.ctx), push_alpha=push_alpha,
                      exclude=near)
    kept = np.zeros_like(previous.disturbed)
    for a, b in sep.runs(previous.disturbed):
        kept[a:b] = flagged[a:b].any()
    dropped = len(sep.runs(previous.disturbed)) - len(sep.runs(kept))
    return Separation(kept, {**previous.info, "spans_explained_by_final_model": dropped}, previous.em)


def raw_residual(prob: Problem, phys: PhysicsFit) -> np.ndarray:
    """(T, n) unfiltered residual of the fitted physics: ``r_raw`` less the chosen effects'
    unfiltered columns at the fitted coefficients."""
    if not phys.S:
        return prob.r_raw
    keys, A = build_atoms(phys.chosen, phys.ctx)
    coef = phys.coefficients()
    return prob.r_raw - A @ np.array([coef.get(k, 0.0) for k in keys])


class AttachedBody(Effect):
    """A rigid body attached to link ``index``: the link's ten inertial parameters (mass, first
    moments, inertia about the link origin), linear, physically consistent in an admissible fit
    (nothing attached is its nominal). Not a contract effect (no name): the yardstick a
    re-identified rigid body is judged against (``reidentify.reidentify``), since CONTRACT section 3
    names a rigid mass on the distal link a ``payload``, and such a mass has its own inertia,
    which ``Payload``'s point mass lacks."""

    scope = "link"

    def atoms(self):
        return tuple(("body", self.index, i) for i in range(10))

    def columns(self, ctx):
        Y = ctx.link_regressor(self.index)
        return [Y[:, :, i] for i in range(10)]

    def bodies(self, ctx):
        return [(self.atoms(), np.zeros(10))]

    @property
    def masses(self):
        return (self.atoms()[0],)

    def where(self, ctx):
        return {"link": ctx.link_names[self.index]}

    def affected_joints(self, ctx):
        return list(range(self.index + 1))


def without_body(prob: Problem) -> Problem:
    """The problem whose library is what a re-identified body must beat (``reidentify``): the
    library less the rigid body, each payload candidate a whole attached body (its ten
    parameters, ``AttachedBody``): the contract names any rigid mass on the distal link a payload,
    and a rigid mass has its own inertia, which a point mass lacks."""
    library = [AttachedBody(e.index) if e.name == "payload" else e for e in prob.library if e.scope != "model"]
    return dataclasses.replace(prob, library=library)


def with_modes(prob: Problem, ms) -> tuple[Problem, list]:
    """The problem once a mode switch is found: the switching effect leaves the library and a
    mode-gated rigid body (``modes.ModeBody``: the switching link's ten parameters, per mode
    that holds the effect) joins it, as an effect the selection starts from. Returns (problem,
    the effects to start from besides the re-identified body)."""
    from .modes import ModeBody

    present = [k for k, pm in enumerate(ms.per_mode) if pm.get("present")]
    body = ModeBody(ms.effect.index, ms.labels, present or [1])
    return dataclasses.replace(prob, library=[e for e in prob.library if e != ms.effect] + [body]), [body]
