"""The corrected model a diagnosis writes (CONTRACT section 2, 1.2): ``corrected.urdf``, ``corrected.xml``.

``corrected.urdf`` is the nominal URDF with the identified rigid body (``inertial_parameters``:
the consistent fit's ``bodies`` whole, else each body's ``delta`` added to its link's inertial) and payloads (a link welded to theirs); the
joints the log does not record are fixed where the diagnosis held them.

``corrected.xml`` is the MJCF of the same bodies (:func:`mmgp.physics.mjcf.build_mjcf` on the
corrected URDF, Pinocchio's parse as everywhere in mmgp) plus what MuJoCo can express of the
findings, each adding to the torque the robot must supply as CONTRACT section 3 says:

=========================  ==============================================================
``coulomb_friction``       joint ``frictionloss`` = tau_c
``load_dependent_friction`` joint ``frictionloss`` = tau_c (the beta * abs(tau) part is not)
``viscous_friction``       joint ``damping`` = b
``armature``               joint ``armature`` = inertia
``joint_spring``           joint ``stiffness`` = k, ``springref`` = q0
``coupled_transmission``   a ``<fixed>`` tendon q_k + c q_coupled with ``frictionloss`` tau_c,
                           ``damping`` b, ``armature`` inertia
=========================  ==============================================================

What MJCF cannot express (sensor offsets, external pushes, the other mode of a mode switch,
load dependence) is named in a comment at the top of ``corrected.xml`` and in the report. A
payload that switches is written for the mode the log spends most time in.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..physics.mjcf import FRICTION_VELOCITY, coupling_tendon

#: finding -> {MuJoCo joint property: the finding's parameter}
JOINT_PROPERTY = {"coulomb_friction": {"frictionloss": "tau_c"}, "load_dependent_friction": {"frictionloss": "tau_c"},
                  "viscous_friction": {"damping": "b"}, "armature": {"armature": "inertia"},
                  "joint_spring": {"stiffness": "k", "springref": "q0"}}

UNITS = {"frictionloss": "N*m", "damping": "N*m*s/rad", "armature": "kg*m^2", "stiffness": "N*m/rad",
         "springref": "rad"}

#: why a finding has no MJCF counterpart
NOT_EXPRESSED = {
    "encoder_offset": "a sensor offset (logged q minus true q): subtract it from the logged angle before using "
                      "the model",
    "torque_offset": "a sensor offset (logged tau minus true tau): subtract it from the logged torque before "
                     "comparing with the model",
    "external_disturbance": "intermittent external force on the robot, not part of it",
}

LOAD_LINES = ('import mujoco, pinocchio as pin',
              'mj_model = mujoco.MjModel.from_xml_path("corrected.xml")     # MuJoCo: bodies + friction, '
              'damping, armature, springs, tendons',
              'pin_model = pin.buildModelFromUrdf("corrected.urdf")         # Pinocchio: the corrected rigid body')

INVERSE_NOTE = ("MuJoCo treats frictionloss as a (soft) constraint: mj_inverse's qfrc_inverse carries it only "
                "through the constraint solver, not as the friction law the diagnosis fitted, "
                "frictionloss*tanh(dq/v_s), with v_s per joint in corrected.xml's custom numeric "
                f"'{FRICTION_VELOCITY}' (findings.json info.v_s). For the joint torque, set mjDSBL_FRICTIONLOSS "
                "(qfrc_inverse is then M(q) ddq with armature, plus bias, plus damping and spring forces) and add "
                "frictionloss*tanh(dq/v_s) per joint and J^T frictionloss*tanh(J dq/v_w) per tendon, "
                "v_w = sqrt(sum_i (J_i v_s_i)^2); mmgp.sim.inverse_dynamics does this. Not sign(dq): where a joint "
                "stands still its static friction can take any value in the band, and sign() of a velocity at "
                "noise level adds the whole level with a random sign.")


@dataclass
class Corrections:
    """What the findings change, per file. ``properties``: MuJoCo joint property -> (n,) values;
    ``tendons``: fixed tendons (``build_mjcf``); ``body_changes``: link -> (10,) inertial
    parameters added (link frame); ``payloads``: welded links; ``mode``: the mode whose payload is
    written (None without a mode switch); ``written`` / ``not_expressed``: sentences."""

    joint_names: list
    properties: dict
    tendons: list = field(default_factory=list)
    body_changes: dict = field(default_factory=dict)
    payloads: list = field(default_factory=list)
    mode: int | None = None
    written: list = field(default_factory=list)
    not_expressed: list = field(default_factory=list)


def _g(x) -> str:
    return f"{float(x):.4g}"


def _joint_index(f: dict, names: list) -> int | None:
    j = f.get("joint")
    if isinstance(j, (int, np.integer)) and not isinstance(j, bool):
        return int(j) if 0 <= j < len(names) else None
    return names.index(j) if j in names else None


def _chosen_mode(findings: list, c: Corrections) -> None:
    """The mode whose payload is written: the one the log spends most time in."""
    ms = next((f for f in findings if f["effect"] == "mode_switch"), None)
    if ms is None:
        return
    per_mode = ms["params"].get("per_mode") or []
    frac = [float(m.get("fraction", 0.0)) for m in per_mode]
    c.mode = int(np.argmax(frac)) if frac else 0
    others = ", ".join(f"mode {k} ({100 * fr:.0f}% of the time)" for k, fr in enumerate(frac) if k != c.mode)
    c.not_expressed.append(
        f"mode_switch: the log switches between {ms['params'].get('n_modes', len(frac))} modes; the files carry mode "
        f"{c.mode} ({100 * frac[c.mode]:.0f}% of the time) and not {others or 'the other'} (a payload per mode is "
        "in findings.json)" if frac else "mode_switch: the files carry mode 0")


def _joint_effect(f: dict, c: Corrections) -> None:
    j = _joint_index(f, c.joint_names)
    if j is None:
        c.not_expressed.append(f"{f['effect']} on {f.get('joint')!r}: not a joint of the corrected model")
        return
    name, p = c.joint_names[j], f["params"]
    for prop, key in JOINT_PROPERTY[f["effect"]].items():
        if prop == "springref":
            c.properties[prop][j] = float(p[key])
        else:
            c.properties[prop][j] += float(p[key])
    said = ", ".join(f"{prop} {_g(p[key])} {UNITS[prop]}" for prop, key in JOINT_PROPERTY[f["effect"]].items())
    c.written.append(f"{name}: {said} ({f['effect']})")
    if f["effect"] == "load_dependent_friction":
        c.not_expressed.append(f"load_dependent_friction on {name}: the load-dependent part beta*abs(tau) (beta = "
                               f"{_g(p['beta'])}); MuJoCo's frictionloss is one level, written as tau_c = "
                               f"{_g(p['tau_c'])} N*m")


def _tendon(f: dict, c: Corrections) -> None:
    """``coupled_transmission``: the motor turns with dq[k] + c dq[coupled]; its friction,
    damping and rotor inertia act along that combination (a fixed tendon)."""
    k, p = _joint_index(f, c.joint_names), f["params"]
    other = p.get("coupled_joint")
    if k is None or other not in c.joint_names:
        c.not_expressed.append(f"coupled_transmission on {f.get('joint')!r} with {other!r}: not joints of the "
                               "corrected model")
        return
    tendon = coupling_tendon(c.joint_names[k], p)
    name = tendon["name"]
    c.tendons.append(tendon)
    c.written.append(f"tendon {name}: {c.joint_names[k]} + {_g(p['ratio'])} x {other}, frictionloss "
                     f"{_g(p.get('tau_c', 0.0))} N*m, damping {_g(p.get('b', 0.0))} N*m*s/rad, armature "
                     f"{_g(p.get('inertia', 0.0))} kg*m^2 (coupled_transmission)")


def _payload(f: dict, c: Corrections) -> None:
    if f.get("mode") is not None and c.mode is not None and int(f["mode"]) != c.mode:
        return
    p = f["params"]
    link = f.get("link") or p.get("link")
    c.payloads.append({"link": link, "mass": float(p["mass"]), "com": [float(x) for x in p["com"]],
                       "inertia": p.get("inertia")})
    mode = "" if f.get("mode") is None else f", mode {f['mode']}"
    c.written.append(f"{link}: payload {_g(p['mass'])} kg at [{', '.join(_g(x) for x in p['com'])}] m (link frame), "
                     f"a link {link}_payload in corrected.urdf (payload{mode})")


def _new_parameters(Y0, d: dict, whole: bool) -> np.ndarray:
    """(10,) Pinocchio dynamic parameters (link frame) of a body: ``d`` the whole body (``whole``)
    or a delta (mass, com, inertia about the com; parts absent are the nominal ``Y0``'s). Built
    without Pinocchio's checks, so an identified body that is not physical can be named, not
    raised on."""
    from ..physics.inertial import point_mass_parameters, vech

    v = np.asarray(d.get("inertia", np.zeros(6)), dtype=np.float64)
    I6 = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    if whole:
        m, com, Ic = float(d["mass"]), np.asarray(d["com"], dtype=np.float64), I6
    else:
        m = float(Y0.mass + d.get("mass", 0.0))
        com = np.asarray(Y0.lever) + np.asarray(d.get("com", np.zeros(3)), dtype=np.float64)
        Ic = np.asarray(Y0.inertia) + I6
    return point_mass_parameters(m, com) + np.r_[np.zeros(4), vech(Ic)]


def _inertial(f: dict, model, c: Corrections) -> None:
    """``inertial_parameters``: the physically consistent fit's bodies whole (``bodies``: they
    carry every identified base parameter), else each body's delta (mass, com, inertia about the
    com; what the log determines) added to Pinocchio's body of the reduced nominal model, as a
    change of the link's ten parameters."""
    import pinocchio as pin

    from ..physics.consistent import consistency_problems
    from ..physics.context import link_names_of

    links = link_names_of(model)
    whole = bool(f["params"].get("bodies"))
    for body, d in (f["params"].get("bodies") or f["params"].get("delta") or {}).items():
        if body not in links or not model.existFrame(body, pin.FrameType.BODY):
            c.not_expressed.append(f"inertial_parameters of {body!r}: not a link of the corrected model")
            continue
        Y0 = model.inertias[links.index(body) + 1]
        new = _new_parameters(Y0, d, whole)
        problems = consistency_problems(new, name=body)
        if problems:
            c.not_expressed.append(f"inertial_parameters of {body}: the {'identified' if whole else 'nominal'} body"
                                   f"{'' if whole else ' plus its delta'} is not physical ({'; '.join(problems)}); "
                                   "the nominal inertial is kept")
            continue
        c.body_changes[body] = new - Y0.toDynamicParameters()
        c.written.append(f"{body}: inertial parameters " + ("of the physically consistent fit: " if whole else
                         "changed by ") + ", ".join(
            f"{k} {_g(v) if np.isscalar(v) else '[' + ', '.join(_g(x) for x in v) + ']'}" for k, v in d.items())
            + " (inertial_parameters)")


