""""Real" recordings with concealed effects, and their truth, for testing the diagnosis.

A case is a nominal URDF (shared by MuJoCo and the Pinocchio model the diagnosis uses) plus
effects that only the MuJoCo "real robot" has: joint friction (``frictionloss``), viscous damping,
armature, joint springs, extra payload bodies, load-dependent friction (``frictionloss`` set every
step from the motor torque), coupled transmissions (a fixed tendon over two joints with friction,
damping and armature), intermittent external pushes and payload modes; encoder and torque
offsets and sensor noise are added to the logged signals. The truth is written in the contract's
vocabulary (CONTRACT section 3), so a diagnosis can be scored pair by pair.

``make_case(spec, seed) -> (Recording, truth)``; :data:`STANDARD_CASES` lists >= 20 specs
(7-DOF Panda and the 1-DOF actuator lever). Recordings come from MuJoCo only.

Spec (dict): ``robot`` ("panda", "actuator", an example-robot-data name or a URDF path), ``effects`` (list of
{"effect", "joint" or "link", "params"}; a param given as {"rel": x} is x times the RMS of that
joint's nominal torque on the same trajectory, measured in a MuJoCo run without effects),
``pushes`` (bool), ``modes`` (payload masses list or None), ``n_samples``, ``rate_hz``,
``tau_noise`` (N*m), ``dq_noise`` (rad/s, None: dq not logged).
"""
from __future__ import annotations

import copy
import atexit
import os
import tempfile
from pathlib import Path

import numpy as np

from ..physics.mjcf import coupling_tendon
from .excitation import push_schedule, sinusoid_reference
from .mjcf import body_name, load_model, panda_urdf_path, reduced_pinocchio_model, robot_urdf_path, set_payload
from .recording import Push, simulate
from .scenarios import PANDA_JOINTS, REPLICA

# Same physical numbers as mmgp.sim.REPLICA: a 0.1 kg rod of 0.2 m and a 0.73 kg ball at its end,
# horizontal joint axis (world -y), q = 0 with the lever horizontal.
_P = REPLICA
ACTUATOR_URDF = f"""<?xml version="1.0"?>
<robot name="actuator">
  <link name="base"/>
  <joint name="lever_joint" type="revolute">
    <parent link="base"/><child link="lever"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 -1 0"/>
    <limit lower="-3.2" upper="3.2" effort="100" velocity="10"/>
  </joint>
  <link name="lever">
    <inertial><origin xyz="{_P['lever_length'] / 2} 0 0" rpy="0 0 0"/><mass value="{_P['lever_mass']}"/>
      <inertia ixx="1e-7" ixy="0" ixz="0" iyy="{_P['lever_mass'] * _P['lever_length'] ** 2 / 12}" iyz="0"
               izz="{_P['lever_mass'] * _P['lever_length'] ** 2 / 12}"/></inertial>
  </link>
  <joint name="load_joint" type="fixed">
    <parent link="lever"/><child link="load"/><origin xyz="{_P['lever_length']} 0 0" rpy="0 0 0"/>
  </joint>
  <link name="load">
    <inertial><origin xyz="0 0 0" rpy="0 0 0"/><mass value="{_P['load_mass']}"/>
      <inertia ixx="{0.4 * _P['load_mass'] * _P['load_radius'] ** 2}" ixy="0" ixz="0"
               iyy="{0.4 * _P['load_mass'] * _P['load_radius'] ** 2}" iyz="0"
               izz="{0.4 * _P['load_mass'] * _P['load_radius'] ** 2}"/></inertial>
  </link>
</robot>
"""


def actuator_urdf_path() -> str:
    """Write the 1-DOF actuator URDF to a temp file (once per process, removed when the process
    exits) and return its path."""
    path = Path(tempfile.gettempdir()) / f"mmgp_actuator_{os.getpid()}.urdf"
    if not path.exists() or path.read_text() != ACTUATOR_URDF:
        path.write_text(ACTUATOR_URDF)
        atexit.register(path.unlink, missing_ok=True)
    return str(path)


def robot_setup(robot: str) -> tuple[str, list[str]]:
    """(URDF path, joint names) of a case's robot: "actuator", "panda", an example-robot-data
    name, or a URDF file (a path ending in ``.urdf``; every movable joint)."""
    if robot == "actuator":
        return actuator_urdf_path(), ["lever_joint"]
    if robot == "panda":
        return panda_urdf_path(), list(PANDA_JOINTS)
    urdf = str(robot) if str(robot).endswith(".urdf") else robot_urdf_path(robot)
    m = reduced_pinocchio_model(urdf)
    return urdf, [str(n) for n in m.names[1:]]


