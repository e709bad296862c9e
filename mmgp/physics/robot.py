"""Rigid-body robot models (Pinocchio): loading, joint selection, batched RNEA and inertial regressors.

A :class:`RobotModel` is the nominal model reduced to the joints a log records, in log order
(CONTRACT section 1: the columns follow Pinocchio's ``model.names[1:]`` order). Every other joint
(gripper fingers, a head, a mobile base) is locked at its neutral position with
``pin.buildReducedModel``, so its links ride along as rigid mass of their parent link.

Conventions used throughout:

* ``q``, ``dq``, ``ddq`` are logged joint angles (rad, m for prismatic), rates (rad/s) and
  accelerations (rad/s^2), shape ``(T, n)`` or ``(n,)``. A continuous (unbounded) joint is logged as
  one angle; Pinocchio stores it as ``(cos, sin)``, and :meth:`RobotModel.configuration` converts.
* Torques are N*m (N for prismatic joints), shape ``(T, n)``.
* Inertial parameters of one body are Pinocchio's ``toDynamicParameters`` order
  ``[m, m*c_x, m*c_y, m*c_z, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]`` (kg, kg*m, kg*m^2), expressed in the
  body's joint frame with the inertia taken about that frame's origin.
"""
from __future__ import annotations

import contextlib
import importlib.metadata
import os
import sys
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
import pinocchio as pin

from ..data.headers import read_table_header
from ..errors import InputError, describe, one_line
from .inertial import transport_matrix

__all__ = [
    "ROBOT_FILES",
    "available_robots",
    "robot_urdf_path",
    "RobotModel",
    "load_robot",
]

# example-robot-data robot name -> URDF path under its ``robots`` folder. Names follow
# example-robot-data's loader names where one exists; entries whose file is not installed are
# simply not offered (see available_robots).
ROBOT_FILES: dict[str, str] = {
    "panda": "panda_description/urdf/panda.urdf",
    "panda_collision": "panda_description/urdf/panda_collision.urdf",
    "ur3": "ur_description/urdf/ur3_robot.urdf",
    "ur3_limited": "ur_description/urdf/ur3_joint_limited_robot.urdf",
    "ur3_gripper": "ur_description/urdf/ur3_gripper.urdf",
    "ur5": "ur_description/urdf/ur5_robot.urdf",
    "ur5_limited": "ur_description/urdf/ur5_joint_limited_robot.urdf",
    "ur5_gripper": "ur_description/urdf/ur5_gripper.urdf",
    "ur10": "ur_description/urdf/ur10_robot.urdf",
    "ur10_limited": "ur_description/urdf/ur10_joint_limited_robot.urdf",
    "baxter": "baxter_description/urdf/baxter.urdf",
    "iiwa": "iiwa_description/urdf/iiwa.urdf",
    "kinova": "kinova_description/robots/kinova.urdf",
    "xarm7": "xarm_description/urdf/xarm7.urdf",
    "z1": "z1_description/urdf/z1.urdf",
    "so100": "so_arm_description/urdf/so100.urdf",
    "so101": "so_arm_description/urdf/so101.urdf",
    "talos": "talos_data/robots/talos_reduced.urdf",
    "talos_box": "talos_data/robots/talos_reduced_box.urdf",
    "talos_full": "talos_data/robots/talos_full_v2.urdf",
    "talos_full_box": "talos_data/robots/talos_full_v2_box.urdf",
    "talos_arm": "talos_data/robots/talos_left_arm.urdf",
    "tiago": "tiago_description/robots/tiago.urdf",
    "tiago_dual": "tiago_description/robots/tiago_dual.urdf",
    "tiago_no_hand": "tiago_description/robots/tiago_no_hand.urdf",
    "tiago_pro": "tiago_pro_description/robots/tiago_pro.urdf",
    "double_pendulum": "double_pendulum_description/urdf/double_pendulum.urdf",
    "double_pendulum_continuous": "double_pendulum_description/urdf/double_pendulum_continuous.urdf",
    "double_pendulum_simple": "double_pendulum_description/urdf/double_pendulum_simple.urdf",
    "asr_twodof": "asr_twodof_description/urdf/TwoDofs.urdf",
    "finger_edu": "finger_edu_description/robots/finger_edu.urdf",
    "allegro_left_hand": "allegro_hand_description/urdf/allegro_left_hand.urdf",
    "allegro_right_hand": "allegro_hand_description/urdf/allegro_right_hand.urdf",
    "romeo": "romeo_description/urdf/romeo.urdf",
    "icub": "icub_description/robots/icub.urdf",
    "icub_reduced": "icub_description/robots/icub_reduced.urdf",
    "pr2": "pr2_description/urdf/pr2.urdf",
    "centauro": "centauro_description/urdf/centauro.urdf",
    "g1": "g1_description/urdf/g1_29dof_rev_1_0.urdf",
    "g1_with_hand": "g1_description/urdf/g1_29dof_with_hand_rev_1_0.urdf",
    "human": "human_description/robots/human.urdf",
    "simple_humanoid": "simple_humanoid_description/urdf/simple_humanoid.urdf",
    "simple_humanoid_classical": "simple_humanoid_description/urdf/simple_humanoid_classical.urdf",
    "a1": "a1_description/urdf/a1.urdf",
    "anymal": "anymal_b_simple_description/robots/anymal.urdf",
    "anymal_kinova": "anymal_b_simple_description/robots/anymal-kinova.urdf",
    "anymal_c": "anymal_c_simple_description/urdf/anymal.urdf",
    "b1": "b1_description/urdf/b1.urdf",
    "b1_z1": "b1_description/urdf/b1-z1.urdf",
    "go1": "go1_description/urdf/go1.urdf",
    "go2": "go2_description/urdf/go2.urdf",
    "hyq": "hyq_description/robots/hyq_no_sensors.urdf",
    "laikago": "laikago_description/urdf/laikago.urdf",
    "solo8": "solo_description/robots/solo.urdf",
    "solo12": "solo_description/robots/solo12.urdf",
    "bolt": "bolt_description/robots/bolt.urdf",
    "quadruped": "quadruped_description/urdf/quadruped.urdf",
    "alexander": "alexander_description/urdf/alexander_v1.lowerBodyOnly.urdf",
    "borinot": "borinot_description/urdf/borinot_flying_arm_2.urdf",
    "hextilt": "hextilt_description/urdf/hextilt_flying_arm_5.urdf",
    "hector": "hector_description/robots/quadrotor_base.urdf",
    "iris": "iris_description/robots/iris.urdf",
}

