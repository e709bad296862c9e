"""The two stock recordings: the 1-DOF actuator replica and the 7-DOF Panda with payload modes.

* :func:`actuator_replica`: 1-DOF lever with load-dependent (Bowden-cable-like) dry friction,
  quasi-static exploration and hand-like pushes (replica of Haninger 2016, ch. 5).
* :func:`panda_modes`: 7-DOF Panda with a payload switching between masses, and pushes.

Units: s, rad, rad/s, N*m, N, kg, m.
"""
from __future__ import annotations

import mujoco
import numpy as np

from .excitation import push_schedule, sinusoid_reference
from .mjcf import load_model, option_element, panda_urdf_path, reduced_pinocchio_model, set_payload
from .recording import Push, Recording, simulate

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
{option_element(timestep)}
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


def _replica_reference(rng):
    """Two-sine lever reference ``0.3 + 0.85 sin(2 pi t / T1 + p1) + 0.35 sin(2 pi t / T2 + p2)`` rad,
    T1 ~ U(14, 20) s, T2 ~ U(5, 8) s; returns (reference(t), its parameters for ``info``)."""
    T1, T2 = rng.uniform(14.0, 20.0), rng.uniform(5.0, 8.0)
    p1, p2 = rng.uniform(0, 2 * np.pi, 2)
    w1, w2 = 2 * np.pi / T1, 2 * np.pi / T2
    a0, a1, a2 = 0.3, 0.85, 0.35

    def reference(t):
        q = a0 + a1 * np.sin(w1 * t + p1) + a2 * np.sin(w2 * t + p2)
        dq = a1 * w1 * np.cos(w1 * t + p1) + a2 * w2 * np.cos(w2 * t + p2)
        ddq = -a1 * w1 ** 2 * np.sin(w1 * t + p1) - a2 * w2 ** 2 * np.sin(w2 * t + p2)
        return np.array([q]), np.array([dq]), np.array([ddq])

    return reference, {"a": [a0, a1, a2], "T": [T1, T2], "phase": [p1, p2]}


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
    to estimate (the true ones are in ``info``). Labels: :data:`~mmgp.sim.recording.LABEL_RULE`, mode 0.
    """
    P = REPLICA
    rng = np.random.default_rng(seed)
    model = mujoco.MjModel.from_xml_string(replica_mjcf())
    duration = n_samples / rate_hz
    reference, ref_info = _replica_reference(rng)
    L = P["lever_length"]
    pushes = []
    for t0, d in push_schedule(rng, duration, gap=(1.2, 3.5), dur=(0.3, 2.0), first=(0.8, 2.5)):
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
        "reference": ref_info,
        "logged": "q (quantised), tau (noisy); dq, ddq omitted",
    })
    return rec


def _mode_segments(rng, n_modes: int, duration: float) -> tuple[list[float], list[int]]:
    """Segment start times (s) of U(8, 20) s each, from 0 past ``duration``, and the mode of each
    segment: the first uniform, then always a different one (when there are several)."""
    bounds, modes = [0.0], [int(rng.integers(n_modes))]
    while bounds[-1] < duration:
        bounds.append(bounds[-1] + rng.uniform(8.0, 20.0))
        others = [k for k in range(n_modes) if k != modes[-1]] or [modes[-1]]
        modes.append(int(rng.choice(others)))
    return bounds, modes


def random_link_pushes(rng, duration: float, links: list[str]) -> list[Push]:
    """World-frame pushes of U(10, 40) N in a uniformly random direction at the origin of a random
    link among ``links``: bumps of U(0.3, 2) s (sin^2 ramps of U(0.1, 0.25) s, flat top), the first
    at U(1, 3) s, then every U(1.5, 5) s."""
    pushes = []
    for t0, d in push_schedule(rng, duration, gap=(1.5, 5.0), dur=(0.3, 2.0), first=(1.0, 3.0)):
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        pushes.append(Push(t0=float(t0), duration=float(d), body=str(rng.choice(links)),
                           force=tuple(float(x) for x in u * rng.uniform(10.0, 40.0)),
                           ramp=float(rng.uniform(0.1, 0.25))))
    return pushes


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
    reference = sinusoid_reference(rng, pin_model.lowerPositionLimit, pin_model.upperPositionLimit,
                                   max_speed=P["max_speed"])
    bounds, modes = _mode_segments(rng, len(payloads), duration)
    bounds_a = np.asarray(bounds)

    def mode_fn(t):
        return modes[int(np.searchsorted(bounds_a, t, side="right")) - 1]

    state = {"mode": None}

    def switch_payload(t, m, d):
        k = mode_fn(t)
        if k != state["mode"]:
            set_payload(m, payloads[k], radius=P["payload_radius"])
            state["mode"] = k

    push_list = random_link_pushes(rng, duration, [f"panda_link{i}" for i in range(3, 8)]) if pushes else []
    rec = simulate(model, reference, duration, rate_hz=rate_hz, kp=P["kp"], kd=P["kd"], controller_model=nominal,
                   gains="acceleration",
                   pushes=push_list, before_step=switch_payload, mode_fn=mode_fn,
                   q_resolution=P["q_resolution"], tau_noise=P["tau_noise"], dq_noise=P["dq_noise"],
                   log_dq=True, seed=int(rng.integers(2 ** 31)), robot="panda", joint_names=PANDA_JOINTS)
    n_seg = len([b for b in bounds if b < duration])
    rec.info.update({
        "generator": "panda_modes", "seed": seed, "physics": {k: (list(v) if isinstance(v, tuple) else v)
                                                              for k, v in P.items()},
        "payloads": list(payloads), "mode_bounds": bounds[:n_seg], "mode_sequence": modes[:n_seg],
        "logged": "q (quantised), dq (noisy), tau (noisy); ddq omitted",
    })
    return rec
