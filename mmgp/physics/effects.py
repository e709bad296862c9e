"""Candidate physical effects missing from a nominal rigid-body model (CONTRACT section 3).

Every effect adds a torque that is *linear in a few coefficients*:

    delta_tau(t) = sum_a  theta_a * column_a(q, dq, ddq, tau_rbd)        column_a: (T, n)

An effect is one class that owns everything about it: its columns ("atoms", keyed by hashable
tuples so that nested effects share them: Coulomb inside load-dependent friction, a torque
offset inside a joint spring), which coefficients must be non-negative and any further physical
admissibility, the contract's parameter names with their units, how coefficients map to those
parameters, and the words of its finding. Adding an effect means adding one subclass with a
``name``: it registers itself in :data:`EFFECT_CLASSES`, so the selector can treat the library
like a PySINDy feature library (build every column once, then choose which effects to switch on).

Sign conventions follow the contract: each effect is torque the robot must *additionally* supply,
so the residual ``tau_logged - tau_rbd(q_logged, dq, ddq)`` is explained by ``+delta_tau``.
"""
from __future__ import annotations

from typing import ClassVar, Sequence

import numpy as np

from .context import Context, combined_velocity_scale
from .identification import body_deltas, body_parameters
from .inertial import point_mass_parameters
from .payload import com_from_moments, linearised_columns

AtomKey = tuple  # ("sign", j), ("dq", j), ("load", j), ("ddq", j), ("q", j), ("one", j), ("enc", j), ("pl", link, i)

#: effect name -> class, in the order the library lists candidates; filled by subclassing Effect
EFFECT_CLASSES: dict[str, type["Effect"]] = {}


def _on_joint(ctx: Context, j: int, values: np.ndarray) -> np.ndarray:
    """(T, n) column acting on joint ``j`` only."""
    col = np.zeros((ctx.T, ctx.n))
    col[:, j] = values
    return col


def _smooth_sign(ctx: Context, j: int) -> np.ndarray:
    return np.tanh(ctx.dq[:, j] / ctx.v_s[j])


def _std(cov: dict, a, b=None) -> float:
    return float(np.sqrt(max(cov.get((a, a if b is None else b), 0.0), 0.0)))


def format_value(x: float, s: float | None = None) -> str:
    """``x`` to 3 significant digits, with ``+/- s`` when a finite standard deviation is given."""
    if s is None or not np.isfinite(s):
        return f"{x:.3g}"
    return f"{x:.3g} +/- {s:.2g}"