_ERD_SUBDIR = Path("cmeel.prefix") / "share" / "example-robot-data" / "robots"


def _robots_dir() -> Path:
    """The ``robots`` folder of the installed example-robot-data (no loader module needed)."""
    env = os.environ.get("EXAMPLE_ROBOT_DATA_ROBOTS_DIR")
    if env and Path(env).is_dir():
        return Path(env)
    try:
        p = Path(importlib.metadata.distribution("example-robot-data").locate_file(_ERD_SUBDIR))
        if p.is_dir():
            return p
    except importlib.metadata.PackageNotFoundError:
        pass
    # A copy unpacked without its dist-info still sits beside the other site-packages.
    for entry in [*sys.path, sys.prefix]:
        for cand in (Path(entry) / _ERD_SUBDIR, Path(entry) / "share" / "example-robot-data" / "robots"):
            if cand.is_dir():
                return cand
    raise InputError("example-robot-data is not installed (pip install example-robot-data), "
                     "or set EXAMPLE_ROBOT_DATA_ROBOTS_DIR to its 'robots' folder")


def available_robots() -> list[str]:
    """Names accepted by :func:`robot_urdf_path` whose URDF is installed here."""
    try:
        root = _robots_dir()
    except InputError:
        return []
    return sorted(k for k, rel in ROBOT_FILES.items() if (root / rel).is_file())


def robot_urdf_path(name: str) -> Path:
    """Path of the URDF of example-robot-data robot ``name`` (e.g. ``panda``, ``ur10``)."""
    key = str(name).strip().lower()
    root = _robots_dir()
    rel = ROBOT_FILES.get(key)
    if rel is None or not (root / rel).is_file():
        why = "is not installed in this example-robot-data" if rel is not None else "is not known"
        raise InputError(f"robot '{name}' {why}; available robots: {', '.join(available_robots())}")
    return root / rel


# --------------------------------------------------------------------------------------------
# Robot model


def _batch(x, n: int, what: str) -> tuple[np.ndarray, bool]:
    a = np.asarray(x, dtype=np.float64)
    single = a.ndim == 1
    if single:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"{what} must have shape (T, {n}) or ({n},), got {np.shape(x)}")
    return a, single


