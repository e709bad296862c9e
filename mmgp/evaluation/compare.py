"""Held-out comparison of rigid-body only, GP only and rigid-body + GP inverse dynamics.

The three predictors of the joint torque ``tau`` (T, n) N*m from ``[q, dq, ddq]``:

* ``rigid_body``: the nominal model's inverse dynamics ``tau_rbd = RNEA(q, dq, ddq)``; nothing is
  fitted, so its held-out error is its error on the test samples.
* ``gp``: an exact RBF GP (:class:`mmgp.gp.ExactGP`, one per joint, ARD) on ``[q, dq, ddq] -> tau``.
* ``rigid_body_gp``: the same GP on the residual ``tau - tau_rbd`` with ``tau_rbd`` added back
  (the rigid-body model is the GP's mean function).

Samples are split into contiguous time blocks (:func:`mmgp.signals.time_block_folds`), never at
random: neighbouring samples of a log are nearly copies of each other, and estimated derivatives
at a sample are made from the raw positions of its neighbours, so a random split would score
interpolation between training samples. ``gap`` samples on each side of a test block are kept out
of training; the default is the length of the default Savitzky-Golay window, the smallest gap
at which no raw sample feeds the derivative estimate of both a training and a test sample.

Every sample is predicted exactly once (by the fold whose test block holds it); the figures are
the normalised MSE per joint of these pooled out-of-fold predictions
(:func:`mmgp.evaluate.normalised_mse`: 0 is perfect, 1 is as good as predicting the log's mean).

``mmgp compare LOG --out DIR`` calls :func:`compare` and :func:`write_compare`.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .metrics import COMPARE_LABELS, normalised_mse
from ..threads import limit_threads
from ..gp.exact import ExactGP
from ..gp.linalg import resolve_device
from ..data.logs import RobotLog
from ..errors import InputError
from ..data.outputs import atomic_write_bytes, jsonable, write_figure
from ..data.folds import default_gap, spread_subset, time_block_folds
from ..labelling.features import StateFeatures
from ..physics.plausibility import fit_warnings, log_warnings

__all__ = ["METHODS", "default_gap", "compare", "format_compare", "write_compare"]

METHODS = tuple(COMPARE_LABELS)


def _fit_gp(X: np.ndarray, Y: np.ndarray, t: np.ndarray, opts: dict, hyper_fit: str, block_s: float) -> ExactGP:
    """ExactGP on X (N, d) -> Y (N, m) sampled at times t (N,) s, hyperparameters chosen by
    ``hyper_fit``: "loo" (ExactGP's own leave-one-out) or "block" (leave-time-block-out)."""
    if hyper_fit == "loo":
        return ExactGP(**opts).fit(X, Y)
    gp = ExactGP(**opts)
    k = min(len(X), int(gp.max_fit_points))
    fit_idx = np.unique(np.linspace(0, len(X) - 1, k).round().astype(int))
    hyper = gp.block_hyper(X[fit_idx], Y[fit_idx], t[fit_idx], block_s)
    return ExactGP(**opts, hyper=hyper, optimise=False).fit(X, Y)


def compare(log: RobotLog, robot=None, *, n_folds: int = 5, gap: int | None = None, max_train: int = 2000,
            seed: int = 0, gp_options: dict | None = None, hyper_fit: str = "block", block_s: float = 2.0,
            progress=None) -> dict:
    """Held-out normalised MSE per joint of the three predictors (module docstring).

    ``log``: a :class:`mmgp.io.RobotLog` with ``dq`` and ``ddq`` present (run
    :func:`mmgp.signals.complete_derivatives` first); ``robot``: a :class:`mmgp.robot.RobotModel`
    of the log's joints, or None (then only ``gp`` is scored). ``n_folds`` time blocks; ``gap``
    samples dropped from training on each side of the test block (None: :func:`default_gap`);
    each fold's GP conditions on at most ``max_train`` training samples drawn at random (``seed``).
    ``gp_options``: keyword arguments of :class:`mmgp.gp.ExactGP` (defaults: ARD, hyperparameters
    fitted on 400 evenly spaced ones of those samples, 60 L-BFGS iterations, CPU; the block
    objective costs O(fit points^3) per iteration, the conditioning on ``max_train`` samples is
    done once per fold).
    ``hyper_fit``: how hyperparameters are chosen on the training samples: "block" (default;
    leave-time-block-out log predictive, blocks of ``block_s`` s, :func:`mmgp.gp.objectives.leave_block_out`)
    or "loo" (plain leave-one-out, :class:`mmgp.gp.ExactGP`). On densely logged trajectories plain
    LOO predicts each sample from its near-copies in time, picks a noise level far below the
    real one and extrapolates wildly into the unseen states of a held-out block.
    ``progress(message: str)``: optional callback.

    Returns a JSON-serialisable dict:

    * ``joint_names`` (n,), ``n_samples``, ``n_folds``, ``gap`` (samples) and ``gap_s`` (s),
      ``max_train``, ``seed``, ``robot`` (model name/URDF or None), ``methods`` scored;
    * ``folds``: per fold ``test`` [first, last + 1) sample indices, ``n_train_available`` and
      ``n_train`` (used);
    * ``nmse[method]`` (n,): pooled out-of-fold normalised MSE per joint; ``rmse[method]`` (n,) N*m;
      ``nmse_per_fold[method]`` (n_folds, n): each fold's MSE over the log's torque variance;
    * ``tau_std`` (n,) N*m; ``gp_improves_rigid_body`` (n,) bools: rigid_body_gp < rigid_body;
      ``timings`` (s);
    * ``warnings``: the log's checks in words (:func:`mmgp.physics.plausibility.log_warnings`,
      the same as train's and the diagnosis's); they change no figure.
    """
    # Each fold is small factorisations (hyperparameters on a few hundred samples, conditioning
    # on max_train): one thread (mmgp.threads says why).
    with limit_threads(1):
        return _compare(log, robot, n_folds=n_folds, gap=gap, max_train=max_train, seed=seed,
                        gp_options=gp_options, hyper_fit=hyper_fit, block_s=block_s, progress=progress)


def _compare(log: RobotLog, robot, *, n_folds, gap, max_train, seed, gp_options, hyper_fit, block_s,
             progress) -> dict:
    if log.dq is None or log.ddq is None:
        raise ValueError("log has no dq/ddq: run mmgp.signals.complete_derivatives() first")
    t0 = time.perf_counter()
    T, n = log.tau.shape
    if robot is not None and robot.n_joints != n:
        raise ValueError(f"robot has {robot.n_joints} joints, log has {n}")
    gap = default_gap(log.t) if gap is None else int(gap)
    if gap < 0:
        raise ValueError("gap must be non-negative")
    if hyper_fit not in ("block", "loo"):
        raise ValueError(f"hyper_fit must be 'block' or 'loo', got {hyper_fit!r}")
    if max_train < 2:
        raise ValueError("max_train must be at least 2")
    folds = time_block_folds(T, n_folds, gap)
    opts = {"ard": True, "objective": "loo", "max_fit_points": min(400, max_train), "max_iter": 60, "device": None}
    opts.update(gp_options or {})
    opts.setdefault("seed", seed)
    opts["device"] = str(resolve_device(opts["device"]))
    tau = np.asarray(log.tau, dtype=np.float64)
    # the GP's inputs are the state alone (no friction input): the peer of a plain GP
    f = StateFeatures("residual", robot)(log.q, log.dq, log.ddq, tau)
    pred, fold_info, t_fit = _fold_predictions(log, tau, f.X, f.tau_rbd, folds, gap=gap, max_train=max_train, seed=seed,
                                               opts=opts, hyper_fit=hyper_fit, block_s=block_s,
                                               say=progress or (lambda m: None))
    out = _result(log, robot, tau, pred, folds, n_folds=n_folds, gap=gap, max_train=max_train, seed=seed)
    learnt = out["nmse"]["rigid_body_gp" if robot is not None else "gp"]
    out["warnings"] = log_warnings(log, out["joint_names"], robot) + fit_warnings(
        out["joint_names"], out["nmse"].get("rigid_body"), learnt, "the rigid body + GP" if robot is not None else "the GP")
    out.update(folds=fold_info, gp_options=dict(opts), hyper_fit=hyper_fit, block_s=float(block_s),
               timings={"fit_predict_s": t_fit, "total_s": time.perf_counter() - t0})
    return out


def _fold_predictions(log: RobotLog, tau, X, tau_rbd, folds, *, gap, max_train, seed, opts, hyper_fit, block_s, say):
    """Out-of-fold predictions {method: (T, n)} from GP inputs X (T, d), per-fold records and the
    fit time (s)."""
    T, n = tau.shape
    rng = np.random.default_rng(seed)
    methods = list(METHODS) if tau_rbd is not None else ["gp"]
    pred = {m: np.full_like(tau, np.nan) for m in methods}
    if tau_rbd is not None:
        pred["rigid_body"] = tau_rbd.copy()
    fold_info = []
    t_fit = 0.0
    for k, (train, test) in enumerate(folds):
        if len(train) < 2:
            raise InputError(f"the log is too short to compare: fold {k} keeps only {len(train)} training "
                             f"samples with gap={gap}; use fewer folds, a smaller gap or a longer log",
                             file=None if log.path == "<arrays>" else log.path)
        sub = spread_subset(train, max_train, rng)
        fold_info.append({"test": [int(test[0]), int(test[-1]) + 1], "n_train_available": int(len(train)),
                          "n_train": int(len(sub))})
        t1 = time.perf_counter()
        gp = _fit_gp(X[sub], tau[sub], log.t[sub], opts, hyper_fit, block_s)
        pred["gp"][test] = gp.predict(X[test], return_std=False).reshape(len(test), n)
        if tau_rbd is not None:
            gp_r = _fit_gp(X[sub], tau[sub] - tau_rbd[sub], log.t[sub], opts, hyper_fit, block_s)
            pred["rigid_body_gp"][test] = tau_rbd[test] + gp_r.predict(X[test], return_std=False).reshape(len(test), n)
        t_fit += time.perf_counter() - t1
        say(f"fold {k + 1}/{len(folds)}: test [{test[0]}, {test[-1] + 1}), {len(sub)} of {len(train)} training "
            f"samples ({time.perf_counter() - t1:.1f} s)")
    return pred, fold_info, t_fit


def _result(log: RobotLog, robot, tau, pred, folds, *, n_folds, gap, max_train, seed) -> dict:
    """The figures of :func:`compare` from the out-of-fold predictions."""
    n = tau.shape[1]
    methods = list(pred)
    var = tau.var(0)
    var = np.where(var > 0, var, 1.0)
    nmse = {m: normalised_mse(tau, pred[m]) for m in methods}
    per_fold = {m: np.stack([((tau[te] - pred[m][te]) ** 2).mean(0) / var for _, te in folds]) for m in methods}
    rmse = {m: np.sqrt(((tau - pred[m]) ** 2).mean(0)) for m in methods}
    dt = float(np.median(np.diff(log.t)))
    robot_id = None
    if robot is not None:
        robot_id = getattr(robot, "name", None) or (str(robot.urdf_path) if getattr(robot, "urdf_path", None) else None)
    joint_names = (log.joint_names or (robot.joint_names if robot is not None else None)
                   or [f"joint_{j}" for j in range(n)])
    out = {
        "log": str(log.path), "robot": robot_id, "joint_names": list(joint_names), "methods": methods,
        "n_samples": int(len(tau)), "n_folds": int(n_folds), "gap": int(gap), "gap_s": gap * dt,
        "max_train": int(max_train), "seed": int(seed),
        "derivatives_estimated": {"dq": bool(log.dq_estimated), "ddq": bool(log.ddq_estimated)},
        "tau_std": np.sqrt(tau.var(0)).tolist(),
        "nmse": {m: v.tolist() for m, v in nmse.items()},
        "rmse": {m: v.tolist() for m, v in rmse.items()},
        "nmse_per_fold": {m: v.tolist() for m, v in per_fold.items()},
    }
    if robot is not None:
        out["gp_improves_rigid_body"] = [bool(a < b) for a, b in zip(nmse["rigid_body_gp"], nmse["rigid_body"])]
    return out


def format_compare(result: dict) -> str:
    """Plain-text table: one row per joint, one column per method (held-out normalised MSE)."""
    methods = result["methods"]
    head = f"{'joint':<24}" + "".join(f"{COMPARE_LABELS[m]:>18}" for m in methods)
    if "gp_improves_rigid_body" in result:
        head += f"{'GP helps':>10}"
    lines = [f"held-out normalised MSE ({result['n_folds']} time-block folds, gap {result['gap']} samples = "
             f"{result['gap_s']:.3g} s, <= {result['max_train']} training samples per fold; 1 = predicting the mean)",
             head]
    for j, name in enumerate(result["joint_names"]):
        row = f"{name:<24}" + "".join(f"{result['nmse'][m][j]:>18.4g}" for m in methods)
        if "gp_improves_rigid_body" in result:
            row += f"{'yes' if result['gp_improves_rigid_body'][j] else 'NO':>10}"
        lines.append(row)
    means = "".join(f"{float(np.mean(result['nmse'][m])):>18.4g}" for m in methods)
    lines.append(f"{'mean':<24}{means}")
    return "\n".join(lines)


def write_compare(result: dict, out_dir) -> list[Path]:
    """Write ``out_dir/compare.json`` (the result), ``out_dir/compare.png`` (grouped bars of
    normalised MSE per joint, log scale, dashed line at 1 = predicting the mean) and
    ``out_dir/report.html`` (both on one self-contained page). Returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    js = out_dir / "compare.json"
    atomic_write_bytes(js, (json.dumps(jsonable(result), indent=2) + "\n").encode())

    methods = result["methods"]
    names = result["joint_names"]
    n = len(names)
    colours = {"rigid_body": "#7f7f7f", "gp": "#1f77b4", "rigid_body_gp": "#d62728"}
    width = 0.8 / len(methods)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * n + 2.0), 4.2))
    x = np.arange(n)
    # Log scale cannot show 0: floor the bars far below anything a real fit reaches.
    floor = 1e-6
    for i, m in enumerate(methods):
        v = np.maximum(np.asarray(result["nmse"][m], dtype=np.float64), floor)
        ax.bar(x + (i - (len(methods) - 1) / 2) * width, v, width, label=COMPARE_LABELS[m], color=colours[m])
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="predicting the mean")
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("held-out normalised MSE")
    ax.set_title(f"{Path(str(result.get('log', ''))).name}: {result['n_folds']} time-block folds, "
                 f"gap {result['gap_s']:.2g} s", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = out_dir / "compare.png"
    write_figure(png, fig, dpi=120)
    plt.close(fig)
    from .reports import write_compare_report

    return [js, png, write_compare_report(out_dir, result)]
