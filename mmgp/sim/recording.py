"""MuJoCo recordings: the simulated "real robot" used by demos, tests and benchmarks.

MuJoCo is the independent physics engine here: recordings never come from Pinocchio's equations,
so a Pinocchio-based learner can be checked against them. The pieces:

* :func:`build_mjcf` / :func:`load_model`: an MJCF model built from a URDF through Pinocchio's
  parsed kinematic tree and inertials (MuJoCo cannot read the ``.dae`` meshes the URDFs reference,
  and no geometry is needed for dynamics). Joints outside ``joint_names`` are locked; optional
  joint friction, damping, armature, springs and a payload welded to a link.
* :func:`simulate`: a 1 kHz PD or computed-torque tracking controller, optional smooth pushes
  (external wrenches), sensor noise/quantisation, logging at a chosen rate, labels per the
  contract rule for "significant" force (:func:`contract_disturbed`).
* :func:`actuator_replica`: 1-DOF lever with load-dependent (Bowden-cable-like) dry friction,
  quasi-static exploration and hand-like pushes (replica of Haninger 2016, ch. 5).
* :func:`panda_modes`: 7-DOF Panda with a payload switching between masses and pushes.

Units: s, rad, rad/s, rad/s^2, N*m, N, kg, m. Array shapes are (T, n) for T samples of n joints.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence
from xml.sax.saxutils import quoteattr

import numpy as np
import pandas as pd

# ----------------------------------------------------------------------------------------------
# Locating URDFs
# ----------------------------------------------------------------------------------------------



def robot_urdf_path(name: str) -> str:
    """Path (str) of the URDF of an example-robot-data robot (e.g. ``"panda"``, ``"ur5"``);
    the lookup is :func:`mmgp.robot.robot_urdf_path`."""
    from ..physics.robot import robot_urdf_path as _lookup

    return str(_lookup(name))


def panda_urdf_path() -> str:
    """Path of example-robot-data's ``panda.urdf`` (7 arm joints + 2 finger joints)."""
    return robot_urdf_path("panda")


# ----------------------------------------------------------------------------------------------
# URDF -> MJCF via Pinocchio
# ----------------------------------------------------------------------------------------------


def reduced_pinocchio_model(urdf_path: str, joint_names: Sequence[str] | None = None):
    """Pinocchio model of ``urdf_path`` with every joint outside ``joint_names`` locked at its
    neutral position (fixed base). ``joint_names=None`` keeps all joints. Joint order of the
    result is Pinocchio's (``model.names[1:]``), whatever order ``joint_names`` lists them in.
    """
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(urdf_path))
    if joint_names is None:
        return model
    keep = set(joint_names)
    unknown = keep - set(model.names[1:])
    if unknown:
        raise ValueError(f"joints {sorted(unknown)} are not in {urdf_path} (has {list(model.names[1:])})")
    lock = [model.getJointId(nm) for nm in model.names[1:] if nm not in keep]
    if not lock:
        return model
    return pin.buildReducedModel(model, lock, pin.neutral(model))


def _per_joint(value, n: int, name: str) -> np.ndarray:
    if value is None:
        return np.zeros(n)
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)).copy()
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite")
    return arr


def _fmt(v) -> str:
    return " ".join(f"{float(x):.17g}" for x in np.ravel(v))


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    import pinocchio as pin

    x, y, z, w = pin.Quaternion(np.asarray(R, dtype=np.float64)).coeffs()
    return np.array([w, x, y, z])


def _body_name(model, j: int) -> str:
    """Name of the MuJoCo body of Pinocchio joint ``j``: the URDF link that the joint moves."""
    import pinocchio as pin

    for f in model.frames:
        if (f.parentJoint == j and f.type == pin.FrameType.BODY
                and np.allclose(f.placement.homogeneous, np.eye(4), atol=1e-12)):
            return f.name
    return f"{model.names[j]}_body"


# MuJoCo's friction constraint is soft: without the no-slip pass a joint held by dry friction creeps
# (about 0.03 rad in 2 s for the replica lever); with it a stuck joint stays exactly still.
NOSLIP_ITERATIONS = 10