class Effect:
    """One candidate effect at one joint (or link) ``index``.

    Class attributes: ``name`` (contract effect name), ``label`` (words of a finding),
    ``units`` (contract parameter -> unit, in order; "" for dimensionless), ``scope`` ("joint"
    or "link"), ``supersedes`` (effects on the same index whose atoms are a subset of ours),
    ``requires`` (effects on the same index a model must hold before this one may extend it),
    ``distal_tiebreak`` (of indices the data cannot tell apart, report the most distal), ``linearised``
    (columns depend on a point re-estimated from the fit: :meth:`relinearise`), ``switchable``
    (may take one of two values over the log: a mode-switch candidate),
    ``sensor`` (an artefact of the logged signals, not a torque the joint transmits: left out of
    the load that load-dependent friction scales with), ``own_joint`` (its columns act on joint
    ``index``'s torque alone: its held-out gain is judged on that joint, ``selection.paired_gains``),
    ``own_family`` (a nonlinear parameter is searched: chosen in a family of its own after the
    others, ``mmgp.diagnosis.coupling``, never a forward-selection candidate), ``static`` (at
    rest its torque is a function of the positions, as gravity's is: what a body's error may look like).

    By default parameter i is the coefficient of atom i (``params``/``coefficients``); effects
    with another map override both.
    """

    name: ClassVar[str] = ""
    label: ClassVar[str] = ""
    units: ClassVar[dict[str, str]] = {}
    scope: ClassVar[str] = "joint"
    supersedes: ClassVar[tuple[str, ...]] = ()
    requires: ClassVar[tuple[str, ...]] = ()
    distal_tiebreak: ClassVar[bool] = False
    linearised: ClassVar[bool] = False
    switchable: ClassVar[bool] = False
    sensor: ClassVar[bool] = False
    own_joint: ClassVar[bool] = False
    own_family: ClassVar[bool] = False
    static: ClassVar[bool] = False

    def __init_subclass__(cls, **declared):
        # a one-column effect is declared in its class statement: name=, label=, units=, kind=
        for key, value in declared.items():
            if not hasattr(cls, key):
                raise TypeError(f"{cls.__name__}: unknown effect attribute {key!r}")
            setattr(cls, key, value)
        super().__init_subclass__()
        if cls.name:
            EFFECT_CLASSES[cls.name] = cls

    def __init__(self, index: int):
        self.index = int(index)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.index})"

    def __eq__(self, other) -> bool:
        return type(self) is type(other) and self.index == other.index

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.index))

    # ---- columns and constraints ----------------------------------------------------------
    def atoms(self) -> tuple[AtomKey, ...]:
        raise NotImplementedError

    def columns(self, ctx: Context) -> list[np.ndarray]:
        """One (T, n) column per atom, in the order of :meth:`atoms` (N*m per unit coefficient)."""
        raise NotImplementedError

    @property
    def nonneg(self) -> tuple[AtomKey, ...]:
        """Atoms whose coefficient is a non-negative physical magnitude."""
        return ()

    def admissible(self, coef: dict, ctx: Context) -> bool:
        """Whether fitted coefficients (atom -> value) describe a physically possible effect."""
        return all(coef[a] >= 0 for a in self.nonneg)

    def cones(self, ctx: Context) -> list:
        """Second-order cone constraints on the coefficients, ``(magnitude atom, [atoms],
        radius)``: the atoms' norm at most radius times the magnitude (a point mass's first
        moment within reach of its frame)."""
        return []

    def bodies(self, ctx: Context) -> list:
        """Rigid bodies among the coefficients, ``(ten atoms, nominal (10,))``: nominal plus the
        atoms' coefficients (Pinocchio's order) must be physically consistent (pseudo-inertia PSD)."""
        return []

    @property
    def masses(self) -> tuple[AtomKey, ...]:
        """Atoms whose coefficient is a mass added to the robot (kg)."""
        return ()

    def relinearise(self, coef: dict, ctx: Context) -> Context:
        """The context with this effect's linearisation point moved to what ``coef`` says."""
        return ctx

    def searched_intervals(self) -> dict:
        """Parameter -> [low, high] of parameters searched outside the linear fit (fixed in its bootstrap)."""
        return {}

    @classmethod
    def candidate_indices(cls, ctx: Context) -> list[int]:
        """Indices this effect is a candidate at on this robot and trajectory."""
        return list(range(ctx.n))

    @classmethod
    def candidates(cls, ctx: Context, indices: Sequence[int] | None = None) -> list["Effect"]:
        """The candidate effects of this class (at ``indices``; None: :meth:`candidate_indices`)."""
        return [cls(k) for k in (cls.candidate_indices(ctx) if indices is None else indices)]

    # ---- parameters -----------------------------------------------------------------------
    def params(self, coef: dict, cov: dict) -> tuple[dict, dict]:
        """Physical parameters and their standard deviations from coefficients (atom -> value)
        and their covariance ((atom, atom) -> value)."""
        pairs = list(zip(self.units, self.atoms()))
        return {k: float(coef[a]) for k, a in pairs}, {k: _std(cov, a) for k, a in pairs}

    def coefficients(self, params: dict) -> dict:
        """Inverse of :meth:`params`: atom -> coefficient."""
        return {a: params[k] for k, a in zip(self.units, self.atoms())}

    def torque(self, params: dict, ctx: Context) -> np.ndarray:
        """The effect's torque (T, n) N*m for physical ``params``."""
        coef = self.coefficients(params)
        return sum(coef[a] * col for a, col in zip(self.atoms(), self.columns(ctx)))

    # ---- where, and in words ----------------------------------------------------------------
    def where(self, ctx: Context) -> dict:
        return {"joint": ctx.joint_names[self.index]}

    def affected_joints(self, ctx: Context) -> list[int]:
        return [self.index]

    def report_params(self, params: dict, ctx: Context) -> dict:
        """The contract's ``params`` of a finding."""
        return params

    def describe(self, params: dict, std: dict, ctx: Context) -> str:
        """The finding in words, e.g. "panda_joint4: Coulomb friction of 1.5 N*m" (URDF names)."""
        parts = [f"{format_value(params[k], std.get(k))}{(' ' + u) if u else ''}" for k, u in self.units.items()]
        if len(parts) == 1:
            what = f"{self.label} of {parts[0]}"
        else:
            what = f"{self.label} ({', '.join(f'{k} = {v}' for k, v in zip(self.units, parts))})"
        return f"{ctx.joint_names[self.index]}: {what}"


