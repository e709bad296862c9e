"""A nominal URDF rewritten with changed inertials: the corrected model's ``corrected.urdf``.

:func:`corrected_urdf` keeps everything of the nominal URDF (links, joints, geometry, limits,
comments) and changes only what a diagnosis identified: the ``<inertial>`` of links whose rigid
body was re-identified, a payload link welded to its link, and the joints a log does not record
made ``fixed`` where the diagnosis held them (Pinocchio's neutral configuration, angle 0), so the
file loads with exactly the log's joints. Units: kg, m, kg*m^2; inertial parameters in
Pinocchio's order (:mod:`mmgp.physics.inertial`).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Sequence

import numpy as np
import pinocchio as pin

from .consistent import consistency_problems
from .mjcf import xml_comment


def _floats(text: str | None, n: int) -> np.ndarray:
    return np.zeros(n) if text is None else np.array([float(x) for x in text.split()], dtype=np.float64)


def link_inertia(link: ET.Element) -> pin.Inertia:
    """The ``<inertial>`` of a URDF ``<link>`` as a Pinocchio inertia in the link frame (zero
    when the link has none)."""
    el = link.find("inertial")
    if el is None:
        return pin.Inertia.Zero()
    origin = el.find("origin")
    xyz = _floats(None if origin is None else origin.get("xyz"), 3)
    rpy = _floats(None if origin is None else origin.get("rpy"), 3)
    mass_el, inertia_el = el.find("mass"), el.find("inertia")
    mass = 0.0 if mass_el is None else float(mass_el.get("value", 0.0))
    v = {k: 0.0 if inertia_el is None else float(inertia_el.get(k, 0.0)) for k in
         ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    I_frame = np.array([[v["ixx"], v["ixy"], v["ixz"]], [v["ixy"], v["iyy"], v["iyz"]],
                        [v["ixz"], v["iyz"], v["izz"]]])
    R = pin.rpy.rpyToMatrix(*rpy)
    return pin.Inertia(mass, xyz, R @ I_frame @ R.T)


def inertial_element(inertia: pin.Inertia) -> ET.Element:
    """URDF ``<inertial>`` of ``inertia`` (link frame): origin at the centre of mass, axes the
    link's, inertia about the centre of mass; every float64 bit kept."""
    f = lambda x: f"{float(x):.17g}"  # noqa: E731
    I = np.asarray(inertia.inertia)
    el = ET.Element("inertial")
    ET.SubElement(el, "origin", xyz=" ".join(f(x) for x in inertia.lever), rpy="0 0 0")
    ET.SubElement(el, "mass", value=f(inertia.mass))
    ET.SubElement(el, "inertia", ixx=f(I[0, 0]), ixy=f(I[0, 1]), ixz=f(I[0, 2]), iyy=f(I[1, 1]), iyz=f(I[1, 2]),
                  izz=f(I[2, 2]))
    return el


def _set_inertial(link: ET.Element, inertia: pin.Inertia) -> None:
    old = link.find("inertial")
    new = inertial_element(inertia)
    if old is None:
        link.insert(0, new)
    else:
        link[list(link).index(old)] = new


def _links(root: ET.Element) -> dict[str, ET.Element]:
    return {el.get("name"): el for el in root.findall("link")}


def _fix_unlogged(root: ET.Element, joint_names: Sequence[str] | None) -> None:
    """Make every movable joint outside ``joint_names`` fixed at its origin (angle 0)."""
    if joint_names is None:
        return
    keep = set(joint_names)
    for j in root.findall("joint"):
        if j.get("type") != "fixed" and j.get("name") not in keep:
            j.set("type", "fixed")
            for child in [c for c in j if c.tag in ("mimic", "axis", "limit", "dynamics", "calibration",
                                                     "safety_controller")]:
                j.remove(child)
    unknown = keep - {j.get("name") for j in root.findall("joint")}
    if unknown:
        raise ValueError(f"joints {sorted(unknown)} are not in the URDF")