def build_mjcf(urdf_path: str, joint_names: list[str] | None = None, *, frictionloss=None, damping=None,
               armature=None, stiffness=None, springref=None, payload: dict | None = None,
               timestep: float = 0.001, gravity: bool = True) -> str:
    """MJCF XML of a fixed-base robot, built from Pinocchio's parse of ``urdf_path``.

    The kinematic tree and link inertials are taken from Pinocchio (which merges links behind
    fixed joints into their parent); there is no geometry and no contact. Joints outside
    ``joint_names`` are locked at their neutral position (their links' inertia is merged). Joint
    order is Pinocchio's (``model.names[1:]`` of :func:`reduced_pinocchio_model`).

    Per-joint arrays (shape (n,) or a scalar), MuJoCo semantics:
    ``frictionloss`` dry friction level (N*m), ``damping`` viscous (N*m*s/rad), ``armature``
    reflected rotor inertia (kg*m^2), ``stiffness`` (N*m/rad) with rest angle ``springref`` (rad).

    ``payload={"link": name, "mass": kg, "com": [x, y, z]}`` (com in that link's frame, m; optional
    ``"inertia"``: 3 principal or 6 ``[xx, yy, zz, xy, xz, yz]`` values about the com in the link
    frame, default a solid 5 cm sphere) adds a body named ``"payload"`` welded to the link.

    Each joint gets a body named after the URDF link it moves, a ``<site>`` for every URDF link
    frame (named after the link) and a plain torque motor named after the joint (gear 1, no
    limits), so ``data.ctrl`` is the joint torque in N*m.
    """
    import pinocchio as pin

    model = reduced_pinocchio_model(urdf_path, joint_names)
    n = model.nv
    if any(model.joints[j].nv != 1 for j in range(1, model.njoints)):
        raise ValueError("only 1-DOF joints (revolute, continuous, prismatic) are supported")
    props = {k: _per_joint(v, n, k) for k, v in (("frictionloss", frictionloss), ("damping", damping),
                                                  ("armature", armature), ("stiffness", stiffness),
                                                  ("springref", springref))}
    for k in ("frictionloss", "damping", "armature", "stiffness"):
        if (props[k] < 0).any():
            raise ValueError(f"{k} must be non-negative")

    children: dict[int, list[int]] = {j: [] for j in range(model.njoints)}
    for j in range(1, model.njoints):
        children[model.parents[j]].append(j)

    payload_xml: dict[int, str] = {}
    if payload is not None:
        link = payload["link"]
        if not model.existFrame(link):
            raise ValueError(f"payload link '{link}' is not a frame of {urdf_path}")
        fr = model.frames[model.getFrameId(link)]
        mass = float(payload.get("mass", 0.0))
        if mass < 0:
            raise ValueError("payload mass must be non-negative")
        com = fr.placement.act(np.asarray(payload.get("com", [0.0, 0.0, 0.0]), dtype=np.float64))
        R = fr.placement.rotation
        if payload.get("inertia") is None:
            Ic = np.eye(3) * 0.4 * mass * 0.05 ** 2
        else:
            v = np.asarray(payload["inertia"], dtype=np.float64)
            Il = np.diag(v) if v.size == 3 else np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
            Ic = R @ Il @ R.T
        # MuJoCo refuses a massless body only when it moves on its own; welded it is fine, but keep a
        # floor so the body can later be given mass (mode switches) without recompiling.
        m_eff = max(mass, 1e-9)
        Ic = Ic if mass > 0 else np.eye(3) * 1e-12
        payload_xml[fr.parentJoint] = (
            f'<body name="payload" pos="{_fmt(com)}"><inertial pos="0 0 0" mass="{m_eff:.17g}" '
            f'fullinertia="{_fmt([Ic[0, 0], Ic[1, 1], Ic[2, 2], Ic[0, 1], Ic[0, 2], Ic[1, 2]])}"/></body>')

    sites: dict[int, list[str]] = {j: [] for j in range(model.njoints)}
    for f in model.frames:
        if f.type == pin.FrameType.BODY and f.parentJoint > 0:
            sites[f.parentJoint].append(
                f'<site name={quoteattr(f.name)} pos="{_fmt(f.placement.translation)}" '
                f'quat="{_fmt(_quat_wxyz(f.placement.rotation))}"/>')

    q0 = pin.neutral(model)
    lines: list[str] = []

    def emit(j: int, depth: int) -> None:
        ind = "  " * depth
        M = model.jointPlacements[j]
        jm = model.joints[j]
        jd = jm.createData()
        jm.calc(jd, q0)
        S = np.asarray(jd.S).reshape(6)
        lin, ang = S[:3], S[3:]
        if np.linalg.norm(ang) > 1e-12 and np.linalg.norm(lin) < 1e-12:
            jtype, axis = "hinge", ang
        elif np.linalg.norm(lin) > 1e-12 and np.linalg.norm(ang) < 1e-12:
            jtype, axis = "slide", lin
        else:
            raise ValueError(f"joint {model.names[j]} ({jm.shortname()}) is neither revolute nor prismatic")
        iv = jm.idx_v
        Y = model.inertias[j]
        Ic = Y.inertia
        lines.append(f'{ind}<body name={quoteattr(_body_name(model, j))} pos="{_fmt(M.translation)}" '
                     f'quat="{_fmt(_quat_wxyz(M.rotation))}">')
        lines.append(
            f'{ind}  <joint name={quoteattr(model.names[j])} type="{jtype}" axis="{_fmt(axis)}" pos="0 0 0" '
            f'limited="false" frictionloss="{props["frictionloss"][iv]:.17g}" damping="{props["damping"][iv]:.17g}" '
            f'armature="{props["armature"][iv]:.17g}" stiffness="{props["stiffness"][iv]:.17g}" '
            f'springref="{props["springref"][iv]:.17g}"/>')
        mass = max(float(Y.mass), 1e-9)
        lines.append(f'{ind}  <inertial pos="{_fmt(Y.lever)}" mass="{mass:.17g}" '
                     f'fullinertia="{_fmt([Ic[0, 0], Ic[1, 1], Ic[2, 2], Ic[0, 1], Ic[0, 2], Ic[1, 2]])}"/>')
        for s in sites[j]:
            lines.append(f"{ind}  {s}")
        if j in payload_xml:
            lines.append(f"{ind}  {payload_xml[j]}")
        for c in children[j]:
            emit(c, depth + 1)
        lines.append(f"{ind}</body>")

    for c in children[0]:
        emit(c, 2)
    world_payload = payload_xml.get(0, "")
    g = "0 0 -9.81" if gravity else "0 0 0"
    motors = "\n".join(f'    <motor name={quoteattr(nm)} joint={quoteattr(nm)} gear="1"/>' for nm in model.names[1:])
    return f"""<mujoco model={quoteattr(Path(urdf_path).stem)}>
  <compiler angle="radian" autolimits="true" balanceinertia="false" boundmass="0" boundinertia="0"/>
  <option timestep="{timestep:.17g}" gravity="{g}" integrator="Euler" noslip_iterations="{NOSLIP_ITERATIONS}">
    <flag contact="disable"/>
  </option>
  <worldbody>
    {world_payload}
{chr(10).join(lines)}
  </worldbody>
  <actuator>
{motors}
  </actuator>
</mujoco>
"""


