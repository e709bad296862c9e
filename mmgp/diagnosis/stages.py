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

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..data.filtering import identity, lowpass_for
from ..data.logs import RobotLog
from ..models.robust import robust_regression
from ..physics.context import Context, build_context, pin_model, smooth_sign_scale
from ..physics.effects import build_atoms, effect_library
from . import separation as sep
from .selection import FoldGrams, atom_indices, signed_rank_p, time_folds


@dataclass(frozen=True)
class Problem:
    """What every stage reads: the (thinned) log's arrays, (T, n); ``r_raw`` = tau - tau_rbd and
    ``r`` its low-passed copy (N*m); ``lowpass`` the filter applied to ``r`` and to every column,
    ``f_c`` its cutoff (Hz, None: none); ``M`` (T, n) valid equations; ``folds`` time blocks;
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
    folds: list
    library: list
    n_samples_in_log: int
    smear_s: float = 0.0

    def atoms(self, ctx: Context) -> tuple[list, np.ndarray]:
        """Atom keys and low-passed columns (T, n, P) of the library in ``ctx``."""
        keys, A = build_atoms(self.library, ctx)
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

    if log.dq is None or log.ddq is None:
        edge = _edge_samples(differentiator, log)
        log = complete_derivatives(log, differentiator)
    else:
        edge = _edge_samples(differentiator, log) if (log.dq_estimated or log.ddq_estimated) else 0
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
    vs = smooth_sign_scale(dq, k=sign_noise_factor)
    ctx = build_context(robot, q, dq, log.ddq, v_s=vs, joint_names=names)
    r_raw = log.tau - ctx.tau_rbd
    lp, f_c = lowpass_for(t, dq) if lowpass else (identity, None)
    return Problem(t=t, tau=log.tau, ctx=ctx, r_raw=r_raw, r=lp(r_raw), lowpass=lp, f_c=f_c,
                   M=sep.valid_mask(dq, vs, t, f_c, factor=rest_factor), folds=time_folds(len(t), n_folds, t, f_c),
                   library=effect_library(ctx, effects=effects, payload_links=payload_links),
                   n_samples_in_log=n_samples_in_log, smear_s=smear_s)


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


def _robust_fit(prob: Problem, A: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Huber weights to convergence, then Tukey-bisquare steps from there: pushes get weight zero,
    # so they stand out in the residual instead of dragging the fit (least squares spreads a
    # push over every column; Huber still lets a long push outweigh a small effect)
    fit = robust_regression(A[use], prob.r[use], mask=prob.M[use], huber_steps=10, tukey_steps=5, tol=1e-4,
                            centre=False, solver="gram")
    weights = np.zeros_like(prob.r)
    weights[use] = fit.weights
    return fit.coef, weights


def fit_library(prob: Problem, ctx: Context, use: np.ndarray, *, relinearise: int = 0) -> LibraryFit:
    """Robust fit of the whole library on samples ``use`` (T,) bool, with ``relinearise`` rounds
    of moving linearised effects (payload centres of mass) to the fit and refitting."""
    keys, A = prob.atoms(ctx)
    coef, weights = _robust_fit(prob, A, use)
    if any(e.linearised for e in prob.library):
        for _ in range(relinearise):
            fitted = dict(zip(keys, coef))
            for e in prob.library:
                ctx = e.relinearise(fitted, ctx)
            keys, A = prob.atoms(ctx)
            coef, weights = _robust_fit(prob, A, use)
    return LibraryFit(ctx, keys, A, coef, weights)


def joint_weights(e: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(n,) inverse residual variance per joint of residual ``e`` over valid equations ``M``
    (a GLS weighting of the joints)."""
    sig2 = (M * e ** 2).sum(0) / np.maximum(M.sum(0), 1)
    return 1.0 / (sig2 + 1e-12 * (sig2.max() + 1e-300))