def _absolute_meshes(root: ET.Element, folder: Path) -> None:
    """Relative mesh paths made absolute, so the file still finds them written elsewhere."""
    for el in root.iter():
        fn = el.get("filename")
        if fn and "://" not in fn and not Path(fn).is_absolute():
            el.set("filename", str((folder / fn).resolve()))


def _change_body(links: dict, name: str, change: np.ndarray) -> None:
    """Add ``change`` (10,) to link ``name``'s own inertial; refuse a result no mass distribution
    has (unless the nominal link already was such)."""
    if name not in links:
        raise ValueError(f"link '{name}' is not in the URDF")
    pi0 = link_inertia(links[name]).toDynamicParameters()
    pi = pi0 + np.asarray(change, dtype=np.float64)
    problems = consistency_problems(pi, name=f"link {name}")
    if problems and not consistency_problems(pi0):
        raise ValueError("; ".join(problems))
    _set_inertial(links[name], pin.Inertia.FromDynamicParameters(pi))


def _add_payload(root: ET.Element, links: dict, payload: dict) -> str:
    """A link ``<link>_payload`` with the payload's inertial, welded to ``payload["link"]`` at its
    origin; the new link's name."""
    parent = payload["link"]
    if parent not in links:
        raise ValueError(f"payload link '{parent}' is not in the URDF")
    names = set(links) | {j.get("name") for j in root.findall("joint")}
    name, k = f"{parent}_payload", 1
    while name in names or f"{name}_joint" in names:
        k += 1
        name = f"{parent}_payload_{k}"
    Ic = np.zeros((3, 3)) if payload.get("inertia") is None else np.asarray(payload["inertia"], dtype=np.float64)
    inertia = pin.Inertia(float(payload["mass"]), np.asarray(payload["com"], dtype=np.float64), Ic)
    problems = consistency_problems(inertia.toDynamicParameters(), name=f"payload on {parent}")
    if problems:
        raise ValueError("; ".join(problems))
    link = ET.SubElement(root, "link", name=name)
    link.append(inertial_element(inertia))
    joint = ET.SubElement(root, "joint", name=f"{name}_joint", type="fixed")
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=name)
    ET.SubElement(joint, "origin", xyz="0 0 0", rpy="0 0 0")
    links[name] = link
    return name


def corrected_urdf(urdf_path, joint_names: Sequence[str] | None = None, *, body_changes: dict | None = None,
                   payloads: Sequence[dict] = (), comment: str | None = None) -> str:
    """Text of the URDF ``urdf_path`` with the diagnosis's changes.

    ``joint_names``: the joints left movable (None: all); every other movable joint becomes
    ``fixed`` at angle 0. ``body_changes``: link name -> (10,) change of that link's inertial
    parameters (Pinocchio order, link frame, inertia about the link origin), added to the link's
    own ``<inertial>``; links merged into it by fixed joints keep theirs, so the rigid body
    Pinocchio builds changes by exactly that amount. ``payloads``: ``{"link", "mass" (kg), "com"
    ((3,) m, link frame), "inertia" (optional (3, 3) kg*m^2 about the com, link axes; default a
    point mass)}``, each a new link welded to its link. ``comment``: an XML comment at the top.
    Raises ValueError for a link or joint the URDF lacks, or a body no mass distribution has.
    """
    path = Path(urdf_path)
    root = ET.parse(path, parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))).getroot()
    if root.tag != "robot":
        raise ValueError(f"{path} is not a URDF (root element <{root.tag}>)")
    _fix_unlogged(root, joint_names)
    _absolute_meshes(root, path.resolve().parent)
    links = _links(root)
    for name, change in (body_changes or {}).items():
        _change_body(links, name, change)
    for p in payloads:
        _add_payload(root, links, p)
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + xml_comment(comment) + ET.tostring(root, encoding="unicode") + "\n"