def nominal_robot(spec: dict):
    """The mmgp RobotModel (nominal, no concealed effect) of a case."""
    from ..physics.robot import RobotModel

    urdf, joints = robot_setup(spec["robot"])
    return RobotModel.from_urdf(urdf, joints)


def _reference(robot: str, rng, urdf, joints, duration):
    m = reduced_pinocchio_model(urdf, joints)
    lo, hi = np.array(m.lowerPositionLimit), np.array(m.upperPositionLimit)
    lo = np.where(np.isfinite(lo) & (lo > -10), lo, -np.pi)
    hi = np.where(np.isfinite(hi) & (hi < 10), hi, np.pi)
    if robot == "actuator":
        # lever swings through most of its range (gravity torque changes sign), as in the replica
        lo, hi = np.array([-1.0]), np.array([1.6])
        return sinusoid_reference(rng, lo, hi, max_speed=1.0, f_range=(0.05, 0.3), fill=0.9)
    return sinusoid_reference(rng, lo, hi, max_speed=0.8, f_range=(0.04, 0.25))


def _mode_switching(spec: dict, rng, duration: float, load_fric):
    """(mode_fn, before_step) of a case: two payload modes alternating in segments of
    U(0.25, 0.45) * duration (when ``spec["modes"]``), load-dependent friction (when
    ``load_fric = (c (n,), beta (n,))``) set every step from the motor torque. None where unused."""
    modes = spec.get("modes")
    if not modes and load_fric is None:
        return None, None
    state = {"mode": None}
    bounds, seq = [0.0], [0]
    if modes:
        while bounds[-1] < duration:
            bounds.append(bounds[-1] + rng.uniform(0.25, 0.45) * duration)
            seq.append(1 - seq[-1])
    bounds_a = np.asarray(bounds)

    def mode_fn(t):
        return seq[int(np.searchsorted(bounds_a, t, side="right")) - 1] if modes else 0

    def before_step(t, m, d):
        if load_fric is not None:
            m.dof_frictionloss[:] = load_fric[0] + load_fric[1] * np.abs(d.ctrl)
        if modes:
            k = mode_fn(t)
            if k != state["mode"]:
                set_payload(m, modes[k])
                state["mode"] = k

    return (mode_fn if modes else None), before_step


def _case_pushes(spec: dict, rng, urdf, joints, duration: float) -> list[Push]:
    """Pushes of a case: Panda, world forces at one of the last links; actuator, a force
    perpendicular to the lever at the load, random sign."""
    if not spec.get("pushes"):
        return []
    actuator = spec["robot"] == "actuator"
    n = len(joints)
    if actuator:
        bodies = ["lever"]
    else:
        bodies = [body_name(reduced_pinocchio_model(urdf, joints), j) for j in range(max(1, n - 4), n + 1)]
    peak = spec.get("push_force", (10.0, 40.0) if n > 1 else (8.0, 20.0))
    pushes = []
    for t0, d in push_schedule(rng, duration, gap=(1.5, 5.0), dur=(0.3, 1.5), first=(1.0, 3.0)):
        u = rng.standard_normal(3)
        if actuator:
            u = np.array([0.0, 0.0, rng.choice([-1.0, 1.0])])
        u /= np.linalg.norm(u)
        pushes.append(Push(t0=float(t0), duration=float(d), body=str(rng.choice(bodies)),
                           force=tuple(float(x) for x in u * rng.uniform(*peak)),
                           point=(REPLICA["lever_length"], 0.0, 0.0) if actuator else (0, 0, 0),
                           frame="body" if actuator else "world", ramp=float(rng.uniform(0.1, 0.25))))
    return pushes


