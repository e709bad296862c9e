"""The first stage on a real robot: re-identify the rigid body, then judge the rest against it.

A URDF's inertial parameters are rarely right (CAD masses, no cables, no motors): the residual
``tau - tau_rbd`` of a real arm is then dominated by inertial-parameter errors, which hide
friction and offsets or get named as them (a "torque-sensor offset" that is a mis-modelled link
mass). The base parameters the trajectory determines (``mmgp.physics.identification``) are one
candidate effect, ``inertial_parameters`` (CONTRACT 1.1), decided *first* by a nested held-out
test: does the rigid body add significantly to the whole effect library (friction, springs,
offsets, armature, a payload on the distal link)? A log whose URDF is right gains nothing that
the library does not already hold; a real arm gains most of its residual. When it is taken,
every other effect is selected with it already in the model.

After selection, :func:`consistent_refit` refits the chosen model with each body physically
consistent (an LMI on its pseudo-inertia) and :func:`model_torque` gives the torque the model
says the joints transmit (the load of load-dependent friction).
"""
from __future__ import annotations

import numpy as np

from ..physics.effects import build_atoms
from ..physics.identification import fit_admissible, fit_consistent, identifiability
from .selection import FoldGrams, signed_rank_p


def rigid_body(library) -> list:
    """The library's rigid-body candidate (a list of at most one effect)."""
    return [e for e in library if e.scope == "model"]


