"""The public estimator: :class:`MultimodalGP` (logs -> modes, disturbance labels, per-mode GPs).

It is the one way to train: ``mmgp train`` parses its options into the constructor and calls
``fit``, so Python and the command line give the same labels for the same inputs.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils.validation import check_is_fitted

from ._version import __version__
from .data.folds import windows_for_duration
from .data.logs import RobotLog, log_from_arrays, names_a_robot
from .errors import InputError
from .gp.hyper import Hyper
from .gp.linalg import resolve_device
from .gp.settings import GP_DEFAULTS as _GP
from .gp.sparse import GP_METHODS, gp_kind, make_gp
from .physics.context import smooth_sign_scale
from .labelling.features import MeanBasis, StateFeatures, load_logs, resolve_mean_basis, rest_band_on, thin_logs
from .labelling.report import labels_frame, training_report
from .labelling.settings import ESTEPS, EMSettings

MODEL_FORMAT = "mmgp-model"
MODEL_VERSION = 4
_CHOICES = {"estep": ESTEPS, "semiparametric": ("residual", "feature", "none"),
            "mean_basis": ("auto", "rbd", "payload", "none"), "objective": ("loo", "marginal"),
            "gp_method": GP_METHODS}
_POSITIVE_INT = ("max_support", "fit_points", "fit_iter", "max_sweeps", "min_sweeps", "average_last",
                 "patience", "n_inducing")
_NON_NEGATIVE = ("exclusion_s", "block_s", "min_push_s", "min_mode_s", "push_scan_s")
_POSITIVE = ("push_s", "gap_s")
_BOOL = ("disturbance", "friction_feature", "calibrate", "ard", "abstain")


_EM = EMSettings()      # the EM's settings are declared there; the estimator's defaults are its


class MultimodalGP(BaseEstimator):
    """Multimodal Gaussian-process inverse dynamics tau = f(q, dq, ddq) from messy robot logs.

    Stochastic EM over ``n_modes`` dynamic modes (e.g. payloads) and a disturbance mode (pushes),
    with one RBF GP per mode over ``[q, dq, ddq, tanh(dq / v_s)(1 - w)]``; every training sample
    gets a mode and a disturbance label. Units: rad (m), rad/s, rad/s^2, N*m (N), s.

    One mode without the disturbance mode has no labels to learn: the EM is skipped and one GP
    is fitted on every sample, its hyperparameters on ``fit_points`` random samples
    (:class:`mmgp.gp.exact.ExactGP`'s procedure; with times, blocks left out, see ``objective``). How the GPs scale: ``gp_method``.

    Parameters (every training setting; the ``train:`` section of a settings file holds the same
    keys, see :func:`mmgp.config.load_settings`)
    ----------
    n_modes : int >= 1 or "auto", default 1
        Dynamic modes; "auto" picks 1, 2 or 3 by a BIC-style score on the chain's log marginal.
    disturbance : bool, default True
        Add the disturbance mode N(mu, Sigma + Sigma_d) around each sample's mode.
    robot : None, str or RobotModel, default None
        The rigid-body model: an example-robot-data name (e.g. "panda"), a URDF path (ends in
        ".urdf") or a :class:`mmgp.RobotModel`. None: the one the first log's metadata names,
        if any (GP only otherwise, and always for arrays).
    estep : "mpm", "ffbs" or "gibbs", default "mpm"
        Labels of each sweep: each sample's most probable state under the chain's posterior
        (deterministic: the answer does not depend on ``seed``), or drawn by joint
        forward-filtering backward-sampling, or by single-site
        Gibbs (the source's method; both depend on ``seed``).
    stay_prob : float in (0, 1) or None, default None
        Fixed p(mode_t = mode_{t-1}); None learns it (Beta prior, mean 0.95).
    rate_hz : float > 0 or None, default None
        Downsample to about this rate after differentiating (None keeps the log's rate);
        ``report_['thinning']`` records the samples read and kept.
    diff_window_s : float or None, default None
        Savitzky-Golay window for estimated dq / ddq in s; None chooses it per joint by
        leave-one-out cross-validation (between max(5 samples, 0.05 s) and 0.5 s).
    semiparametric : "residual", "feature" or "none", default "residual"
        With a robot: the GP learns tau - tau_rbd, or takes tau_rbd as an extra input, or
        ignores the robot.
    exclusion_s : float >= 0, default 1.0
        Samples within this many seconds of a sample are left out of its likelihood
        (leave-window-out; 0 = plain leave-one-out).
    block_s : float >= 0, default 2.0
        Block length in s of the leave-block-out hyperparameter objective (0: per-sample LOO).
    friction_feature : bool, default True
        Add tanh(dq / v_s) (1 - w) per joint to the GP inputs (Coulomb friction's step, faded out
        at rest, :func:`mmgp.labelling.features.sliding_sign`); v_s is the package's one smooth-sign
        rule (:func:`mmgp.physics.context.smooth_sign_scale`), the same the diagnosis uses.
    mean_basis : "auto", "payload", "rbd" or "none", default "auto"
        With a robot and "residual": each mode's mean is linear in rigid-body regressors,
        fitted robustly per mode, under its GP, so a mode extrapolates like physics. "payload"
        (what "auto" picks with a robot): the distal body's 10 inertial parameters shared by
        all joints; "rbd": every body's parameters per joint (so many columns that they also
        absorb smooth pushes). Without a robot "auto" is "none".
    push_s, gap_s : float > 0, default 1.0, 5.0
        Prior push duration and time between pushes in s (worth 3 observed pushes): a flicker of
        one sample costs the same at any sampling rate.
    push_floor_z : float >= 0, default 5.0
        A push is at least this many predictive standard deviations (floor of its spread).
    min_push_s : float >= 0, default 0.15
        A push lasts at least this long (s): shorter flagged stretches of the final labels are
        model error (friction at a velocity reversal, an impact) and are labelled undisturbed.
        Pushes last 0.2-3 s.
    push_scan_s : float >= 0, default 0.2
        A push is a sustained offset: undisturbed samples whose standardised residual, averaged
        over this many seconds, stands more than ``push_scan_z`` robust standard deviations of
        that average off on some joint are flagged too (0: off; docs/training.md).
    push_scan_z : float > 0, default 6.0
        The scan's threshold (about T / window x joints windows are tested; a Gaussian would
        need ~4.7 for a 1% chance of one false window per 100 s log at 100 Hz, 7 joints).
    rest_band : bool or "auto", default "auto"
        A resting joint may hold any torque in its friction band; friction in the mean (docs/training.md). "auto": on with a rigid-body mean.
    abstain : bool, default True
        Flag nothing when the disturbance mode does not raise the log marginal likelihood of
        the labels' chain by more than its BIC price (a log without pushes).
    max_support : int, default 500
        At most this many undisturbed samples condition each mode's GP during the sweeps.
    final_support : int or None, default None
        At most this many of a mode's undisturbed samples (evenly spaced) condition its returned
        GP (used by predict and the export); None: every one.
    gp_method : "auto", "exact", "sgpr" or "subset", default "auto"
        The returned GPs' kind. "auto" (:func:`mmgp.gp.sparse.choose_gp_method`): an exact GP
        on every sample up to 16,000 samples per mode, when one output's kernel matrix and its
        factor fit in a third of the free RAM (half the free GPU memory); SGPR over every sample
        with ``n_inducing`` k-means inducing inputs above (O(N M^2) time, O(M^2) memory: the
        path for 10^5+ samples on a GPU). "subset" (exact GP on ``n_inducing`` random samples),
        less accurate than both at the same size, is never picked by "auto".
    n_inducing : int, default 2000
        SGPR inducing inputs (or the subset size of "subset").
    fit_points, fit_iter : int, default 2000, 50
        Hyperparameter fitting subset size (evenly spaced samples) and L-BFGS iterations. The sweeps
        fit on their support (at most ``max_support``); one mode without disturbance fits on
        ``fit_points`` of all samples, one optimiser run per joint.
    max_sweeps, min_sweeps : int, default 40, 6
        EM sweep limits.
    tol_changed : float in (0, 1], default 0.05
        Converged when, over the last ``patience`` sweeps, fewer than this fraction of the labels
        change on average and the mean log joint stops rising (or fewer than a fifth change).
    patience : int, default 3
        Sweeps compared by the convergence test.
    average_last : int, default 5
        Sweeps after convergence whose posterior marginals are averaged into the labels.
    mode_smoothing_s : float > 0, default 4.0
        Running-median length in s of the residuals clustered into the initial modes.
    min_mode_s : float >= 0, default 4.0
        A mode lasts at least this long (s): a payload stays on for seconds to minutes, a push
        lasts 0.2-3 s. With ``n_modes="auto"`` a number of modes is accepted only if each of its
        modes holds this long in one stretch (:func:`mmgp.labelling.sem.select_n_modes`); with
        several modes, shorter stretches of one mode in the final labels take a neighbouring
        stretch's mode.
    calibrate : bool, default True
        Scale each mode's predictive variance per joint by its undisturbed mean z^2 (>= 1).
    objective : "loo" or "marginal", default "loo"
        GP hyperparameter objective without times (with them: leave-block-out, sweeps by
        ``block_s``, one mode alone by :func:`mmgp.labelling.mstep.honest_block_s`).
    ard : bool, default True
        One lengthscale per input.
    device : str, default "cpu"
        torch device: "cpu", "cuda" or "auto".
    seed : int, default 0
        Seed of the "ffbs" and "gibbs" E-steps (unused by "mpm").
    progress : callable or None, default None
        Called with each sweep's :class:`mmgp.labelling.convergence.SweepRecord`.

    Attributes (after ``fit``; ``load`` restores those marked *)
    ----------
    labels_ : DataFrame, the columns of ``labels.parquet`` (docs/contract.md): t, (log, with
        several logs), mode, disturbed, p_disturbed, p_mode_<k>.
    modes_ (T,) int, nominal mode 0; p_mode_ (T, K); p_disturbed_ (T,); disturbed_ (T,) bool.
    report_ : dict, the content of ``report.json``; ``heldout``: the held-out score per joint
        (:func:`mmgp.evaluation.heldout.heldout_score`: model, rigid body, mean).
    n_modes_ *, joint_names_ *, robot_ * (RobotModel or None), robot_spec_ *, semiparametric_ *,
    friction_scale_ * ((n,) v_s in rad/s, or None), sign_fades_ * (input faded at rest: with the band), mean_basis_ * (a
    :class:`mmgp.labelling.features.MeanBasis` or None), basis_coef_ * (per mode
    (n, p) or None), support_X_ * / support_Y_ * (per mode GP inputs / targets), hypers_ *.
    logs_ (the checked logs), features_ (GP inputs and targets), sem_ (the fitted
    :class:`mmgp.labelling.sem.MultimodalSEM`, with its trace and last sweep).
    """

    def __init__(self, n_modes=1, disturbance=_EM.disturbance, robot=None, *, estep=_EM.estep,
                 stay_prob=_EM.stay_prob, rate_hz=None, diff_window_s=None, semiparametric="residual",
                 exclusion_s=_EM.exclusion_s, block_s=_EM.block_s, friction_feature=True, mean_basis="auto",
                 max_support=_EM.max_support, final_support=_EM.final_support, gp_method=_EM.gp_method,
                 n_inducing=_EM.n_inducing, fit_points=_EM.fit_points, fit_iter=_EM.fit_iter,
                 max_sweeps=_EM.max_sweeps, min_sweeps=_EM.min_sweeps, tol_changed=_EM.tol_changed,
                 patience=_EM.patience, push_s=_EM.push_s, gap_s=_EM.gap_s, push_floor_z=_EM.push_floor_z,
                 min_push_s=_EM.min_push_s, push_scan_s=_EM.push_scan_s, push_scan_z=_EM.push_scan_z,
                 rest_band="auto", abstain=_EM.abstain, average_last=_EM.average_last,
                 mode_smoothing_s=_EM.mode_smoothing_s, min_mode_s=_EM.min_mode_s, calibrate=_EM.calibrate,
                 objective=_GP.objective, ard=_GP.ard, device="cpu", seed=0, progress=None):
        self.n_modes = n_modes
        self.disturbance = disturbance
        self.robot = robot
        self.estep = estep
        self.stay_prob = stay_prob
        self.rate_hz = rate_hz
        self.diff_window_s = diff_window_s
        self.semiparametric = semiparametric
        self.exclusion_s = exclusion_s
        self.block_s = block_s
        self.friction_feature = friction_feature
        self.mean_basis = mean_basis
        self.max_support = max_support
        self.final_support = final_support
        self.gp_method = gp_method
        self.n_inducing = n_inducing
        self.fit_points = fit_points
        self.fit_iter = fit_iter
        self.max_sweeps = max_sweeps
        self.min_sweeps = min_sweeps
        self.tol_changed = tol_changed
        self.patience = patience
        self.push_s = push_s
        self.gap_s = gap_s
        self.push_floor_z = push_floor_z
        self.min_push_s = min_push_s
        self.push_scan_s = push_scan_s
        self.push_scan_z = push_scan_z
        self.rest_band = rest_band
        self.abstain = abstain
        self.average_last = average_last
        self.mode_smoothing_s = mode_smoothing_s
        self.min_mode_s = min_mode_s
        self.calibrate = calibrate
        self.objective = objective
        self.ard = ard
        self.device = device
        self.seed = seed
        self.progress = progress

    # -- settings ------------------------------------------------------------------------------
    def _validate(self) -> None:
        """Refuse a bad setting with an InputError naming it."""
        def bad(key, expected):
            raise InputError(f"setting '{key}': expected {expected}, got {getattr(self, key)!r}")
        n = self.n_modes
        if not (n == "auto" or (isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 1)):
            bad("n_modes", "a positive integer or 'auto'")
        for key, choices in _CHOICES.items():
            if getattr(self, key) not in choices:
                bad(key, " or ".join(repr(c) for c in choices))
        for key in _POSITIVE_INT:
            v = getattr(self, key)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                bad(key, "a positive integer")
        for key in _NON_NEGATIVE:
            if not _is_number(getattr(self, key)) or getattr(self, key) < 0:
                bad(key, "a number of seconds >= 0")
        if not _is_number(self.push_floor_z) or self.push_floor_z < 0:
            bad("push_floor_z", "a number of standard deviations >= 0")
        if not _is_number(self.push_scan_z) or self.push_scan_z <= 0:
            bad("push_scan_z", "a positive number of standard deviations")
        for key in _POSITIVE:
            if not _is_number(getattr(self, key)) or getattr(self, key) <= 0:
                bad(key, "a positive number of seconds")
        for key in _BOOL:
            if not isinstance(getattr(self, key), (bool, np.bool_)):
                bad(key, "true or false")
        if not isinstance(self.rest_band, (bool, np.bool_)) and not (isinstance(self.rest_band, str) and self.rest_band == "auto"):
            bad("rest_band", "true, false or 'auto'")
        if self.final_support is not None and not (isinstance(self.final_support, (int, np.integer))
                                                   and not isinstance(self.final_support, bool)
                                                   and self.final_support >= 1):
            bad("final_support", "a positive integer, or null (every sample)")
        if self.stay_prob is not None and not (_is_number(self.stay_prob) and 0.0 < self.stay_prob < 1.0):
            bad("stay_prob", "a probability strictly between 0 and 1, or null")
        if self.rate_hz is not None and not (_is_number(self.rate_hz) and self.rate_hz > 0):
            bad("rate_hz", "a positive rate in Hz, or null")
        if self.diff_window_s is not None and not (_is_number(self.diff_window_s) and self.diff_window_s > 0):
            bad("diff_window_s", "a positive window in seconds, or null")
        if not (_is_number(self.tol_changed) and 0.0 < self.tol_changed <= 1.0):
            bad("tol_changed", "a fraction in (0, 1]")
        if not (_is_number(self.mode_smoothing_s) and self.mode_smoothing_s > 0):
            bad("mode_smoothing_s", "a positive number of seconds")
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool):
            bad("seed", "an integer")
        if self.progress is not None and not callable(self.progress):
            bad("progress", "a function of a SweepRecord, or None")
        try:
            resolve_device(self.device)
        except (ValueError, RuntimeError, TypeError) as exc:
            raise InputError(f"setting 'device': {exc}") from None

    def _validate_saved(self, path: Path) -> None:
        """:meth:`_validate` for settings read from ``path``; the device is checked when used (a
        model trained on a GPU may be loaded on a machine without one, to predict on another)."""
        if not isinstance(self.device, str):
            raise InputError(f"setting 'device': expected a device name, got {self.device!r}", file=path)
        device, self.device = self.device, "cpu"
        try:
            self._validate()
        except InputError as exc:
            raise InputError(exc.message, file=path) from None
        finally:
            self.device = device

    def _em_settings(self, mean_basis, shortened: dict) -> EMSettings:
        """The EM's settings: this estimator's of the same names, then the windows ``shortened``."""
        return EMSettings.of(self, shared_basis=mean_basis is not None and mean_basis.shared,
                             gp_kwargs={"ard": self.ard, "objective": self.objective, "device": self.device},
                             **shortened)

    def _settings_record(self) -> dict:
        """The settings as JSON-able values (the robot as its name or URDF path; no progress)."""
        out = self.get_params(deep=False)
        out.pop("progress")
        if out["robot"] is not None and not isinstance(out["robot"], (str, os.PathLike)):
            spec = _robot_spec(out["robot"])
            out["robot"] = spec["robot"] or spec["urdf"]
        elif out["robot"] is not None:
            out["robot"] = str(out["robot"])
        return out

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, logs=None, *, t=None, q=None, tau=None, dq=None, ddq=None) -> "MultimodalGP":
        """Learn modes, disturbance labels and per-mode GPs.

        ``logs``: a log file (Parquet or CSV, docs/contract.md), a :class:`mmgp.RobotLog`, or a
        list of them (separate recordings of one robot). Or, instead, arrays of one recording:
        ``t`` (T,) s, strictly increasing; ``q``, ``tau`` (T, n) (or (T,) for one joint);
        ``dq``, ``ddq`` (T, n) or None (estimated from q). Inputs are never modified.
        Returns self.
        """
        import time

        from .evaluation.heldout import heldout_score, heldout_warnings
        from .labelling.dissipation import fit_dissipative
        from .labelling.sem import MultimodalSEM, select_n_modes

        t0 = time.perf_counter()
        self._validate()
        sources = _sources(logs, t=t, q=q, tau=tau, dq=dq, ddq=ddq)
        robot = _resolve_robot(self.robot, sources[0])
        logs_, thinning = thin_logs(load_logs(sources, robot=robot, diff_window_s=self.diff_window_s), self.rate_hz)
        t_load = time.perf_counter() - t0
        semi = self.semiparametric if robot is not None else "none"
        fscale = smooth_sign_scale(np.concatenate([lg.dq for lg in logs_])) if self.friction_feature else None
        basis = resolve_mean_basis(self.mean_basis, robot, semi)
        band = fscale is not None and rest_band_on(self.rest_band, basis)
        basis = dataclasses.replace(basis, friction=True) if band and basis is not None else basis
        feats = StateFeatures(semi, robot, fscale, band, basis).of_logs(logs_)
        k_max = 3 if self.n_modes == "auto" else int(self.n_modes)
        if len(feats.Y) < 5 * k_max:
            raise InputError(f"{len(feats.Y)} samples are too few for {k_max} modes (at least {5 * k_max})")
        shortened = windows_for_duration(min(lg.t[-1] - lg.t[0] for lg in logs_), exclusion_s=self.exclusion_s,
                                         block_s=self.block_s, mode_smoothing_s=self.mode_smoothing_s,
                                         min_push_s=self.min_push_s, min_mode_s=self.min_mode_s,
                                         push_scan_s=self.push_scan_s)
        kw = dict(settings=self._em_settings(basis, shortened), seed=self.seed, progress=self.progress)
        data = dict(t=feats.t, starts=feats.starts, basis=feats.basis, muted=feats.muted,
                    rest=feats.rest_band(basis, fscale) if band else None)
        first, selection = select_n_modes(feats.X, feats.Y, (1, 2, 3), **data, **kw) if self.n_modes == "auto" else (None, None)
        K = first.n_modes if first is not None else k_max
        sem, dissipation = fit_dissipative(lambda: MultimodalSEM(n_modes=K, **kw), feats.X, feats.Y,
                                           feats.velocity_reversal(basis), first=first, **data)
        self.robot_, self.robot_spec_ = robot, _robot_spec(robot)
        self.semiparametric_, self.mean_basis_, self.friction_scale_, self.sign_fades_ = semi, basis, fscale, band
        self.joint_names_ = logs_[0].joint_names or (robot.joint_names if robot is not None else
                                                     [f"joint_{j}" for j in range(logs_[0].n_joints)])
        self._set_sem(sem)
        self.logs_, self.features_ = logs_, feats
        self.labels_ = labels_frame(sem, logs_)
        self.report_ = training_report(
            settings=self._settings_record(), sem=sem, logs=logs_, joint_names=self.joint_names_,
            robot_spec=self.robot_spec_, semiparametric=semi, mean_basis=basis, robot=robot,
            with_friction=fscale is not None, mode_selection=selection,
            timings=dict(sem.timings_, load_s=t_load, total_s=time.perf_counter() - t0))
        self.report_.update(windows_shortened_s=shortened, thinning=thinning, dissipation=dissipation,
                            heldout=heldout_score(self))
        self.report_["timings"].update(heldout_s=self.report_["heldout"]["seconds"], total_s=time.perf_counter() - t0)
        self.report_["warnings"] += heldout_warnings(self.report_["heldout"], self.joint_names_)
        return self

    def _set_sem(self, sem) -> None:
        self.sem_ = sem
        self.n_modes_ = len(sem.gps_)
        self.modes_ = sem.labels_
        self.p_mode_ = sem.p_mode_
        self.p_disturbed_ = sem.p_disturbed_
        self.disturbed_ = sem.disturbed_
        self.support_X_, self.support_Y_ = list(sem.support_X_), list(sem.support_Y_)
        self.hypers_ = [g.hyper_ for g in sem.gps_]
        self.basis_coef_ = list(sem.coef_)
        self.gp_kinds_ = [gp_kind(g) for g in sem.gps_]
        self.inducing_ = [getattr(g, "inducing_", None) for g in sem.gps_]
        self._gps = list(sem.gps_)

    # -- prediction ----------------------------------------------------------------------------
    @property
    def support_q_(self) -> np.ndarray:
        """Positions (N, n) of the nominal mode's support samples (what the export fits on)."""
        check_is_fitted(self, "support_X_")
        return self.support_X_[0][:, : len(self.joint_names_)]

    def gp(self, mode: int = 0):
        """Mode ``mode``'s GP over the inputs [q, dq, ddq(, the sliding sign)(, tau_rbd)]: an
        :class:`mmgp.gp.exact.ExactGP` or :class:`mmgp.gp.sparse.SparseGP` (``gp_kinds_``)."""
        check_is_fitted(self, "support_X_")
        if not isinstance(mode, (int, np.integer)) or not 0 <= mode < self.n_modes_:
            raise InputError(f"mode must be in 0..{self.n_modes_ - 1}, got {mode!r}")
        if not hasattr(self, "_gps"):
            self._gps = [None] * self.n_modes_
        if self._gps[mode] is None:
            kind = self.gp_kinds_[mode]
            gp = make_gp(len(self.support_Y_[mode]), method=kind, device=self.device, ard=self.ard, seed=self.seed,
                         n_inducing=self.n_inducing, n_subset=self.n_inducing, hyper=self.hypers_[mode], optimise=False)
            extra = {"inducing": self.inducing_[mode]} if kind == "sgpr" else {}
            if kind == "exact":  # solved weights stored with the model, where it has them
                extra["weights"] = (getattr(self, "gp_weights_", None) or [None] * self.n_modes_)[mode]
            self._gps[mode] = gp.fit(self.support_X_[mode], self.support_Y_[mode], **extra)
        return self._gps[mode]

    def predict(self, q, dq, ddq, mode: int = 0, return_std: bool = True):
        """Torque mean and std (T, n) in N*m (N) in ``mode`` (0 = nominal) at q, dq, ddq (T, n)
        (or (T,) for one joint, or (n,) for one sample); only the mean with ``return_std=False``.
        With a robot the rigid-body part is included."""
        mean, std = self._predict(q, dq, ddq, mode, return_std=return_std)
        return (mean, std) if return_std else mean

    def nominal_torque(self, q) -> np.ndarray:
        """Position-only feedforward target tau(q, 0, 0) of the nominal mode: (T, n) -> (T, n).

        With the friction input, the prediction is averaged over both sliding directions: at
        rest the friction torque can be anywhere in its band, so the band's centre is what a
        position-only feedforward should supply, and a moving log has data on both branches but
        almost none at the sign's zero crossing (evaluating there extrapolates)."""
        z = np.zeros_like(self._states(q, "q"))
        if self.friction_scale_ is None:
            return self._predict(q, z, z, 0, return_std=False)[0]
        both = self._predict(np.vstack([q, q]), np.vstack([z, z]), np.vstack([z, z]), 0,
                             friction_sign=np.repeat([1.0, -1.0], len(z))[:, None], return_std=False)[0]
        return 0.5 * (both[:len(z)] + both[len(z):])

    def _states(self, a, name: str) -> np.ndarray:
        check_is_fitted(self, "support_X_")
        n = len(self.joint_names_)
        a = np.asarray(a, dtype=np.float64)
        if a.ndim == 1:
            a = a.reshape(-1, 1) if n == 1 else a.reshape(1, -1)
        if a.ndim != 2 or a.shape[1] != n:
            raise InputError(f"{name} must be (T, {n}) for this model's {n} joint(s), got shape {np.shape(a)}")
        return a

    def _predict(self, q, dq, ddq, mode, friction_sign=None, return_std: bool = True):
        # an exact GP's std costs O(N^2) per query and output, its mean O(N) (N support samples)
        q, dq, ddq = (self._states(a, name) for a, name in ((q, "q"), (dq, "dq"), (ddq, "ddq")))
        if not (len(q) == len(dq) == len(ddq)):
            raise InputError(f"q, dq, ddq must have the same number of rows, got {len(q)}, {len(dq)}, {len(ddq)}")
        gp = self.gp(mode)
        coef = self.basis_coef_[mode]
        recipe = StateFeatures(self.semiparametric_, self.robot_, self.friction_scale_, self.sign_fades_, self.mean_basis_)
        f = recipe(q, dq, ddq, np.zeros_like(q), friction_sign=friction_sign, basis=coef is not None)
        mean, std = gp.predict(f.X, include_noise=True) if return_std else (gp.predict(f.X, return_std=False), None)
        mean, std = mean.reshape(len(q), -1), (None if std is None else std.reshape(len(q), -1))
        if coef is not None:
            mean = mean + np.einsum("tjp,jp->tj", f.basis, coef)
        if f.tau_rbd is not None and self.semiparametric_ == "residual":
            mean = mean + f.tau_rbd
        return mean, std

    def to_compensator(self, max_support: int = 1000, seed: int = 0):
        """The passive position-only feedforward tau_ff(q) = grad V(q) of the nominal mode, fitted
        to :meth:`nominal_torque` on up to ``max_support`` support positions (random subset,
        ``seed``). See :func:`mmgp.compensator.fit.compensator_from_model`."""
        from .compensator.fit import compensator_from_model

        check_is_fitted(self, "support_X_")
        return compensator_from_model(self, max_support=max_support, seed=seed)

    # -- persistence ---------------------------------------------------------------------------
    def save(self, out_dir: str | os.PathLike) -> None:
        """Write ``model.npz`` (per mode ``X_k``, ``Y_k`` support, ``lengthscale_k``,
        ``signal_var_k``, ``noise_var_k``, optional ``basis_coef_k`` and ``inducing_k`` (SGPR
        inducing inputs), ``friction_scale``) and ``model.json`` (format, version, settings,
        robot, joints, ``gp_kinds``) into ``out_dir`` (created); a large exact GP's solved
        weights too (``weights_k``, :func:`mmgp.saved_model.store_gp_weights`)."""
        import io

        from .data.outputs import atomic_write_bytes
        from .saved_model import store_gp_weights

        check_is_fitted(self, "support_X_")
        arrays = {}
        for k in range(self.n_modes_):
            arrays[f"X_{k}"], arrays[f"Y_{k}"] = self.support_X_[k], self.support_Y_[k]
            arrays[f"lengthscale_{k}"] = self.hypers_[k].lengthscale
            arrays[f"signal_var_{k}"] = self.hypers_[k].signal_var
            arrays[f"noise_var_{k}"] = self.hypers_[k].noise_var
            if self.basis_coef_[k] is not None:
                arrays[f"basis_coef_{k}"] = self.basis_coef_[k]
            if self.inducing_[k] is not None:
                arrays[f"inducing_{k}"] = self.inducing_[k]
        if self.friction_scale_ is not None:
            arrays["friction_scale"] = self.friction_scale_
        digests = store_gp_weights(self.n_modes_, getattr(self, "_gps", None), getattr(self, "gp_weights_", None),
                                   arrays)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        meta = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "mmgp_version": __version__,
                "n_modes": self.n_modes_, "joint_names": self.joint_names_, "settings": self._settings_record(),
                "robot": self.robot_spec_, "mean_basis": getattr(self.mean_basis_, "name", None), "gp_kinds": self.gp_kinds_,
                "gp_weights_sha256": digests, "sign_fades": bool(self.sign_fades_)}
        out_dir = Path(out_dir)
        atomic_write_bytes(out_dir / "model.npz", buf.getvalue())
        atomic_write_bytes(out_dir / "model.json", json.dumps(meta, indent=2).encode())

    @classmethod
    def load(cls, model_dir: str | os.PathLike) -> "MultimodalGP":
        """A fitted estimator from a folder written by :meth:`save` (or ``mmgp train``); reads
        format versions 1 to 4. ``labels_``, ``report_``, ``logs_``, ``features_`` and ``sem_``
        are not restored."""
        from .saved_model import read_gp_weights, read_model_arrays, read_model_meta, read_model_robot

        model_dir = Path(model_dir)
        meta = read_model_meta(model_dir, MODEL_FORMAT, (1, 2, 3, MODEL_VERSION))
        try:
            model = cls(**meta["settings"])
        except TypeError as exc:
            raise InputError(f"'settings' of this model are not this mmgp's ({exc})", file=model_dir / "model.json") from None
        model._validate_saved(model_dir / "model.json")
        K = model.n_modes_ = int(meta["n_modes"])
        model.joint_names_ = list(meta["joint_names"])
        z = read_model_arrays(model_dir, meta)
        model.support_X_ = [z[f"X_{k}"] for k in range(K)]
        model.support_Y_ = [z[f"Y_{k}"] for k in range(K)]
        model.hypers_ = [Hyper(z[f"lengthscale_{k}"], z[f"signal_var_{k}"], z[f"noise_var_{k}"]) for k in range(K)]
        model.basis_coef_ = [z.get(f"basis_coef_{k}") for k in range(K)]
        model.friction_scale_ = z.get("friction_scale")
        model.sign_fades_ = meta.get("sign_fades", False)        # versions 1 to 3: no fade
        model.inducing_ = [z.get(f"inducing_{k}") for k in range(K)]
        model.gp_weights_ = read_gp_weights(meta, z)
        # versions 1 and 2 conditioned every mode's exact GP on its (subset) support
        model.gp_kinds_ = list(meta.get("gp_kinds") or ["exact"] * K)
        model.mean_basis_ = MeanBasis.parse(meta.get("mean_basis"))
        model.robot_spec_ = meta.get("robot") or None
        model.robot_ = read_model_robot(model.robot_spec_, model_dir / "model.json")
        model.semiparametric_ = model.semiparametric if model.robot_spec_ else "none"
        model._gps = [None] * K
        return model