def _simulate(spec: dict, seed: int, physics: dict, offsets: dict):
    robot = spec["robot"]
    urdf, joints = robot_setup(robot)
    n = len(joints)
    rate = float(spec.get("rate_hz", 200.0))
    duration = int(spec.get("n_samples", 4000)) / rate
    rng = np.random.default_rng(seed)
    reference = _reference(robot, rng, urdf, joints, duration)
    kw = {k: physics[k] for k in ("frictionloss", "damping", "armature", "stiffness", "springref", "tendons")
          if k in physics}
    payload = physics.get("payload")
    if spec.get("modes") and payload is None:
        payload = {"link": "panda_link7" if n > 1 else "lever", "mass": float(spec["modes"][0]), "com": [0.0, 0.0, 0.1]}
    model = load_model(urdf, joints, payload=payload, **kw)
    mode_fn, before_step = _mode_switching(spec, rng, duration, physics.get("load_friction"))
    pushes = _case_pushes(spec, rng, urdf, joints, duration)
    if robot == "actuator":
        ctrl_kw = dict(kp=REPLICA["kp"], kd=REPLICA["kd"], controller_model=None)
    else:
        ctrl_kw = dict(kp=400.0, kd=40.0, controller_model=load_model(urdf, joints))
    tau_noise = float(spec.get("tau_noise", 0.05 if n > 1 else 0.02))
    dq_noise = spec.get("dq_noise", 0.005 if n > 1 else None)
    rec = simulate(model, reference, duration, rate_hz=rate, pushes=pushes, before_step=before_step, mode_fn=mode_fn,
                   q_resolution=2 * np.pi / 2 ** (19 if n > 1 else 16), tau_noise=tau_noise,
                   dq_noise=dq_noise, log_dq=dq_noise is not None, seed=int(rng.integers(2 ** 31)),
                   robot=spec["robot"] if robot != "actuator" else None, joint_names=joints, **ctrl_kw)
    # offsets go onto the logged signals only
    for j, off in offsets.get("encoder", {}).items():
        rec.q[:, j] += off
    for j, off in offsets.get("torque", {}).items():
        rec.tau[:, j] += off
    rec.info["urdf"] = urdf
    return rec


def _nominal_torque_rms(spec: dict, seed: int) -> np.ndarray:
    s = dict(spec, effects=[], pushes=False, modes=None)
    rec = _simulate(s, seed, {}, {})
    return np.sqrt(np.mean(rec.info["tau_true"] ** 2, axis=0))


def make_case(spec: dict, seed: int = 0):
    """Simulate one case. Returns ``(Recording, truth)``; ``truth`` is a list of contract-style
    dicts {"effect", "joint" | "link", "params"} (plus "external_disturbance" / "mode_switch"
    entries without joint). The Recording's ``info`` has ``urdf``, ``joint_names`` and the spec."""
    spec = copy.deepcopy(spec)
    urdf, joints = robot_setup(spec["robot"])
    n = len(joints)
    effs = spec.get("effects", [])
    rms = None
    if any(isinstance(v, dict) and "rel" in v for e in effs for v in e.get("params", {}).values()):
        rms = _nominal_torque_rms(spec, seed)
    fl, dmp, arm, stiff, sref = (np.zeros(n) for _ in range(5))
    lf_c, lf_b = np.zeros(n), np.zeros(n)
    physics: dict = {}
    offsets: dict = {"encoder": {}, "torque": {}}
    truth = []
    for e in effs:
        name = e["effect"]
        j = joints.index(e["joint"]) if "joint" in e else None
        p = {}
        for k, v in e.get("params", {}).items():
            p[k] = float(v["rel"] * rms[j]) if isinstance(v, dict) and "rel" in v else v
        if name == "coulomb_friction":
            fl[j] = p["tau_c"]
        elif name == "viscous_friction":
            dmp[j] = p["b"]
        elif name == "armature":
            arm[j] = p["inertia"]
        elif name == "joint_spring":
            stiff[j], sref[j] = p["k"], p["q0"]
        elif name == "load_dependent_friction":
            lf_c[j], lf_b[j] = p["tau_c"], p["beta"]
        elif name == "encoder_offset":
            offsets["encoder"][j] = p["offset"]
        elif name == "torque_offset":
            offsets["torque"][j] = p["offset"]
        elif name == "payload":
            physics["payload"] = {"link": e["link"], "mass": p["mass"], "com": list(p["com"]),
                                  "inertia": p.get("inertia")}  # (None: a solid 5 cm sphere)
        elif name == "coupled_transmission":
            physics.setdefault("tendons", []).append(coupling_tendon(e["joint"], p))
        else:
            raise ValueError(f"unknown effect {name}")
        t = {"effect": name, "params": p}
        t.update({"joint": e["joint"]} if "joint" in e else {"link": e["link"]})
        truth.append(t)
    physics.update(frictionloss=fl, damping=dmp, armature=arm, stiffness=stiff, springref=sref)
    if (lf_b > 0).any() or (lf_c > 0).any():
        physics["load_friction"] = (lf_c + fl, lf_b)
    rec = _simulate(spec, seed, physics, offsets)
    if spec.get("pushes") and (rec.labels["disturbed"] == 1).any():
        truth.append({"effect": "external_disturbance", "params": {"n_samples": int((rec.labels["disturbed"] == 1).sum())}})
    if spec.get("modes"):
        truth.append({"effect": "mode_switch", "params": {"masses": list(spec["modes"])}})
    rec.info["spec"] = spec
    rec.info["truth"] = truth
    rec.info["joint_names"] = joints
    return rec, truth