def admissible_side(prob, fit, library, body: bool) -> tuple[np.ndarray, dict]:
    """One side of the re-identification test as columns (T, n, N) and the constraints of
    ``identification.fit_admissible`` on them: ``fit``'s atoms of ``library``'s effects (the rigid
    body's base columns left out), after the full regressor of every link the body may change when
    ``body``. What each side holds of the robot's masses is held physical: a payload's mass
    non-negative with its centre of mass within reach, an attached body and each body of the rigid
    body physically consistent, and every mass, added or a link's, at most the nominal robot's
    own (the plausibility rule of a payload). The other effects' signs are left free on both sides:
    held non-negative, the library alone cannot take what a negative armature or spring fits, and
    the body is credited with it as a lighter link, on a lever whose URDF is right
    (benchmarks/README.md, "2026-11-28 sixth session: held-pose payload")."""
    from .stages import rigid_regressor

    ctx = fit.ctx
    robot_mass = float(np.sum(ctx.pi0[0::10]))
    cols, bodies, upper, n = [], [], [], 0
    if body:
        Y = prob.lowpass(rigid_regressor(ctx.regressor, library))
        for k in range(len(ctx.pi0) // 10):
            if np.abs(Y[:, :, 10 * k:10 * k + 10]).max() > 0:
                p0 = ctx.pi0[10 * k:10 * k + 10]
                bodies.append((np.arange(n, n + 10), p0))
                upper.append((n, robot_mass - p0[0]))
                cols.append(Y[:, :, 10 * k:10 * k + 10])
                n += 10
    keep = [i for i, a in enumerate(fit.keys) if a[0] != "rb"]
    cols.append(fit.A[:, :, keep])
    index = {fit.keys[i]: n + j for j, i in enumerate(keep)}
    effects = [e for e in library if e.scope != "model"]
    bodies += [([index[a] for a in atoms], p0) for e in effects for atoms, p0 in e.bodies(ctx)]
    upper += [(index[a], robot_mass) for e in effects for a in e.masses]
    cones = [(index[m], [index[a] for a in h], r) for e in effects for m, h, r in e.cones(ctx)]
    nonneg = sorted({index[a] for e in effects for a in e.masses})
    return np.concatenate(cols, axis=2), {"bodies": bodies, "nonneg": nonneg, "cones": cones, "upper": upper}


def admissible_cv(prob, A: np.ndarray, constraints: dict, W: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Held-out squared errors (K, n) of the columns ``A`` (T, n, N), each fold's training part
    fitted under ``constraints`` (``fit_admissible``) with sample weights ``W`` (T, n) and joint
    weights ``w`` (n,)."""
    grams = FoldGrams(A, prob.r, np.ones(len(prob.t), bool), prob.folds, W=W)
    S = list(range(A.shape[2]))
    thetas = [fit_admissible(*grams.normal_equations(S, w, k), **constraints)[0] for k in range(grams.K)]
    return grams.test_errors(S, thetas)


def trusted_weights(prob, lib, lib_rest) -> np.ndarray:
    """(T, n) sample weights of the re-identification test: the smaller of the two robust fits'
    weights, and zero at every joint of a sample where either fit rejects a valid equation
    (weight zero): an external force loads every joint from the base to where it acts, so a push
    one joint's equation shows is in the others' too, below what their own fits can tell (UR5
    holding a pose: the second push, 5 N*m on the shoulder, kept its weight on the elbow, where
    the body's coupled gravity stiffness fitted it)."""
    W = np.minimum(lib.weights, lib_rest.weights)
    rejected = ((W <= 0) & (prob.M > 0)).any(axis=1)
    return W * ~rejected[:, None]


def reidentify(prob, lib, lib_rest, *, alpha: float, min_gain: float) -> tuple[list, dict]:
    """Whether the rigid body is re-identified: the paired held-out gain over the time blocks
    of the whole library plus the rigid body (``lib``) against the whole library alone
    (``lib_rest``, each payload a whole attached body), one-sided signed-rank test at level
    ``alpha`` over the number of candidates (as any candidate of a selection step), and a gain of
    at least ``min_gain`` of the held-out error the library alone leaves: the body must account for
    a material part of what is left. Measured against the nominal error instead, a real arm's body
    is never material: the library's springs, offsets and payload mimic most of an inertial
    mismatch (benchmarks/README.md, "sixth session: tuning history"). The payload links are not
    part of the body (``stages.rigid_regressor``), so a payload stays a payload.

    Each side is fitted at its own linearisation (``lib_rest`` relinearised without the body):
    the body's parameters of the links next to a payload's reproduce part of it, so at the whole
    library's fit a payload's centre of mass is far off. Each fold is fitted with its masses
    physical (``admissible_side``): on a pose held still the library's columns are nearly
    collinear (a static torque is an offset, a spring, an encoder offset or a mass alike), and
    unconstrained each side explains its training blocks with an impossible robot (UR5 holding
    2.5 kg: an attached body of -204 kg; with the body, links of tonnes) whose error on the
    held-out blocks decides the test. Both sides are scored alike, on the samples both robust fits trust
    (``trusted_weights``; each joint by its logged torque's variance): a push the body alone
    absorbs (UR5: a 16 N*m push held 2 s, fitted by base parameters of an upper arm of tonnes)
    is no gain of the body's. Returns (the effects the selection starts from, evidence)."""
    rb = rigid_body(prob.library)
    if not rb:
        return [], {}
    from .stages import torque_variance, without_body

    # each joint's error relative to its logged torque's variance (the report's nMSE), fixed before
    # either side is fitted. Not the nominal residual's: a joint the URDF already fits has a residual
    # at noise level, and its weight 1/noise^2 lets noise-level changes on the right joints outvote
    # a large cut on the wrong ones (benchmarks/README, the body on FIGAROH's rows)
    w = 1.0 / torque_variance(prob, np.ones(len(prob.t), bool))
    W = trusted_weights(prob, lib, lib_rest)
    e0 = admissible_cv(prob, *admissible_side(prob, lib_rest, without_body(prob).library, False), W, w) @ w
    e1 = admissible_cv(prob, *admissible_side(prob, lib, prob.library, True), W, w) @ w
    # tried as one more candidate of the selection's first step: the same family-wise level
    level = alpha / max(len(prob.library), 1)
    p, gain = signed_rank_p(e0 - e1), float((e0.sum() - e1.sum()) / max(e0.sum(), 1e-300))
    take = p < level and gain >= min_gain
    ev = {"p_value": p, "level": level, "held_out_gain": gain, "min_gain": min_gain, "re_identified": bool(take),
          "n_base_parameters": rb[0].base.n_base,
          "criterion": f"{len(prob.folds)}-fold time-block CV of the whole effect library with and without the "
                       f"rigid body (each relinearised at its own fit, each fold's masses physical, "
                       f"scored on the samples both robust fits trust; joints weighted by their torque's "
                       f"variance), one-sided Wilcoxon signed-rank test at level {level:.3g} (Bonferroni over "
                       f"the library's candidates) and a held-out gain >= {min_gain:g} of what the library leaves"}
    return (rb if take else []), ev


def _weighted_system(prob, ctx, A_e: np.ndarray, use: np.ndarray, w: np.ndarray):
    """Normal equations (G, c) of the full regressor (low-passed) next to effect columns ``A_e``
    (T, n, p), over valid equations of samples ``use`` with joint weights ``w``."""
    from .stages import rigid_regressor

    Y = prob.lowpass(rigid_regressor(ctx.regressor, prob.library))
    X = np.concatenate([Y, A_e], axis=2)[use]
    sw = np.sqrt(prob.M[use] * w[None, :])
    Xw = (X * sw[:, :, None]).reshape(-1, X.shape[2])
    return Xw.T @ Xw, Xw.T @ (prob.r[use] * sw).reshape(-1)


def consistent_refit(prob, phys, use: np.ndarray) -> tuple[dict, dict]:
    """The chosen model refitted with every body of the re-identified rigid body physically
    consistent and the effects' magnitudes non-negative. Returns (atom -> coefficient, with the
    full parameter change under ``("pi", i)``; evidence: solver status, condition number and
    the base parameters' names). Without a re-identified body: ({}, {})."""
    rb = rigid_body(phys.chosen)
    if not rb:
        return {}, {}
    base, ctx, keys = rb[0].base, phys.ctx, phys.keys
    others = [i for i in phys.S if keys[i][0] != "rb"]
    nonneg = np.array([any(keys[i] in e.nonneg for e in phys.chosen) for i in others], bool)
    G, c = _weighted_system(prob, ctx, phys.A[:, :, others], use, phys.w)
    x, info = fit_consistent(G, c, ctx.pi0, nonneg=nonneg)
    P = len(ctx.pi0)
    dpi = x[:P]
    beta = base.regroup @ dpi
    coef = {("rb", i): float(v) for i, v in enumerate(beta)}
    coef.update({keys[i]: float(v) for i, v in zip(others, x[P:])})
    coef.update({("pi", i): float(v) for i, v in enumerate(dpi)})
    rb_idx = [i for i in phys.S if keys[i][0] == "rb"]
    Gb, _ = phys.grams.normal_equations(rb_idx, phys.w)
    ev = {"solver_status": info["status"], **identifiability(Gb)}
    return coef, ev


def model_torque(prob, ctx, effects, coef: dict) -> np.ndarray:
    """(T, n) the torque the joints transmit by the model (N*m): the nominal rigid body plus
    every fitted effect that is physics rather than a sensor artefact, low-passed like the
    residual (its absolute value must not rectify noise)."""
    phys = [e for e in effects if not e.sensor]
    tau = ctx.tau_rbd.copy()
    if phys:
        keys, A = build_atoms(phys, ctx)
        th = np.array([coef.get(k, 0.0) for k in keys])
        tau = tau + A @ th
    return prob.lowpass(tau)