# ----------------------------------------------------------------------------------------------
# Inputs

def _is_number(x) -> bool:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        return False
    try:  # a Python int beyond int64 is no input np.isfinite takes; one beyond 1e308 no float
        return math.isfinite(float(x))
    except OverflowError:
        return False


def _sources(logs, **arrays) -> list:
    given = {k: v for k, v in arrays.items() if v is not None}
    if logs is not None and given:
        raise InputError("give either logs or arrays (t, q, tau, ...), not both")
    if logs is None:
        if not given:
            raise InputError("nothing to fit: give a log path, a RobotLog, a list of them, or t, q, tau arrays")
        return [log_from_arrays(**arrays)]
    items = list(logs) if isinstance(logs, (list, tuple)) else [logs]
    if not items:
        raise InputError("no logs given")
    for x in items:
        if not isinstance(x, (str, os.PathLike, RobotLog)):
            raise InputError(f"a log must be a path or a RobotLog, got {type(x).__name__}")
    return items


def _resolve_robot(robot, first):
    """The RobotModel to use: ``robot`` (name, URDF path or model), else the first log's metadata."""
    if robot is not None and not isinstance(robot, (str, os.PathLike)):
        if not hasattr(robot, "rnea") or not hasattr(robot, "joint_names"):
            raise InputError(f"setting 'robot': expected a name, a URDF path or a RobotModel, got {robot!r}")
        return robot
    log_path = None if getattr(first, "path", None) == "<arrays>" else first
    if robot is None and (log_path is None or not names_a_robot(log_path)):
        return None                         # GP only: Pinocchio is not needed (nor imported)
    from .physics.robot import load_robot

    if robot is None:
        return load_robot(log_path=log_path)
    if isinstance(robot, os.PathLike) or str(robot).lower().endswith(".urdf"):
        return load_robot(urdf=robot, log_path=log_path)
    return load_robot(robot=str(robot), log_path=log_path)


def _robot_spec(robot) -> dict | None:
    if robot is None:
        return None
    name = getattr(robot, "name", None)
    return {"robot": name, "urdf": None if name else str(robot.urdf_path), "joint_names": robot.joint_names}