def recording_to_log(rec):
    """RobotLog of a Recording (what the diagnosis sees: no truth, no labels)."""
    from ..data.logs import RobotLog

    return RobotLog(path=f"<concealed {rec.info.get('spec', {}).get('name', '')}>", t=rec.t, q=rec.q, tau=rec.tau,
                    dq=rec.dq, ddq=rec.ddq, metadata={"joint_names": rec.info["joint_names"]})


def _c(name, robot, effects=(), **kw):
    return {"name": name, "robot": robot, "effects": list(effects), **kw}


def _e(effect, where, **params):
    key = "link" if effect == "payload" else "joint"
    return {"effect": effect, key: where, "params": params}


J = [f"panda_joint{i}" for i in range(1, 8)]
A = "lever_joint"

STANDARD_CASES: list[dict] = [
    _c("panda_control", "panda"),
    _c("panda_coulomb_j4", "panda", [_e("coulomb_friction", J[3], tau_c=1.5)]),
    _c("panda_viscous_j2", "panda", [_e("viscous_friction", J[1], b=4.0)]),
    _c("panda_armature_j1", "panda", [_e("armature", J[0], inertia=0.6)]),
    _c("panda_spring_j3", "panda", [_e("joint_spring", J[2], k=6.0, q0=0.4)]),
    _c("panda_encoder_j2", "panda", [_e("encoder_offset", J[1], offset=0.02)]),
    _c("panda_torque_offset_j5", "panda", [_e("torque_offset", J[4], offset=0.6)]),
    _c("panda_payload", "panda", [_e("payload", "panda_link7", mass=1.2, com=[0.0, 0.0, 0.15])]),
    _c("panda_loadfric_j2", "panda", [_e("load_dependent_friction", J[1], tau_c=0.4, beta=0.05)]),
    _c("panda_friction_all", "panda", [_e("coulomb_friction", J[i], tau_c=c) for i, c in
                                       enumerate([0.8, 1.0, 0.6, 0.9, 0.5, 0.4, 0.3])]),
    _c("panda_mixed_a", "panda", [_e("coulomb_friction", J[1], tau_c=1.0), _e("viscous_friction", J[1], b=2.0),
                                  _e("armature", J[5], inertia=0.15), _e("torque_offset", J[0], offset=-0.5)]),
    _c("panda_mixed_b", "panda", [_e("joint_spring", J[3], k=8.0, q0=-1.5), _e("coulomb_friction", J[6], tau_c=0.4),
                                  _e("payload", "panda_link7", mass=0.8, com=[0.05, 0.0, 0.1])]),
    _c("panda_small_coulomb_j6", "panda", [_e("coulomb_friction", J[5], tau_c={"rel": 0.05})]),
    _c("panda_small_viscous_j3", "panda", [_e("viscous_friction", J[2], b={"rel": 0.1})]),
    _c("panda_small_offset_j7", "panda", [_e("torque_offset", J[6], offset={"rel": 0.05})]),
    _c("panda_pushes_coulomb", "panda", [_e("coulomb_friction", J[3], tau_c=1.2)], pushes=True),
    _c("panda_pushes_only", "panda", [], pushes=True),
    _c("panda_modes", "panda", [_e("coulomb_friction", J[1], tau_c=1.0)], modes=[0.0, 1.5]),
    _c("actuator_control", "actuator"),
    _c("actuator_coulomb", "actuator", [_e("coulomb_friction", A, tau_c=0.3)]),
    _c("actuator_load_friction", "actuator", [_e("load_dependent_friction", A, tau_c=0.3, beta=0.2)]),
    _c("actuator_viscous_armature", "actuator", [_e("viscous_friction", A, b=0.3), _e("armature", A, inertia=0.02)]),
    _c("actuator_spring", "actuator", [_e("joint_spring", A, k=0.8, q0=0.5)]),
    _c("actuator_torque_offset", "actuator", [_e("torque_offset", A, offset=0.1)]),
    _c("actuator_small_coulomb", "actuator", [_e("coulomb_friction", A, tau_c={"rel": 0.05})]),
    _c("actuator_pushes_coulomb", "actuator", [_e("coulomb_friction", A, tau_c=0.3)], pushes=True),
]
