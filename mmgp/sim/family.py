"""A family of simulated logs spanning what labs record, for judging labels over many scenarios.

``draw(seed, kind)`` turns a seed into a :class:`ScenarioSpec`: every number of the scenario
(physics, controller, reference knots or sines, each push, sensors, payload segments), so that
``record(spec)`` is a pure function of the spec and a spec written to JSON can be replayed.
``record(spec)`` runs MuJoCo (through :func:`mmgp.sim.recording.simulate`) and returns a
:class:`~mmgp.sim.recording.Recording` whose ``labels`` follow the contract's rule for
``disturbed`` (1 significant / 0 no force / -1 ambiguous, :data:`~mmgp.sim.recording.LABEL_RULE`)
and whose ``info["spec"]`` is the spec.

What a draw spans (issue 10):
- ``kind="lever"``: a 1-DOF lever about a horizontal axis, inertia 0.05-1 kg*m^2 about the axis,
  peak gravity torque G = m g l of 1-15 N*m, a URDF of it (the nominal model; armature is
  concealed). Dry friction (Coulomb, or load-dependent ``c + beta |tau|``) of 2-30% of G, viscous
  friction on about half of the levers. Controller: PD without gravity compensation, PD with
  gravity compensation (from the nominal model), or computed torque. Reference: sums of sines or
  waypoints with holds (where a joint with dry friction sticks). Rates 20-1000 Hz; ``dq``
  measured, finite-differenced or absent (``ddq`` absent or measured).
- ``kind="source"``: a lever in the source experiment's shape (issue 29): a 0.5-1.2 kg load,
  Bowden-like dry friction, PD without gravity compensation, 20 Hz, holds, firm pushes.
- ``kind="panda"`` / ``"ur5"``: the example-robot-data arm, computed torque or PD + gravity
  compensation, friction on some joints, and a payload at the tool: none, fixed (a concealed
  inertial change, one mode), or switching between two masses in segments (two modes).
- Pushes on 10-40% of the time (none on about 15% of the logs), each 0.2-3 s long with a flat
  top between smooth ramps; on a lever the peak joint torque is 0.5-10x its dry-friction level,
  on an arm 5-40 N at a random link.

Units: s, rad, N*m, N, kg, m. Arrays in the spec are plain lists (JSON).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .mjcf import load_model, reduced_pinocchio_model, robot_urdf_path, set_payload
from .recording import LABEL_RULE, Push, Recording, simulate
from .scenarios import PANDA_JOINTS

LEVER_RATES = (20, 25, 40, 50, 100, 125, 200, 250, 500, 1000)
ARM_RATES = (100, 125, 200, 250, 500)
GRAVITY = 9.81
ARMS = {
    # joints, payload link, centre and half-range of the motion (rad); the UR5's are kept where its
    # shoulder holds the arm up (its URDF allows +-2 pi everywhere).
    "panda": {"joints": PANDA_JOINTS, "link": "panda_link7",
              "centre": [0.0, 0.0, 0.0, -1.8, 0.0, 1.8, 0.8], "half": [1.4, 0.9, 1.4, 0.9, 1.4, 1.0, 1.4]},
    "ur5": {"joints": ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                       "wrist_2_joint", "wrist_3_joint"], "link": "wrist_3_link",
            "centre": [0.0, -1.4, 1.2, -1.4, 0.0, 0.0], "half": [1.5, 0.7, 1.0, 1.2, 1.2, 1.5]},
}


@dataclass
class ScenarioSpec:
    """Everything that makes one log (see the module docstring). ``n`` joints.

    friction: ``coulomb`` (n,) N*m, ``beta`` (n,) (dry level ``coulomb + beta |tau_motor|``),
    ``viscous`` (n,) N*m*s/rad. controller: ``type`` ("pd", "pd_gravity", "ctc"), ``kp``, ``kd``
    (n,) (N*m/rad and N*m*s/rad, or 1/s^2 and 1/s for "ctc"). motion: ``type`` "sines" with
    ``centre`` (n,), ``a``, ``w``, ``ph`` (n, h) (q = centre + sum a sin(w t + ph)), or
    "waypoints" with knot ``times`` (m,) and ``q`` (m, n), a quintic move between unequal knots and
    a hold between equal ones. pushes: :class:`Push` fields. sensor: ``tau_noise`` (n,),
    ``q_resolution``, ``dq`` ("measured", "finite_diff", "absent"), ``dq_noise``, ``ddq``
    ("absent", "measured"), ``ddq_noise``. payload: ``link``, ``com`` (m, link frame), ``masses``
    (kg per mode), ``segments`` [[t_start, mode], ...]; None for no payload body."""

    seed: int
    robot: str
    rate_hz: float
    duration: float
    joint_names: list
    friction: dict
    controller: dict
    motion: dict
    sensor: dict
    pushes: list = field(default_factory=list)
    lever: dict | None = None
    payload: dict | None = None
    settle: float = 2.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ScenarioSpec":
        return cls(**d)

    @property
    def n_modes(self) -> int:
        return 1 if self.payload is None else len({m for _, m in self.payload["segments"]})


# ----------------------------------------------------------------------------------------------
# References
# ----------------------------------------------------------------------------------------------

def _quintic(s):
    """Minimum-jerk profile and its first two derivatives on s in [0, 1]."""
    return (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5, 30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4,
            60 * s - 180 * s ** 2 + 120 * s ** 3)


def make_reference(motion: dict):
    """``reference(t) -> (q, dq, ddq)`` (each (n,)) of a spec's ``motion``."""
    if motion["type"] == "sines":
        c, a, w, ph = (np.asarray(motion[k], dtype=np.float64) for k in ("centre", "a", "w", "ph"))

        def sines(t):
            arg = w * t + ph
            return c + (a * np.sin(arg)).sum(1), (a * w * np.cos(arg)).sum(1), -(a * w * w * np.sin(arg)).sum(1)

        return sines
    times = np.asarray(motion["times"], dtype=np.float64)
    knots = np.asarray(motion["q"], dtype=np.float64)
    zero = np.zeros(knots.shape[1])

    def waypoints(t):
        i = int(np.searchsorted(times, t, side="right")) - 1
        if i < 0:
            return knots[0].copy(), zero, zero
        if i >= len(times) - 1:
            return knots[-1].copy(), zero, zero
        span = times[i + 1] - times[i]
        p, dp, ddp = _quintic((t - times[i]) / span)
        step = knots[i + 1] - knots[i]
        return knots[i] + p * step, dp * step / span, ddp * step / span ** 2

    return waypoints


