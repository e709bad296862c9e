"""The shared datasets stored as text: Panda (Gaz 2019), Staubli TX40 and TIAGo (FIGAROH), iiwa 14.

Conventions (each also written into the log's ``notes`` metadata):

* ``panda_gaz2019``: exciting trajectory at ~1 kHz with jittered stamps; ``t`` as logged,
  q | dq | measured tau (files of 7 values per sample, ``reshape(-1, 7)``); no ddq (mmgp
  estimates it); robot ``panda``.
* ``staubli_tx40_figaroh``: MOTOR-side encoder positions and motor torques at 5 kHz
  (``t = row * 0.0002`` s). With the reduction matrix R = diag(32, 32, 45, -48, 45, 32) plus the
  wrist coupling R[5, 4] = 32 (motor 6 turns with joints 5 and 6), joint positions are
  q = R^-1 m, then joint 2 -pi/2 and joint 3 +pi/2 (FIGAROH's TX40 tools and config); joint
  torques are tau = R^T tau_m (the same power flows through motors and joints, so the coupling
  puts motor 6's torque on joint 5 as well). The coupled wrist's extra motor inertia and friction
  (driven by dq5 + dq6) stay in the data: they are not one joint's effect, so mmgp's GP, not a
  per-joint physics term, absorbs them. The URDF is copied next to the log.
* ``tiago_figaroh``: joint_states at 100 Hz, three CSVs with the same ``t``; ``effort`` is
  motor current, turned into joint torque with FIGAROH's constants (gear ratio times motor torque
  constant: arm 1-2: 100 * 0.136, arm 3-4: 100 * -0.087, arm 5-7: 336 * -0.0613 N*m/A; torso
  force + 9.81 * the mass the torso lifts, from the tiago model) unless option ``raw_effort``.
  Robot ``tiago``.
* ``iiwa14_lasa_subset``: 750 rows q | dq | ddq | tau (every 20th row of a longer log); ``t``
  from the estimated row spacing; the file's torque sign is the opposite of the actuation
  torque (-tau matches the shipped URDF's gravity torque, +tau anti-correlates), so ``tau`` is
  negated unless option ``flip_tau`` is false. The URDF is copied next to the log.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from ..base import ConvertedLog
from ..tables import numeric_block, read_table
from .mat_sets import estimate_row_spacing

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
IIWA_JOINTS = [f"iiwa_joint_{i}" for i in range(1, 8)]
TX40_RATIOS = np.array([32.0, 32.0, 45.0, -48.0, 45.0, 32.0])
TX40_DT = 0.0002  # s (5 kHz, TX40_config.yaml)
TIAGO_TORQUE_PER_EFFORT = {"arm_1_joint": 100 * 0.136, "arm_2_joint": 100 * 0.136,
                           "arm_3_joint": 100 * -0.087, "arm_4_joint": 100 * -0.087,
                           "arm_5_joint": 336 * -0.0613, "arm_6_joint": 336 * -0.0613,
                           "arm_7_joint": 336 * -0.0613, "torso_lift_joint": 1.0}
GRAVITY = 9.81  # m/s^2, as FIGAROH uses for the torso


def _text_matrix(path: Path, width: int, delimiter: str | None = None) -> np.ndarray:
    if not path.is_file():
        raise InputError("file is missing from the dataset folder", file=path)
    try:
        A = np.loadtxt(path, delimiter=delimiter, ndmin=2 if width > 1 else 1)
    except ValueError as exc:
        raise InputError(f"expected numbers only ({exc})", file=path) from None
    if width > 1 and A.shape[1] != width:
        raise InputError(f"expected {width} columns, found {A.shape[1]}", file=path)
    return A


def read_panda(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    d = folder / "rbt_log"
    t = _text_matrix(d / "exciting_traj_time.txt", 1)
    q, dq, tau = (_text_matrix(d / f"exciting_traj_{k}.txt", 1) for k in ("positions", "velocity", "torques"))
    for arr, k in ((q, "positions"), (dq, "velocity"), (tau, "torques")):
        if arr.size != 7 * t.size:
            raise InputError(f"{arr.size} values for {t.size} time stamps: expected 7 per stamp",
                             file=d / f"exciting_traj_{k}.txt")
    return [ConvertedLog.of(name="panda_gaz2019", t=t, q=q.reshape(-1, 7), dq=dq.reshape(-1, 7),
                         tau=tau.reshape(-1, 7), joint_names=list(PANDA_JOINTS), robot="panda",
                         source="Gaz et al. RA-L 2019, exciting trajectory 1",
                         notes=["ddq not logged (left out: mmgp estimates it)", "tau: measured joint torques"])]


def tx40_matrix() -> np.ndarray:
    """Motor angles = R @ joint angles (TX40 reductions, wrist coupling motor 6 <- joint 5)."""
    R = np.diag(TX40_RATIOS)
    R[5, 4] = TX40_RATIOS[5]
    return R


def read_staubli(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    pos, cur = folder / "pos_read_data.csv", folder / "curr_data.csv"
    cols = [f"Joint_{i}" for i in range(1, 7)]
    m = numeric_block(read_table(pos), cols, pos)
    tau_m = numeric_block(read_table(cur), cols, cur)
    if m.shape != tau_m.shape:
        raise InputError(f"{len(m)} position rows but {len(tau_m)} current rows", file=cur)
    R = tx40_matrix()
    q = np.linalg.solve(R, m.T).T
    q[:, 1] -= np.pi / 2
    q[:, 2] += np.pi / 2
    return [ConvertedLog.of(name="staubli_tx40", t=np.arange(len(q)) * TX40_DT, q=q, tau=tau_m @ R,
                         joint_names=[f"joint_{i}" for i in range(1, 7)], urdf=folder / "tx40_mdh_modified.urdf",
                         source="FIGAROH Staubli TX40 identification data (motor side)",
                         notes=["5 kHz: t = row * 0.0002 s", "q = R^-1 motor angles (coupled wrist), joint 2 "
                                "-pi/2, joint 3 +pi/2; tau = R^T motor torques", "dq, ddq not logged "
                                "(left out: mmgp estimates them)"])]


def _tiago_torso_mass(names: list[str]) -> float:
    import pinocchio as pin

    from ...physics.robot import RobotModel

    model = RobotModel.from_name("tiago", names).pin_model
    data = model.createData()
    pin.computeSubtreeMasses(model, data)
    return float(data.mass[model.getJointId("torso_lift_joint")])


def read_tiago(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    tables, names = {}, None
    for kind in ("position", "velocity", "effort"):
        path = folder / f"tiago_{kind}.csv"
        df = read_table(path, {"delimiter": ","})
        joints = [c.lstrip("- ").removesuffix(f"_{kind}") for c in df.columns[1:]]
        if names is not None and joints != names:
            raise InputError(f"joint columns {joints} differ from tiago_position.csv's {names}", file=path)
        names, tables[kind] = joints, numeric_block(df, list(df.columns), path)
    if not all(np.array_equal(tables["position"][:, 0], tables[k][:, 0]) for k in ("velocity", "effort")):
        raise InputError("the three files' t columns differ", file=folder)
    effort = tables["effort"][:, 1:]
    notes = ["dq from the velocity file; ddq not logged (left out: mmgp estimates it)"]
    if options.get("raw_effort", False):
        tau = effort
        notes.append("tau = effort as logged (motor current, not N*m)")
    else:
        tau = effort * np.array([TIAGO_TORQUE_PER_EFFORT[j] for j in names])
        mass = _tiago_torso_mass(names)
        tau[:, names.index("torso_lift_joint")] += GRAVITY * mass
        notes.append(f"tau = effort * gear ratio * motor torque constant (FIGAROH); torso + 9.81 * {mass:.3f} kg")
    return [ConvertedLog.of(name="tiago_figaroh", t=tables["position"][:, 0], q=tables["position"][:, 1:],
                         dq=tables["velocity"][:, 1:], tau=tau, joint_names=names, robot="tiago",
                         source="FIGAROH TIAGo dynamic identification log (joint_states)", notes=notes)]


def read_iiwa(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    A = _text_matrix(folder / "gprProcessedActualData.csv", 28, delimiter=",")
    q, dq, ddq, tau = A[:, 0:7], A[:, 7:14], A[:, 14:21], A[:, 21:28]
    flip = options.get("flip_tau", True)
    if flip:
        # sensor sign convention: -tau matches the URDF's gravity torque (corr 0.99 on joints 2, 4)
        tau = -tau
    dt = estimate_row_spacing(q, dq)
    return [ConvertedLog.of(name="iiwa14_lasa_subset", t=np.arange(len(A)) * dt, q=q, dq=dq, ddq=ddq, tau=tau,
                         joint_names=list(IIWA_JOINTS), urdf=folder / "iiwa14.urdf",
                         source="EPFL LASA iiwa 14 subset (Uebersax), every 20th row",
                         notes=[f"rate not stated: t = row * {dt:.6f} s (row spacing estimated from q and dq)",
                                "tau negated (the file's sign is opposite to the actuation torque)" if flip
                                else "tau as in the file (opposite sign convention)"])]
