"""A UR-class arm holding poses while a hand pushes it: the most common contact test.

:func:`held_pose` records example-robot-data's UR5 in MuJoCo with a known payload on the flange
(``tool0``), held at one pose (or a few, joined by slow moves) by an impedance controller (PD
on the payload-free nominal model's computed torque), while 2-4 pushes of 20-50 N act on a link
for 0.3-2 s. Between pushes the joint velocities are zero up to the controller's sag; the
logged signals carry what a real arm's do: torque noise, a quantised encoder, velocity noise.

What one pose can show (``info["identifiable"]``): a point mass's torque at rest is gravity's,
``tau_j = z_j . ((p - o_j) x m g)``; it carries the mass and the centre of mass's components
across gravity, not its component along gravity (a vertical force has no moment about a point
above or below it). Several poses whose flange turns in different directions carry all of it.

Units: s, rad, rad/s, N*m, N, kg, m.
"""
from __future__ import annotations

import numpy as np

from .family import ARMS, make_reference
from .mjcf import load_model, robot_urdf_path
from .recording import Push, Recording, simulate

UR5_JOINTS = list(ARMS["ur5"]["joints"])

#: the held-pose recording's physics, controller and sensors
HELD = {
    "payload_link": "tool0",
    "payload_mass": 2.5,                    # kg, half the UR5's rated payload
    "payload_com": (0.03, -0.02, 0.06),     # m in the tool0 frame: a gripper's load off the flange axis
    "kp": 2500.0,                           # 1/s^2 (computed torque, 50 rad/s: a stiff hold)
    "kd": 100.0,                            # 1/s
    "tau_noise": 0.1,                       # N*m, std of the (current-based) torque reading
    "dq_noise": 0.002,                      # rad/s, std of the logged velocity
    "q_resolution": 2 * np.pi / 2 ** 19,    # rad (19-bit encoder)
    "push_force": (20.0, 50.0),             # N, peak of a hand push
    "push_links": ("forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"),
    "move_s": 2.5,                          # s, each slow move between held poses
}

#: held poses (rad): the flange down (a com offset along it is along gravity), sideways, tilted
POSES = (
    (0.0, -1.3, 1.6, -1.87, -1.57, 0.0),
    (0.6, -1.0, 1.2, -0.6, 0.8, 1.2),
    (-0.5, -1.8, 1.9, -1.2, -0.6, -1.0),
    (0.3, -1.5, 1.0, 0.3, 1.5, -0.5),
)


def _knots(n_poses: int, duration: float) -> dict:
    """Waypoint motion: ``n_poses`` holds of equal length joined by moves of ``HELD["move_s"]``."""
    hold = (duration - HELD["move_s"] * (n_poses - 1)) / n_poses
    times, q = [0.0], [POSES[0]]
    for k in range(n_poses):
        times.append(times[-1] + hold)
        q.append(POSES[k])
        if k + 1 < n_poses:
            times.append(times[-1] + HELD["move_s"])
            q.append(POSES[k + 1])
    return {"type": "waypoints", "times": times, "q": [list(p) for p in q]}


def _holds(motion: dict) -> list[tuple[float, float]]:
    """(start, end) s of the stretches where the reference stands still."""
    t, q = motion["times"], motion["q"]
    return [(t[i], t[i + 1]) for i in range(len(t) - 1) if q[i] == q[i + 1]]


def _pushes(rng, holds: list, n_pushes: int) -> list[Push]:
    """``n_pushes`` hand pushes inside the holds (at least 1 s from a hold's ends and 1 s apart):
    U(0.3, 2) s with sin^2 ramps, U(*push_force) N in a random direction at a random link."""
    slots = [(a + 1.0, b - 1.0) for a, b in holds if b - a > 2.5]
    per = [n_pushes // len(slots) + (k < n_pushes % len(slots)) for k in range(len(slots))]
    out = []
    for (a, b), m in zip(slots, per):
        if m == 0:
            continue
        room = (b - a - 1.0 * (m - 1)) / m
        for i in range(m):
            d = float(rng.uniform(0.3, min(2.0, 0.9 * room)))
            t0 = a + i * (room + 1.0) + float(rng.uniform(0, room - d))
            u = rng.standard_normal(3)
            u *= rng.uniform(*HELD["push_force"]) / np.linalg.norm(u)
            out.append(Push(t0=t0, duration=d, body=str(rng.choice(HELD["push_links"])),
                            force=tuple(float(x) for x in u), ramp=float(rng.uniform(0.1, 0.25))))
    return out


def held_pose(seed: int = 0, *, n_poses: int = 1, duration: float = 18.0, rate_hz: float = 100.0,
              payload_mass: float | None = None, frictionloss=None) -> Recording:
    """UR5 holding ``n_poses`` of :data:`POSES` (equal holds joined by moves of 2.5 s) for
    ``duration`` s, pushed 2-4 times (about one a hold, at least two), logged at ``rate_hz``.

    Physics and sensors in :data:`HELD`: a payload of ``payload_mass`` kg (default 2.5) at com
    (0.03, -0.02, 0.06) m in the ``tool0`` frame (a 5 cm solid sphere), absent from the
    controller's model; optional ``frictionloss`` (6,) N*m (the "real" robot only). Logged: q
    (19-bit), dq (+ N(0, 0.002) rad/s), tau (+ N(0, 0.1) N*m); ddq left out. ``info``: the
    payload (``payload``: link, mass, com in ``tool0`` and in ``wrist_3_link``), ``holds``
    (start, end) s, ``push_spans`` (start, end) s and the contract labels."""
    rng = np.random.default_rng(seed)
    urdf = robot_urdf_path("ur5")
    mass = HELD["payload_mass"] if payload_mass is None else float(payload_mass)
    payload = {"link": HELD["payload_link"], "mass": mass, "com": list(HELD["payload_com"])}
    model = load_model(urdf, UR5_JOINTS, payload=payload, frictionloss=frictionloss)
    nominal = load_model(urdf, UR5_JOINTS)
    motion = _knots(n_poses, duration)
    holds = _holds(motion)
    pushes = _pushes(rng, holds, max(2, min(4, n_poses + int(rng.integers(1, 3)))))
    rec = simulate(model, make_reference(motion), duration, rate_hz=rate_hz, kp=HELD["kp"], kd=HELD["kd"],
                   controller_model=nominal, gains="acceleration", pushes=pushes,
                   q_resolution=HELD["q_resolution"], tau_noise=HELD["tau_noise"], dq_noise=HELD["dq_noise"],
                   log_dq=True, seed=int(rng.integers(2 ** 31)), robot="ur5", joint_names=UR5_JOINTS, settle=1.0)
    # tool0 sits 0.0823 m along wrist_3_link's y, its z along that link's y: the com in the
    # frame the diagnosis reports a payload on wrist_3_link in
    cx, cy, cz = HELD["payload_com"]
    rec.info.update({
        "generator": "held_pose", "seed": seed, "urdf": urdf, "motion": motion, "holds": holds,
        "payload": {**payload, "com_wrist_3_link": [cx, 0.0823 + cz, -cy]},
        "push_spans": [(p.t0, p.t0 + p.duration) for p in pushes],
        "identifiable": ("one pose: the mass and the com across gravity; several poses turning the "
                         "flange: the whole com"),
        "logged": "q (quantised), dq (noisy), tau (noisy); ddq omitted",
    })
    return rec