def _draw_sines(rng, centre, half, max_speed, periods=(3.0, 20.0), n_harm=3) -> dict:
    n = len(centre)
    w = 2 * np.pi / rng.uniform(*periods, size=(n, n_harm))
    a = rng.uniform(0.3, 1.0, size=(n, n_harm))
    a *= (np.asarray(half) * rng.uniform(0.5, 1.0, n) / a.sum(1))[:, None]
    a *= np.minimum(1.0, max_speed / (a * w).sum(1))[:, None]
    return {"type": "sines", "centre": list(map(float, centre)), "a": a.tolist(), "w": w.tolist(),
            "ph": rng.uniform(0, 2 * np.pi, size=(n, n_harm)).tolist()}


def _draw_waypoints(rng, centre, half, max_speed, duration, move=(1.0, 4.0), hold=(0.0, 1.5)) -> dict:
    """Knots: moves (quintic, peak speed 1.875 dq / T <= max_speed) alternating with holds."""
    centre, half = np.asarray(centre, float), np.asarray(half, float)
    q = centre + rng.uniform(-1, 1, centre.size) * half
    times, knots = [0.0], [q]
    while times[-1] < duration + 1.0:
        h = rng.uniform(*hold)
        if h > 0.05:
            times.append(times[-1] + h)
            knots.append(knots[-1])
        target = centre + rng.uniform(-1, 1, centre.size) * half
        T = max(rng.uniform(*move), 1.875 * float(np.abs(target - knots[-1]).max()) / max_speed)
        times.append(times[-1] + T)
        knots.append(target)
    return {"type": "waypoints", "times": times, "q": np.asarray(knots).tolist()}


