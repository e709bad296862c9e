"""What every reader returns, and the checks and conventions every reader shares.

A reader turns one input (a bag, a CSV, a dataset folder) into one or more
:class:`ConvertedLog` parts: arrays already in contract units (s, rad, rad/s, rad/s^2, N*m) and
in log joint order. The same time policy (:func:`order_in_time`) and the same robot-model joint
ordering (:func:`order_for_robot`) apply whatever the format.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..data.logs import MIN_SAMPLES, RobotLog

KINDS = ("q", "dq", "ddq", "tau")

# A backward step in time larger than this many median steps is a clock reset or two recordings
# glued together, not messages that arrived out of order: sorting would interleave two runs.
MAX_REORDER_STEPS = 10.0


@dataclass(frozen=True)
class ConvertedLog(RobotLog):
    """One contract log, ready to write: a :class:`RobotLog` plus where it goes and came from.

    Arrays as in :class:`RobotLog` (``t`` (T,) s; ``q``/``dq``/``ddq``/``tau`` (T, n) rad,
    rad/s, rad/s^2, N*m; m, m/s, N for prismatic joints), ``dq``/``ddq`` None when the source
    lacks them (mmgp estimates them); ``metadata`` holds ``robot``, ``joint_names`` and, where the
    recording has a wall clock, ``start_time`` (UTC ISO 8601 of the first sample); ``path``
    is the input read. ``name`` names the part (file name in a folder output); ``urdf`` is a URDF
    file to copy next to the log (named in its metadata); ``source`` says where the numbers came
    from and ``notes`` every convention applied on the way (both stored in the Parquet metadata).
    ``metadata["time_origin"]`` (inputs with absolute stamps: bags, ROS CSV exports) places ``t``
    on the recording's clock: ``{"stamp_ns": stamp of t = 0 in integer ns}``, plus for bags the
    ``clock`` ("header" or "receive"), ``topic`` and ``bag`` (file name); ``mmgp annotate`` uses it.
    """

    name: str = ""
    urdf: Path | None = None
    source: str = ""
    notes: tuple[str, ...] = ()

    @classmethod
    def of(cls, name: str, t, q, tau, *, dq=None, ddq=None, joint_names: Sequence[str] | None = None,
           robot: str | None = None, urdf: Path | None = None, source: str = "",
           notes: Sequence[str] = (), file: str | Path = "", start_time: str | None = None) -> "ConvertedLog":
        """A log from arrays (converted to float64) and what is known about them."""
        meta = {} if robot is None else {"robot": robot}
        if joint_names is not None:
            meta["joint_names"] = list(joint_names)
        if start_time is not None:
            meta["start_time"] = start_time
        as_float = lambda a: None if a is None else np.asarray(a, dtype=np.float64)  # noqa: E731
        return cls(path=str(file), t=as_float(t), q=as_float(q), tau=as_float(tau), dq=as_float(dq),
                   ddq=as_float(ddq), metadata=meta, name=name, urdf=urdf, source=source, notes=tuple(notes))

    @property
    def robot(self) -> str | None:
        return self.metadata.get("robot")

    @property
    def start_time(self) -> str | None:
        return self.metadata.get("start_time")

    def with_time_origin(self, **fields) -> "ConvertedLog":
        """The same log with ``fields`` added to its ``time_origin`` metadata (see the class doc)."""
        origin = dict(self.metadata.get("time_origin") or {}, **fields)
        return replace(self, metadata=dict(self.metadata, time_origin=origin))

    def noted(self, *notes: str) -> "ConvertedLog":
        return replace(self, notes=self.notes + notes)

    def arrays(self) -> dict[str, np.ndarray]:
        """The joint arrays present, by kind."""
        return {k: getattr(self, k) for k in KINDS if getattr(self, k) is not None}

    def with_columns(self, idx: Sequence[int], names: list[str] | None) -> "ConvertedLog":
        """The same log restricted/reordered to joint columns ``idx``, named ``names``."""
        idx = list(idx)
        meta = {k: v for k, v in self.metadata.items() if k != "joint_names"}
        if names is not None:
            meta["joint_names"] = list(names)
        return replace(self, metadata=meta, **{k: a[:, idx] for k, a in self.arrays().items()})

    def with_robot(self, robot: str) -> "ConvertedLog":
        """Named robot ``robot`` (an example-robot-data model replaces any URDF)."""
        return replace(self, metadata=dict(self.metadata, robot=robot), urdf=None)


def check_log(log: ConvertedLog, file: str | Path) -> None:
    """Refuse a part that would not be a valid contract log, naming the joint and the row."""
    T, n = log.q.shape
    if log.t.shape != (T,):
        raise InputError(f"{log.name}: {log.t.shape[0]} time stamps for {T} samples", file=file)
    for kind, arr in log.arrays().items():
        if arr.shape != (T, n):
            raise InputError(f"{log.name}: '{kind}' has shape {arr.shape}, expected ({T}, {n})", file=file)
    if log.joint_names is not None and len(log.joint_names) != n:
        raise InputError(f"{log.name}: {len(log.joint_names)} joint names for {n} joints", file=file)
    for kind, arr in {"t": log.t[:, None], **log.arrays()}.items():
        bad = ~np.isfinite(arr)
        if bad.any():
            row, j = (int(v[0]) for v in np.nonzero(bad))
            who = "" if kind == "t" else f" of joint {_joint_label(log, j)}"
            raise InputError(f"{log.name}: '{kind}'{who} is {arr[row, j]} at sample {row}: expected a "
                             "finite number", file=file, row=row)
    if T < MIN_SAMPLES:
        raise InputError(f"{log.name}: too few samples: {T}, at least {MIN_SAMPLES} needed", file=file)
    step = np.diff(log.t)
    if (step <= 0).any():
        row = int(np.flatnonzero(step <= 0)[0]) + 1
        raise InputError(f"{log.name}: time must increase strictly: t[{row}]={log.t[row]} after "
                         f"t[{row - 1}]={log.t[row - 1]}", file=file, row=row)


def _joint_label(log: ConvertedLog, j: int) -> str:
    return f"'{log.joint_names[j]}'" if log.joint_names else str(j)


def order_in_time(log: ConvertedLog, file: str | Path, what: str = "time stamp") -> ConvertedLog:
    """Apply the one time policy of every reader; notes say what was done.

    * Samples a little out of order (each backward step shorter than ``MAX_REORDER_STEPS``
      median steps: messages that arrived late) are sorted by time.
    * A longer backward step (a clock reset, two recordings in one file) is refused.
    * Samples repeated exactly (same time, same values: a message recorded twice) are dropped.
    * Two different samples with the same time are refused: which one is right is unknown.
    """
    t = log.t
    if not np.isfinite(t).all():
        row = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"{what} {t[row]} at sample {row}: expected a finite time", file=file, row=row)
    step = np.diff(t)
    if step.size == 0 or (step > 0).all():
        return log
    typical = float(np.median(step[step > 0])) if (step > 0).any() else 0.0
    back = step < 0
    if back.any():
        k = int(np.argmin(step))
        if -step[k] > MAX_REORDER_STEPS * typical:
            raise InputError(
                f"{what} goes back by {-step[k]:.6g} s at sample {k + 1} ({t[k]:.6f} -> {t[k + 1]:.6f}): "
                f"more than {MAX_REORDER_STEPS:g} sample steps, a clock reset or two recordings in one "
                "input; split it first", file=file, row=k + 1)
        order = np.argsort(t, kind="stable")
        log = log.subset(order).noted(f"{int((order != np.arange(order.size)).sum())} samples out of "
                                      f"{what} order were sorted by time")
    return _drop_repeats(log, file, what)


def _drop_repeats(log: ConvertedLog, file, what: str) -> ConvertedLog:
    same_t = np.flatnonzero(np.diff(log.t) == 0) + 1
    if same_t.size == 0:
        return log
    rows = np.concatenate([a for a in log.arrays().values()], axis=1)
    differ = ~np.all(rows[same_t] == rows[same_t - 1], axis=1)
    if differ.any():
        k = int(same_t[np.flatnonzero(differ)[0]])
        raise InputError(
            f"{int(differ.sum())} pair(s) of different samples share a {what} (first: samples {k - 1} "
            f"and {k} at t={log.t[k]:.9f}); which is right is unknown: fix the stamps, or for a bag "
            "use the recording time (map key 'stamp: receive')", file=file, row=k)
    keep = np.ones(log.n_samples, dtype=bool)
    keep[same_t] = False
    return log.subset(np.flatnonzero(keep)).noted(f"{same_t.size} exact repeats (same {what}, same values) dropped")


def order_for_robot(log: ConvertedLog, robot: str, file: str | Path) -> ConvertedLog:
    """Joints in the robot model's order (CONTRACT section 1), names checked against the model.

    Joints the model does not have are dropped (noted). A log without joint names is taken to
    be in model order already (the model's first n joints, when those form one serial chain).
    """
    from ..physics.robot import load_robot

    if log.joint_names is None:
        model = load_robot(robot=robot, n_joints=log.n_joints)
        return log.with_columns(range(log.n_joints), model.joint_names).with_robot(robot).noted(
            f"no joint names in the input: columns taken as {robot}'s joints in model order")
    model_order = load_robot(robot=robot).joint_names
    keep = [nm for nm in model_order if nm in log.joint_names]
    if not keep:
        raise InputError(f"none of the input's joints {log.joint_names} is a joint of robot '{robot}' "
                         f"({model_order})", file=file)
    load_robot(robot=robot, joint_names=keep)  # refuses joints that cannot be one log column
    out = log.with_columns([log.joint_names.index(nm) for nm in keep], keep).with_robot(robot)
    dropped = [nm for nm in log.joint_names if nm not in keep]
    if dropped:
        out = out.noted(f"joints not in robot '{robot}' dropped: {dropped}")
    if keep != [nm for nm in log.joint_names if nm in keep]:
        out = out.noted(f"joints reordered to {robot}'s model order")
    return out


def select_joints(log: ConvertedLog, joints: Sequence[str], file: str | Path) -> ConvertedLog:
    """Keep only ``joints`` (map key ``joints``), in that order."""
    names = log.joint_names or []
    missing = [nm for nm in joints if nm not in names]
    if missing:
        raise InputError(f"joint(s) {missing} asked for in the map are not in the input; it has {names}",
                         file=file)
    return log.with_columns([names.index(nm) for nm in joints], list(joints))
