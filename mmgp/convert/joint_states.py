"""``sensor_msgs/JointState`` messages (from a bag or a ``rostopic echo -p`` CSV) into one log.

position -> q, velocity -> dq, effort -> tau; joints named by the messages. A topic can carry
messages of different joint sets (e.g. the arm and the gripper published separately on
``/joint_states``): the log takes one set, chosen by the map's ``joints``, else the one set that
has joints of ``--robot``, else the only set; messages of other, disjoint sets are skipped (noted);
a message with only part of the chosen joints is refused.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..data.times import wall_clock_iso
from ..errors import InputError
from .base import ConvertedLog


@dataclass
class JointStateMessage:
    """One message: ``stamp_ns`` (int, ns), joint ``names``, and its position/velocity/effort
    (each (len(names),) or empty)."""

    stamp_ns: int
    names: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


def _groups(messages: Sequence[JointStateMessage]) -> dict[frozenset, tuple[tuple[str, ...], int]]:
    out: dict[frozenset, tuple[tuple[str, ...], int]] = {}
    for m in messages:
        key = frozenset(m.names)
        first, count = out.get(key, (m.names, 0))
        out[key] = (first, count + 1)
    return out


def _describe(groups) -> str:
    return "; ".join(f"{list(names)} ({count} messages)" for names, count in groups.values())


def target_joints(messages: Sequence[JointStateMessage], options: dict[str, Any], robot: str | None,
                  file: str | Path) -> list[str]:
    """The joints the log will hold, in message order (see the module doc for the rule)."""
    if options.get("joints"):
        return list(options["joints"])
    groups = _groups(messages)
    if robot is not None and len(groups) > 1:
        from ..physics.robot import load_robot

        model = set(load_robot(robot=robot).joint_names)
        hit = {k: v for k, v in groups.items() if k & model}
        if len(hit) == 1:
            return list(next(iter(hit.values()))[0])
        groups = hit or groups
    if len(groups) == 1:
        names = list(next(iter(groups.values()))[0])
        if not names:
            raise InputError("the messages name no joints (empty 'name'): their columns cannot be matched "
                             "to joints", file=file)
        return names
    raise InputError(f"the messages carry {len(groups)} different joint sets: {_describe(groups)}; "
                     "choose the joints with map key 'joints' (or --robot)", file=file)


def _stack(messages, rows: list[int], field: str, idx: list[np.ndarray]) -> np.ndarray | None:
    values = [getattr(messages[k], field) for k in rows]
    if any(v.size == 0 for v in values):
        return None
    return np.stack([v[i] for v, i in zip(values, idx)])


def assemble(messages: Sequence[JointStateMessage], options: dict[str, Any], robot: str | None,
             file: str | Path, name: str, source: str, origin_ns: int | None = 0) -> ConvertedLog:
    """One log from JointState messages; ``t`` relative to the first kept stamp. ``origin_ns``:
    the Unix time in ns of stamp 0 (0 for a bag's absolute stamps; None when the stamps are no
    wall clock); ``start_time`` is the first kept stamp's time where it is a wall clock."""
    if not messages:
        raise InputError(f"{source}: no messages", file=file)
    joints = target_joints(messages, options, robot, file)
    wanted = set(joints)
    rows, idx = [], []
    for k, m in enumerate(messages):
        have = set(m.names)
        if not have & wanted:
            continue
        lacking = [nm for nm in joints if nm not in have]
        if lacking:
            raise InputError(f"{source}: message {k} has joints {list(m.names)}, without {lacking} of the "
                             f"chosen joints {joints}: refused (choose 'joints' in the map)", file=file)
        for field in ("position", "velocity", "effort"):
            size = getattr(m, field).size
            if size not in (0, len(m.names)):
                raise InputError(f"{source}: message {k} has {len(m.names)} names but {size} {field} values",
                                 file=file)
        rows.append(k)
        idx.append(np.array([m.names.index(nm) for nm in joints]))
    q, dq, tau = (_stack(messages, rows, f, idx) for f in ("position", "velocity", "effort"))
    for arr, field, kind in ((q, "position", "q"), (tau, "effort", "tau")):
        if arr is None:
            raise InputError(f"{source}: some messages have no {field} values; {kind} is required", file=file)
    stamps = np.array([messages[k].stamp_ns for k in rows], dtype=np.int64)
    notes = [f"t = stamp - {int(stamps.min())} ns"]
    if len(rows) < len(messages):
        notes.append(f"{len(messages) - len(rows)} messages of other joint sets skipped")
    if dq is None:
        notes.append("velocity missing in some messages: dq left out (mmgp estimates it)")
    start = None if origin_ns is None else wall_clock_iso(ns=origin_ns + int(stamps.min()))
    return ConvertedLog.of(name=name, t=(stamps - stamps.min()) * 1e-9, q=q, tau=tau, dq=dq,
                        joint_names=joints, source=source, notes=notes, start_time=start).with_time_origin(
        stamp_ns=(origin_ns or 0) + int(stamps.min()))