# ----------------------------------------------------------------------------------------------
# Pushes
# ----------------------------------------------------------------------------------------------

def _push_times(rng, duration, fraction, dur_hi) -> list[tuple[float, float]]:
    """(t0, length) of pushes covering about ``fraction`` of [0, duration]."""
    mean_len = 0.5 * (0.2 + dur_hi)
    mean_gap = mean_len * (1.0 - fraction) / fraction
    out, t = [], rng.uniform(0.3, 1.0) * mean_gap
    while True:
        d = rng.uniform(0.2, dur_hi)
        if t + d > duration - 0.2:
            return out
        out.append((float(t), float(d)))
        t += d + rng.uniform(0.5, 1.5) * mean_gap


def _push_plan(rng, duration) -> tuple[list, float]:
    """Push times for a log (empty for about 15% of the logs) and the log's push strength scale."""
    if rng.uniform() < 0.15:
        return [], 0.0
    return _push_times(rng, duration, rng.uniform(0.1, 0.4), rng.uniform(0.6, 3.0)), float(np.exp(rng.uniform(
        np.log(1.5), np.log(9.0))))


def _ramp(rng, d) -> float:
    return float(rng.uniform(0.1, 0.4) * d)


# ----------------------------------------------------------------------------------------------
# Drawing a scenario
# ----------------------------------------------------------------------------------------------

def _draw_sensor(rng, n, torque_scale, rate, with_ddq=True) -> dict:
    dq = str(rng.choice(["measured", "finite_diff", "absent"]))
    return {"tau_noise": (np.asarray(torque_scale) * rng.uniform(0.004, 0.015, n) + 0.002).tolist(),
            "q_resolution": float(2 * np.pi / 2 ** int(rng.integers(14, 21))),
            "dq": dq, "dq_noise": float(rng.uniform(0.002, 0.02)),
            "ddq": "measured" if with_ddq and rng.uniform() < 0.15 else "absent",
            "ddq_noise": float(rng.uniform(0.05, 0.3))}


def _rate_and_duration(rng, rates, max_samples, lo, hi, shortest) -> tuple[float, float]:
    """A rate from ``rates`` and a duration U(lo, hi) s, shortened to fit ``max_samples`` but
    not below ``shortest`` s: where even that does not fit, the fastest rate that does is taken
    (a capped family keeps logs of a realistic length rather than seconds at 1 kHz)."""
    rate = float(rng.choice(rates))
    duration = rng.uniform(lo, hi)
    fits = [r for r in rates if r * shortest <= max_samples] or [min(rates)]
    if rate * shortest > max_samples:
        rate = float(max(fits))
    return rate, float(min(duration, max(max_samples / rate, shortest)))


