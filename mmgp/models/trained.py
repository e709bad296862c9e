"""The training pipeline (log -> checked arrays -> features -> multimodal model) and the saved model.

A :class:`TrainedModel` holds, per mode, the GP's support inputs/targets and hyperparameters,
which is all an exact GP needs to be rebuilt; it is saved as ``model.npz`` + ``model.json`` and
reloaded by ``predict``, ``export`` and ``evaluate``.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .. import __version__
from ..config import TrainConfig
from ..data.logs import RobotLog
from ..errors import InputError
from ..gp.exact import ExactGP
from ..gp.hyper import Hyper
from .features import Features, _features, _input_names, build_features, friction_velocity_scale, load_logs, resolve_mean_basis
from .sem import MultimodalSEM, select_n_modes

MODEL_FORMAT = "mmgp-model"
MODEL_VERSION = 1


class TrainedModel:
    """A trained multimodal model: per-mode GPs over inputs ``[q, dq, ddq(, tau_rbd)]``.

    ``predict(q, dq, ddq, mode)`` gives torques (T, n) in N*m with the rigid-body part added back
    when the GP learned a residual. ``nominal_torque(q)`` is the position-only feedforward target
    (dq = ddq = 0, nominal mode 0). ``support_q_`` (N, n): positions of the nominal mode's support.
    """

    def __init__(self, *, config: TrainConfig, joint_names: list[str], support_X: list[np.ndarray],
                 support_Y: list[np.ndarray], hypers: list[Hyper], robot_spec: dict | None = None,
                 friction_scale: np.ndarray | None = None, report: dict | None = None,
                 basis_coef: list[np.ndarray | None] | None = None, basis_kind: str | None = None):
        self.config = config
        self.friction_scale_ = None if friction_scale is None else np.asarray(friction_scale, dtype=np.float64)
        self.joint_names_ = list(joint_names)
        self.support_X_ = [np.asarray(a, dtype=np.float64) for a in support_X]
        self.support_Y_ = [np.asarray(a, dtype=np.float64) for a in support_Y]
        self.hypers_ = hypers
        # Per mode (n, p) coefficients of the rigid-body regressor mean, or None.
        self.basis_coef_ = list(basis_coef) if basis_coef is not None else [None] * len(self.support_X_)
        self.basis_kind_ = basis_kind
        self.robot_spec = robot_spec or None
        self.report = report or {}
        self._robot = None
        self._gps: list[ExactGP | None] = [None] * len(self.support_X_)

    @property
    def n_modes(self) -> int:
        return len(self.support_X_)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names_)

    @property
    def support_q_(self) -> np.ndarray:
        return self.support_X_[0][:, : self.n_joints]

    @property
    def robot(self):
        if self._robot is None and self.robot_spec:
            from ..physics.robot import load_robot

            self._robot = load_robot(robot=self.robot_spec.get("robot"), urdf=self.robot_spec.get("urdf"),
                                     joint_names=self.robot_spec.get("joint_names"))
        return self._robot

    def gp(self, mode: int = 0) -> ExactGP:
        if not 0 <= mode < self.n_modes:
            raise ValueError(f"mode must be in 0..{self.n_modes - 1}, got {mode}")
        if self._gps[mode] is None:
            g = ExactGP(device=self.config.device, ard=self.config.ard)
            self._gps[mode] = g.fit(self.support_X_[mode], self.support_Y_[mode], hyper=self.hypers_[mode],
                                    optimise=False)
        return self._gps[mode]

    def predict(self, q, dq, ddq, mode: int = 0, *, friction_sign: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Torque mean and std (T, n) in ``mode`` at states q, dq, ddq (T, n).

        ``friction_sign`` (+1 or -1) overrides the smooth-sign friction input (sliding direction)."""
        q, dq, ddq = (np.atleast_2d(np.asarray(a, dtype=np.float64)) for a in (q, dq, ddq))
        semi = self.config.semiparametric if self.robot_spec else "none"
        coef = self.basis_coef_[mode]
        f = _features(q, dq, ddq, np.zeros_like(q), semi, self.robot if self.robot_spec else None,
                      friction_scale=self.friction_scale_, friction_sign=friction_sign,
                      basis_kind=self.basis_kind_ if coef is not None else None)
        mean, std = self.gp(mode).predict(f.X, include_noise=True)
        mean, std = mean.reshape(len(q), -1), std.reshape(len(q), -1)
        if coef is not None:
            mean = mean + np.einsum("tjp,jp->tj", f.basis, coef)
        if f.tau_rbd is not None and semi == "residual":
            mean = mean + f.tau_rbd
        return mean, std

    def nominal_torque(self, q) -> np.ndarray:
        """Position-only feedforward target tau(q, 0, 0) of the nominal mode: (T, n) -> (T, n).

        With the friction input, the prediction is averaged over both sliding directions: at
        rest the friction torque can be anywhere in its band, so the band's centre is what a
        position-only feedforward should supply, and a moving log has data on both branches but
        almost none at the sign's zero crossing (evaluating there extrapolated: 0.73 vs 0.17 N*m
        static error on the replica lever)."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        z = np.zeros_like(q)
        if self.friction_scale_ is None:
            return self.predict(q, z, z, mode=0)[0]
        up = self.predict(q, z, z, mode=0, friction_sign=1.0)[0]
        down = self.predict(q, z, z, mode=0, friction_sign=-1.0)[0]
        return 0.5 * (up + down)

    # -- persistence ---------------------------------------------------------------------------
    def save(self, out_dir: str | Path) -> None:
        out_dir = Path(out_dir)
        arrays = {}
        for k in range(self.n_modes):
            arrays[f"X_{k}"] = self.support_X_[k]
            arrays[f"Y_{k}"] = self.support_Y_[k]
            arrays[f"lengthscale_{k}"] = self.hypers_[k].lengthscale
            arrays[f"signal_var_{k}"] = self.hypers_[k].signal_var
            arrays[f"noise_var_{k}"] = self.hypers_[k].noise_var
            if self.basis_coef_[k] is not None:
                arrays[f"basis_coef_{k}"] = self.basis_coef_[k]
        if self.friction_scale_ is not None:
            arrays["friction_scale"] = self.friction_scale_
        np.savez(out_dir / "model.npz", **arrays)
        meta = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "mmgp_version": __version__,
                "n_modes": self.n_modes, "joint_names": self.joint_names_, "config": self.config.as_dict(),
                "robot": self.robot_spec, "mean_basis": self.basis_kind_}
        (out_dir / "model.json").write_text(json.dumps(meta, indent=2))

    @classmethod
    def load(cls, model_dir: str | Path) -> "TrainedModel":
        model_dir = Path(model_dir)
        meta_path = model_dir / "model.json"
        if not meta_path.is_file():
            raise InputError("not a trained model folder (model.json missing; run 'mmgp train' first)",
                             file=model_dir)
        meta = json.loads(meta_path.read_text())
        if meta.get("format") != MODEL_FORMAT or meta.get("version") != MODEL_VERSION:
            raise InputError(f"unsupported model format {meta.get('format')} v{meta.get('version')}", file=meta_path)
        with np.load(model_dir / "model.npz") as z:
            K = meta["n_modes"]
            sx = [z[f"X_{k}"] for k in range(K)]
            sy = [z[f"Y_{k}"] for k in range(K)]
            hy = [Hyper(z[f"lengthscale_{k}"], z[f"signal_var_{k}"], z[f"noise_var_{k}"]) for k in range(K)]
            fs = z["friction_scale"] if "friction_scale" in z.files else None
            bc = [z[f"basis_coef_{k}"] if f"basis_coef_{k}" in z.files else None for k in range(K)]
        return cls(config=TrainConfig(**meta["config"]), joint_names=meta["joint_names"], support_X=sx,
                   support_Y=sy, hypers=hy, robot_spec=meta.get("robot"), friction_scale=fs, basis_coef=bc,
                   basis_kind=meta.get("mean_basis"))


@dataclass
class TrainResult:
    model: TrainedModel
    sem: MultimodalSEM
    logs: list[RobotLog]
    features: Features
    report: dict


def train(paths: Sequence[str | Path], cfg: TrainConfig, *, robot=None,
          progress: Callable | None = None) -> TrainResult:
    """Run the whole training pipeline on one or more logs."""
    t0 = time.perf_counter()
    logs = load_logs(paths, cfg, robot)
    t_load = time.perf_counter() - t0
    semi = cfg.semiparametric if robot is not None else "none"
    fscale = (friction_velocity_scale(np.concatenate([lg.dq for lg in logs]))
              if cfg.friction_feature else None)
    basis_kind = resolve_mean_basis(cfg.mean_basis, robot, semi)
    feats = build_features(logs, semi, robot, fscale, basis_kind=basis_kind)
    kw = dict(disturbance=cfg.disturbance, estep=cfg.estep, stay_prob=cfg.stay_prob, max_sweeps=cfg.max_sweeps,
              min_sweeps=cfg.min_sweeps, average_last=cfg.average_last, max_support=cfg.max_support,
              final_support=cfg.final_support,
              fit_points=cfg.fit_points, fit_iter=cfg.fit_iter, exclusion_s=cfg.exclusion_s, seed=cfg.seed,
              progress=progress,
              shared_basis=basis_kind == "payload",
              gp_kwargs={"ard": cfg.ard, "objective": cfg.objective, "device": cfg.device})
    mode_selection = None
    if cfg.modes == "auto":
        sem, mode_selection = select_n_modes(feats.X, feats.Y, (1, 2, 3), t=feats.t, starts=feats.starts,
                                             basis=feats.basis, **kw)
    else:
        sem = MultimodalSEM(n_modes=int(cfg.modes), **kw).fit(feats.X, feats.Y, t=feats.t, starts=feats.starts,
                                                              basis=feats.basis)
    joint_names = logs[0].joint_names or (robot.joint_names if robot is not None else
                                          [f"joint_{j}" for j in range(logs[0].n_joints)])
    robot_spec = None
    if robot is not None:
        robot_spec = {"robot": getattr(robot, "name", None),
                      "urdf": None if getattr(robot, "name", None) else str(robot.urdf_path),
                      "joint_names": robot.joint_names}
    hypers = [g.hyper_ for g in sem.gps_]
    model = TrainedModel(config=cfg, joint_names=joint_names, support_X=sem.support_X_, support_Y=sem.support_Y_,
                         hypers=hypers, robot_spec=robot_spec, friction_scale=fscale, basis_coef=sem.coef_,
                         basis_kind=basis_kind)
    model._robot = robot
    report = {
        "mmgp_version": __version__,
        "logs": [lg.path for lg in logs],
        "n_samples": int(len(feats.Y)),
        "n_joints": len(joint_names),
        "joint_names": joint_names,
        "derivatives_estimated": {"dq": any(lg.dq_estimated for lg in logs), "ddq": any(lg.ddq_estimated for lg in logs)},
        "robot": robot_spec,
        "semiparametric": semi,
        # The per-mode coefficients themselves are in model.npz (basis_coef_<k>).
        "mean_basis": {"kind": basis_kind, "rank": int(sem.basis_rank_)},
        "config": cfg.as_dict(),
        "n_modes": len(sem.gps_),
        "mode_selection": mode_selection,
        "hyperparameters": [
            {"mode": k, "per_joint": [
                {"joint": joint_names[j], "lengthscale": g.lengthscale_[j].tolist(),
                 "signal_std": float(math.sqrt(g.hyper_.signal_var[j]) * g.y_scaler_.scale_[j]),
                 "noise_std": float(g.noise_std_[j])} for j in range(len(joint_names))],
             "inputs": _input_names(len(joint_names), semi == "feature", fscale is not None),
             "n_support": int(len(sem.support_Y_[k]))}
            for k, g in enumerate(sem.gps_)],
        "disturbance": {"enabled": cfg.disturbance, "sigma_d_std": np.sqrt(sem.sigma_d_).tolist(),
                        "p_enter": sem.p_enter_, "p_leave": sem.p_leave_,
                        "n_disturbed": int(sem.disturbed_.sum())},
        "switching_prior": {"stay_prob": sem.stay_prob_, "learned": cfg.stay_prob is None},
        "likelihood_trace": [{"sweep": r.sweep, "log_joint": r.log_joint, "log_marginal": r.log_marginal,
                              "changed": r.changed, "n_disturbed": r.n_disturbed, "mode_sizes": r.mode_sizes,
                              "seconds": r.seconds} for r in sem.trace_],
        "converged": bool(sem.converged_),
        "n_sweeps": int(sem.n_sweeps_),
        "timings": dict(sem.timings_, load_s=t_load, total_s=time.perf_counter() - t0),
    }
    model.report = report
    return TrainResult(model, sem, logs, feats, report)


def labels_frame(result: TrainResult):
    """The contract's labels table: t, mode, disturbed, p_disturbed, p_mode_<k>."""
    import pandas as pd

    sem = result.sem
    t = np.concatenate([lg.t for lg in result.logs])
    df = pd.DataFrame({"t": t, "mode": sem.labels_.astype(np.int64),
                       "disturbed": sem.disturbed_.astype(np.int64), "p_disturbed": sem.p_disturbed_})
    for k in range(sem.p_mode_.shape[1]):
        df[f"p_mode_{k}"] = sem.p_mode_[:, k]
    if len(result.logs) > 1:
        df.insert(1, "log", np.concatenate([np.full(lg.n_samples, i) for i, lg in enumerate(result.logs)]))
    return df