def load_model(urdf_path: str, joint_names: list[str] | None = None, **kwargs):
    """``mujoco.MjModel`` of :func:`build_mjcf` (same arguments)."""
    import mujoco

    return mujoco.MjModel.from_xml_string(build_mjcf(urdf_path, joint_names, **kwargs))


def set_payload(model, mass: float, *, radius: float = 0.05) -> None:
    """Change the mass of the ``"payload"`` body in place (solid sphere of ``radius`` m).

    MuJoCo recomputes composite inertias from ``body_mass``/``body_inertia`` at every step, so the
    dynamics change at once; no recompilation is needed.
    """
    import mujoco

    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "payload")
    if bid < 0:
        raise ValueError("model has no 'payload' body (build it with payload=...)")
    model.body_mass[bid] = max(float(mass), 1e-9)
    model.body_inertia[bid] = 0.4 * float(mass) * radius ** 2 if mass > 0 else 1e-12


# ----------------------------------------------------------------------------------------------
# Simulation
# ----------------------------------------------------------------------------------------------

LABEL_RULE = ("disturbed = 1 where, for some joint j, |tau_push_j| > 3*tau_noise_j + 2*frictionloss_j "
              "(the joint torque of the external push vs. the torque-noise std and the dry-friction level "
              "at that sample); 0 where no push force acts; -1 otherwise (ambiguous).")


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
    import mujoco

    rng = np.random.default_rng(seed)
    n = model.nv
    data = mujoco.MjData(model)
    dt = float(model.opt.timestep)
    per = int(round(1.0 / (rate_hz * dt)))
    if abs(per * dt * rate_hz - 1.0) > 1e-9:
        raise ValueError(f"rate_hz={rate_hz} must divide the simulation rate {1.0 / dt:g} Hz")
    n_steps = int(round(duration / dt))
    n_pre = int(round(settle / dt))
    kp = np.broadcast_to(np.asarray(kp, dtype=np.float64), (n,))
    kd = np.broadcast_to(np.asarray(kd, dtype=np.float64), (n,))
    cdata = mujoco.MjData(controller_model) if controller_model is not None else None
    if gains not in ("acceleration", "torque"):
        raise ValueError("gains must be 'acceleration' or 'torque'")
    push_bodies = []
    for p in pushes:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, p.body)
        if bid < 0:
            raise ValueError(f"push body '{p.body}' not in the model")
        push_bodies.append(bid)

    q0, dq0, _ = reference(-n_pre * dt)
    data.qpos[:] = q0
    data.qvel[:] = dq0
    mujoco.mj_forward(model, data)

    rows = {k: [] for k in ("t", "q", "dq", "ddq", "tau", "tau_push", "push_force", "frictionloss", "mode",
                            "q_ref", "tau_constraint")}
    qfrc = np.zeros(n)
    for k in range(-n_pre, n_steps):
        t = k * dt
        q_r, dq_r, ddq_r = (np.asarray(a, dtype=np.float64) for a in reference(t))
        e = q_r - data.qpos
        de = dq_r - data.qvel
        if cdata is None:
            u = kp * e + kd * de
        else:
            cdata.qpos[:] = data.qpos
            cdata.qvel[:] = data.qvel
            if gains == "acceleration":
                cdata.qacc[:] = ddq_r + kp * e + kd * de
                mujoco.mj_inverse(controller_model, cdata)
                u = cdata.qfrc_inverse.copy()
            else:
                cdata.qacc[:] = ddq_r
                mujoco.mj_inverse(controller_model, cdata)
                u = cdata.qfrc_inverse + kp * e + kd * de
        data.ctrl[:] = u
        if before_step is not None:
            before_step(t, model, data)
        # Pushes: a wrench at a point = the same force plus a moment about the body com (xfrc_applied
        # acts at the com); its joint torque is what MuJoCo's mj_applyFT maps it to.
        data.xfrc_applied[:] = 0.0
        tau_push = np.zeros(n)
        fmag = 0.0
        if pushes and any(p.scale(t) != 0.0 for p in pushes):
            # After mj_step, poses still belong to the previous state; mj_step will apply the
            # wrench at the current one, so the point and the Jacobian must be taken there.
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
        for p, bid in zip(pushes, push_bodies):
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
        log_now = k >= 0 and k % per == 0
        if log_now:
            rows["t"].append(t)
            rows["q"].append(data.qpos.copy())
            rows["dq"].append(data.qvel.copy())
            rows["tau"].append(data.ctrl.copy())
            rows["tau_push"].append(tau_push)
            rows["push_force"].append(fmag)
            rows["frictionloss"].append(model.dof_frictionloss.copy())
            rows["mode"].append(int(mode_fn(t)) if mode_fn is not None else 0)
            rows["q_ref"].append(q_r)
        mujoco.mj_step(model, data)
        if log_now:
            rows["ddq"].append(data.qacc.copy())
            rows["tau_constraint"].append(data.qfrc_constraint.copy())
        # MuJoCo resets the state and only warns when it blows up; a recording must not go on.
        if (not np.isfinite(data.qpos).all() or data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
                or data.warning[mujoco.mjtWarning.mjWARN_BADCTRL].number):
            raise RuntimeError(f"simulation diverged at t={t:.3f}s (lower the gains or the time step)")

    arr = {k: np.asarray(v) for k, v in rows.items()}
    T = arr["t"].shape[0]
    tau_noise_v = np.broadcast_to(np.asarray(tau_noise, dtype=np.float64), (n,))
    q_log = arr["q"] + q_noise * rng.standard_normal((T, n))
    if q_resolution:
        q_log = np.round(q_log / q_resolution) * q_resolution
    dq_log = None
    if log_dq:
        dq_log = arr["dq"] + (dq_noise or 0.0) * rng.standard_normal((T, n))
    tau_log = arr["tau"] + tau_noise_v * rng.standard_normal((T, n))
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