def _draw_lever(rng, seed, max_samples) -> ScenarioSpec:
    G = float(np.exp(rng.uniform(np.log(1.0), np.log(15.0))))       # peak gravity torque, N*m
    length = float(rng.uniform(0.1, min(0.5, 0.95 * GRAVITY / G)))     # com distance, so m l^2 < 1
    mass = G / (GRAVITY * length)
    i_min = max(0.05, 1.05 * mass * length ** 2)
    inertia = float(np.exp(rng.uniform(np.log(i_min), np.log(1.0))))   # about the axis
    frac = rng.uniform(0.02, 0.3)                                      # dry friction / G
    share = rng.uniform() if rng.uniform() < 0.5 else 1.0             # Coulomb share of it
    coulomb, beta = frac * share * G, frac * (1.0 - share)
    max_speed = float(rng.uniform(0.3, 1.5))
    viscous = rng.uniform(0.0, 0.1) * G / max_speed if rng.uniform() < 0.5 else 0.0
    ctrl_type = str(rng.choice(["pd", "pd_gravity", "ctc"]))
    zeta = rng.uniform(0.5, 1.0)
    if ctrl_type == "pd":
        kp = G / rng.uniform(0.005, 0.05)                              # sag of 0.005-0.05 rad at G
        kd = 2 * zeta * np.sqrt(kp * inertia)
    elif ctrl_type == "pd_gravity":
        wn = rng.uniform(8.0, 40.0)
        kp, kd = inertia * wn ** 2, 2 * zeta * inertia * wn
    else:
        wn = rng.uniform(8.0, 40.0)
        kp, kd = wn ** 2, 2 * zeta * wn
    rate, duration = _rate_and_duration(rng, LEVER_RATES, max_samples, 15.0, 40.0, 10.0)
    if rng.uniform() < 0.5:
        motion = _draw_sines(rng, [0.0], [rng.uniform(0.5, 1.2)], max_speed)
    else:
        motion = _draw_waypoints(rng, [0.0], [1.1], max_speed, duration, hold=(0.0, rng.uniform(0.3, 2.0)))
    times, strength = _push_plan(rng, duration)
    dry = coulomb + beta * G
    reach = float(rng.uniform(0.6, 1.0)) * 2.0 * length               # where the hand pushes, m
    pushes = []
    for t0, d in times:
        peak = float(np.clip(strength * np.exp(rng.uniform(-0.4, 0.4)), 0.5, 10.0)) * dry
        pushes.append({"t0": t0, "duration": d, "body": "lever", "force": [0.0, 0.0, float(rng.choice([-1, 1]) * peak / reach)],
                       "torque": [0.0, 0.0, 0.0], "point": [reach, 0.0, 0.0], "frame": "body", "ramp": _ramp(rng, d)})
    return ScenarioSpec(
        seed=seed, robot="lever", rate_hz=rate, duration=duration, joint_names=["lever_joint"],
        lever={"mass": mass, "com": length, "inertia": inertia, "armature": float(rng.uniform(0, 0.1) * inertia),
               "gravity_torque": G},
        friction={"coulomb": [coulomb], "beta": [beta], "viscous": [float(viscous)]},
        controller={"type": ctrl_type, "kp": [float(kp)], "kd": [float(kd)]},
        motion=motion, sensor=_draw_sensor(rng, 1, [G], rate), pushes=pushes)


def _draw_source_lever(rng, seed, max_samples) -> ScenarioSpec:
    """A lever in the source experiment's shape (Haninger 2016, ch. 5; issue 29): a load of
    0.5-1.2 kg on a 0.15-0.3 m lever (peak gravity torque 0.7-3.5 N*m), Bowden-like dry friction
    (load-dependent ``c + beta |tau|`` on 70% of the levers, Coulomb alone otherwise, c 0.1-0.4
    N*m, beta 0.1-0.3), PD without gravity compensation (kp 100-400 N*m/rad), 20 Hz for 330-1,500
    samples, waypoint moves with holds of 0.5-3 s (where the lever sticks), firm pushes of 15-60
    N at the load for 0.2-2 s on 20-35% of the time, q only (dq and ddq left to be estimated)."""
    mass, length = float(rng.uniform(0.5, 1.2)), float(rng.uniform(0.15, 0.3))
    G = mass * GRAVITY * length
    inertia = float(1.1 * mass * length ** 2)
    load_dependent = rng.uniform() < 0.7
    coulomb = float(rng.uniform(0.1, 0.4))
    beta = float(rng.uniform(0.1, 0.3)) if load_dependent else 0.0
    viscous = float(rng.uniform(0.0, 0.05))
    kp = float(rng.uniform(100.0, 400.0))
    kd = float(2 * rng.uniform(0.5, 1.0) * np.sqrt(kp * inertia) + rng.uniform(0.0, 20.0))
    rate = 20.0
    duration = float(min(rng.uniform(330, 1500), max_samples) / rate)
    motion = _draw_waypoints(rng, [0.3], [1.0], float(rng.uniform(0.4, 0.8)), duration, move=(1.5, 5.0),
                             hold=(0.5, 3.0))
    pushes = []
    for t0, d in _push_times(rng, duration, rng.uniform(0.2, 0.35), 2.0):
        force = float(rng.choice([-1, 1]) * rng.uniform(15.0, 60.0))
        pushes.append({"t0": t0, "duration": d, "body": "lever", "force": [0.0, 0.0, force],
                       "torque": [0.0, 0.0, 0.0], "point": [length, 0.0, 0.0], "frame": "body",
                       "ramp": _ramp(rng, d)})
    sensor = {"tau_noise": [0.02], "q_resolution": float(2 * np.pi / 2 ** 14), "dq": "absent",
              "dq_noise": 0.0, "ddq": "absent", "ddq_noise": 0.0}
    return ScenarioSpec(
        seed=seed, robot="lever", rate_hz=rate, duration=duration, joint_names=["lever_joint"],
        lever={"mass": mass, "com": length, "inertia": inertia, "armature": 1e-3, "gravity_torque": G},
        friction={"coulomb": [coulomb], "beta": [beta], "viscous": [viscous]},
        controller={"type": "pd", "kp": [kp], "kd": [kd]}, motion=motion, sensor=sensor, pushes=pushes)