class _JointColumnEffect(Effect):
    """An effect of one column acting on its own joint: ``coefficient * values(ctx)``, the atom
    ``(kind, joint)``; ``nonnegative``: the coefficient is a magnitude (>= 0)."""

    kind: ClassVar[str] = ""
    nonnegative: ClassVar[bool] = True
    own_joint = True

    def atoms(self):
        return ((self.kind, self.index),)

    def columns(self, ctx):
        return [_on_joint(ctx, self.index, self.values(ctx))]

    @property
    def nonneg(self):
        return self.atoms() if self.nonnegative else ()

    def values(self, ctx: Context) -> np.ndarray:
        """(T,) the column on the effect's joint; by default the context's state ``kind``
        ("q", "dq" or "ddq") of that joint."""
        return getattr(ctx, self.kind)[:, self.index]


class CoulombFriction(_JointColumnEffect, name="coulomb_friction", label="Coulomb friction",
                      units={"tau_c": "N*m"}, kind="sign"):
    """tau_c * tanh(dq / v_s): dry friction opposing motion (tau_c >= 0, N*m)."""

    def values(self, ctx):
        return _smooth_sign(ctx, self.index)


class ViscousFriction(_JointColumnEffect, name="viscous_friction", label="viscous friction",
                      units={"b": "N*m*s/rad"}, kind="dq"):
    """b * dq (b >= 0, N*m*s/rad)."""


class LoadDependentFriction(Effect):
    """(tau_c + beta * |load|) * tanh(dq / v_s): friction growing with the transmitted load
    (gear friction). The load is ``ctx.load`` (the nominal model's torque unless the context
    sets another)."""

    name = "load_dependent_friction"
    label = "load-dependent friction"
    units = {"tau_c": "N*m", "beta": ""}
    supersedes = ("coulomb_friction",)
    own_joint = True
    # nested: load dependence is tested only as an extension of Coulomb friction on the joint,
    # so small Coulomb friction is not reported as load-dependent because one step added both
    requires = ("coulomb_friction",)

    def atoms(self):
        return (("sign", self.index), ("load", self.index))

    def columns(self, ctx):
        j = self.index
        sign = _smooth_sign(ctx, j)
        return [_on_joint(ctx, j, sign), _on_joint(ctx, j, np.abs(ctx.load[:, j]) * sign)]

    @property
    def nonneg(self):
        return self.atoms()


class Armature(_JointColumnEffect, name="armature", label="armature (rotor inertia)",
               units={"inertia": "kg*m^2"}, kind="ddq"):
    """inertia * ddq: reflected rotor inertia (kg*m^2 >= 0)."""


class JointSpring(Effect):
    """k * (q - q0), k >= 0 (N*m/rad). Linear in (k, -k q0): columns q and 1; a spring therefore
    contains a torque offset on the same joint (the two are not separately identifiable)."""

    name = "joint_spring"
    label = "a joint spring"
    units = {"k": "N*m/rad", "q0": "rad"}
    supersedes = ("torque_offset",)
    own_joint = True
    static = True

    def atoms(self):
        return (("q", self.index), ("one", self.index))

    def columns(self, ctx):
        return [_on_joint(ctx, self.index, ctx.q[:, self.index]), _on_joint(ctx, self.index, 1.0)]

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

    def coefficients(self, params):
        a, b = self.atoms()
        return {a: params["k"], b: -params["k"] * params["q0"]}