class RobotModel:
    """Nominal rigid-body model of the logged joints.

    Attributes: ``joint_names`` (list of n logged joint names, model order), ``n_joints``,
    ``pin_model`` (the reduced Pinocchio model: exactly these joints, everything else locked),
    ``full_model`` (as parsed), ``urdf_path``, ``name`` (example-robot-data name or None),
    ``link_names`` (body frames of the reduced model), ``body_names`` (the link carried by each
    regressor block, ``n_bodies`` of them).
    """

    def __init__(self, full_model: pin.Model, joint_names: Sequence[str] | None = None, *,
                 n_joints: int | None = None, urdf_path: str | os.PathLike | None = None,
                 name: str | None = None, locked_positions: dict[str, float] | None = None):
        self.full_model = full_model
        self.urdf_path = None if urdf_path is None else Path(urdf_path)
        self.name = name
        chosen = self._select_joints(full_model, joint_names, n_joints)
        ref = pin.neutral(full_model)
        for jname, val in (locked_positions or {}).items():
            if not full_model.existJointName(jname):
                raise InputError(f"locked joint '{jname}' is not in the model")
            jid = full_model.getJointId(jname)
            i, nq = full_model.idx_qs[jid], full_model.nqs[jid]
            ref[i:i + nq] = [np.cos(val), np.sin(val)] if nq == 2 else [val]
        lock = [j for j in range(1, full_model.njoints) if j not in chosen]
        self.pin_model = pin.buildReducedModel(full_model, lock, ref) if lock else full_model.copy()
        self.pin_data = self.pin_model.createData()
        self.joint_names = [str(n) for n in self.pin_model.names[1:]]
        expected = [str(full_model.names[j]) for j in chosen]
        if self.joint_names != expected:  # buildReducedModel keeps model order; guard anyway
            raise RuntimeError(f"reduced model joints {self.joint_names} != selection {expected}")
        self.n_joints = len(self.joint_names)
        m = self.pin_model
        if m.nv != self.n_joints:
            raise InputError(f"selected joints {self.joint_names} are not all 1-DOF")
        self.link_names = [f.name for f in m.frames if f.type == pin.FrameType.BODY]
        self.n_bodies = m.njoints - 1
        self.body_names = []
        for j in range(1, m.njoints):
            bodies = [f.name for f in m.frames if f.type == pin.FrameType.BODY and f.parentJoint == j]
            self.body_names.append(bodies[0] if bodies else str(m.names[j]))
        # Index maps from a logged angle vector (n,) to Pinocchio's configuration (nq,).
        self._lin_q, self._lin_j, self._cont_q, self._cont_j = [], [], [], []
        for k, j in enumerate(range(1, m.njoints)):
            if m.nqs[j] == 2:
                self._cont_q.append(m.idx_qs[j])
                self._cont_j.append(k)
            else:
                self._lin_q.append(m.idx_qs[j])
                self._lin_j.append(k)
        self.continuous_joints = [self.joint_names[k] for k in self._cont_j]

    # ---- construction ---------------------------------------------------------------------
    @staticmethod
    def _select_joints(model: pin.Model, joint_names, n_joints) -> list[int]:
        one_dof = [j for j in range(1, model.njoints) if model.nvs[j] == 1]
        names = {str(model.names[j]): j for j in range(1, model.njoints)}
        if joint_names is not None:
            joint_names = [str(s) for s in joint_names]
            unknown = [s for s in joint_names if s not in names]
            if unknown:
                raise InputError(f"joint(s) {unknown} are not in the robot model; its movable joints are "
                                 f"{[str(model.names[j]) for j in one_dof]}", column="joint_names")
            dup = sorted({s for s in joint_names if joint_names.count(s) > 1})
            if dup:
                raise InputError(f"joint(s) {dup} are listed more than once", column="joint_names")
            bad = [s for s in joint_names if model.nvs[names[s]] != 1]
            if bad:
                raise InputError(f"joint(s) {bad} are not 1-DOF joints and cannot be logged as one column",
                                 column="joint_names")
            if n_joints is not None and n_joints != len(joint_names):
                raise InputError(f"the log has {n_joints} joints but {len(joint_names)} joint names are "
                                 f"given: {joint_names}", column="joint_names")
            ids = [names[s] for s in joint_names]
            if ids != sorted(ids):
                expected = [str(model.names[j]) for j in sorted(ids)]
                wrong = [(a, b) for a, b in zip(joint_names, expected) if a != b]
                raise InputError(
                    f"joints are not in the robot model's order: log order {joint_names}, model order "
                    f"{expected} (first mismatch: log has '{wrong[0][0]}' where the model has "
                    f"'{wrong[0][1]}'); reorder the q_/dq_/ddq_/tau_ columns", column="joint_names")
            return ids
        all_names = [str(model.names[j]) for j in one_dof]
        if n_joints is None or n_joints == len(one_dof):
            return one_dof
        if n_joints > len(one_dof):
            raise InputError(f"the log has {n_joints} joints but the robot model has only {len(one_dof)} "
                             f"movable joints: {all_names}", column=f"q_{len(one_dof)}")
        first = one_dof[:n_joints]
        # The first n joints are only a safe guess when they form one serial chain from the root:
        # otherwise (two arms, a head before an arm) the log could mean several different subsets.
        chain = all(model.parents[first[k]] == first[k - 1] for k in range(1, n_joints))
        root = all(model.nvs[a] != 1 for a in _ancestors(model, first[0]))
        if not (chain and root):
            raise InputError(
                f"ambiguous joint selection: the log has {n_joints} joints but the robot model has "
                f"{len(one_dof)} movable joints {all_names}, and the first {n_joints} do not form one "
                f"serial chain; give the joint names (--joint-names or metadata 'joint_names')",
                column="joint_names")
        # Unlogged joints are locked; that is only safe for end joints (gripper fingers): a locked
        # joint with movable joints below it would silently freeze part of the arm the log moves.
        rest = [j for j in one_dof if j not in first]
        inner = [str(model.names[j]) for j in rest if any(j in _ancestors(model, k) for k in rest)]
        if inner:
            raise InputError(
                f"the log has {n_joints} joint(s) but the robot model has {len(one_dof)} movable joints "
                f"{all_names}; joints {inner} would be left out though movable joints follow them: log "
                f"every joint of the arm, or name the logged joints (metadata 'joint_names')",
                column=f"q_{n_joints}")
        return first

    @classmethod
    def from_urdf(cls, path: str | os.PathLike, joint_names: Sequence[str] | None = None, *,
                  n_joints: int | None = None, name: str | None = None,
                  locked_positions: dict[str, float] | None = None) -> "RobotModel":
        """Parse a URDF (fixed base; fixed joints merged by the parser) and reduce it."""
        path = Path(path)
        if not path.is_file():
            raise InputError("URDF file does not exist", file=path)
        try:
            with _parser_output() as said:
                model = pin.buildModelFromUrdf(str(path))
        except Exception as exc:  # Pinocchio raises ValueError/RuntimeError with parser text
            detail = f"; the parser says: {said[0]}" if said and said[0] else ""
            raise InputError(f"cannot parse URDF ({describe(exc)}{detail})", file=path) from None
        return cls(model, joint_names, n_joints=n_joints, urdf_path=path, name=name,
                   locked_positions=locked_positions)

    @classmethod
    def from_name(cls, name: str, joint_names: Sequence[str] | None = None, *,
                  n_joints: int | None = None,
                  locked_positions: dict[str, float] | None = None) -> "RobotModel":
        """Model of example-robot-data robot ``name`` (see :func:`available_robots`)."""
        return cls.from_urdf(robot_urdf_path(name), joint_names, n_joints=n_joints,
                             name=str(name).strip().lower(), locked_positions=locked_positions)

    def __repr__(self) -> str:
        src = self.name or (self.urdf_path.name if self.urdf_path else "?")
        return f"RobotModel({src}, joints={self.joint_names})"

    def check_log(self, n_joints: int, joint_names: Sequence[str] | None = None,
                  file: str | os.PathLike | None = None) -> None:
        """Refuse a log whose joint count or (when given) joint names/order differ from the model."""
        if joint_names is not None:
            joint_names = [str(s) for s in joint_names]
            if joint_names != self.joint_names:
                missing = [s for s in self.joint_names if s not in joint_names]
                extra = [s for s in joint_names if s not in self.joint_names]
                if not missing and not extra:
                    msg = (f"log joints are in a different order than the model: log {joint_names}, "
                           f"model {self.joint_names}")
                else:
                    msg = (f"log joints {joint_names} do not match the model joints {self.joint_names} "
                           f"(not in the log: {missing}; not in the model: {extra})")
                raise InputError(msg, file=file, column="joint_names")
        if n_joints != self.n_joints:
            raise InputError(f"log has {n_joints} joints but the robot model has {self.n_joints}: "
                             f"{self.joint_names}", file=file,
                             column=f"q_{min(n_joints, self.n_joints)}")

    # ---- kinematic conversion -------------------------------------------------------------
    def configuration(self, q) -> np.ndarray:
        """Logged angles ``(T, n)`` -> Pinocchio configurations ``(T, nq)`` (cos/sin for continuous)."""
        qa, single = _batch(q, self.n_joints, "q")
        out = np.empty((qa.shape[0], self.pin_model.nq))
        out[:, self._lin_q] = qa[:, self._lin_j]
        if self._cont_q:
            ang = qa[:, self._cont_j]
            out[:, self._cont_q] = np.cos(ang)
            out[:, np.asarray(self._cont_q) + 1] = np.sin(ang)
        return out[0] if single else out

    def _prepare(self, q, dq, ddq):
        qp = self.configuration(q)
        qp2 = qp[None, :] if qp.ndim == 1 else qp
        T = qp2.shape[0]
        out = []
        for x, what in ((dq, "dq"), (ddq, "ddq")):
            if x is None:
                out.append(np.zeros((T, self.n_joints)))
            else:
                a, _ = _batch(x, self.n_joints, what)
                if a.shape[0] != T:
                    raise ValueError(f"{what} has {a.shape[0]} samples, q has {T}")
                out.append(a)
        return qp2, out[0], out[1], qp.ndim == 1

    # ---- dynamics -------------------------------------------------------------------------
    def rnea(self, q, dq=None, ddq=None) -> np.ndarray:
        """Inverse dynamics tau = M(q) ddq + C(q, dq) dq + g(q), ``(T, n)`` N*m (``(n,)`` for one sample).

        ``dq``/``ddq`` default to zero. A Python loop over ``pin.rnea``: about 3 us per 7-DOF sample.
        """
        qp, v, a, single = self._prepare(q, dq, ddq)
        m, d = self.pin_model, self.pin_data
        out = np.empty((qp.shape[0], self.n_joints))
        for t in range(qp.shape[0]):
            out[t] = pin.rnea(m, d, qp[t], v[t], a[t])
        return out[0] if single else out

    def gravity(self, q) -> np.ndarray:
        """Gravity torque g(q), ``(T, n)`` N*m."""
        qp, _, _, single = self._prepare(q, None, None)
        m, d = self.pin_model, self.pin_data
        out = np.empty((qp.shape[0], self.n_joints))
        for t in range(qp.shape[0]):
            out[t] = pin.computeGeneralizedGravity(m, d, qp[t])
        return out[0] if single else out

    def mass_matrix(self, q) -> np.ndarray:
        """Joint-space inertia matrix M(q), ``(T, n, n)`` kg*m^2."""
        qp, _, _, single = self._prepare(q, None, None)
        m, d = self.pin_model, self.pin_data
        out = np.empty((qp.shape[0], self.n_joints, self.n_joints))
        for t in range(qp.shape[0]):
            M = pin.crba(m, d, qp[t])
            out[t] = np.triu(M) + np.triu(M, 1).T
        return out[0] if single else out

    def dynamic_parameters(self) -> np.ndarray:
        """Nominal inertial parameters of every body, ``(10 * n_bodies,)`` (regressor order)."""
        return np.concatenate([self.pin_model.inertias[j].toDynamicParameters()
                               for j in range(1, self.pin_model.njoints)])

    def regressor(self, q, dq=None, ddq=None) -> np.ndarray:
        """Joint torque regressor Y with tau = Y @ dynamic_parameters(), ``(T, n, 10 * n_bodies)``."""
        qp, v, a, single = self._prepare(q, dq, ddq)
        m, d = self.pin_model, self.pin_data
        out = np.empty((qp.shape[0], self.n_joints, 10 * self.n_bodies))
        for t in range(qp.shape[0]):
            out[t] = pin.computeJointTorqueRegressor(m, d, qp[t], v[t], a[t])
        return out[0] if single else out

    def _frame(self, link: str) -> pin.Frame:
        if not self.pin_model.existFrame(link):
            raise InputError(f"link '{link}' is not in the robot model; links: {self.link_names}")
        return self.pin_model.frames[self.pin_model.getFrameId(link)]

    def link_regressor(self, q, dq=None, ddq=None, link: str | None = None) -> np.ndarray:
        """Regressor of extra mass rigidly attached to ``link``, ``(T, n, 10)``.

        Parameters are expressed in the *link* frame (com in link coordinates, inertia about the
        link origin), so ``tau_extra = link_regressor(...) @ pi_link``. ``link`` is any frame of
        the reduced model (a body, or a fixed frame such as ``panda_hand`` or ``tool0``).
        """
        if link is None:
            raise ValueError("link is required")
        frame = self._frame(link)
        j = frame.parentJoint
        A = transport_matrix(frame.placement)
        Y = self.regressor(q, dq, ddq)
        Yj = Y[..., 10 * (j - 1):10 * j]
        return Yj @ A

    def add_payload(self, link: str, mass: float, com, inertia=None) -> "RobotModel":
        """A copy of this model with a rigid payload on ``link`` (com (3,) m and inertia (3, 3)
        kg*m^2 about the com, both in the link frame). For simulations and tests."""
        frame = self._frame(link)
        I_c = np.zeros((3, 3)) if inertia is None else np.asarray(inertia, dtype=np.float64)
        payload = frame.placement.act(pin.Inertia(float(mass), np.asarray(com, dtype=np.float64), I_c))
        new = object.__new__(RobotModel)
        new.__dict__.update(self.__dict__)
        new.pin_model = self.pin_model.copy()
        new.pin_model.inertias[frame.parentJoint] = new.pin_model.inertias[frame.parentJoint] + payload
        new.pin_data = new.pin_model.createData()
        return new