@functools.lru_cache(maxsize=None)
def _arm_scales(robot: str, n_states: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint, over states in the motion range: RMS of the nominal gravity torque with a floor of
    1 N*m (wrists; the scale of friction levels and noise), N*m; the mass matrix diagonal at the
    centre and the smallest apparent inertia 1 / (M^-1)_jj (what one joint's PD loop sees when
    the others are free; it bounds the damping gain of an explicit 1 ms loop), kg*m^2."""
    import pinocchio as pin

    arm = ARMS[robot]
    model = reduced_pinocchio_model(robot_urdf_path(robot), arm["joints"])
    data = model.createData()
    rng = np.random.default_rng(0)
    q = np.asarray(arm["centre"]) + rng.uniform(-1, 1, (n_states, model.nq)) * np.asarray(arm["half"])
    g = np.array([pin.computeGeneralizedGravity(model, data, qi) for qi in q])

    def mass(qi):
        M = pin.crba(model, data, np.asarray(qi, dtype=np.float64))
        return np.triu(M) + np.triu(M, 1).T

    apparent = np.min([1.0 / np.diag(np.linalg.inv(mass(qi))) for qi in q], axis=0)
    return np.maximum(np.sqrt((g ** 2).mean(0)), 1.0), np.diag(mass(arm["centre"])), apparent


def _draw_arm(rng, seed, robot, max_samples) -> ScenarioSpec:
    arm = ARMS[robot]
    n = len(arm["joints"])
    scale, m_diag, m_apparent = _arm_scales(robot)
    rate, duration = _rate_and_duration(rng, ARM_RATES, max_samples, 40.0, 160.0, 30.0)
    has = rng.uniform(size=n) < 0.5
    frac = np.where(has, rng.uniform(0.02, 0.15, n), 0.0)
    share = np.where(rng.uniform(size=n) < 0.5, 1.0, rng.uniform(size=n))
    viscous = np.where(rng.uniform(size=n) < 0.3, rng.uniform(0.0, 0.05, n) * scale / 0.8, 0.0)
    ctrl_type = str(rng.choice(["ctc", "pd_gravity"]))
    wn, zeta = rng.uniform(15.0, 30.0), rng.uniform(0.7, 1.0)
    if ctrl_type == "ctc":
        kp, kd = np.full(n, wn ** 2), np.full(n, 2 * zeta * wn)
    else:
        # Joint-space PD on the centre's inertia, the damping capped at 0.5 m_app / dt: an explicit
        # 1 ms loop on a joint whose apparent inertia is 40x below M_jj (Panda joint 1) diverged.
        # The stiffness floor keeps a wrist within ~0.1 rad of its reference under its torque scale.
        kp = np.maximum(m_diag * (0.5 * wn) ** 2, 10.0 * scale)
        kd = np.minimum(2 * zeta * np.sqrt(kp * m_diag), 0.5 * m_apparent / 1e-3)
    max_speed = float(rng.uniform(0.3, 0.8))
    if rng.uniform() < 0.6:
        motion = _draw_sines(rng, arm["centre"], arm["half"], max_speed, periods=(4.0, 25.0), n_harm=4)
    else:
        motion = _draw_waypoints(rng, arm["centre"], arm["half"], max_speed, duration, move=(2.0, 6.0))
    times, _ = _push_plan(rng, duration)
    links = _push_links(robot)
    pushes = []
    for t0, d in times:
        u = rng.standard_normal(3)
        pushes.append({"t0": t0, "duration": d, "body": str(rng.choice(links)),
                       "force": (u / np.linalg.norm(u) * rng.uniform(5.0, 40.0)).tolist(), "torque": [0.0, 0.0, 0.0],
                       "point": [0.0, 0.0, 0.0], "frame": "world", "ramp": _ramp(rng, d)})
    return ScenarioSpec(
        seed=seed, robot=robot, rate_hz=rate, duration=duration, joint_names=list(arm["joints"]),
        friction={"coulomb": (frac * share * scale).tolist(), "beta": (frac * (1 - share)).tolist(),
                  "viscous": viscous.tolist()},
        controller={"type": ctrl_type, "kp": kp.tolist(), "kd": kd.tolist()},
        motion=motion, sensor=_draw_sensor(rng, n, 0.3 * scale, rate), pushes=pushes,
        payload=_draw_payload(rng, arm["link"], duration))


def _push_links(robot: str) -> list[str]:
    if robot == "panda":
        return [f"panda_link{i}" for i in range(3, 8)]
    return ["forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]


def _draw_payload(rng, link, duration) -> dict | None:
    """No payload (1/3), a fixed one (1/3: a concealed inertial change, one mode) or one switching
    between two masses in segments of 8-25 s (1/3: two modes)."""
    kind = rng.integers(3)
    if kind == 0:
        return None
    com = (rng.uniform(-0.05, 0.05, 3) + [0.0, 0.0, rng.uniform(0.0, 0.15)]).tolist()
    if kind == 1:
        return {"link": link, "com": com, "masses": [float(rng.uniform(0.5, 3.0))], "segments": [[0.0, 0]]}
    masses = [0.0, float(rng.uniform(0.5, 3.0))] if rng.uniform() < 0.5 else sorted(rng.uniform(0.3, 3.0, 2).tolist())
    segments, t, mode = [], 0.0, int(rng.integers(2))
    while t < duration:
        segments.append([t, mode])
        t += rng.uniform(8.0, 25.0)
        mode = 1 - mode
    if len(segments) == 1:                                  # a log shorter than one segment: split it
        segments.append([0.5 * duration, 1 - segments[0][1]])
    return {"link": link, "com": com, "masses": masses, "segments": segments}


def draw(seed: int, kind: str = "lever", *, max_samples: int | None = None) -> ScenarioSpec:
    """The scenario of ``seed``: ``kind`` "lever", "source" (a lever in the source experiment's
    shape, :func:`_draw_source_lever`), "panda", "ur5" or "arm" (Panda or UR5 by the seed). ``max_samples`` caps the log length (default 6,000 for levers, 16,000 for arms) by
    shortening it. The same seed and kind always give the same spec."""
    rng = np.random.default_rng([int(seed), 0x6D6D6770])
    if kind == "lever":
        return _draw_lever(rng, int(seed), max_samples or 20000)
    if kind == "source":
        return _draw_source_lever(rng, int(seed), max_samples or 1500)
    if kind == "arm":
        kind = str(rng.choice(["panda", "ur5"]))
    if kind not in ARMS:
        raise ValueError(f"kind must be 'lever', 'source', 'arm', 'panda' or 'ur5', got {kind!r}")
    return _draw_arm(rng, int(seed), kind, max_samples or 16000)


def push_free_holds(seed: int, robot: str = "panda", *, coulomb_frac: float = 0.08,
                    max_samples: int = 6000) -> ScenarioSpec:
    """A log without pushes in which every joint sticks: the first waypoint scenario of ``robot``
    drawn from ``seed`` on (moves alternating with holds), without pushes or payload, with Coulomb
    friction of ``coulomb_frac`` of each joint's torque scale on every joint (no load-dependent
    part). Why: the family's arms rarely stop with dry friction on every joint, yet a held joint
    holds any torque within its band and is the false alarm a real arm gives (real TIAGo); this is
    the "logs without pushes flag < 1%" check for arms that stop. ``spec.seed`` is the seed used."""
    k = int(seed)
    spec = draw(k, robot, max_samples=max_samples)
    while spec.motion["type"] != "waypoints":
        k += 1
        spec = draw(k, robot, max_samples=max_samples)
    scale, _, _ = _arm_scales(robot)
    friction = {"coulomb": (coulomb_frac * scale).tolist(), "beta": [0.0] * len(spec.joint_names),
                "viscous": list(spec.friction["viscous"])}
    return dataclasses.replace(spec, pushes=[], payload=None, friction=friction)


# ----------------------------------------------------------------------------------------------
# Recording a scenario
# ----------------------------------------------------------------------------------------------

def lever_urdf(lever: dict) -> str:
    """URDF of a spec's lever: joint ``lever_joint`` about the horizontal y axis, the com at
    ``com`` m along x (q = 0 horizontal), inertia ``inertia`` kg*m^2 about the axis (armature is
    not in it: it is concealed)."""
    m, l, i_axis = lever["mass"], lever["com"], lever["inertia"]
    i_c = max(i_axis - m * l * l, 1e-6)
    return f"""<?xml version="1.0"?>
