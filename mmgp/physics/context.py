"""Robot quantities along a trajectory that the effect columns are functions of.

``build_context`` runs Pinocchio once per sample (RNEA, its position derivatives and the joint
torque regressor) and returns a :class:`Context`: the nominal torque, its Jacobian in q, the
inertial regressor, the smooth-sign velocity scale and names. Effects (``mmgp.physics.effects``)
read their regressor columns from it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..data.statistics import difference_noise_sd


def pin_model(robot):
    """Pinocchio model of ``robot`` (a RobotModel with ``.pin_model`` or a ``pinocchio.Model``)."""
    model = getattr(robot, "pin_model", robot)
    if not hasattr(model, "nv"):
        raise TypeError("robot must be an mmgp RobotModel or a pinocchio.Model")
    return model


def link_names_of(model) -> list[str]:
    """Name of the link that each actuated joint moves (the URDF child link: the body frame whose
    parent is that joint and whose placement is the joint frame), in joint order."""
    names = []
    for jid in range(1, model.njoints):
        name = None
        for f in model.frames:
            if f.parentJoint == jid and str(f.type).endswith("BODY") and np.allclose(f.placement.homogeneous, np.eye(4)):
                name = f.name
                break
        names.append(name if name is not None else model.names[jid])
    return names


def reach_of(model) -> float | None:
    """Upper bound on how far (m) any link frame lies from the base: the sum of the joint
    placements' offsets. None for a robot without offsets."""
    reach = float(sum(np.linalg.norm(model.jointPlacements[j].translation) for j in range(1, model.njoints)))
    return reach if reach > 0 else None


def rest_weight(dq: np.ndarray, v_s: np.ndarray) -> np.ndarray:
    """How much each joint is at rest at each sample, in [0, 1]: ``exp(-(dq / v_s)^2 / 2)`` (T, n)
    for velocities ``dq`` (T, n) rad/s and the smooth-sign scale ``v_s`` (n,) rad/s
    (:func:`smooth_sign_scale`). 1 at zero velocity, 0.61 at ``v_s``, below 0.01 beyond 3 ``v_s``.

    Why: a joint with dry friction that is at rest may be stuck, and static friction then takes
    whatever value in its band balances the other torques (set by the controller's history, not
    by q, dq, ddq). Training widens the undisturbed spread there (its rest slack); the diagnosis
    leaves such samples out of its fits (:func:`mmgp.diagnosis.separation.valid_mask`).
    """
    dq = np.asarray(dq, dtype=np.float64)
    return np.exp(-0.5 * (dq / np.maximum(np.asarray(v_s, dtype=np.float64), 1e-12)) ** 2)


def resting(weight: np.ndarray) -> np.ndarray:
    """Where a joint counts as at rest (may be stuck in its friction band): rest weight
    (:func:`rest_weight`) above 1/2, i.e. |dq| below ~1.18 v_s. The complement is where it slides
    and dry friction acts with the velocity's sign. Same shape as ``weight``, bool."""
    return np.asarray(weight) > 0.5


def smooth_sign_scale(dq: np.ndarray, *, k: float = 3.0, speed_frac: float = 0.05,
                      floor_frac: float = 0.01) -> np.ndarray:
    """Velocity scale ``v_s`` (n,) of the smooth sign ``tanh(dq / v_s)``, in rad/s: the one rule of
    the package, ``max(k * velocity noise, speed_frac * 95th-percentile speed, floor_frac * RMS
    speed)`` per joint.

    The noise term keeps the sign from flipping on noise: it is estimated from second differences
    of ``dq`` (a smooth signal's second difference is ~0, white noise's has variance 6 sigma^2; the
    MAD makes it robust to turning points). The speed term makes the sign saturate for all but the
    slowest samples; the floor keeps a noise-free (simulated) log from a discontinuous sign.

    Two users, two settings of the same rule: the GP input of training uses the defaults (with the
    noise term alone the sign is so steep that the GP takes pushes for friction); the diagnosis's
    friction columns model a hard Coulomb sign and pass ``speed_frac=0`` (a softer sign no longer
    matches the step of the friction, and its load dependence goes unnamed)
    (benchmarks/README.md, "sixth session: tuning history").
    """
    dq = np.asarray(dq, dtype=np.float64)
    rms = np.sqrt(np.mean(dq ** 2, axis=0)) if dq.shape[0] else np.zeros(dq.shape[1:])
    speed = speed_frac * np.percentile(np.abs(dq), 95, axis=0) if dq.shape[0] else np.zeros(dq.shape[1:])
    floor = np.maximum.reduce([floor_frac * rms, speed, np.full_like(rms, 1e-4)])
    if dq.shape[0] < 5:
        return np.maximum(floor, 1e-3)
    return np.maximum(k * difference_noise_sd(dq), floor)


def combined_velocity_scale(weights: np.ndarray, v_s: np.ndarray) -> np.ndarray:
    """Smooth-sign scale (rad/s) of a combined velocity w = sum_i weights_i dq_i (a coupled motor,
    a tendon): ``sqrt(sum_i (weights_i v_s_i)^2)`` over the last axis, the joints' velocity noises
    taken as independent. ``weights`` (..., n), ``v_s`` (n,) the joints' scales."""
    w = np.asarray(weights, dtype=np.float64) * np.asarray(v_s, dtype=np.float64)
    return np.sqrt((w ** 2).sum(axis=-1))