# ----------------------------------------------------------------------------------------------
# Generators
# ----------------------------------------------------------------------------------------------


def _push_schedule(rng, t_end: float, *, gap: tuple, dur: tuple, first: tuple) -> list[tuple[float, float]]:
    """(t0, duration) of pushes separated by random gaps, all ending before ``t_end``."""
    out = []
    t = rng.uniform(*first)
    while True:
        d = rng.uniform(*dur)
        if t + d > t_end:
            break
        out.append((t, d))
        t += d + rng.uniform(*gap)
    return out


# Replica physics (Haninger 2016, ch. 5, re-created): a horizontal-axis revolute joint lifting a
# 0.73 kg load on a 0.2 m lever, driven through a Bowden cable whose dry friction grows with the
# transmitted torque.
REPLICA = {
    "lever_length": 0.2,          # m, joint axis to load centre
    "lever_mass": 0.1,            # kg, uniform rod from the axis to the load
    "load_mass": 0.73,            # kg
    "load_radius": 0.03,          # m, solid sphere (own inertia 2/5 m r^2)
    "armature": 1.0e-3,           # kg*m^2, reflected motor/gear inertia
    "damping": 0.01,              # N*m*s/rad, viscous
    "friction_c": 0.3,            # N*m, dry friction at zero torque
    "friction_beta": 0.2,         # dry friction grows by beta * |motor torque|
    "kp": 150.0,                  # N*m/rad, PD position gain
    "kd": 3.0,                    # N*m*s/rad
    "tau_noise": 0.02,            # N*m, std of the torque reading
    "encoder_counts": 2 ** 14,    # counts per revolution
}