@dataclass(frozen=True)
class Separation:
    """Pushed samples ``disturbed`` (T,) bool, what the separation reports (``info``), and the
    learner's last run (``em``, None when it did not run)."""

    disturbed: np.ndarray
    info: dict
    em: dict | None


def run_learner(prob: Problem, n_modes: int, *, max_points: int, seed: int, previous: dict | None = None) -> dict:
    """The learner's separation on the nominal residual (reusing ``previous`` when it had as
    many modes)."""
    if previous is not None and previous["n_modes"] == n_modes:
        return previous
    ctx = prob.ctx
    return sep.em_separate(prob.r_raw, ctx.q, ctx.dq, ctx.ddq, prob.t, n_modes=n_modes, max_points=max_points,
                           seed=seed)


def separate_pushes(prob: Problem, lib: LibraryFit, selector, *, method: str, push_alpha: float, em_modes: int,
                    em_points: int, em_gate_peak: float, seed: int) -> Separation:
    """Which samples an external force disturbed (``method``: see ``SEPARATION_METHODS``).

    Physics first, pushes from what it leaves: effects are selected on the robust fit's weights
    (pushes carry small weights there), then the residual of the *selected* model is scanned.
    Scanning the full library's residual instead would see an over-fitted, too-quiet residual
    wherever the log has few independent samples (slow trajectories).
    """
    T = len(prob.t)
    info = {"method": sep.SEPARATION_METHODS[method]}
    if method == "none":
        return Separation(np.zeros(T, bool), info, None)
    if method == "em":
        # the learner alone: its flags, at its own (thinned) resolution
        em = run_learner(prob, em_modes, max_points=em_points, seed=seed)
        return Separation(em["p_disturbed"] > 0.5, {**info, **sep.em_summary(em)}, em)
    w0 = joint_weights(prob.r - lib.A @ lib.coef, prob.M)
    g0 = FoldGrams(lib.A, prob.r, np.ones(T, bool), prob.folds, W=lib.weights)
    chosen = selector.fit(prob.library, lib.keys, g0, w0, lib.ctx).selected_
    S0 = atom_indices(chosen, {a: i for i, a in enumerate(lib.keys)})
    e0 = prob.r - (lib.A[:, :, S0] @ g0.fit(S0, w0) if S0 else 0.0)
    disturbed, scan = sep.scan_disturbances(e0, prob.t, f_c=prob.f_c, valid=prob.M > 0, alpha=push_alpha)
    info = {**info, **scan}
    em = None
    if method == "auto" and disturbed.any():
        # as a gate the learner can only drop spans: with none scanned it is not needed
        em = run_learner(prob, em_modes, max_points=em_points, seed=seed)
        disturbed, gate = sep.gate_spans(disturbed, em["p_disturbed"], peaks=scan["peaks"], strong=em_gate_peak)
        info = {**info, **sep.em_summary(em), **gate}
    return Separation(disturbed, info, em)


def nnls_gram(G: np.ndarray, c: np.ndarray, nonneg: np.ndarray) -> np.ndarray:
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


@dataclass(frozen=True)
class PhysicsFit:
    """The chosen effects refitted: atoms ``S`` (indices into ``keys``) with coefficients
    ``coef`` (|S|,) and block-jackknife covariance ``cov`` (|S|, |S|); ``grams`` of ``A`` in
    ``ctx``; ``w`` (n,) joint weights."""

    ctx: Context
    keys: list
    A: np.ndarray
    grams: FoldGrams
    chosen: list
    S: list
    coef: np.ndarray
    cov: np.ndarray
    w: np.ndarray

    def coefficients(self) -> dict:
        """atom key -> fitted coefficient."""
        return {self.keys[i]: float(v) for i, v in zip(self.S, self.coef)}

    def residual(self, r: np.ndarray) -> np.ndarray:
        """(T, n) what the fitted effects leave of ``r``."""
        return r - (self.A[:, :, self.S] @ self.coef if self.S else 0.0)