@contextlib.contextmanager
def _parser_output():
    """Hold back what the C++ URDF parser writes to file descriptor 2 (the error line says it
    instead); yields a list that receives that text, on one line, after the block."""
    said: list[str] = []
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 to protect
        yield said
        return
    with tempfile.TemporaryFile() as sink:
        sys.stderr.flush()
        os.dup2(sink.fileno(), 2)
        try:
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            said.append(one_line(sink.read(4000).decode("utf-8", "replace"), 200))


def _ancestors(model: pin.Model, j: int) -> list[int]:
    out = []
    j = model.parents[j]
    while j > 0:
        out.append(j)
        j = model.parents[j]
    return out


# --------------------------------------------------------------------------------------------
# Loading by the contract's rules


def _log_header(log_path) -> tuple[str | None, dict, int | None]:
    """(file, metadata, number of q_ columns) of a log path or an mmgp.io.RobotLog."""
    if hasattr(log_path, "metadata") and hasattr(log_path, "q"):
        return str(log_path.path), dict(log_path.metadata), int(log_path.q.shape[1])
    cols, meta = read_table_header(log_path)
    nq = sum(1 for c in cols if c.startswith("q_") and c[2:].isdigit())
    return str(log_path), meta, (nq or None)


def load_robot(robot: str | None = None, urdf: str | os.PathLike | None = None,
               joint_names: Sequence[str] | None = None, n_joints: int | None = None,
               log_path=None) -> RobotModel | None:
    """The robot model a command should use, or None (GP only) when nothing names one.

    Flags (``robot``, ``urdf``, ``joint_names``, ``n_joints``) override the log's metadata
    (``robot``, ``urdf`` relative to the log's folder, ``joint_names``). ``log_path`` is a log file
    or an ``mmgp.io.RobotLog``; its joint count and names are checked against the model.
    """
    if robot is not None and urdf is not None:
        raise InputError("give either a robot name or a URDF, not both")
    file, meta, n_log = (None, {}, None) if log_path is None else _log_header(log_path)
    if robot is None and urdf is None:
        if meta.get("robot") and meta.get("urdf"):
            raise InputError("log metadata names both a 'robot' and a 'urdf'; keep one, or choose with "
                             "--robot/--urdf", file=file)
        robot = meta.get("robot") or None
        if meta.get("urdf"):
            u = Path(meta["urdf"])
            urdf = u if u.is_absolute() else Path(file).parent / u
    if robot is None and urdf is None:
        return None
    names = list(joint_names) if joint_names is not None else meta.get("joint_names")
    n = n_joints if n_joints is not None else n_log
    try:
        if robot is not None:
            model = RobotModel.from_name(robot, names, n_joints=n)
        else:
            model = RobotModel.from_urdf(urdf, names, n_joints=n)
    except InputError as exc:
        if file is not None and exc.file is None:
            raise InputError(str(exc), file=file) from None
        raise
    if n_log is not None:
        model.check_log(n_log, meta.get("joint_names") if joint_names is None else None, file=file)
    return model
