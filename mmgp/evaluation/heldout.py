"""Held-out score of a trained model (``report.json`` -> ``heldout``, the ``mmgp train`` summary
and report.html): does the learnt model predict torque it has not seen, and is it better than
the nominal rigid body and than the torque's mean?

Choices (docs/training.md, "Held-out score"):

* **No EM per fold** (it would multiply the training time by the number of folds). The labels
  (mode, disturbed) and each mode's GP hyperparameters are the trained model's; they saw every
  block, so the figure is a little optimistic about those. What is held out is what a GP
  remembers: the samples it conditions on, and the coefficients of its rigid-body mean basis.
* **Time blocks**: the samples (all logs end to end) are split into ``n_folds`` contiguous
  blocks (:func:`mmgp.data.folds.time_block_folds`, as ``mmgp compare``); ``gap`` samples on each
  side of the test block are kept out of training, the longest derivative window training may
  have used (:func:`mmgp.data.folds.default_gap` at ``diff_window_s``, or the cross-validated
  windows' upper bound, 0.5 s, when derivatives were estimated), capped at a quarter of a block
  so a short log keeps its training samples (the cap is reported: ``gap``).
* **Per fold and mode**: mode k's GP is conditioned, with the model's hyperparameters fixed in
  data units (no optimisation), on the training blocks' samples mode k's GP learnt from
  (labelled undisturbed in mode k, less those where a joint may be stuck: the model's
  ``MultimodalSEM.members_``), evenly spaced down to the model's own support size for that
  mode and at most ``max_support`` (default 2,000; above, the figure is pessimistic); with a
  mean basis, its
  coefficients are refitted on those samples (the model's robust fit); it predicts the test
  block's samples labelled undisturbed in mode k. A mode with fewer than max(5, joints) training
  samples in a fold leaves its test samples unscored (``n_unscored``). The fold GP is always
  exact (a model whose GPs are SGPR is scored with an exact GP on ``max_support`` samples).
* **Only undisturbed samples are scored**: a disturbed sample's torque holds an external torque
  no model of the robot can predict. The model, the rigid body and the mean are scored on the
  same samples, pooled over folds; a stuck joint's samples are scored (the model's GP did not
  learn from them, but its prediction there is what a user gets).
* **Figures**: normalised MSE per joint (:func:`mmgp.evaluation.metrics.normalised_mse`: 0 is
  perfect, 1 is predicting the scored samples' own mean) of ``model``; ``rigid_body`` (the
  nominal model's inverse dynamics, nothing fitted; null without a robot model); ``mean``: each
  test block predicted by the mean torque of its fold's training samples, computed, not 1 by
  definition (it is a little above 1: the training blocks' mean is not the scored samples').
"""
from __future__ import annotations

import time

import numpy as np

from ..data.differentiation import SavitzkyGolay
from ..data.folds import default_gap, time_block_folds
from ..gp.exact import ExactGP
from ..gp.hyper import Hyper, Standardiser
from ..labelling.mstep import ModeFitter, evenly_spaced
from ..physics.plausibility import fit_warnings
from ..progress import report
from .metrics import HELDOUT_LABELS, normalised_mse

__all__ = ["heldout_score", "heldout_warnings", "format_heldout"]

SCORED = "undisturbed samples only: a disturbed sample's torque holds an unmeasured external torque"


def heldout_score(model, *, n_folds: int = 5, max_support: int = 2000, gap: int | None = None) -> dict:
    """Held-out normalised MSE per joint of a :class:`mmgp.MultimodalGP` just fitted (it needs
    ``logs_`` and ``features_``, which :meth:`~mmgp.MultimodalGP.load` does not restore), of the
    nominal rigid body and of the torque's mean (module docstring). ``gap`` None: the module's
    rule. Returns a JSON-able dict: ``scored`` (what was scored), ``n_folds``, ``gap`` (samples),
    ``gap_s``, ``max_support``, ``support`` (per mode, the most samples a fold's GP conditioned
    on), ``n_scored``, ``n_disturbed_left_out``, ``n_unscored``, ``joint_names``, ``nmse``
    {model, rigid_body (or None), mean: (n,) lists, or None when nothing could be scored},
    ``mean_predictor`` and ``seconds``."""
    t0 = time.perf_counter()
    report(f"held-out score: {n_folds} time blocks")
    feats = model.features_
    tau = np.concatenate([lg.tau for lg in model.logs_])
    T, n = tau.shape
    gap = _gap(model, feats.t, T, n_folds) if gap is None else int(gap)
    folds = time_block_folds(T, n_folds, gap)
    undisturbed = ~np.asarray(model.disturbed_, bool)
    pred_y, support = _model_predictions(model, folds, undisturbed, max_support)
    use = undisturbed & np.isfinite(pred_y).all(1)
    preds = {"model": pred_y + (tau - feats.Y), "rigid_body": _rigid_body(model, tau), "mean": np.empty_like(tau)}
    for train, test in folds:
        preds["mean"][test] = tau[train[undisturbed[train]]].mean(0) if undisturbed[train].any() else np.nan
    use &= np.isfinite(preds["mean"]).all(1)
    nmse = {m: (None if p is None or use.sum() < 2 else normalised_mse(tau[use], p[use]).tolist())
            for m, p in preds.items()}
    dt = float(np.median(np.diff(feats.t))) if T > 1 else 0.0
    return {"scored": SCORED, "n_folds": int(n_folds), "gap": int(gap), "gap_s": gap * dt,
            "max_support": int(max_support), "support": support, "n_scored": int(use.sum()),
            "n_disturbed_left_out": int((~undisturbed).sum()), "n_unscored": int((undisturbed & ~use).sum()),
            "joint_names": list(model.joint_names_), "nmse": nmse,
            "mean_predictor": "each test block predicted by its fold's training-sample mean (computed, not 1 "
                              "by definition)",
            "seconds": time.perf_counter() - t0}


