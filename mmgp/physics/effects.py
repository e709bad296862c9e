"""Candidate physical effects missing from a nominal rigid-body model (CONTRACT section 3).

Every effect adds a torque that is *linear in a few coefficients*:

    delta_tau(t) = sum_a  theta_a * column_a(q, dq, ddq, tau_rbd)        column_a: (T, n)

An effect is a small class that names its columns ("atoms"), says which coefficients must be
non-negative, and maps fitted coefficients (with their covariance) to the contract's physical
parameters. Atoms are shared between effects that nest (Coulomb inside load-dependent friction,
torque offset inside a joint spring), so a selector can treat the library like a PySINDy feature
library: build every column once, then choose which effects to switch on.

Sign conventions follow the contract: each effect is torque the robot must *additionally* supply,
so the residual ``tau_logged - tau_rbd(q_logged, dq, ddq)`` is explained by ``+delta_tau``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Hashable, Sequence

import numpy as np

AtomKey = tuple  # ("sign", j), ("dq", j), ("load", j), ("ddq", j), ("q", j), ("one", j), ("enc", j), ("pl", link, i)


# --------------------------------------------------------------------------------------------
# Robot quantities the columns need
# --------------------------------------------------------------------------------------------

def _pin_model(robot):
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


def smooth_sign_scale(dq: np.ndarray, *, k: float = 3.0, floor_frac: float = 0.01) -> np.ndarray:
    """Velocity scale ``v_s`` (n,) of the smooth sign ``tanh(dq / v_s)``, in rad/s.

    ``v_s`` is ``k`` times the velocity noise, estimated from second differences of ``dq``
    (a smooth signal's second difference is ~0, white noise's has variance 6 sigma^2; the MAD
    makes it robust to turning points). A floor of ``floor_frac`` of the RMS velocity keeps a
    noise-free (simulated) log from getting a discontinuous sign.
    """
    dq = np.asarray(dq, dtype=np.float64)
    if dq.shape[0] < 5:
        return np.maximum(1e-3, floor_frac * np.sqrt(np.mean(dq ** 2, axis=0)))
    d2 = dq[2:] - 2 * dq[1:-1] + dq[:-2]
    sigma = 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / np.sqrt(6.0)
    rms = np.sqrt(np.mean(dq ** 2, axis=0))
    return np.maximum.reduce([k * sigma, floor_frac * rms, np.full_like(rms, 1e-4)])


@dataclass
class Context:
    """Everything the effect columns are functions of, for T samples of an n-joint robot.

    ``q, dq, ddq, tau_rbd``: (T, n) in rad, rad/s, rad/s^2, N*m (logged state, nominal torque).
    ``dtau_dq``: (T, n, n), ``[t, i, j] = d tau_rbd_i / d q_j`` (N*m/rad).
    ``regressor``: (T, n, 10 n), per-link inertial regressor blocks ``[..., 10 k: 10 k + 10]``
    for parameters [m, m c_x, m c_y, m c_z, Ixx, Ixy, Iyy, Ixz, Iyz, Izz] of link k in its
    own frame (inertia about the frame origin), as in Pinocchio.
    ``v_s``: (n,) smooth-sign velocity scale (rad/s).
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
    payload_com: dict = field(default_factory=dict)  # link index -> com guess (3,) used for point-mass inertia
    #: (T, n) transmitted load for load-dependent friction (N*m); None = the nominal torque tau_rbd
    tau_load: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.q.shape[1]

    @property
    def T(self) -> int:
        return self.q.shape[0]

    def subset(self, idx: np.ndarray) -> "Context":
        return Context(self.q[idx], self.dq[idx], self.ddq[idx], self.tau_rbd[idx], self.dtau_dq[idx],
                       self.regressor[idx], self.v_s, self.joint_names, self.link_names, dict(self.payload_com),
                       None if self.tau_load is None else self.tau_load[idx])

    @property
    def load(self) -> np.ndarray:
        """(T, n) load that load-dependent friction scales with (N*m)."""
        return self.tau_rbd if self.tau_load is None else self.tau_load

    def link_regressor(self, link: int) -> np.ndarray:
        """(T, n, 10) inertial regressor of link ``link`` (0-based, the link joint ``link`` moves)."""
        return self.regressor[:, :, 10 * link:10 * link + 10]


def build_context(robot, q, dq, ddq, *, v_s: np.ndarray | None = None,
                  joint_names: Sequence[str] | None = None) -> Context:
    """Nominal torque, its position Jacobian and the inertial regressor along a trajectory.

    ``q, dq, ddq``: (T, n). One Pinocchio pass per sample (RNEA derivatives + joint torque
    regressor); about 50 us per sample for a 7-DOF arm.
    """
    import pinocchio as pin

    model = _pin_model(robot)
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
    vs = smooth_sign_scale(dq) if v_s is None else np.asarray(v_s, dtype=np.float64)
    return Context(q, dq, ddq, tau, dtdq, Y, vs, names, link_names_of(model))