def replica_mjcf(timestep: float = 0.001) -> str:
    """MJCF of the 1-DOF replica lever (joint ``lever_joint`` about the horizontal world -y axis,
    q = 0 with the lever horizontal, q > 0 lifting the load; needed static torque
    ``(m_load L + m_lever L/2) g cos q``). Bodies ``lever`` and ``load``; one torque motor."""
    P = REPLICA
    L, ml, mL, r = P["lever_length"], P["lever_mass"], P["load_mass"], P["load_radius"]
    i_rod = ml * L * L / 12.0
    i_ball = 0.4 * mL * r * r
    return f"""<mujoco model="actuator_replica">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:.17g}" gravity="0 0 -9.81" integrator="Euler" noslip_iterations="{NOSLIP_ITERATIONS}">
    <flag contact="disable"/>
  </option>
  <worldbody>
    <body name="lever">
      <joint name="lever_joint" type="hinge" axis="0 -1 0" limited="false" frictionloss="{P['friction_c']:.17g}"
             damping="{P['damping']:.17g}" armature="{P['armature']:.17g}"/>
      <inertial pos="{L / 2:.17g} 0 0" mass="{ml:.17g}" diaginertia="1e-7 {i_rod:.17g} {i_rod:.17g}"/>
      <body name="load" pos="{L:.17g} 0 0">
        <inertial pos="0 0 0" mass="{mL:.17g}" diaginertia="{i_ball:.17g} {i_ball:.17g} {i_ball:.17g}"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="lever_joint" joint="lever_joint" gear="1"/>
  </actuator>
</mujoco>
"""