<robot name="family_lever">
  <link name="base"/>
  <joint name="lever_joint" type="revolute">
    <parent link="base"/><child link="lever"/><origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3.2" upper="3.2" effort="200" velocity="10"/>
  </joint>
  <link name="lever">
    <inertial><origin xyz="{l:.17g} 0 0" rpy="0 0 0"/><mass value="{m:.17g}"/>
      <inertia ixx="{i_c:.17g}" ixy="0" ixz="0" iyy="{i_c:.17g}" iyz="0" izz="{i_c:.17g}"/></inertial>
  </link>
</robot>
"""


def _models(spec: ScenarioSpec):
    """(real MuJoCo model, nominal MuJoCo model, URDF text or None)."""
    fr = spec.friction
    real_kw = {"frictionloss": fr["coulomb"], "damping": fr["viscous"]}
    if spec.robot == "lever":
        text = lever_urdf(spec.lever)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "lever.urdf"
            path.write_text(text)
            real = load_model(str(path), None, armature=spec.lever["armature"], **real_kw)
            nominal = load_model(str(path), None)
        return real, nominal, text
    urdf = robot_urdf_path(spec.robot)
    pl = spec.payload
    if pl is not None:
        first = pl["masses"][pl["segments"][0][1]]
        real_kw["payload"] = {"link": pl["link"], "mass": first, "com": pl["com"]}
    return load_model(urdf, spec.joint_names, **real_kw), load_model(urdf, spec.joint_names), None


def _mode_function(spec: ScenarioSpec):
    if spec.payload is None:
        return None
    starts = np.asarray([s for s, _ in spec.payload["segments"]])
    modes = [m for _, m in spec.payload["segments"]]
    return lambda t: modes[max(int(np.searchsorted(starts, t, side="right")) - 1, 0)]


def _before_step(spec: ScenarioSpec, nominal, mode_fn):
    """Per 1 ms step: gravity compensation (from the nominal model) added to the command, the dry
    friction level set from the command, the payload mass of the current mode."""
    import mujoco

    coulomb = np.asarray(spec.friction["coulomb"], dtype=np.float64)
    beta = np.asarray(spec.friction["beta"], dtype=np.float64)
    gravity_comp = spec.controller["type"] == "pd_gravity"
    cdata = mujoco.MjData(nominal)
    masses = spec.payload["masses"] if spec.payload is not None else None
    state = {"mode": None}

    def step(t, model, data):
        if gravity_comp:
            cdata.qpos[:] = data.qpos
            cdata.qvel[:] = 0.0
            cdata.qacc[:] = 0.0
            mujoco.mj_inverse(nominal, cdata)
            data.ctrl[:] += cdata.qfrc_inverse
        model.dof_frictionloss[:] = coulomb + beta * np.abs(data.ctrl)
        if mode_fn is not None:
            k = mode_fn(t)
            if k != state["mode"]:
                set_payload(model, masses[k])
                state["mode"] = k

    return step


def record(spec: ScenarioSpec) -> Recording:
    """Simulate ``spec`` (1 kHz MuJoCo, logged at ``spec.rate_hz``) into a Recording.

    ``tau`` is the commanded torque plus noise; ``q`` quantised; ``dq`` as the spec's sensor says
    (measured: true + noise; finite_diff: central differences of the logged q; absent: None);
    ``ddq`` measured (true + noise) or None. ``info`` adds ``spec`` (its dict), ``urdf_text`` for a
    lever, and the true signals of :func:`~mmgp.sim.recording.simulate`."""
    real, nominal, urdf_text = _models(spec)
    mode_fn = _mode_function(spec)
    c = spec.controller
    ctc = c["type"] == "ctc"
    s = spec.sensor
    rec = simulate(real, make_reference(spec.motion), spec.duration, rate_hz=spec.rate_hz, kp=c["kp"], kd=c["kd"],
                   controller_model=nominal if ctc else None, gains="acceleration",
                   pushes=[Push(**{**p, "force": tuple(p["force"]), "torque": tuple(p["torque"]),
                                   "point": tuple(p["point"])}) for p in spec.pushes],
                   before_step=_before_step(spec, nominal, mode_fn), mode_fn=mode_fn,
                   q_resolution=s["q_resolution"], tau_noise=s["tau_noise"], dq_noise=s["dq_noise"],
                   log_dq=s["dq"] == "measured", log_ddq=False, seed=spec.seed,
                   robot=None if spec.robot == "lever" else spec.robot, joint_names=spec.joint_names,
                   settle=spec.settle)
    rng = np.random.default_rng([spec.seed, 1])
    if s["dq"] == "finite_diff":
        rec.dq = np.gradient(rec.q, rec.t, axis=0)
    if s["ddq"] == "measured":
        rec.ddq = rec.info["ddq_true"] + s["ddq_noise"] * rng.standard_normal(rec.q.shape)
    rec.info.update({"generator": "mmgp.sim.family", "spec": spec.to_dict(), "urdf_text": urdf_text,
                     "label_rule": LABEL_RULE})
    return rec


def write_scenario(rec: Recording, folder: str | Path, stem: str) -> tuple[Path, Path]:
    """Write ``stem.parquet`` (the log; a lever's URDF ``stem.urdf`` beside it, named in the log's
    metadata), ``stem.labels.parquet`` and ``stem.spec.json`` in ``folder``. Returns (log, labels)."""
    from ..data.logs import write_log
    from ..data.outputs import atomic_write_text, write_table

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    urdf = None
    if rec.info.get("urdf_text"):
        urdf = f"{stem}.urdf"
        atomic_write_text(folder / urdf, rec.info["urdf_text"])
    log, labels = folder / f"{stem}.parquet", folder / f"{stem}.labels.parquet"
    write_log(log, rec.t, rec.q, rec.tau, dq=rec.dq, ddq=rec.ddq, robot=rec.info.get("robot"), urdf=urdf,
              joint_names=rec.info.get("joint_names"))
    write_table(labels, rec.labels, metadata={"label_rule": rec.info.get("label_rule", LABEL_RULE)})
    atomic_write_text(folder / f"{stem}.spec.json", json.dumps(rec.info["spec"], indent=1))
    return log, labels
