"""MuJoCo models of URDF robots, built through Pinocchio's parse, and payload bodies.

The MJCF text is :mod:`mmgp.physics.mjcf` (:func:`build_mjcf`, re-exported here); this module
compiles it (:func:`load_model`) and changes a compiled payload (:func:`set_payload`).
"""
from __future__ import annotations

import mujoco

from ..physics.mjcf import (JOINT_PROPERTIES, NOSLIP_ITERATIONS, body_name, build_mjcf, option_element,
                            reduced_pinocchio_model)
from ..physics.robot import robot_urdf_path as _robot_urdf_path

__all__ = ["JOINT_PROPERTIES", "NOSLIP_ITERATIONS", "body_name", "build_mjcf", "load_model", "option_element",
           "panda_urdf_path", "reduced_pinocchio_model", "robot_urdf_path", "set_payload"]


def robot_urdf_path(name: str) -> str:
    """Path (str) of the URDF of an example-robot-data robot (e.g. ``"panda"``, ``"ur5"``);
    the lookup is :func:`mmgp.physics.robot.robot_urdf_path`."""
    return str(_robot_urdf_path(name))


def panda_urdf_path() -> str:
    """Path of example-robot-data's ``panda.urdf`` (7 arm joints + 2 finger joints)."""
    return robot_urdf_path("panda")


def load_model(urdf_path: str, joint_names: list[str] | None = None, **kwargs):
    """``mujoco.MjModel`` of :func:`build_mjcf` (same arguments)."""
    return mujoco.MjModel.from_xml_string(build_mjcf(urdf_path, joint_names, **kwargs))


def set_payload(model, mass: float, *, radius: float = 0.05) -> None:
    """Change the mass of the ``"payload"`` body in place (solid sphere of ``radius`` m).

    MuJoCo recomputes composite inertias from ``body_mass``/``body_inertia`` at every step, so the
    dynamics change at once; no recompilation is needed.
    """
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "payload")
    if bid < 0:
        raise ValueError("model has no 'payload' body (build it with payload=...)")
    model.body_mass[bid] = max(float(mass), 1e-9)
    model.body_inertia[bid] = 0.4 * float(mass) * radius ** 2 if mass > 0 else 1e-12


def urdf_with_link_error(text: str, link: str, added_mass: float, com_shift: float) -> str:
    """URDF ``text`` with ``link`` ``added_mass`` kg heavier and its centre of mass ``com_shift`` m
    further along the link's x: a robot its nominal URDF is wrong about (inertia tensor kept)."""
    import re

    block = re.search(rf'<link name="{link}">.*?</link>', text, re.S)
    inertial = re.search(r"<inertial>.*?</inertial>", block.group(0), re.S)
    body = inertial.group(0)
    m = re.search(r'<mass value="([^"]+)"', body)
    body = body[:m.start(1)] + repr(float(m.group(1)) + added_mass) + body[m.end(1):]
    o = re.search(r'<origin[^>]*xyz="([^"]+)"', body)
    x, y, z = (float(v) for v in o.group(1).split())
    body = body[:o.start(1)] + f"{x + com_shift} {y} {z}" + body[o.end(1):]
    start = block.start() + inertial.start()
    return text[:start] + body + text[start + len(inertial.group(0)):]


def urdf_with_joint_range(text: str, joint: str, lower: float, upper: float) -> str:
    """URDF ``text`` with ``joint``'s position limits set to [``lower``, ``upper``] rad (the
    recordings' references stay within a joint's limits)."""
    import re

    m = re.search(rf'<joint name="{joint}".*?<limit[^>]*lower="([^"]+)"[^>]*upper="([^"]+)"', text, re.S)
    return text[:m.start(1)] + repr(lower) + text[m.end(1):m.start(2)] + repr(upper) + text[m.end(2):]