def heldout_warnings(heldout: dict, joint_names: list) -> list[str]:
    """The fit warnings (:func:`mmgp.physics.plausibility.fit_warnings`) of a held-out score:
    the nominal rigid body's and the learnt model's normalised MSE per joint."""
    nmse = heldout["nmse"]
    return fit_warnings(joint_names, nmse["rigid_body"], nmse["model"])


def _gap(model, t: np.ndarray, T: int, n_folds: int) -> int:
    """The longest derivative window training may have used, in samples, at most a quarter block."""
    estimated = any(lg.dq_estimated or lg.ddq_estimated for lg in model.logs_)
    window = model.diff_window_s
    if window is None and estimated:
        window = SavitzkyGolay().max_window_s     # the cross-validated windows' upper bound
    return min(default_gap(t, window), T // (4 * n_folds))


def _model_predictions(model, folds, undisturbed: np.ndarray, max_support: int) -> tuple[np.ndarray, list]:
    """Out-of-fold predictions (T, n) of the GP targets (NaN where not scored) and, per mode, the
    most samples a fold's GP conditioned on."""
    feats = model.features_
    X, Y = feats.X, feats.Y
    T, n = Y.shape
    modes = np.asarray(model.modes_)
    fitter = ModeFitter(X, Y, model.sem_.settings.fitter, basis=feats.basis)
    pred = np.full((T, n), np.nan)
    support = [0] * model.n_modes_
    for train, test in folds:
        for k in range(model.n_modes_):
            learnt = np.zeros(T, bool)
            learnt[model.sem_.members_[k]] = True
            tr, te = train[learnt[train]], test[(undisturbed & (modes == k))[test]]
            if not len(te) or len(tr) < max(5, n):
                continue
            offset = np.zeros((T, n))
            if model.basis_coef_[k] is not None:
                offset = np.einsum("tjp,jp->tj", feats.basis, fitter.basis_coefficients(tr))
            sub = evenly_spaced(tr, min(len(model.support_Y_[k]), max_support))
            support[k] = max(support[k], int(len(sub)))
            gp = _fold_gp(model, k, X[sub], Y[sub] - offset[sub])
            pred[te] = gp.predict(X[te], return_std=False).reshape(len(te), n) + offset[te]
    return pred, support


def _fold_gp(model, k: int, X: np.ndarray, Y: np.ndarray) -> ExactGP:
    """An exact GP on X (N, d) -> Y (N, n) with mode k's hyperparameters fixed in data units.

    Hyperparameters live in the units of the inputs and targets the GP standardised itself on; a
    fold's samples standardise a little differently, so they are carried over: lengthscale x
    (model's input scale / fold's), variances x (model's target scale / fold's)^2. An isotropic
    lengthscale becomes one per input, which the kernel takes as it is."""
    g = model.gp(k)
    sx, sy = Standardiser().fit(X).scale_, Standardiser().fit(Y).scale_
    rx, ry = g.x_scaler_.scale_ / sx, (g.y_scaler_.scale_ / sy) ** 2
    h = g.hyper_
    hyper = Hyper(np.asarray(h.lengthscale) * rx[None, :], np.asarray(h.signal_var) * ry, np.asarray(h.noise_var) * ry)
    return ExactGP(ard=model.ard, device=model.device, hyper=hyper, optimise=False).fit(X, Y)


def _rigid_body(model, tau: np.ndarray) -> np.ndarray | None:
    """The nominal rigid body's torque (T, n) at the logged states, or None without a robot model."""
    if model.robot_ is None:
        return None
    if model.features_.tau_rbd is not None:
        return model.features_.tau_rbd
    q, dq, ddq = (np.concatenate([getattr(lg, a) for lg in model.logs_]) for a in ("q", "dq", "ddq"))
    return model.robot_.rnea(q, dq, ddq)


def format_heldout(h: dict) -> str:
    """Plain-text table: one row per joint, the held-out nMSE of the model, the rigid body, the mean."""
    head = (f"held-out normalised MSE ({h['n_folds']} time blocks, gap {h['gap']} samples; {h['n_scored']} "
            f"undisturbed samples scored, {h['n_disturbed_left_out']} disturbed left out; 0 perfect, "
            "1 = the torque's mean)")
    if h["nmse"]["model"] is None:
        return head + ": too few samples to score"
    width = max([5] + [len(j) for j in h["joint_names"]]) + 2
    lines = [head, f"{'joint':<{width}}" + "".join(f"{label:>12}" for label in HELDOUT_LABELS.values())]
    for j, name in enumerate(h["joint_names"]):
        cells = [h["nmse"][m][j] if h["nmse"][m] is not None else None for m in HELDOUT_LABELS]
        lines.append(f"{name:<{width}}" + "".join(f"{'-':>12}" if v is None else f"{v:>12.4g}" for v in cells))
    return "\n".join(lines)