def actuator_replica(seed: int = 0, n_samples: int = 330, rate_hz: float = 20.0) -> Recording:
    """1-DOF replica of the source experiment: quasi-static PD exploration of a lever under gravity
    with load-dependent dry friction and intermittent hand-like pushes.

    Physics in :data:`REPLICA`. Dry friction ``0.3 + 0.2 |tau_motor|`` N*m is set each 1 ms step
    in ``dof_frictionloss`` from the current motor torque, so MuJoCo's friction constraint
    produces stiction. Reference: ``0.3 + 0.85 sin(2 pi t / T1 + p1) + 0.35 sin(2 pi t / T2 + p2)``
    rad with T1 ~ U(14, 20) s, T2 ~ U(5, 8) s (peak speed < 0.75 rad/s; inertial torque < 0.02 N*m).
    Pushes: a force perpendicular to the lever at the load, bumps of U(0.3, 2) s (sin^2 ramps of
    U(0.1, 0.25) s around a flat top), random sign,
    peak joint torque U(1.5, 4) N*m (7.5-20 N at the load), gaps U(1.2, 3.5) s (about a third of the samples pushed).
    Logged: q (2^14 counts/rev encoder) and tau (+ N(0, 0.02) N*m); dq/ddq are left out for mmgp
    to estimate (the true ones are in ``info``). Labels: :data:`LABEL_RULE`, mode 0.
    """
    import mujoco

    P = REPLICA
    rng = np.random.default_rng(seed)
    model = mujoco.MjModel.from_xml_string(replica_mjcf())
    duration = n_samples / rate_hz
    T1, T2 = rng.uniform(14.0, 20.0), rng.uniform(5.0, 8.0)
    p1, p2 = rng.uniform(0, 2 * np.pi, 2)
    w1, w2 = 2 * np.pi / T1, 2 * np.pi / T2
    a0, a1, a2 = 0.3, 0.85, 0.35

    def reference(t):
        q = a0 + a1 * np.sin(w1 * t + p1) + a2 * np.sin(w2 * t + p2)
        dq = a1 * w1 * np.cos(w1 * t + p1) + a2 * w2 * np.cos(w2 * t + p2)
        ddq = -a1 * w1 ** 2 * np.sin(w1 * t + p1) - a2 * w2 ** 2 * np.sin(w2 * t + p2)
        return np.array([q]), np.array([dq]), np.array([ddq])

    L = P["lever_length"]
    pushes = []
    for t0, d in _push_schedule(rng, duration, gap=(1.2, 3.5), dur=(0.3, 2.0), first=(0.8, 2.5)):
        tau_peak = rng.choice([-1.0, 1.0]) * rng.uniform(1.5, 4.0)
        # Body z of the load is perpendicular to the lever in its plane of motion; +z gives +tau.
        pushes.append(Push(t0=float(t0), duration=float(d), body="load", force=(0.0, 0.0, float(tau_peak / L)),
                           frame="body", ramp=float(rng.uniform(0.1, 0.25))))

    c, beta = P["friction_c"], P["friction_beta"]

    def load_dependent_friction(t, m, d):
        m.dof_frictionloss[0] = c + beta * abs(d.ctrl[0])

    rec = simulate(model, reference, duration, rate_hz=rate_hz, kp=P["kp"], kd=P["kd"], pushes=pushes,
                   before_step=load_dependent_friction, q_resolution=2 * np.pi / P["encoder_counts"],
                   tau_noise=P["tau_noise"], log_dq=False, seed=int(rng.integers(2 ** 31)),
                   robot=None, joint_names=["lever_joint"], settle=2.0)
    rec.info.update({
        "generator": "actuator_replica", "seed": seed, "physics": dict(P),
        "static_torque": "(load_mass*L + lever_mass*L/2) * 9.81 * cos(q)",
        "friction_model": "frictionloss = friction_c + friction_beta * |motor torque|, updated every step",
        "reference": {"a": [a0, a1, a2], "T": [T1, T2], "phase": [p1, p2]},
        "logged": "q (quantised), tau (noisy); dq, ddq omitted",
    })
    return rec