@dataclass
class Context:
    """Everything the effect columns are functions of, for T samples of an n-joint robot.

    ``q, dq, ddq, tau_rbd``: (T, n) in rad, rad/s, rad/s^2, N*m (logged state, nominal torque).
    ``dtau_dq``: (T, n, n), ``[t, i, j] = d tau_rbd_i / d q_j`` (N*m/rad).
    ``regressor``: (T, n, 10 n), per-link inertial regressor blocks ``[..., 10 k: 10 k + 10]``
    for parameters [m, m c_x, m c_y, m c_z, Ixx, Ixy, Iyy, Ixz, Iyz, Izz] of link k in its
    own frame (inertia about the frame origin), as in Pinocchio.
    ``v_s``: (n,) smooth-sign velocity scale (rad/s).
    ``payload_com``: link index -> centre-of-mass guess (3,) m at which payload columns are
    linearised (absent: the link origin). ``payload_held``: link index -> (k, 3) orthonormal
    directions (link frame) along which the payload's centre of mass is held at the link origin's
    line (the log does not determine it there). ``tau_load``: (T, n) load that load-dependent friction
    scales with (N*m); None = the nominal torque. ``reach``: how far a link frame can be from the
    base (m; None: unknown), bounding where an attached mass can sit. ``pi0``: (10 n,) nominal
    inertial parameters in the regressor's order; ``base``: the base parameters this trajectory
    determines (``mmgp.physics.identification.BaseParameters``; None: no re-identification);
    ``distal``: indices of the links no other joint moves (where a payload is a ``payload``,
    CONTRACT section 3).
    """

    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    tau_rbd: np.ndarray
    dtau_dq: np.ndarray
    regressor: np.ndarray
    v_s: np.ndarray
    joint_names: list[str]
    link_names: list[str]
    payload_com: dict = field(default_factory=dict)
    payload_held: dict = field(default_factory=dict)
    tau_load: np.ndarray | None = None
    reach: float | None = None
    pi0: np.ndarray | None = None
    base: object | None = None
    distal: tuple = ()
    T: int = field(init=False)      # samples, from q
    n: int = field(init=False)      # joints, from q

    def __post_init__(self):
        self.T, self.n = np.shape(self.q)

    @property
    def load(self) -> np.ndarray:
        """(T, n) load that load-dependent friction scales with (N*m)."""
        return self.tau_rbd if self.tau_load is None else self.tau_load

    def link_regressor(self, link: int) -> np.ndarray:
        """(T, n, 10) inertial regressor of link ``link`` (0-based, the link joint ``link`` moves)."""
        return self.regressor[:, :, 10 * link:10 * link + 10]

    def with_payload_com(self, link: int, com: np.ndarray) -> "Context":
        """A copy whose payload on ``link`` is linearised at ``com`` (3,) m."""
        return dataclasses.replace(self, payload_com={**self.payload_com, link: np.asarray(com, dtype=np.float64)})

    def with_payload_held(self, link: int, directions: np.ndarray) -> "Context":
        """A copy whose payload on ``link`` has no first moment along ``directions`` (k, 3)
        (orthonormal rows, link frame)."""
        return dataclasses.replace(self, payload_held={**self.payload_held,
                                                       link: np.atleast_2d(np.asarray(directions, dtype=np.float64))})

    def with_load(self, tau_load: np.ndarray | None) -> "Context":
        """A copy whose load-dependent friction scales with ``tau_load`` (T, n) N*m."""
        return dataclasses.replace(self, tau_load=tau_load)

    def with_base(self, base) -> "Context":
        """A copy that re-identifies the base parameters ``base`` (None: none)."""
        return dataclasses.replace(self, base=base)


def build_context(robot, q, dq, ddq, *, v_s: np.ndarray | None = None,
                  joint_names: Sequence[str] | None = None) -> Context:
    """Nominal torque, its position Jacobian and the inertial regressor along a trajectory.

    ``robot``: an mmgp RobotModel or a pinocchio.Model; ``q, dq, ddq``: (T, n). One Pinocchio
    pass per sample (RNEA derivatives + joint torque regressor); about 50 us per sample for a
    7-DOF arm.
    """
    import pinocchio as pin

    model = pin_model(robot)
    data = model.createData()
    q = np.asarray(q, dtype=np.float64)
    dq = np.asarray(dq, dtype=np.float64)
    ddq = np.asarray(ddq, dtype=np.float64)
    T, n = q.shape
    if model.nv != n:
        raise ValueError(f"robot has nv={model.nv} but the log has {n} joints")
    # continuous joints are stored as (cos, sin) in Pinocchio's configuration
    qc = robot.configuration(q) if hasattr(robot, "configuration") else q
    if qc.shape != (T, model.nq):
        raise ValueError(f"robot configuration has nq={model.nq}; cannot map {n} logged angles")
    tau = np.empty((T, n))
    dtdq = np.empty((T, n, n))
    Y = np.empty((T, n, 10 * n))
    for i in range(T):
        dq_, _, _ = pin.computeRNEADerivatives(model, data, qc[i], dq[i], ddq[i])
        tau[i] = data.tau
        dtdq[i] = dq_
        Y[i] = pin.computeJointTorqueRegressor(model, data, qc[i], dq[i], ddq[i])
    names = list(joint_names) if joint_names is not None else [model.names[j] for j in range(1, model.njoints)]
    vs = smooth_sign_scale(dq, speed_frac=0.0) if v_s is None else np.asarray(v_s, dtype=np.float64)
    pi0 = np.concatenate([model.inertias[j].toDynamicParameters() for j in range(1, model.njoints)])
    return Context(q, dq, ddq, tau, dtdq, Y, vs, names, link_names_of(model), reach=reach_of(model), pi0=pi0,
                   distal=distal_links(model))


def distal_links(model) -> tuple:
    """0-based indices of the joints no other joint has as parent: their links are the most
    distal moving links (one for a serial arm)."""
    parents = {int(model.parents[j]) for j in range(1, model.njoints)}
    return tuple(j - 1 for j in range(1, model.njoints) if j not in parents)