# --------------------------------------------------------------------------------------------
# Atom columns
# --------------------------------------------------------------------------------------------

def _point_mass_inertia_vec(c: np.ndarray) -> np.ndarray:
    """Inertia per unit mass of a point at ``c`` about the frame origin, in Pinocchio's order
    (Ixx, Ixy, Iyy, Ixz, Iyz, Izz): |c|^2 I - c c^T."""
    c = np.asarray(c, dtype=np.float64)
    I = np.dot(c, c) * np.eye(3) - np.outer(c, c)
    return np.array([I[0, 0], I[0, 1], I[1, 1], I[0, 2], I[1, 2], I[2, 2]])


def atom_column(key: AtomKey, ctx: Context) -> np.ndarray:
    """Column of atom ``key``: its torque per unit coefficient, (T, n) in N*m per unit."""
    kind = key[0]
    T, n = ctx.T, ctx.n
    if kind == "enc":
        # logged q = true q + offset  =>  tau_true = tau_rbd(q_log - offset) ~ tau_rbd - dtau/dq_j * offset
        return -ctx.dtau_dq[:, :, key[1]]
    if kind == "pl":
        link, i = key[1], key[2]
        Yk = ctx.link_regressor(link)
        if i == 0:
            # mass column carries the point-mass inertia at the current com guess, so that a
            # payload does not leak into armature-like terms on upstream joints
            c = ctx.payload_com.get(link, np.zeros(3))
            return Yk[:, :, 0] + Yk[:, :, 4:10] @ _point_mass_inertia_vec(c)
        return Yk[:, :, i]
    j = key[1]
    col = np.zeros((T, n))
    if kind == "sign":
        col[:, j] = np.tanh(ctx.dq[:, j] / ctx.v_s[j])
    elif kind == "dq":
        col[:, j] = ctx.dq[:, j]
    elif kind == "load":
        col[:, j] = np.abs(ctx.load[:, j]) * np.tanh(ctx.dq[:, j] / ctx.v_s[j])
    elif kind == "ddq":
        col[:, j] = ctx.ddq[:, j]
    elif kind == "q":
        col[:, j] = ctx.q[:, j]
    elif kind == "one":
        col[:, j] = 1.0
    else:
        raise KeyError(f"unknown atom {key!r}")
    return col


# --------------------------------------------------------------------------------------------
# Effects
# --------------------------------------------------------------------------------------------

class Effect:
    """One candidate effect at one joint (or link).

    ``atoms()``: the atom keys its torque is a combination of; ``nonneg``: atoms whose coefficient
    is a non-negative physical magnitude; ``params(coef, cov)``: physical parameters and standard
    deviations from coefficients (dict atom -> value) and their covariance (dict (a, b) -> cov).
    ``torque(params, ctx)``: closed-form torque (T, n), for checks and plots.
    """

    name: ClassVar[str] = ""
    param_names: ClassVar[tuple[str, ...]] = ()
    scope: ClassVar[str] = "joint"
    #: effects this one contains (their atoms are a subset of ours on the same joint)
    supersedes: ClassVar[tuple[str, ...]] = ()
    #: effects (same index) that must already be in a model before this one may extend it
    requires: ClassVar[tuple[str, ...]] = ()

    def __init__(self, index: int):
        self.index = int(index)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.index})"

    def __eq__(self, other) -> bool:
        return type(self) is type(other) and self.index == other.index

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.index))

    @property
    def key(self) -> tuple:
        return (self.name, self.index)

    def atoms(self) -> tuple[AtomKey, ...]:
        raise NotImplementedError

    @property
    def nonneg(self) -> tuple[AtomKey, ...]:
        return ()

    def where(self, ctx: Context) -> dict:
        return {"joint": ctx.joint_names[self.index]}

    def params(self, coef: dict, cov: dict) -> tuple[dict, dict]:
        raise NotImplementedError

    def torque(self, params: dict, ctx: Context) -> np.ndarray:
        raise NotImplementedError

    def affected_joints(self, ctx: Context) -> list[int]:
        return [self.index]


def _std(cov: dict, a, b=None) -> float:
    return float(np.sqrt(max(cov.get((a, a if b is None else b), 0.0), 0.0)))


class CoulombFriction(Effect):
    """tau_c * tanh(dq / v_s): dry friction opposing motion (tau_c >= 0, N*m)."""

    name = "coulomb_friction"
    param_names = ("tau_c",)

    def atoms(self):
        return (("sign", self.index),)

    @property
    def nonneg(self):
        return self.atoms()

    def params(self, coef, cov):
        a = ("sign", self.index)
        return {"tau_c": float(coef[a])}, {"tau_c": _std(cov, a)}

    def torque(self, params, ctx):
        out = np.zeros((ctx.T, ctx.n))
        j = self.index
        out[:, j] = params["tau_c"] * np.tanh(ctx.dq[:, j] / ctx.v_s[j])
        return out


