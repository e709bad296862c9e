"""Recording a MuJoCo robot: a 1 kHz tracking loop with pushes, sensor models and contract labels.

:func:`simulate` tracks a reference with a PD or computed-torque controller, applies smooth
external pushes (:class:`Push`), adds sensor noise and quantisation, logs at a chosen rate and
labels every sample by the contract rule for a "significant" force (:func:`contract_disturbed`).
The result is a :class:`Recording` holding the logged signals and the truth behind them.

Units: s, rad, rad/s, rad/s^2, N*m, N, m. Array shapes are (T, n) for T samples of n joints.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import mujoco
import numpy as np
import pandas as pd

LABEL_RULE = ("disturbed = 1 where, for some joint j, |tau_push_j| > 3*tau_noise_j + 2*frictionloss_j "
              "(the joint torque of the external push vs. the torque-noise std and the dry-friction level "
              "at that sample); 0 where no push force acts; -1 otherwise (ambiguous).")

# Per-sample signals the loop keeps (the logged ones get sensor noise afterwards).
_ROWS = ("t", "q", "dq", "ddq", "tau", "tau_push", "push_force", "frictionloss", "mode", "q_ref", "tau_constraint")


@dataclass(frozen=True)
class Push:
    """A smooth external push: wrench ``s(t) * (force, torque)`` with ``s = sin^2(pi (t - t0) / duration)``
    on ``[t0, t0 + duration]`` (or, with ``ramp``, sin^2 ramps of ``ramp`` s around a flat top) and 0
    elsewhere, applied at ``point`` (m, in the body frame) of
    ``body``. ``frame="world"``: force/torque (N, N*m) are world vectors; ``frame="body"``: they
    turn with the body (e.g. always tangential to a lever)."""

    t0: float
    duration: float
    body: str
    force: tuple = (0.0, 0.0, 0.0)
    torque: tuple = (0.0, 0.0, 0.0)
    point: tuple = (0.0, 0.0, 0.0)
    frame: str = "world"
    ramp: float | None = None

    def scale(self, t: float) -> float:
        """Push profile in [0, 1]; with ``ramp`` (s) a flat top between raised-cosine ramps."""
        tau = t - self.t0
        if not 0.0 < tau < self.duration:
            return 0.0
        if self.ramp is None:
            return float(np.sin(np.pi * tau / self.duration) ** 2)
        r = min(self.ramp, 0.5 * self.duration)
        edge = min(tau, self.duration - tau)
        return 1.0 if edge >= r else float(np.sin(0.5 * np.pi * edge / r) ** 2)


@dataclass
class Recording:
    """A simulated log. ``t`` (T,) s; ``q``, ``tau`` (T, n) as logged (with sensor noise);
    ``dq``/``ddq`` (T, n) as logged or None when left for mmgp to estimate; ``labels`` has
    ``t``, ``disturbed``, ``mode``; ``info`` holds the physics, the rule and the true signals
    (``q_true``, ``dq_true``, ``ddq_true``, ``tau_true``, ``tau_push``, ``push_force``,
    ``frictionloss``: arrays over the logged samples)."""

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray | None
    ddq: np.ndarray | None
    tau: np.ndarray
    labels: pd.DataFrame
    info: dict = field(default_factory=dict)

    def write(self, log_path, labels_path=None) -> None:
        """Write the log (contract section 1, metadata ``robot``/``joint_names`` from ``info``) and
        the labels file."""
        from ..data.logs import write_log
        from ..data.outputs import write_table

        write_log(log_path, self.t, self.q, self.tau, dq=self.dq, ddq=self.ddq, robot=self.info.get("robot"),
                  joint_names=self.info.get("joint_names"))
        if labels_path is not None:
            write_table(labels_path, self.labels, metadata={"label_rule": self.info.get("label_rule", LABEL_RULE)})


def contract_disturbed(tau_push: np.ndarray, push_force: np.ndarray, tau_noise, frictionloss) -> np.ndarray:
    """Contract labels from the push's joint torque.

    ``tau_push`` (T, n) N*m, ``push_force`` (T,) magnitude of the applied wrench (0 = no push),
    ``tau_noise`` scalar or (n,) N*m std, ``frictionloss`` (T, n) or (n,) N*m dry-friction level.
    Returns (T,) int: 1 significant, 0 no force, -1 ambiguous (see :data:`LABEL_RULE`).
    """
    tau_push = np.atleast_2d(np.asarray(tau_push, dtype=np.float64))
    thr = 3.0 * np.asarray(tau_noise, dtype=np.float64) + 2.0 * np.asarray(frictionloss, dtype=np.float64)
    big = (np.abs(tau_push) > thr).any(axis=1)
    out = np.where(big, 1, -1)
    out[np.asarray(push_force) == 0.0] = 0
    return out.astype(int)


def _controller(n: int, kp, kd, controller_model, gains: str) -> Callable:
    """``control(data, q_r, dq_r, ddq_r) -> (n,)`` joint torque of the tracking law of :func:`simulate`."""
    if gains not in ("acceleration", "torque"):
        raise ValueError("gains must be 'acceleration' or 'torque'")
    kp = np.broadcast_to(np.asarray(kp, dtype=np.float64), (n,))
    kd = np.broadcast_to(np.asarray(kd, dtype=np.float64), (n,))
    if controller_model is None:
        return lambda data, q_r, dq_r, ddq_r: kp * (q_r - data.qpos) + kd * (dq_r - data.qvel)
    cdata = mujoco.MjData(controller_model)

    def inverse_dynamics(data, q_r, dq_r, ddq_r):
        e = q_r - data.qpos
        de = dq_r - data.qvel
        cdata.qpos[:] = data.qpos
        cdata.qvel[:] = data.qvel
        if gains == "acceleration":
            cdata.qacc[:] = ddq_r + kp * e + kd * de
            mujoco.mj_inverse(controller_model, cdata)
            return cdata.qfrc_inverse.copy()
        cdata.qacc[:] = ddq_r
        mujoco.mj_inverse(controller_model, cdata)
        return cdata.qfrc_inverse + kp * e + kd * de

    return inverse_dynamics


def _push_body_ids(model, pushes: Sequence[Push]) -> list[int]:
    ids = []
    for p in pushes:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, p.body)
        if bid < 0:
            raise ValueError(f"push body '{p.body}' not in the model")
        ids.append(bid)
    return ids


def _apply_pushes(model, data, pushes: Sequence[Push], bodies: list[int], t: float) -> tuple[np.ndarray, float]:
    """Set ``data.xfrc_applied`` to the pushes acting at ``t``; returns their joint torque (n,) N*m
    and the summed wrench magnitude (0 when no push acts)."""
    # A wrench at a point = the same force plus a moment about the body com (xfrc_applied acts at
    # the com); its joint torque is what MuJoCo's mj_applyFT maps it to.
    data.xfrc_applied[:] = 0.0
    tau_push = np.zeros(model.nv)
    qfrc = np.zeros(model.nv)
    fmag = 0.0
    if pushes and any(p.scale(t) != 0.0 for p in pushes):
        # After mj_step, poses still belong to the previous state; mj_step will apply the
        # wrench at the current one, so the point and the Jacobian must be taken there.
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
    for p, bid in zip(pushes, bodies):
        s = p.scale(t)
        if s == 0.0:
            continue
        R = data.xmat[bid].reshape(3, 3)
        f = s * np.asarray(p.force, dtype=np.float64)
        m = s * np.asarray(p.torque, dtype=np.float64)
        if p.frame == "body":
            f, m = R @ f, R @ m
        point = data.xpos[bid] + R @ np.asarray(p.point, dtype=np.float64)
        data.xfrc_applied[bid, :3] += f
        data.xfrc_applied[bid, 3:] += m + np.cross(point - data.xipos[bid], f)
        qfrc[:] = 0.0
        mujoco.mj_applyFT(model, data, f, m, point, bid, qfrc)
        tau_push += qfrc
        fmag += float(np.linalg.norm(np.concatenate([f, m])))
    return tau_push, fmag


def _track(model, data, reference, control, steps: range, per: int, pushes, before_step, mode_fn) -> dict:
    """Run the 1 kHz loop over the step indices ``steps`` (negative ones are settling, not logged);
    log every ``per``-th step from 0. Returns the per-sample arrays named in :data:`_ROWS`."""
    dt = float(model.opt.timestep)
    bodies = _push_body_ids(model, pushes)
    rows = {k: [] for k in _ROWS}
    for k in steps:
        t = k * dt
        q_r, dq_r, ddq_r = (np.asarray(a, dtype=np.float64) for a in reference(t))
        data.ctrl[:] = control(data, q_r, dq_r, ddq_r)
        if before_step is not None:
            before_step(t, model, data)
        tau_push, fmag = _apply_pushes(model, data, pushes, bodies, t)
        log_now = k >= 0 and k % per == 0
        if log_now:
            for key, v in (("t", t), ("q", data.qpos.copy()), ("dq", data.qvel.copy()), ("tau", data.ctrl.copy()),
                           ("tau_push", tau_push), ("push_force", fmag),
                           ("frictionloss", model.dof_frictionloss.copy()),
                           ("mode", int(mode_fn(t)) if mode_fn is not None else 0), ("q_ref", q_r)):
                rows[key].append(v)
        mujoco.mj_step(model, data)
        if log_now:
            rows["ddq"].append(data.qacc.copy())
            rows["tau_constraint"].append(data.qfrc_constraint.copy())
        # MuJoCo resets the state and only warns when it blows up; a recording must not go on.
        if (not np.isfinite(data.qpos).all() or data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
                or data.warning[mujoco.mjtWarning.mjWARN_BADCTRL].number):
            raise RuntimeError(f"simulation diverged at t={t:.3f}s (lower the gains or the time step)")
    return {k: np.asarray(v) for k, v in rows.items()}


def _sensors(arr: dict, rng, *, q_noise, q_resolution, log_dq, dq_noise, tau_noise) -> tuple:
    """Logged (q, dq or None, tau) (T, n) from the true signals: q + N(0, q_noise) rounded to
    ``q_resolution``, dq + N(0, dq_noise), tau + N(0, tau_noise), drawn from ``rng`` in that order."""
    T, n = arr["q"].shape
    q_log = arr["q"] + q_noise * rng.standard_normal((T, n))
    if q_resolution:
        q_log = np.round(q_log / q_resolution) * q_resolution
    dq_log = None
    if log_dq:
        dq_log = arr["dq"] + (dq_noise or 0.0) * rng.standard_normal((T, n))
    tau_log = arr["tau"] + tau_noise * rng.standard_normal((T, n))
    return q_log, dq_log, tau_log


def simulate(model, reference: Callable[[float], tuple], duration: float, *, rate_hz: float,
             kp, kd, controller_model=None, gains: str = "acceleration", pushes: Sequence[Push] = (),
             before_step: Callable | None = None, mode_fn: Callable[[float], int] | None = None,
             q_resolution: float | None = None, q_noise: float = 0.0, dq_noise: float | None = None,
             tau_noise=0.0, log_dq: bool = True, log_ddq: bool = False, seed: int | None = 0,
             robot: str | None = None, joint_names: Sequence[str] | None = None,
             settle: float = 0.0) -> Recording:
    """Track ``reference`` at the model's time step (1 kHz by default) and log at ``rate_hz``.

    ``reference(t) -> (q_r, dq_r, ddq_r)``, each (n,). Control, every step:
    ``controller_model is None``: PD, ``tau = kp (q_r - q) + kd (dq_r - dq)`` (kp N*m/rad,
    kd N*m*s/rad); otherwise inverse dynamics ``ID`` of ``controller_model`` (the nominal model,
    via ``mj_inverse``) at the measured state, with ``gains="acceleration"`` computed torque
    ``tau = ID(q, dq, ddq_r + kp e + kd de)`` (kp 1/s^2, kd 1/s), with ``gains="torque"``
    feedforward + PD ``tau = ID(q, dq, ddq_r) + kp e + kd de`` (kp N*m/rad, kd N*m*s/rad).
    ``before_step(t, model, data)`` runs after ``data.ctrl`` is set and before ``mj_step`` (to
    change friction from the torque, switch payloads, ...). ``pushes`` go to ``xfrc_applied``.

    Logged ``tau`` = actuator torque (``data.ctrl``) + N(0, tau_noise); ``q`` = true q + noise,
    then rounded to ``q_resolution``; ``dq`` = true dq + N(0, dq_noise) if ``log_dq``;
    ``ddq`` = true acceleration if ``log_ddq``. The state and torque of a sample belong together:
    q, dq at the start of a step, ctrl and the acceleration MuJoCo computed in that step.
    Initial state: q = q_r(-settle), dq = dq_r(-settle); the first ``settle`` seconds (reference
    evaluated at negative times) are simulated but not logged, so a PD loop without feedforward
    has taken up the load by t = 0. Pushes should start at t >= 0.
    """
    rng = np.random.default_rng(seed)
    n = model.nv
    dt = float(model.opt.timestep)
    per = int(round(1.0 / (rate_hz * dt)))
    if abs(per * dt * rate_hz - 1.0) > 1e-9:
        raise ValueError(f"rate_hz={rate_hz} must divide the simulation rate {1.0 / dt:g} Hz")
    n_pre = int(round(settle / dt))
    control = _controller(n, kp, kd, controller_model, gains)
    data = mujoco.MjData(model)
    q0, dq0, _ = reference(-n_pre * dt)
    data.qpos[:] = q0
    data.qvel[:] = dq0
    mujoco.mj_forward(model, data)
    arr = _track(model, data, reference, control, range(-n_pre, int(round(duration / dt))), per, pushes,
                 before_step, mode_fn)
    tau_noise_v = np.broadcast_to(np.asarray(tau_noise, dtype=np.float64), (n,))
    q_log, dq_log, tau_log = _sensors(arr, rng, q_noise=q_noise, q_resolution=q_resolution, log_dq=log_dq,
                                      dq_noise=dq_noise, tau_noise=tau_noise_v)
    disturbed = contract_disturbed(arr["tau_push"], arr["push_force"], tau_noise_v, arr["frictionloss"])
    labels = pd.DataFrame({"t": arr["t"], "disturbed": disturbed, "mode": arr["mode"].astype(int)})
    names = list(joint_names) if joint_names is not None else [
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, i) for i in range(model.njnt)]
    info = {
        "robot": robot, "joint_names": names, "label_rule": LABEL_RULE, "rate_hz": rate_hz,
        "sim_timestep": dt, "tau_noise": tau_noise_v.copy(), "q_noise": q_noise, "q_resolution": q_resolution,
        "dq_noise": dq_noise if log_dq else None, "seed": seed, "settle": settle,
        "pushes": [p.__dict__ for p in pushes],
        "q_true": arr["q"], "dq_true": arr["dq"], "ddq_true": arr["ddq"], "tau_true": arr["tau"],
        "tau_push": arr["tau_push"], "push_force": arr["push_force"], "frictionloss": arr["frictionloss"],
        "q_ref": arr["q_ref"], "tau_constraint": arr["tau_constraint"],
    }
    return Recording(t=arr["t"], q=q_log, dq=dq_log, ddq=arr["ddq"].copy() if log_ddq else None, tau=tau_log,
                     labels=labels, info=info)