def fit_physics(prob: Problem, lib: LibraryFit, grams: FoldGrams, chosen: list, w: np.ndarray,
                use: np.ndarray, *, relinearise: int = 3) -> PhysicsFit:
    """Non-negative least squares of the chosen effects on samples ``use``, with ``relinearise``
    rounds for linearised effects (a payload's point-mass inertia at its fitted centre of mass),
    and a block jackknife over the folds for the covariance: honest under time-correlated
    residuals."""
    ctx, keys, A = lib.ctx, lib.keys, lib.A
    S = atom_indices(chosen, {a: i for i, a in enumerate(keys)})
    nonneg = np.array([any(keys[i] in e.nonneg for e in chosen) for i in S], bool)
    coef = nnls_gram(*grams.normal_equations(S, w), nonneg)
    for _ in range(relinearise if any(e.linearised for e in chosen) else 0):
        fitted = {keys[i]: v for i, v in zip(S, coef)}
        for e in chosen:
            ctx = e.relinearise(fitted, ctx)
        keys, A = prob.atoms(ctx)
        grams = FoldGrams(A, prob.r, use, prob.folds, W=prob.M)
        coef = nnls_gram(*grams.normal_equations(S, w), nonneg)
    K = grams.K
    thK = np.array([nnls_gram(*grams.normal_equations(S, w, k), nonneg) for k in range(K)]) if S else np.zeros((K, 0))
    dev = thK - thK.mean(0)
    return PhysicsFit(ctx, keys, A, grams, list(chosen), S, coef, (K - 1) / K * dev.T @ dev, w)


def _evidence(phys: PhysicsFit, e, err_phys: np.ndarray, alpha: float) -> tuple[dict, int]:
    """Held-out evidence for effect ``e`` in the fitted model: the model without it (and what
    it nests) against the model with it, per fold; and the joint it helps most."""
    index = {a: i for i, a in enumerate(phys.keys)}
    ctx, K, w, names = phys.ctx, phys.grams.K, phys.w, phys.ctx.joint_names
    # an effect nested in a reported one (Coulomb in load-dependent) goes with it
    S_wo = [i for i in atom_indices([o for o in phys.chosen if o is not e], index) if phys.keys[i] not in e.atoms()]
    err_wo = phys.grams.cv_errors(S_wo, w)
    per_joint = 1 - err_phys.sum(0) / np.maximum(err_wo.sum(0), 1e-300)
    d = (err_wo - err_phys) @ w
    aff = e.affected_joints(ctx)
    jmain = max(aff, key=lambda j: per_joint[j]) if aff else int(np.argmax(per_joint))
    return {"cv_error_reduction": float(per_joint[jmain]),
            "cv_error_reduction_joint": names[jmain],
            "cv_error_reduction_per_joint": {names[j]: float(per_joint[j]) for j in aff},
            "cv_improvement_in_se": float(d.mean() / (d.std(ddof=1) / np.sqrt(K) + 1e-300)),
            "p_value_without_it": signed_rank_p(d),
            "selection_step": phys.chosen.index(e) + 1,
            "criterion": f"{K}-fold time-block CV, one-sided Wilcoxon signed-rank test of the paired held-out "
                         f"gains at family-wise level {alpha:g} (Bonferroni over each step's candidates)"}, jmain


def effect_findings(phys: PhysicsFit, *, alpha: float) -> list[dict]:
    """One finding per chosen effect that no other chosen effect contains."""
    from .result import effect_finding

    err_phys = phys.grams.cv_errors(phys.S, phys.w)
    coef = phys.coefficients()
    cov = {(phys.keys[a], phys.keys[b]): float(phys.cov[ia, ib])
           for ia, a in enumerate(phys.S) for ib, b in enumerate(phys.S)}
    findings = []
    for e in phys.chosen:
        if any(o is not e and o.index == e.index and e.name in o.supersedes for o in phys.chosen):
            continue
        ev, jmain = _evidence(phys, e, err_phys, alpha)
        params, std = e.params(coef, cov)
        findings.append(effect_finding(e, params, std, {**ev, "params_std": std}, phys.ctx, jmain))
    return findings