def corrections(findings: list, model, joint_names: list) -> Corrections:
    """What ``findings`` (CONTRACT section 2) change in the files, against ``model`` (the reduced
    nominal Pinocchio model the diagnosis used, joints ``joint_names``)."""
    n = len(joint_names)
    c = Corrections(list(joint_names), {k: np.zeros(n) for k in ("frictionloss", "damping", "armature", "stiffness",
                                                                  "springref")})
    _chosen_mode(findings, c)
    for f in findings:
        e = f["effect"]
        if e in JOINT_PROPERTY:
            _joint_effect(f, c)
        elif e == "coupled_transmission":
            _tendon(f, c)
        elif e == "payload":
            _payload(f, c)
        elif e == "inertial_parameters":
            _inertial(f, model, c)
        elif e in NOT_EXPRESSED:
            where = f.get("joint") if f.get("joint") is not None else "the whole log"
            c.not_expressed.append(f"{e} ({where}): {NOT_EXPRESSED[e]}")
        elif e != "mode_switch":
            c.not_expressed.append(f"{e} ({f.get('joint') or f.get('link') or 'the whole log'}): no MJCF counterpart "
                                   "is written for it")
    return c


def _bodies(c: Corrections, nominal) -> str:
    if c.body_changes or c.payloads:
        return f"the nominal {Path(nominal).name} with the identified inertial parameters and payloads"
    return f"the nominal {Path(nominal).name}'s bodies: no inertial parameters or payload were found"