# Panda defaults: a 1 kHz computed-torque loop on the nominal (payload-free) model. Gains act through
# the mass matrix, so the light wrist (effective inertia down to 0.005 kg*m^2) stays stable at 1 kHz,
# unlike joint-space torque gains of similar stiffness; 50 rad/s keeps payload tracking errors small.
PANDA = {
    "payload_link": "panda_link8",   # flange
    "payload_com": (0.0, 0.0, 0.12),  # m in the flange frame: an object held between the fingers
    "payload_radius": 0.05,          # m, solid sphere
    "kp": 2500.0,                    # 1/s^2 (critically damped, 50 rad/s)
    "kd": 100.0,                     # 1/s
    "tau_noise": 0.05,               # N*m
    "dq_noise": 0.005,               # rad/s
    "q_resolution": 2 * np.pi / 2 ** 19,  # rad (19-bit encoder)
    "max_speed": 0.8,                # rad/s, per joint bound of the reference
}
PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]


def _sines_reference(centre, a, w, ph, amp, max_speed):
    """``reference(t)`` -> (q, dq, ddq) of per-joint sums of sines a sin(w t + ph) around
    ``centre``, the weights ``a`` (n, h) rescaled to peak |q - centre| = ``amp`` (n,) and then
    shrunk where the peak speed would exceed ``max_speed``."""
    a = a * (amp / a.sum(axis=1))[:, None]
    a = a * np.minimum(1.0, max_speed / (a * w).sum(axis=1))[:, None]

    def reference(t):
        arg = w * t + ph
        return (centre + (a * np.sin(arg)).sum(1), (a * w * np.cos(arg)).sum(1),
                -(a * w * w * np.sin(arg)).sum(1))

    return reference


def _sinusoid_reference(rng, lower, upper, *, n_harm: int = 4, f_range=(0.04, 0.25), max_speed=0.8,
                        fill=0.7):
    """Sum of sinusoids per joint, centred in the limits, with peak |q - centre| <= fill * half-range
    (capped at 1.2 rad) and peak speed <= max_speed. Returns ``reference(t)``."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    n = lower.size
    w = 2 * np.pi * rng.uniform(*f_range, size=(n, n_harm))
    a = rng.uniform(0.3, 1.0, size=(n, n_harm))
    ph = rng.uniform(0, 2 * np.pi, size=(n, n_harm))
    return _sines_reference(0.5 * (lower + upper), a, w, ph, np.minimum(fill * 0.5 * (upper - lower), 1.2),
                            max_speed)


def fourier_reference(rng, lower, upper, period: float, *, n_harm: int = 3, fill: float = 0.3,
                      max_amp: float = 0.9, max_speed: float = 0.7, decay: float = 1.0):
    """Periodic exciting trajectory (base period ``period`` s, repeats exactly): harmonics
    k = 1..n_harm per joint with weights U(0.3, 1) / k^decay and random phases, centred in the
    limits, peak |q - centre| = min(fill * range, max_amp), peak speed <= max_speed.
    Returns ``reference(t)`` -> (q, dq, ddq)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    n = lower.size
    k = np.arange(1, n_harm + 1)
    w = 2 * np.pi * k / period
    a = rng.uniform(0.3, 1.0, (n, n_harm)) / k ** decay
    ph = rng.uniform(0, 2 * np.pi, (n, n_harm))
    return _sines_reference(0.5 * (lower + upper), a, w, ph, np.minimum(fill * (upper - lower), max_amp), max_speed)


