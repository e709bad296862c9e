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
from ..physics.identification import fit_consistent, identifiability
from .selection import FoldGrams, signed_rank_p


def rigid_body(library) -> list:
    """The library's rigid-body candidate (a list of at most one effect)."""
    return [e for e in library if e.scope == "model"]


def reidentify(prob, lib, lib_rest, *, alpha: float, min_gain: float) -> tuple[list, dict]:
    """Whether the rigid body is re-identified: the paired held-out gain over the time blocks
    of the whole library plus the base parameters (``lib``) against the whole library alone
    (``lib_rest``), one-sided signed-rank test at level ``alpha`` over the number of candidates
    (as any candidate of a selection step), and a gain of at least ``min_gain`` of the held-out
    error the library alone leaves: the body must account for a material part of what is left.
    Measured against the nominal error instead, a real arm's body is never material: the
    library's springs, offsets and payload mimic most of an inertial mismatch
    (benchmarks/README.md, "sixth session: tuning history"). The payload links are
    not part of the body (``stages.rigid_regressor``), so a payload stays a payload.

    Each side is scored at its own linearisation (``lib_rest`` relinearised without the body):
    the body's parameters of the links next to a payload's reproduce part of it (a mass on the
    distal link's axis), so at the whole library's fit a payload's centre of mass is far off
    and the library alone, held there, seems to leave what the body then takes (the body
    re-identified, the payload found too light; relinearised on its own the library leaves
    almost none of the nominal error). Both sides
    are weighted alike (the whole library's robust weights; each joint by its logged torque's
    variance), so the blocks' errors pair. Returns (the effects the selection starts from, evidence)."""
    rb = rigid_body(prob.library)
    if not rb:
        return [], {}
    from .stages import torque_variance

    ones = np.ones(len(prob.t), bool)
    # each joint's error relative to its logged torque's variance (the report's nMSE), fixed before
    # either side is fitted. Not the nominal residual's: a joint the URDF already fits has a residual
    # at noise level, and its weight 1/noise^2 lets noise-level changes on the right joints outvote
    # a large cut on the wrong ones (benchmarks/README, the body on FIGAROH's rows)
    w = 1.0 / torque_variance(prob, ones)

    def cv(fit):
        # every atom of the fit's own library
        grams = FoldGrams(fit.A, prob.r, ones, prob.folds, W=lib.weights)
        return grams.cv_errors(list(range(len(fit.keys))), w) @ w, grams.K

    (e0, _), (e1, K) = cv(lib_rest), cv(lib)
    # tried as one more candidate of the selection's first step: the same family-wise level
    level = alpha / max(len(prob.library), 1)
    p, gain = signed_rank_p(e0 - e1), float((e0.sum() - e1.sum()) / max(e0.sum(), 1e-300))
    take = p < level and gain >= min_gain
    ev = {"p_value": p, "held_out_gain": gain, "min_gain": min_gain, "re_identified": bool(take),
          "n_base_parameters": rb[0].base.n_base,
          "criterion": f"{K}-fold time-block CV of the whole effect library with and without the base "
                       f"parameters (each relinearised at its own fit; joints weighted by their torque's variance), one-sided Wilcoxon signed-rank test at "
                       f"level {level:.3g} (Bonferroni over the library's candidates) and a held-out gain >= "
                       f"{min_gain:g} of what the library leaves"}
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