def _nmse(sq: np.ndarray, nte: np.ndarray, denom: np.ndarray, names: list) -> dict:
    nm = sq / nte / denom
    return {"nmse": {names[j]: float(nm[j]) for j in range(len(names))}, "mean_nmse": float(nm.mean())}


def torque_variance(prob: Problem, use: np.ndarray) -> np.ndarray:
    """(n,) variance of each joint's logged torque over samples ``use`` (N*m)^2: the normaliser
    of the held-out errors."""
    tau = prob.tau[use]
    return np.array([np.sum((tau[:, j] - tau[:, j].mean()) ** 2) / use.sum() for j in range(tau.shape[1])]) + 1e-300


def stage_errors(phys: PhysicsFit, denom: np.ndarray) -> dict:
    """Held-out normalised MSE per joint of the nominal model and of nominal + found physics:
    fold-wise squared error over the torque's variance ``denom`` (n,)."""
    names, g = phys.ctx.joint_names, phys.grams
    nte = g.nte.sum(0)
    return {"nominal": _nmse(g.cv_errors([], phys.w).sum(0), nte, denom, names),
            "with_physics": _nmse(g.cv_errors(phys.S, phys.w).sum(0), nte, denom, names)}


def gp_stage_errors(prob: Problem, phys: PhysicsFit, use: np.ndarray, denom: np.ndarray, *, points: int,
                    hyper_points: int, n_iter: int, seed: int) -> dict:
    """Held-out normalised MSE per joint of nominal + physics + a GP (``ExactGP`` on
    [q, dq, ddq]) fitted per fold to what the fold's physics fit leaves."""
    from ..gp.exact import ExactGP

    ctx, S, A, r, M = phys.ctx, phys.S, phys.A, prob.r, prob.M
    X = np.concatenate([ctx.q, ctx.dq, ctx.ddq], axis=1)
    rng = np.random.default_rng(seed)
    sq = np.zeros(ctx.n)
    hyper = None
    for k, (tr, te) in enumerate(prob.folds):
        tr, te = tr[use[tr]], te[use[te]]
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
            gp = ExactGP(seed=seed).fit(X[sub], res_tr[pos], hyper=hyper, optimise=False)
        mu = gp.predict(X[te], return_std=False)
        sq += (M[te] * (res_te - mu) ** 2).sum(0)
    return _nmse(sq, phys.grams.nte.sum(0), denom, ctx.joint_names)


def rescan_pushes(prob: Problem, ms, phys: PhysicsFit, previous: Separation, *, method: str, push_alpha: float,
                  em_modes: int, em_points: int, em_gate_peak: float, seed: int) -> Separation:
    """Pushes looked for again once the mode switch ``ms`` explains its part of the residual.

    The learner gating them then runs with at least two modes: with one it would call the rarer
    mode's samples disturbed and confirm everything; with two it learns both (99.9% agreement
    with the simulator's modes on panda_modes) and confirms only what neither explains.
    """
    from .modes import mode_prediction, near_switches

    index = {a: i for i, a in enumerate(phys.keys)}
    C = phys.A[:, :, [index[a] for a in ms.effect.atoms()]]
    e = phys.residual(prob.r) - mode_prediction(ms, C)
    valid = (prob.M > 0) & ~near_switches(ms, prob.t, prob.f_c, margin_s=prob.smear_s)[:, None]
    disturbed, scan = sep.scan_disturbances(e, prob.t, f_c=prob.f_c, valid=valid, alpha=push_alpha)
    info, em = {**previous.info, **scan}, previous.em
    if method == "auto" and disturbed.any():
        em = run_learner(prob, max(2, em_modes), max_points=em_points, seed=seed, previous=em)
        disturbed, gate = sep.gate_spans(disturbed, em["p_disturbed"], peaks=scan["peaks"], strong=em_gate_peak)
        info = {**info, **sep.em_summary(em), **gate}
    return Separation(disturbed, info, em)