class EncoderOffset(Effect):
    """Logged q minus true q (rad). Enters through the model: tau_rbd(q_log - offset) ~
    tau_rbd(q_log) - (d tau_rbd / d q_j) offset, so it shows on every joint the configuration
    of joint j loads (mostly through gravity)."""

    name = "encoder_offset"
    label = "an encoder offset"
    units = {"offset": "rad"}
    static = True

    def atoms(self):
        return (("enc", self.index),)

    def columns(self, ctx):
        return [-ctx.dtau_dq[:, :, self.index]]

    def affected_joints(self, ctx):
        col = np.abs(ctx.dtau_dq[:, :, self.index]).max(axis=0)
        return [int(i) for i in np.flatnonzero(col > 1e-9 * max(col.max(), 1e-300))]


class TorqueOffset(_JointColumnEffect, name="torque_offset", label="a torque-sensor offset",
                   units={"offset": "N*m"}, kind="one", nonnegative=False, sensor=True, static=True):
    """Constant bias of the logged torque: logged tau = true tau + offset (N*m)."""

    def values(self, ctx):
        return np.ones(ctx.T)


class CoupledTransmission(Effect):
    """A motor driving joint ``index`` (k) and turning with joint ``coupled`` (m) too (a coupled wrist), at w =
    dq[k] + ratio dq[m]: its loss f = tau_c tanh(w / v_w) + b w + inertia dw/dt (N*m, >= 0) needs f more on k and
    ratio f on m. (m, k, 1/c) gives the torques of (k, m, c) (tau_c |c|, b c^2, inertia c^2): reported with |ratio|
    <= 1. The ratio is searched, not in the library; parameters zip with the atoms in ``units`` order, ratio last."""

    name = "coupled_transmission"
    label = "a coupled transmission"
    units = {"tau_c": "N*m", "b": "N*m*s/rad", "inertia": "kg*m^2", "ratio": ""}
    own_family = True
    __hash__ = Effect.__hash__  # (equal effects share their index)

    def __init__(self, index: int, coupled: int = 0, ratio: float = 1.0, ratio_interval=None):
        super().__init__(index)
        self.coupled, self.ratio, self.ratio_interval = int(coupled), float(ratio), ratio_interval

    def __eq__(self, other):
        return type(other) is type(self) and self.atoms() == other.atoms()

    def canonical(self) -> "CoupledTransmission":
        """The same torques with |ratio| <= 1 (the joint the motor turns most with is the driven one)."""
        lo_hi = None if self.ratio_interval is None else sorted(1.0 / x for x in self.ratio_interval)
        return self if abs(self.ratio) <= 1.0 else CoupledTransmission(self.coupled, self.index, 1 / self.ratio, lo_hi)

    @classmethod
    def candidates(cls, ctx, indices=None):
        return []

    def atoms(self):
        return tuple((kind, self.index, self.coupled, self.ratio) for kind in ("ct_sign", "ct_dq", "ct_ddq"))

    def columns(self, ctx):
        k, m, c = self.index, self.coupled, self.ratio
        w = ctx.dq[:, k] + c * ctx.dq[:, m]
        cols = [_on_joint(ctx, k, x) for x in (np.tanh(w / combined_velocity_scale([1.0, c], ctx.v_s[[k, m]])), w,
                                               ctx.ddq[:, k] + c * ctx.ddq[:, m])]
        for col in cols:
            col[:, m] = c * col[:, k]
        return cols

    @property
    def nonneg(self):
        return self.atoms()

    def params(self, coef, cov):
        p, s = super().params(coef, cov)
        ci = self.ratio_interval
        return {"ratio": self.ratio, **p}, {"ratio": np.nan if ci is None else (ci[1] - ci[0]) / 3.92, **s}

    def searched_intervals(self):
        return {} if self.ratio_interval is None else {"ratio": [float(x) for x in self.ratio_interval]}

    def affected_joints(self, ctx):
        return [self.index, self.coupled]

    def report_params(self, params, ctx):
        return {"coupled_joint": ctx.joint_names[self.coupled], **params}

    def describe(self, params, std, ctx):
        return f"{super().describe(params, std, ctx)} with joint {self.coupled} ({ctx.joint_names[self.coupled]})"