def panda_modes(seed: int = 0, n_samples: int = 5000, rate_hz: float = 100.0, payloads=(0.0, 2.0),
                pushes: bool = True, *, frictionloss=None, damping=None, armature=None) -> Recording:
    """7-DOF Panda (example-robot-data URDF, fingers locked) in MuJoCo with a switching payload.

    Tracks a sum of 4 sinusoids per joint (0.04-0.25 Hz, within 70% of the joint range, speed
    <= 0.8 rad/s) with computed torque on the payload-free model (:data:`PANDA`). A sphere of mass
    ``payloads[k]`` kg at ``panda_link8`` (com [0, 0, 0.12] m in that frame) switches between the
    listed masses in segments of U(8, 20) s; label ``mode`` = k. With ``pushes``: world-frame forces
    of U(10, 40) N in a random direction at the origin of a random link among panda_link3..7,
    bumps of U(0.3, 2) s (sin^2 ramps of U(0.1, 0.25) s, flat top) every U(1.5, 5) s. Optional joint friction/damping/armature
    (per joint, MuJoCo semantics) are part of the "real" robot only, not of the controller model.
    Logged: q (19-bit), dq (+ N(0, 0.005) rad/s), tau (+ N(0, 0.05) N*m). Metadata robot="panda".
    """
    import mujoco

    P = PANDA
    rng = np.random.default_rng(seed)
    payloads = tuple(float(m) for m in payloads)
    urdf = panda_urdf_path()
    pl = {"link": P["payload_link"], "mass": max(payloads[0], 0.0), "com": list(P["payload_com"])}
    model = load_model(urdf, PANDA_JOINTS, frictionloss=frictionloss, damping=damping, armature=armature,
                       payload=pl)
    nominal = load_model(urdf, PANDA_JOINTS)
    pin_model = reduced_pinocchio_model(urdf, PANDA_JOINTS)
    duration = n_samples / rate_hz
    reference = _sinusoid_reference(rng, pin_model.lowerPositionLimit, pin_model.upperPositionLimit,
                                    max_speed=P["max_speed"])

    # Mode segments.
    bounds, modes = [0.0], [int(rng.integers(len(payloads)))]
    while bounds[-1] < duration:
        bounds.append(bounds[-1] + rng.uniform(8.0, 20.0))
        others = [k for k in range(len(payloads)) if k != modes[-1]] or [modes[-1]]
        modes.append(int(rng.choice(others)))
    bounds_a = np.asarray(bounds)

    def mode_fn(t):
        return modes[int(np.searchsorted(bounds_a, t, side="right")) - 1]

    state = {"mode": None}

    def switch_payload(t, m, d):
        k = mode_fn(t)
        if k != state["mode"]:
            set_payload(m, payloads[k], radius=P["payload_radius"])
            state["mode"] = k

    push_list = []
    if pushes:
        links = [f"panda_link{i}" for i in range(3, 8)]
        for t0, d in _push_schedule(rng, duration, gap=(1.5, 5.0), dur=(0.3, 2.0), first=(1.0, 3.0)):
            u = rng.standard_normal(3)
            u /= np.linalg.norm(u)
            push_list.append(Push(t0=float(t0), duration=float(d), body=str(rng.choice(links)),
                                  force=tuple(float(x) for x in u * rng.uniform(10.0, 40.0)),
                                  ramp=float(rng.uniform(0.1, 0.25))))

    rec = simulate(model, reference, duration, rate_hz=rate_hz, kp=P["kp"], kd=P["kd"], controller_model=nominal,
                   gains="acceleration",
                   pushes=push_list, before_step=switch_payload, mode_fn=mode_fn,
                   q_resolution=P["q_resolution"], tau_noise=P["tau_noise"], dq_noise=P["dq_noise"],
                   log_dq=True, seed=int(rng.integers(2 ** 31)), robot="panda", joint_names=PANDA_JOINTS)
    rec.info.update({
        "generator": "panda_modes", "seed": seed, "physics": {k: (list(v) if isinstance(v, tuple) else v)
                                                              for k, v in P.items()},
        "payloads": list(payloads), "mode_bounds": [b for b in bounds if b < duration],
        "mode_sequence": modes[:len([b for b in bounds if b < duration])],
        "logged": "q (quantised), dq (noisy), tau (noisy); ddq omitted",
    })
    return rec
