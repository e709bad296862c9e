"""The training report (``report.json``): what was learned, from what, and how the EM went; and the
labels table (``labels.parquet``)."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .._version import __version__
from ..data.logs import RobotLog
from ..physics.plausibility import log_warnings
from .features import input_names


def training_report(*, settings: dict, sem, logs: Sequence[RobotLog], joint_names: list[str],
                    robot_spec: dict | None, semiparametric: str, mean_basis,
                    with_friction: bool, mode_selection: dict | None, timings: dict, robot=None) -> dict:
    """The report of one training run: ``sem`` a fitted MultimodalSEM on ``logs``; ``settings``
    the estimator's JSON-able settings; ``timings`` in s; ``robot`` the RobotModel or None, for
    the log checks (``warnings``: :func:`mmgp.physics.plausibility.log_warnings`)."""
    n = len(joint_names)
    return {
        "mmgp_version": __version__,
        "logs": [lg.path for lg in logs],
        "n_samples": int(sum(lg.n_samples for lg in logs)),
        "n_joints": n,
        "joint_names": joint_names,
        "derivatives_estimated": {"dq": any(lg.dq_estimated for lg in logs),
                                  "ddq": any(lg.ddq_estimated for lg in logs)},
        "robot": robot_spec,
        "warnings": log_warnings(logs, joint_names, robot),
        "semiparametric": semiparametric,
        # The per-mode coefficients themselves are in model.npz (basis_coef_<k>).
        "mean_basis": {"kind": mean_basis.name if mean_basis is not None else None, "rank": int(sem.basis_rank_)},
        "config": settings,
        "n_modes": len(sem.gps_),
        "mode_selection": mode_selection,
        "hyperparameters": [
            {"mode": k, "per_joint": [
                {"joint": joint_names[j], "lengthscale": g.lengthscale_[j].tolist(),
                 "signal_std": float(math.sqrt(g.hyper_.signal_var[j]) * g.y_scaler_.scale_[j]),
                 "noise_std": float(g.noise_std_[j])} for j in range(n)],
             "inputs": input_names(n, semiparametric == "feature", with_friction),
             "n_support": int(len(sem.support_Y_[k]))}
            for k, g in enumerate(sem.gps_)],
        "disturbance": {"enabled": sem.settings.disturbance, "sigma_d_std": np.sqrt(sem.sigma_d_).tolist(),
                        "p_enter": sem.p_enter_, "p_leave": sem.p_leave_,
                        "n_disturbed": int(sem.disturbed_.sum()),
                        # log-evidence gain of the disturbance states over their BIC price;
                        # <= 0 with abstain on: the chain flags nothing (a log without pushes).
                        "evidence_gain": float(getattr(sem, "disturbance_gain_", 0.0)),
                        # samples the sustained-offset scan added (before the shortest-push rule)
                        "n_by_scan": int(getattr(sem, "scan_flagged_", 0)),
                        "abstained": bool(sem.settings.disturbance and sem.settings.abstain
                                          and getattr(sem, "disturbance_gain_", 1.0) <= 0.0)},
        # rest_band: each mode's friction band at rest (median half-width over resting
        # samples, N*m, per joint); zeros when it is off or nothing rests
        "friction_band_half_width": np.asarray(getattr(sem, "friction_band_", np.zeros((1, n)))).tolist(),
        "deterministic": sem.settings.estep == "mpm",
        "switching_prior": {"stay_prob": sem.stay_prob_, "learned": sem.settings.stay_prob is None},
        "likelihood_trace": [{"sweep": r.sweep, "log_joint": r.log_joint, "log_marginal": r.log_marginal,
                              "changed": r.changed, "n_disturbed": r.n_disturbed, "mode_sizes": r.mode_sizes,
                              "seconds": r.seconds} for r in sem.trace_],
        "converged": bool(sem.converged_),
        # the sweep whose labels were kept where the sweeps did not converge (None: averaged)
        "labels_from_sweep": getattr(sem, "labels_sweep_", None),
        "n_sweeps": int(sem.n_sweeps_),
        "timings": timings,
    }


def labels_frame(sem, logs: Sequence[RobotLog]):
    """The contract's labels table: t, (log), mode, disturbed, p_disturbed, p_mode_<k>."""
    import pandas as pd

    t = np.concatenate([lg.t for lg in logs])
    df = pd.DataFrame({"t": t, "mode": sem.labels_.astype(np.int64),
                       "disturbed": sem.disturbed_.astype(np.int64), "p_disturbed": sem.p_disturbed_})
    for k in range(sem.p_mode_.shape[1]):
        df[f"p_mode_{k}"] = sem.p_mode_[:, k]
    if len(logs) > 1:
        df.insert(1, "log", np.concatenate([np.full(lg.n_samples, i) for i, lg in enumerate(logs)]))
    return df