class Payload(Effect):
    """Extra rigid mass on link ``index`` (the link joint ``index`` moves): mass (kg >= 0) and
    centre of mass in the link frame (m), as a point mass. Columns: the point mass linearised at
    the context's centre-of-mass guess (``mmgp.physics.payload.linearised_columns``), so the
    coefficients are (m, m c_x, m c_y, m c_z); :meth:`relinearise` moves the guess to the fit."""

    name = "payload"
    label = "a payload"
    units = {"mass": "kg", "com": "m"}
    scope = "link"
    # a mass on joint i+1's axis loads the joints exactly as the same mass on link i does
    distal_tiebreak = True
    linearised = True
    switchable = True  # attached and removed during a log

    def atoms(self):
        return tuple(("pl", self.index, i) for i in range(4))

    def columns(self, ctx):
        # along a held direction the first moment's columns are zero (its coefficient stays 0)
        D = ctx.payload_held.get(self.index, np.zeros((0, 3)))
        P = np.eye(3) - D.T @ D
        C = linearised_columns(ctx.link_regressor(self.index), P @ ctx.payload_com.get(self.index, np.zeros(3)))
        C[:, :, 1:4] = C[:, :, 1:4] @ P
        return [C[:, :, i] for i in range(4)]

    @property
    def nonneg(self):
        return (("pl", self.index, 0),)

    @property
    def masses(self):
        return (("pl", self.index, 0),)

    def admissible(self, coef, ctx):
        # attached to the robot: the centre of mass lies within the robot's reach of the link
        # frame (else the first-moment columns are fitting something else)
        m, h = self._moments(coef)
        # (a constrained fit lands on the cone's surface up to the solver's tolerance)
        return m >= 0 and (ctx.reach is None or np.linalg.norm(h) <= ctx.reach * m * (1 + 1e-6) + 1e-9)

    def cones(self, ctx):
        a = self.atoms()
        return [(a[0], list(a[1:]), ctx.reach)] if ctx.reach is not None else []

    def relinearise(self, coef, ctx):
        return ctx.with_payload_com(self.index, com_from_moments(*self._moments(coef)))

    @classmethod
    def candidate_indices(cls, ctx):
        # the most distal links (CONTRACT section 3: a mass elsewhere is an inertial-parameter
        # difference), where the mass column is not identically zero: a point mass on the first
        # link's axis, or on the only link of a 1-DOF robot, moves nothing the torques can see
        scale = np.abs(ctx.tau_rbd).max() + 1e-12
        links = ctx.distal or tuple(range(ctx.n))
        return [k for k in links if np.abs(ctx.link_regressor(k)[:, :, 0]).max() > 1e-6 * scale]

    def _moments(self, coef: dict) -> tuple[float, np.ndarray]:
        th = np.array([coef[a] for a in self.atoms()])
        return float(th[0]), th[1:]

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

    def coefficients(self, params):
        m, c = params["mass"], np.asarray(params["com"], dtype=np.float64)
        return dict(zip(self.atoms(), [m, *(m * c)]))

    def torque(self, params, ctx):
        # the exact point mass, whatever the linearisation point of the columns
        return ctx.link_regressor(self.index) @ point_mass_parameters(params["mass"], params["com"])

    def where(self, ctx):
        return {"link": ctx.link_names[self.index]}

    def affected_joints(self, ctx):
        return list(range(self.index + 1))

    def report_params(self, params, ctx):
        return {"link": ctx.link_names[self.index], **params}

    def describe(self, params, std, ctx):
        com = ", ".join(f"{c:.3f}" for c in params["com"])
        return (f"link {ctx.link_names[self.index]}: {self.label} of {format_value(params['mass'], std['mass'])} kg "
                f"at [{com}] m (link frame)")


