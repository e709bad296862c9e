"""The shared datasets stored as MATLAB files: IAS splits, GPML SARCOS, Polydoros UR10 and Baxter.

Conventions (each also written into the log's ``notes`` metadata):

* ``ias_nguyen_tuong``: the published Nguyen-Tuong train/test splits (real and SL-simulated
  Barrett WAM and SARCOS), one GP-only log per split (no robot model); parts
  ``ias_barrett_{train,test}``, ``ias_sarcos_*``, ``ias_sl_barrett_*``, ``ias_sl_sarcos_*``.
  No time column and no stated rate: ``t`` = row * the row spacing estimated from the data
  (:func:`estimate_row_spacing`). Option ``drop_test_duplicates`` leaves out test rows that
  are exact copies of training rows (2,785 of the real SARCOS test rows are).
* ``sarcos``: the GPML test file, 4,449 rows q | dq | ddq | tau, GP only, ``t`` as above.
* ``polydoros_ur10_pickplace``: UR10 at 125 Hz (``t = k * 0.008`` s), q | dq | ddq | tau in the
  classic UR10 URDF joint order, robot ``ur10``. The file's ddq is exactly the backward
  difference of dq divided by 0.0083 s while q advances by 0.008 * dq per row, so ddq is rescaled
  by 0.0083/0.008 unless option ``fix_ddq`` is false.
* ``polydoros_baxter_forward``: ten trajectories (parts ``baxter_traj01`` ..), q | dq | tau (and
  next-step q, dq, not used: they equal the next row). The joint columns are in the order Baxter
  publishes them (alphabetical: e0, e1, s0, s1, w0, w1, w2): in model order
  (s0, s1, e0, e1, w0, w1, w2) the nominal gravity torque correlates with tau at 0.99-1.0 on
  e0, e1, w0, w1, in file order at -0.25..0.84. Which arm is not stated; the left arm's names are
  used (the two arms are mirror images: their rigid-body torques as functions of their joint
  angles are the same). ``t`` = row * row spacing estimated from all trajectories (about 100 Hz).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from ..base import ConvertedLog

IAS_FILES = {"ias_barrett": "ias_real_barrett_data.mat", "ias_sarcos": "ias_sarcos_data.mat",
             "ias_sl_barrett": "ias_sl_barrett_data.mat", "ias_sl_sarcos": "ias_sl_sarcos_data.mat"}
UR_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
             "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
UR10_DT = 0.008  # s; diff(q) = 0.008 * dq (least squares on moving rows: 0.00799)
UR10_DDQ_DT = 0.0083  # s; the file's ddq is exactly diff(dq) / 0.0083
BAXTER_FILE_ORDER = ["e0", "e1", "s0", "s1", "w0", "w1", "w2"]
BAXTER_MODEL_ORDER = ["s0", "s1", "e0", "e1", "w0", "w1", "w2"]


def load_mat(path: Path, variables: list[str] | None = None) -> dict[str, np.ndarray]:
    """Variables of a MATLAB file as float64 arrays (all when ``variables`` is None)."""
    from scipy.io import loadmat

    if not path.is_file():
        raise InputError("file is missing from the dataset folder", file=path)
    try:
        mat = loadmat(path)
    except (ValueError, OSError, NotImplementedError) as exc:
        raise InputError(f"unreadable MATLAB file ({type(exc).__name__}: {exc})", file=path) from None
    names = variables or [k for k in mat if not k.startswith("__")]
    missing = [v for v in names if v not in mat]
    if missing:
        raise InputError(f"variable(s) {missing} not in the file", file=path)
    return {v: np.asarray(mat[v], dtype=np.float64) for v in names}


def _columns(A: np.ndarray, width: int, path: Path, what: str) -> np.ndarray:
    if A.ndim != 2 or A.shape[1] < width:
        raise InputError(f"{what}: expected at least {width} columns, found shape {A.shape}", file=path)
    return A


def estimate_row_spacing(q: np.ndarray, dq: np.ndarray, max_step: float = 0.2) -> float:
    """Seconds between consecutive rows, from diff(q) ~ dt * mean(dq[k], dq[k+1]) (least squares).

    Row pairs whose q jumps by more than ``max_step`` rad (segment boundaries) are left out.
    """
    dqq = np.diff(q, axis=0)
    v = 0.5 * (dq[1:] + dq[:-1])
    ok = np.abs(dqq).max(axis=1) < max_step
    return float((dqq[ok] * v[ok]).sum() / (v[ok] ** 2).sum())


def _gp_only(name: str, X: np.ndarray, Y: np.ndarray, source: str, notes: list[str]) -> ConvertedLog:
    q, dq, ddq = X[:, 0:7], X[:, 7:14], X[:, 14:21]
    dt = estimate_row_spacing(q, dq)
    notes = [f"GP only (no robot model); rate not stated: t = row * {dt:.6f} s (row spacing estimated "
             "from q and dq)"] + notes
    return ConvertedLog.of(name=name, t=np.arange(len(X)) * dt, q=q, dq=dq, ddq=ddq, tau=Y,
                        source=source, notes=notes)


def read_ias(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    names = [k for k, f in IAS_FILES.items() if file is None or f == file.name]
    present = [k for k in names if (folder / IAS_FILES[k]).is_file()]
    if not present:
        raise InputError(f"none of {[IAS_FILES[k] for k in names]} is in the folder", file=folder)
    parts = []
    for key in present:
        path = folder / IAS_FILES[key]
        m = load_mat(path, ["X_train", "Y_train", "X_test", "Y_test"])
        train_rows = {r.tobytes() for r in np.concatenate([m["X_train"], m["Y_train"]], axis=1)}
        for split in ("train", "test"):
            X, Y = _columns(m[f"X_{split}"], 21, path, f"X_{split}"), m[f"Y_{split}"]
            notes = []
            if split == "test" and options.get("drop_test_duplicates", False):
                keep = np.array([r.tobytes() not in train_rows for r in np.concatenate([X, Y], axis=1)])
                notes.append(f"{int((~keep).sum())} test rows identical to training rows dropped")
                X, Y = X[keep], Y[keep]
            parts.append(_gp_only(f"{key}_{split}", X, Y,
                                  f"Nguyen-Tuong/Seeger/Peters {path.name} ({split} split)", notes))
    return parts


def read_sarcos(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    path = folder / "sarcos_inv_test.mat"
    A = _columns(load_mat(path, ["sarcos_inv_test"])["sarcos_inv_test"], 28, path, "sarcos_inv_test")
    return [_gp_only("sarcos_gpml_test", A[:, :21], A[:, 21:28], "GPML SARCOS inverse dynamics, test file",
                     ["torque units not documented (as in the file)"])]


def read_ur10(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    path = folder / "URpickNplace.mat"
    A = _columns(load_mat(path, ["urPicknPlace"])["urPicknPlace"], 24, path, "urPicknPlace")
    ddq = A[:, 12:18]
    fix = options.get("fix_ddq", True)
    if fix:
        # q advances by dq * 0.008 per row, but the file's ddq divides by 0.0083
        ddq = ddq * (UR10_DDQ_DT / UR10_DT)
    notes = ["125 Hz: t = row * 0.008 s (the file has no time); a 5 kg object is carried part of the "
             "time (when: not stated)",
             "ddq rescaled by 0.0083/0.008 (the file used an 8.3 ms step)" if fix
             else "ddq as in the file (= diff(dq) / 0.0083)"]
    return [ConvertedLog.of(name="polydoros_ur10_pickplace", t=np.arange(len(A)) * UR10_DT, q=A[:, 0:6],
                         dq=A[:, 6:12], ddq=ddq, tau=A[:, 18:24], joint_names=list(UR_JOINTS), robot="ur10",
                         source="Polydoros et al. IROS 2015, UR10 pick and place (urPicknPlace)", notes=notes)]


def read_baxter(folder: Path, file: Path | None, options: dict[str, Any]) -> list[ConvertedLog]:
    path = folder / "BaxterDirectDynamics.mat"
    mat = load_mat(path)
    keys = sorted((k for k in mat if k.startswith("baxtertraj")), key=lambda k: int(k[len("baxtertraj"):]))
    if not keys:
        raise InputError("no baxtertraj<k> variables in the file", file=path)
    trajs = {k: _columns(mat[k], 21, path, k) for k in keys}
    perm = [BAXTER_FILE_ORDER.index(j) for j in BAXTER_MODEL_ORDER]
    both = [(A[:, 0:7], A[:, 7:14]) for A in trajs.values()]
    dt = estimate_row_spacing(np.concatenate([q for q, _ in both]), np.concatenate([v for _, v in both]))
    names = [f"left_{j}" for j in BAXTER_MODEL_ORDER]
    notes = [f"rate not stated: t = row * {dt:.6f} s (row spacing estimated from q and dq of all trajectories)",
             "columns reordered from the file's e0,e1,s0,s1,w0,w1,w2 to model order; left-arm names "
             "(which arm is not stated)", "ddq not logged (left out: mmgp estimates it)"]
    return [ConvertedLog.of(name=f"baxter_traj{int(k[len('baxtertraj'):]):02d}", t=np.arange(len(A)) * dt,
                         q=A[:, 0:7][:, perm], dq=A[:, 7:14][:, perm], tau=A[:, 14:21][:, perm],
                         joint_names=names, robot="baxter", notes=list(notes),
                         source=f"Polydoros & Nalpantidis IROS 2016, Baxter {k}")
            for k, A in trajs.items()]
