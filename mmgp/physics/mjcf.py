"""MJCF text of URDF robots, built through Pinocchio's parse (no MuJoCo needed to write it).

MuJoCo cannot read the ``.dae`` meshes the example-robot-data URDFs reference, and no geometry is
needed for dynamics, so :func:`build_mjcf` writes an MJCF from Pinocchio's kinematic tree and
inertials. Joints outside ``joint_names`` are locked; optional joint friction, damping, armature,
springs and a payload welded to a link. Units: m, kg, kg*m^2, N*m, rad. The text lives in the core
(``diagnose`` writes the corrected model's MJCF without MuJoCo installed); compiling it is
``mmgp.sim.load_model``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin

# MuJoCo's friction constraint is soft: without the no-slip pass a joint held by dry friction creeps
# (about 0.03 rad in 2 s for the replica lever); with it a stuck joint stays exactly still.
NOSLIP_ITERATIONS = 10

# Joint properties build_mjcf passes to MuJoCo, in MuJoCo's names; all but springref are >= 0.
JOINT_PROPERTIES = ("frictionloss", "damping", "armature", "stiffness", "springref")


#: name of the MJCF ``<numeric>`` holding the per-joint velocity scale v_s (rad/s) of the dry
#: friction law ``frictionloss * tanh(dq / v_s)`` (``mmgp.sim.inverse_dynamics`` reads it)
FRICTION_VELOCITY = "mmgp_friction_velocity"


def reduced_pinocchio_model(urdf_path: str, joint_names: Sequence[str] | None = None):
    """Pinocchio model of ``urdf_path`` with every joint outside ``joint_names`` locked at its
    neutral position (fixed base). ``joint_names=None`` keeps all joints. Joint order of the
    result is Pinocchio's (``model.names[1:]``), whatever order ``joint_names`` lists them in.
    """
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


def body_name(model, j: int) -> str:
    """Name of the MuJoCo body of Pinocchio joint ``j``: the URDF link that the joint moves."""
    for f in model.frames:
        if (f.parentJoint == j and f.type == pin.FrameType.BODY
                and np.allclose(f.placement.homogeneous, np.eye(4), atol=1e-12)):
            return f.name
    return f"{model.names[j]}_body"


def _fmt(v) -> str:
    # 17 significant digits: the MJCF text carries every float64 bit.
    return " ".join(f"{float(x):.17g}" for x in np.ravel(v))


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    x, y, z, w = pin.Quaternion(np.asarray(R, dtype=np.float64)).coeffs()
    return np.array([w, x, y, z])


def _full_inertia(I: np.ndarray) -> str:
    return _fmt([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])


def option_element(timestep: float, gravity: bool = True) -> str:
    """MJCF ``<option>`` of every recording: Euler at ``timestep`` s, gravity -9.81 m/s^2 along world
    z (or none), no-slip friction (:data:`NOSLIP_ITERATIONS`), contacts off."""
    g = "0 0 -9.81" if gravity else "0 0 0"
    return (f'  <option timestep="{timestep:.17g}" gravity="{g}" integrator="Euler" '
            f'noslip_iterations="{NOSLIP_ITERATIONS}">\n    <flag contact="disable"/>\n  </option>')


def _joint_properties(n: int, values: dict) -> dict[str, np.ndarray]:
    """Per-joint (n,) arrays of :data:`JOINT_PROPERTIES` (None -> zeros, scalars broadcast)."""
    props = {}
    for k in JOINT_PROPERTIES:
        v = values.get(k)
        arr = np.zeros(n) if v is None else np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy()
        if not np.isfinite(arr).all():
            raise ValueError(f"{k} must be finite")
        if k != "springref" and (arr < 0).any():
            raise ValueError(f"{k} must be non-negative")
        props[k] = arr
    return props


def _payload_body(model, payload: dict, urdf_path) -> tuple[int, str]:
    """(Pinocchio joint the payload moves with, MJCF ``<body name="payload">``) of a payload dict
    (see :func:`build_mjcf`)."""
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
    return fr.parentJoint, (f'<body name="payload" pos="{_fmt(com)}"><inertial pos="0 0 0" mass="{m_eff:.17g}" '
                            f'fullinertia="{_full_inertia(Ic)}"/></body>')


def _joint_element(model, j: int, props: dict[str, np.ndarray], q0: np.ndarray) -> str:
    """MJCF ``<joint>`` of Pinocchio joint ``j`` (hinge or slide along its motion subspace)."""
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
    return (f'<joint name={quoteattr(model.names[j])} type="{jtype}" axis="{_fmt(axis)}" pos="0 0 0" '
            f'limited="false" frictionloss="{props["frictionloss"][iv]:.17g}" damping="{props["damping"][iv]:.17g}" '
            f'armature="{props["armature"][iv]:.17g}" stiffness="{props["stiffness"][iv]:.17g}" '
            f'springref="{props["springref"][iv]:.17g}"/>')


def loadable_inertia(I: np.ndarray, mass: float) -> tuple[np.ndarray, str | None]:
    """(3, 3) rotational inertia about the centre of mass (kg*m^2) that MuJoCo accepts, and what
    was changed in words (None: nothing). A URDF's may be a point mass (all zero: FIGAROH's TX40
    link_6) or miss the triangle inequality A + B >= C that every rigid body's principal moments
    meet (CAD rounding: FIGAROH's TIAGo arm_1_link by 2e-4); MuJoCo refuses both. Principal
    moments are floored at ``mass`` x (0.1 mm)^2 (a point mass's spread, torques below 1e-8 of
    its own), then a remaining shortfall C - A - B is closed by the least change in the
    Frobenius norm: a third of it on each moment (A, B up, C down)."""
    I = 0.5 * (np.asarray(I, dtype=np.float64) + np.asarray(I, dtype=np.float64).T)
    w, V = np.linalg.eigh(I)
    floor = max(float(mass), 1e-9) * 1e-8
    notes = []
    if w[0] < floor:
        notes.append(f"principal moments {_fmt(w)} kg*m^2 floored at {floor:.3g}")
        w = np.maximum(w, floor)
    short = float(w[2] - w[0] - w[1])
    if short > 0.0:
        notes.append(f"principal moments miss the triangle inequality by {short:.3g} kg*m^2: each moved by a "
                     "third of it")
        # a hair past equality: MuJoCo's own eigen-decomposition of the written matrix must not fall short
        d = short / 3.0 + 1e-12 * float(w[2])
        w = w + np.array([d, d, -d])
    return ((V * w) @ V.T, "; ".join(notes)) if notes else (I, None)


def _body_lines(model, j: int, depth: int, props, extras: dict[int, list[str]], children, q0,
                notes: list) -> list[str]:
    """MJCF lines of the body of Pinocchio joint ``j`` and, nested, of its subtree. ``extras[j]``:
    elements (sites, payload) placed inside that body; a body whose inertia had to be changed to
    load (:func:`loadable_inertia`) is named in ``notes``."""
    ind = "  " * depth
    M = model.jointPlacements[j]
    Y = model.inertias[j]
    inertia, note = loadable_inertia(Y.inertia, float(Y.mass))
    if note:
        notes.append(f"body {body_name(model, j)} (MuJoCo refuses the URDF's inertia): {note}")
    lines = [f'{ind}<body name={quoteattr(body_name(model, j))} pos="{_fmt(M.translation)}" '
             f'quat="{_fmt(_quat_wxyz(M.rotation))}">',
             f"{ind}  {_joint_element(model, j, props, q0)}",
             f'{ind}  <inertial pos="{_fmt(Y.lever)}" mass="{max(float(Y.mass), 1e-9):.17g}" '
             f'fullinertia="{_full_inertia(inertia)}"/>']
    lines += [f"{ind}  {e}" for e in extras[j]]
    for c in children[j]:
        lines += _body_lines(model, c, depth + 1, props, extras, children, q0, notes)
    lines.append(f"{ind}</body>")
    return lines


def build_mjcf(urdf_path: str, joint_names: list[str] | None = None, *, frictionloss=None, damping=None,
               armature=None, stiffness=None, springref=None, payload: dict | None = None,
               tendons: Sequence[dict] = (), comment: str | None = None, friction_velocity=None,
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

    A link inertia MuJoCo refuses (a point mass, moments that miss the triangle inequality) is
    moved the least that it loads (:func:`loadable_inertia`) and named in the comment.

    ``tendons``: fixed tendons, each ``{"name", "joints": [(joint name, coef), ...], "frictionloss"
    (N*m), "damping" (N*m*s/rad), "armature" (kg*m^2)}`` (:func:`tendon_element`). ``comment``: text
    of an XML comment put before the ``<mujoco>`` element. ``friction_velocity`` (n,) rad/s: the
    velocity scale v_s of the friction law the values were fitted with, written as the custom
    numeric :data:`FRICTION_VELOCITY` (MuJoCo's own solver does not read it).

    Each joint gets a body named after the URDF link it moves, a ``<site>`` for every URDF link
    frame (named after the link) and a plain torque motor named after the joint (gear 1, no
    limits), so ``data.ctrl`` is the joint torque in N*m.
    """
    model = reduced_pinocchio_model(urdf_path, joint_names)
    if any(model.joints[j].nv != 1 for j in range(1, model.njoints)):
        raise ValueError("only 1-DOF joints (revolute, continuous, prismatic) are supported")
    props = _joint_properties(model.nv, {"frictionloss": frictionloss, "damping": damping, "armature": armature,
                                         "stiffness": stiffness, "springref": springref})
    children: dict[int, list[int]] = {j: [] for j in range(model.njoints)}
    for j in range(1, model.njoints):
        children[model.parents[j]].append(j)
    extras: dict[int, list[str]] = {j: [] for j in range(model.njoints)}
    for f in model.frames:
        if f.type == pin.FrameType.BODY and f.parentJoint > 0:
            extras[f.parentJoint].append(f'<site name={quoteattr(f.name)} pos="{_fmt(f.placement.translation)}" '
                                         f'quat="{_fmt(_quat_wxyz(f.placement.rotation))}"/>')
    world_payload = ""
    if payload is not None:
        j, xml = _payload_body(model, payload, urdf_path)
        if j == 0:
            world_payload = xml
        else:
            extras[j].append(xml)
    q0 = pin.neutral(model)
    notes: list[str] = []
    lines = [ln for c in children[0] for ln in _body_lines(model, c, 2, props, extras, children, q0, notes)]
    comment = "\n".join([comment] * bool(comment) + notes) or None
    motors = "\n".join(f'    <motor name={quoteattr(nm)} joint={quoteattr(nm)} gear="1"/>' for nm in model.names[1:])
    names = list(model.names[1:])
    tendon = "  <tendon>\n" + "".join(tendon_element(t, names) for t in tendons) + "  </tendon>\n" if tendons else ""
    return f"""{xml_comment(comment)}<mujoco model={quoteattr(Path(urdf_path).stem)}>
  <compiler angle="radian" autolimits="true" balanceinertia="false" boundmass="0" boundinertia="0"/>
{option_element(timestep, gravity)}
{_custom_element(friction_velocity, model.nv)}  <worldbody>
    {world_payload}
{chr(10).join(lines)}
  </worldbody>
{tendon}  <actuator>
{motors}
  </actuator>
</mujoco>
"""


def _custom_element(friction_velocity, n: int) -> str:
    """``<custom>`` with the :data:`FRICTION_VELOCITY` numeric (n,) (empty for None)."""
    if friction_velocity is None:
        return ""
    v = np.broadcast_to(np.asarray(friction_velocity, dtype=np.float64), (n,))
    if not (np.isfinite(v).all() and (v >= 0).all()):
        raise ValueError(f"friction_velocity must be finite and non-negative, got {v}")
    return f'  <custom>\n    <numeric name="{FRICTION_VELOCITY}" data="{" ".join(f"{x:.17g}" for x in v)}"/>\n  </custom>\n'


def coupling_tendon(joint: str, params: dict) -> dict:
    """The :func:`build_mjcf` tendon of a ``coupled_transmission`` on ``joint`` (contract params
    ``coupled_joint``, ``ratio``, ``tau_c``, ``b``, ``inertia``): a fixed tendon of length
    q[joint] + ratio * q[coupled_joint] carrying the motor's friction loss, damping and armature."""
    other = params["coupled_joint"]
    return {"name": f"coupled_{joint}_{other}", "joints": [(joint, 1.0), (other, float(params["ratio"]))],
            "frictionloss": float(params.get("tau_c", 0.0)), "damping": float(params.get("b", 0.0)),
            "armature": float(params.get("inertia", 0.0))}


def tendon_element(tendon: dict, joint_names: Sequence[str]) -> str:
    """MJCF ``<fixed>`` tendon (length ``sum coef_i q_i``) of ``tendon`` (see :func:`build_mjcf`);
    MuJoCo applies its friction loss, damping and armature along the tendon, on each joint
    ``coef_i`` times (virtual work)."""
    joints = list(tendon["joints"])
    unknown = [nm for nm, _ in joints if nm not in joint_names]
    if unknown:
        raise ValueError(f"tendon {tendon['name']!r}: joints {unknown} are not in the model ({list(joint_names)})")
    vals = {k: float(tendon.get(k, 0.0)) for k in ("frictionloss", "damping", "armature")}
    coefs = [float(c) for _, c in joints]
    if not all(np.isfinite(v) and v >= 0 for v in vals.values()) or not np.isfinite(coefs).all():
        raise ValueError(f"tendon {tendon['name']!r}: friction loss, damping and armature must be finite and "
                         f"non-negative, coefficients finite; got {vals}, {coefs}")
    attrs = " ".join(f'{k}="{v:.17g}"' for k, v in vals.items())
    rows = "".join(f'      <joint joint={quoteattr(nm)} coef="{c:.17g}"/>\n' for (nm, _), c in zip(joints, coefs))
    return f'    <fixed name={quoteattr(tendon["name"])} {attrs}>\n{rows}    </fixed>\n'


def xml_comment(text: str | None) -> str:
    """``<!-- text -->`` and a newline (empty for None); a ``--`` in ``text``, which XML forbids
    inside a comment, becomes ``- -``."""
    if not text:
        return ""
    while "--" in text:
        text = text.replace("--", "- -")
    return f"<!--\n{text.rstrip()}\n-->\n"