class ViscousFriction(Effect):
    """b * dq (b >= 0, N*m*s/rad)."""

    name = "viscous_friction"
    param_names = ("b",)

    def atoms(self):
        return (("dq", self.index),)

    @property
    def nonneg(self):
        return self.atoms()

    def params(self, coef, cov):
        a = ("dq", self.index)
        return {"b": float(coef[a])}, {"b": _std(cov, a)}

    def torque(self, params, ctx):
        out = np.zeros((ctx.T, ctx.n))
        out[:, self.index] = params["b"] * ctx.dq[:, self.index]
        return out


class LoadDependentFriction(Effect):
    """(tau_c + beta * |load|) * tanh(dq / v_s): friction growing with the transmitted load
    (gear friction). The load is ``ctx.load``: the low-passed logged torque when the diagnosis
    sets it (what the gears transmit, friction included), else the nominal model's torque."""

    name = "load_dependent_friction"
    param_names = ("tau_c", "beta")
    supersedes = ("coulomb_friction",)
    # nested: load dependence is tested only as an extension of Coulomb friction on the joint,
    # so small Coulomb friction is not reported as load-dependent because one step added both
    requires = ("coulomb_friction",)

    def atoms(self):
        return (("sign", self.index), ("load", self.index))

    @property
    def nonneg(self):
        return self.atoms()

    def params(self, coef, cov):
        a, b = self.atoms()
        return ({"tau_c": float(coef[a]), "beta": float(coef[b])},
                {"tau_c": _std(cov, a), "beta": _std(cov, b)})

    def torque(self, params, ctx):
        out = np.zeros((ctx.T, ctx.n))
        j = self.index
        out[:, j] = (params["tau_c"] + params["beta"] * np.abs(ctx.load[:, j])) * np.tanh(ctx.dq[:, j] / ctx.v_s[j])
        return out


class Armature(Effect):
    """inertia * ddq: reflected rotor inertia (kg*m^2 >= 0)."""

    name = "armature"
    param_names = ("inertia",)

    def atoms(self):
        return (("ddq", self.index),)

    @property
    def nonneg(self):
        return self.atoms()

    def params(self, coef, cov):
        a = ("ddq", self.index)
        return {"inertia": float(coef[a])}, {"inertia": _std(cov, a)}

    def torque(self, params, ctx):
        out = np.zeros((ctx.T, ctx.n))
        out[:, self.index] = params["inertia"] * ctx.ddq[:, self.index]
        return out


class TorqueOffset(Effect):
    """Constant bias of the logged torque: logged tau = true tau + offset (N*m)."""

    name = "torque_offset"
    param_names = ("offset",)

    def atoms(self):
        return (("one", self.index),)

    def params(self, coef, cov):
        a = ("one", self.index)
        return {"offset": float(coef[a])}, {"offset": _std(cov, a)}

    def torque(self, params, ctx):
        out = np.zeros((ctx.T, ctx.n))
        out[:, self.index] = params["offset"]
        return out


class JointSpring(Effect):
    """k * (q - q0), k >= 0 (N*m/rad). Linear in (k, -k q0): columns q and 1; a spring therefore
    contains a torque offset on the same joint (the two are not separately identifiable)."""

    name = "joint_spring"
    param_names = ("k", "q0")
    supersedes = ("torque_offset",)

    def atoms(self):
        return (("q", self.index), ("one", self.index))

    @property
    def nonneg(self):
        return (("q", self.index),)

    def params(self, coef, cov):
        a, b = self.atoms()
        k, c = float(coef[a]), float(coef[b])
        q0 = -c / k if k != 0 else float("nan")
        # delta method for q0 = -c / k
        g = np.array([c / k ** 2, -1.0 / k]) if k != 0 else np.array([np.nan, np.nan])
        C = np.array([[cov.get((a, a), 0.0), cov.get((a, b), 0.0)], [cov.get((b, a), 0.0), cov.get((b, b), 0.0)]])
        q0_std = float(np.sqrt(max(g @ C @ g, 0.0))) if k != 0 else float("nan")
        return {"k": k, "q0": q0}, {"k": _std(cov, a), "q0": q0_std}

    def torque(self, params, ctx):
        out = np.zeros((ctx.T, ctx.n))
        j = self.index
        out[:, j] = params["k"] * (ctx.q[:, j] - params["q0"])
        return out