class InertialParameters(Effect):
    """The rigid body re-identified: the base parameters the trajectory determines (``ctx.base``)
    move by ``beta`` from the nominal ones (columns: the regressor's independent ones). Reported as
    ``inertial_parameters`` for the whole model (``link`` null): ``base`` (name -> identified
    minus nominal), ``delta`` per body for what they determine, ``bodies`` the consistent fit's
    changed bodies whole (in the corrected model; beyond CONTRACT 1.2's keys)."""

    name = "inertial_parameters"
    label = "inertial parameters different from the URDF's"
    units = {"base": ""}
    scope = "model"

    def __init__(self, index: int = 0, base=None, pi0=None):
        super().__init__(index)
        self.base = base
        self.pi0 = pi0

    def atoms(self):
        return tuple(("rb", i) for i in range(self.base.n_base))

    def columns(self, ctx):
        return [ctx.regressor[:, :, c] for c in self.base.columns]

    @classmethod
    def candidates(cls, ctx, indices=None):
        return [cls(0, ctx.base, ctx.pi0)] if ctx.base is not None and ctx.base.n_base else []

    def params(self, coef, cov):
        atoms = self.atoms()
        names = self.base.names
        params = {"base": {nm: float(coef[a]) for nm, a in zip(names, atoms)}}
        if ("pi", 0) in coef and self.pi0 is not None:
            # the physically consistent fit's bodies: what the data fix (delta) and whole (bodies)
            pi = self.pi0 + np.array([coef[("pi", i)] for i in range(len(self.pi0))])
            params = {"delta": body_deltas(self.pi0, pi, self.base), **params, "bodies": body_parameters(self.pi0, pi, self.base)}
        return params, {"base": {nm: _std(cov, a) for nm, a in zip(names, atoms)}}

    def coefficients(self, params):
        return dict(zip(self.atoms(), (params["base"][nm] for nm in self.base.names)))

    def where(self, ctx):
        return {"link": None}

    def affected_joints(self, ctx):
        return list(range(ctx.n))

    def report_params(self, params, ctx):
        return {"link": None, **params}

    def describe(self, params, std, ctx):
        rel = sorted(((abs(v) / max(std["base"].get(k, 0.0), 1e-300), k, v) for k, v in params["base"].items()),
                     reverse=True)[:3]
        top = "; ".join(f"{k} by {format_value(v, std['base'].get(k))}" for _, k, v in rel)
        return (f"the rigid body ({len(params['base'])} base parameters re-identified): {self.label}; the "
                f"best-determined changes: {top}")


JOINT_EFFECTS = tuple(name for name, cls in EFFECT_CLASSES.items() if cls.scope == "joint")


def effect_classes(effects: Sequence[str | type[Effect]] | None = None) -> list[type[Effect]]:
    """Effect classes from names (CONTRACT section 3) or classes; None = every registered one."""
    if effects is None:
        return list(EFFECT_CLASSES.values())
    unknown = [e for e in effects if not isinstance(e, type) and e not in EFFECT_CLASSES]
    if unknown:
        raise ValueError(f"unknown effects {unknown}; known: {list(EFFECT_CLASSES)}")
    return [e if isinstance(e, type) else EFFECT_CLASSES[e] for e in effects]


def effect_library(ctx: Context, *, effects: Sequence[str | type[Effect]] | None = None,
                   payload_links: Sequence[int] | str = "auto") -> list[Effect]:
    """Every candidate effect for this robot: each joint effect on each joint, and each link
    effect on each link where it is identifiable from this trajectory (``payload_links="auto"``)
    or on the given 0-based links. Joint effects come first, in the order of ``effects``."""
    classes = effect_classes(effects)
    lib: list[Effect] = []
    for scope in ("joint", "link", "model"):
        for cls in classes:
            if cls.scope != scope:
                continue
            auto = scope != "link" or isinstance(payload_links, str)
            lib.extend(cls.candidates(ctx, None if auto else payload_links))
    return lib


def build_atoms(effects: Sequence[Effect], ctx: Context) -> tuple[list[AtomKey], np.ndarray]:
    """Unique atoms of ``effects`` and their columns stacked as (T, n, P)."""
    keys: list[AtomKey] = []
    cols: list[np.ndarray] = []
    for e in effects:
        if all(a in keys for a in e.atoms()):
            continue
        for a, col in zip(e.atoms(), e.columns(ctx)):
            if a not in keys:
                keys.append(a)
                cols.append(col)
    A = np.empty((ctx.T, ctx.n, len(keys)))
    for p, col in enumerate(cols):
        A[:, :, p] = col
    return keys, A
