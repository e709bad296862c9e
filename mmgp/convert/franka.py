"""``franka_msgs/FrankaState`` (franka_ros) samples, from a bag or a CSV export, into one log.

Fields (libfranka ``RobotState``): ``q`` measured joint position (rad), ``dq`` measured joint
velocity (rad/s), ``tau_J`` measured link-side joint torque (N*m, the joint torque sensors:
everything the joint transmits, gravity included), ``tau_J_d`` desired link-side torque *without
gravity* (what the user's controller commanded; libfranka adds gravity itself).

``tau`` = ``tau_J``: the contract's tau is the total joint torque, which only ``tau_J`` is.
``tau_J_d`` is taken only when the map says ``tau_source: tau_J_d`` (noted: it lacks gravity
and everything the controller did not command). No acceleration is logged: ddq is left out.
Joint names default to ``panda_joint1`` .. ``panda_joint7`` (franka_ros with arm_id ``panda``);
the map's ``joint_names`` renames them.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .base import ConvertedLog
from .mapping import choice

FRANKA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
FRANKA_TAU = ("tau_J", "tau_J_d")
FRANKA_FIELDS = ("q", "dq", "tau_J", "tau_J_d")


def franka_log(name: str, t: np.ndarray, fields: dict[str, np.ndarray], options: dict[str, Any],
               source: str, notes: list[str], file: str | Path, start_time: str | None = None) -> ConvertedLog:
    """The log of FrankaState samples: ``fields`` maps field name -> (T, 7) array; ``start_time``
    the wall-clock time of ``t`` = 0 where the stamps have one."""
    src = choice(options, "tau_source", FRANKA_TAU, "tau_J")
    for field in ("q", src):
        if field not in fields:
            raise InputError(f"{source}: no '{field}' values (expected e.g. field.{field}0 in a CSV export)",
                             file=file, column=field)
    notes = list(notes)
    if src == "tau_J":
        notes.append("tau = tau_J (measured link-side joint torque)")
    else:
        notes.append("tau = tau_J_d (desired torque WITHOUT gravity, chosen in the map): not the total "
                     "joint torque")
    names = options.get("joint_names") or FRANKA_JOINTS
    return ConvertedLog.of(name=name, t=np.asarray(t, dtype=np.float64), q=fields["q"], tau=fields[src],
                        dq=fields.get("dq"), joint_names=list(names), source=source, notes=notes,
                        start_time=start_time)


def franka_source(path: Path, where: str) -> str:
    return f"franka_ros FrankaState {where} in {path.name}"