class EncoderOffset(Effect):
    """Logged q minus true q (rad). Enters through the model: tau_rbd(q_log - offset) ~
    tau_rbd(q_log) - (d tau_rbd / d q_j) offset, so it shows on every joint the configuration
    of joint j loads (mostly through gravity)."""

    name = "encoder_offset"
    param_names = ("offset",)

    def atoms(self):
        return (("enc", self.index),)

    def params(self, coef, cov):
        a = ("enc", self.index)
        return {"offset": float(coef[a])}, {"offset": _std(cov, a)}

    def torque(self, params, ctx):
        return -ctx.dtau_dq[:, :, self.index] * params["offset"]

    def affected_joints(self, ctx):
        col = np.abs(ctx.dtau_dq[:, :, self.index]).max(axis=0)
        return [int(i) for i in np.flatnonzero(col > 1e-9 * max(col.max(), 1e-300))]


class Payload(Effect):
    """Extra rigid mass on link ``index`` (the link joint ``index`` moves): mass (kg >= 0) and
    centre of mass in the link frame (m). Columns: the inertial regressor's mass column (with
    the point-mass inertia at the current com guess) and its three first-moment columns, so the
    coefficients are (m, m c_x, m c_y, m c_z)."""

    name = "payload"
    param_names = ("link", "mass", "com")
    scope = "link"

    def atoms(self):
        return tuple(("pl", self.index, i) for i in range(4))

    @property
    def nonneg(self):
        return (("pl", self.index, 0),)

    def where(self, ctx):
        return {"link": ctx.link_names[self.index]}

    def params(self, coef, cov):
        keys = self.atoms()
        th = np.array([coef[k] for k in keys])
        C = np.array([[cov.get((a, b), 0.0) for b in keys] for a in keys])
        m = th[0]
        com = th[1:] / m if m > 0 else np.full(3, np.nan)
        # delta method: d(h/m)/dm = -h/m^2, d(h/m)/dh = I/m
        if m > 0:
            J = np.zeros((3, 4))
            J[:, 0] = -th[1:] / m ** 2
            J[:, 1:] = np.eye(3) / m
            com_std = np.sqrt(np.clip(np.diag(J @ C @ J.T), 0, None))
        else:
            com_std = np.full(3, np.nan)
        return ({"mass": float(m), "com": [float(x) for x in com]},
                {"mass": float(np.sqrt(max(C[0, 0], 0.0))), "com": [float(x) for x in com_std]})

    def torque(self, params, ctx):
        Yk = ctx.link_regressor(self.index)
        m = params["mass"]
        c = np.asarray(params["com"], dtype=np.float64)
        pi = np.concatenate([[m], m * c, m * _point_mass_inertia_vec(c)])
        return Yk @ pi

    def affected_joints(self, ctx):
        return list(range(self.index + 1))


EFFECT_CLASSES: dict[str, type[Effect]] = {
    c.name: c for c in (CoulombFriction, ViscousFriction, LoadDependentFriction, Armature,
                        JointSpring, EncoderOffset, TorqueOffset, Payload)
}
JOINT_EFFECTS = ("coulomb_friction", "viscous_friction", "load_dependent_friction", "armature",
                 "joint_spring", "encoder_offset", "torque_offset")


def effect_library(ctx: Context, *, effects: Sequence[str] | None = None,
                   payload_links: Sequence[int] | str = "auto") -> list[Effect]:
    """Every candidate effect for this robot: each joint effect on each joint, and a payload on
    each link whose mass is identifiable from this trajectory (``payload_links="auto"``: links
    whose mass column is not identically zero -- a point mass on the first link's axis, or on
    the only link of a 1-DOF robot, moves nothing the joint torques can see)."""
    names = list(EFFECT_CLASSES) if effects is None else list(effects)
    unknown = [e for e in names if e not in EFFECT_CLASSES]
    if unknown:
        raise ValueError(f"unknown effects {unknown}; known: {list(EFFECT_CLASSES)}")
    lib: list[Effect] = []
    for name in names:
        if name == "payload":
            continue
        for j in range(ctx.n):
            lib.append(EFFECT_CLASSES[name](j))
    if "payload" in names:
        if isinstance(payload_links, str):
            links = []
            for k in range(ctx.n):
                mcol = ctx.link_regressor(k)[:, :, 0]
                scale = np.abs(ctx.tau_rbd).max() + 1e-12
                if np.abs(mcol).max() > 1e-6 * scale:
                    links.append(k)
        else:
            links = list(payload_links)
        lib.extend(Payload(k) for k in links)
    return lib


def build_atoms(effects: Sequence[Effect], ctx: Context) -> tuple[list[AtomKey], np.ndarray]:
    """Unique atoms of ``effects`` and their columns stacked as (T, n, P)."""
    keys: list[AtomKey] = []
    for e in effects:
        for a in e.atoms():
            if a not in keys:
                keys.append(a)
    A = np.empty((ctx.T, ctx.n, len(keys)))
    for p, a in enumerate(keys):
        A[:, :, p] = atom_column(a, ctx)
    return keys, A