def header(c: Corrections, nominal, fixed: list) -> str:
    """The comment at the top of corrected.xml: where it comes from, what it carries, what not."""
    lines = [f"corrected.xml: the corrected model of mmgp diagnose (mmgp {__version__}; CONTRACT section 2, 1.2).",
             f"Bodies: corrected.urdf ({_bodies(c, nominal)}) as Pinocchio parses it (links behind fixed joints "
             "merged); no geometry, contacts off.",
             f"Joints: {', '.join(c.joint_names)}"
             + (f"; fixed where the diagnosis held them (angle 0): {', '.join(fixed)}." if fixed else "."),
             "", "Found effects written here:"]
    lines += [f"- {w}" for w in c.written] or ["- none (the nominal model)"]
    lines += ["", "Not expressed in MJCF (also in report.md and findings.json 'corrected_model'):"]
    lines += [f"- {w}" for w in c.not_expressed] or ["- nothing: every finding is in this file"]
    lines += ["", "Inverse dynamics: " + INVERSE_NOTE]
    return "\n".join(lines)


def write_corrected(findings: list, urdf, joint_names: list, out, friction_velocity: dict | None = None) -> dict:
    """Write ``out/corrected.urdf`` and ``out/corrected.xml`` (atomically) for ``findings``
    against the nominal ``urdf`` reduced to ``joint_names`` (``friction_velocity``: joint -> v_s,
    rad/s, the friction law's velocity scale, written into corrected.xml); returns what was
    written, in words, for findings.json and the report. Without a URDF, or when the files cannot be built (a link
    the URDF lacks, a body no mass distribution has), nothing is written and the answer says why."""
    if urdf is None:
        return {"written": False, "why": "the diagnosis had no URDF (a robot given as a Pinocchio model, or none): "
                                         "no corrected model is written"}
    from ..data.outputs import atomic_write_bytes
    from ..physics.mjcf import build_mjcf
    from ..physics.robot import RobotModel
    from ..physics.urdf import corrected_urdf

    try:
        robot = RobotModel.from_urdf(urdf, joint_names)
        c = corrections(findings, robot.pin_model, robot.joint_names)
        fixed = [str(nm) for nm in robot.full_model.names[1:] if str(nm) not in robot.joint_names]
        note = (f"corrected.urdf: the nominal {Path(urdf).name} changed by mmgp diagnose (mmgp {__version__}): "
                "identified inertial parameters and payloads; joints the log does not record fixed at angle 0. "
                "Friction, damping, armature and springs are in corrected.xml.")
        text = corrected_urdf(urdf, robot.joint_names, body_changes=c.body_changes, payloads=c.payloads, comment=note)
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "corrected.urdf").write_text(text)
            v_s = None if friction_velocity is None else [friction_velocity[nm] for nm in robot.joint_names]
            mjcf = build_mjcf(str(Path(tmp) / "corrected.urdf"), robot.joint_names, tendons=c.tendons,
                              comment=header(c, urdf, fixed), friction_velocity=v_s, **c.properties)
    except ValueError as exc:
        return {"written": False, "why": f"the corrected model could not be built: {exc}"}
    out = Path(out)
    atomic_write_bytes(out / "corrected.urdf", text.encode())
    atomic_write_bytes(out / "corrected.xml", mjcf.encode())
    return {"written": True, "urdf": "corrected.urdf", "mjcf": "corrected.xml", "nominal_urdf": str(urdf),
            "joints": c.joint_names, "fixed_joints": fixed, "mode": c.mode, "bodies": _bodies(c, urdf),
            "carries": c.written,
            "not_expressed": c.not_expressed, "load": list(LOAD_LINES), "inverse_dynamics": INVERSE_NOTE}


def corrected_markdown(summary: dict | None) -> list[str]:
    """The report's "Corrected model" section (lines) of :func:`write_corrected`'s answer."""
    if summary is None:
        return []
    lines = ["", "## Corrected model", ""]
    if not summary.get("written"):
        return lines + [f"Not written: {summary.get('why')}.", ""]
    mode = "" if summary.get("mode") is None else f" A switching payload is written for mode {summary['mode']}."
    lines += [f"`corrected.urdf` ({summary['bodies']}; Pinocchio) and `corrected.xml` (the same bodies plus "
              f"the joint friction, damping, armature, springs and coupled transmissions found; MuJoCo).{mode}", "",
              "Written into the model:", ""]
    lines += [f"- {w}" for w in summary["carries"]] or ["- nothing: no finding changes the nominal model"]
    lines += ["", "Not expressed in MJCF (named at the top of corrected.xml too):", ""]
    lines += [f"- {w}" for w in summary["not_expressed"]] or ["- nothing: every finding is in the files"]
    lines += ["", "Load it (paths relative to this folder):", "", "```python", *summary["load"], "```", "",
              summary["inverse_dynamics"], ""]
    return lines
