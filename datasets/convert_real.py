"""Convert the real robot datasets in the shared folder into contract logs (CONTRACT section 1).

The raw files stay where they are (read-only, never copied into the project); each converter
reads them and writes Parquet logs into ``--out``. Which dataset is which, and its caveats, is in
``<shared>/datasets/<name>/SOURCE.md``; the conventions chosen here:

* ``panda_gaz2019``: Franka Panda exciting trajectory, ~1 kHz with jittered timestamps. ``t`` is
  the logged time; ``q``/``dq``/measured ``tau`` as logged (text files of 7 values per sample,
  ``reshape(-1, 7)``). No accelerations were logged: ``ddq`` is left out so mmgp estimates it,
  unless ``ddq="savgol"``: dq is interpolated on a uniform 1 ms grid, differentiated with a
  Savitzky-Golay filter (quadratic, 41 samples = 40 ms) and interpolated back. Robot ``panda``.
* ``polydoros_ur10_pickplace``: UR10 at 125 Hz (``t = k * 0.008`` s, the file has no time
  column), columns q | dq | ddq | tau, joint order = the classic UR10 URDF order. Robot ``ur10``.
  The authors state a 5 kg object was carried; nothing in the file says when. The file's ddq is
  exactly the backward difference of dq divided by 0.0083 s although q advances by 0.008 * dq
  per row, so ddq is rescaled by 0.0083/0.008 unless ``fix_ddq=False``. Caveats kept as they
  are: q, dq and tau are rounded to 1e-4; while moving, q repeats the previous row about every
  10th row (a stale sample); tau does not behave like N*m joint torques of the nominal UR10
  (see tests/test_convert_real.py).
* ``ias_barrett``, ``ias_sarcos`` (and the simulated ``ias_sl_barrett``, ``ias_sl_sarcos``):
  the published Nguyen-Tuong train/test splits as two GP-only logs (no robot model):
  ``<name>_train.parquet`` and ``<name>_test.parquet``. The files have no time and their rate is
  not stated: ``t`` is the row index times the row spacing estimated from the data itself
  (least squares of diff(q) on the mean of consecutive dq), so the time axis has roughly the
  right scale for any time-based processing. ``drop_test_duplicates=True`` removes test rows
  that are exact copies of training rows (2,785 of the real SARCOS test rows are).
* ``iiwa14_lasa_subset``: 750 rows q | dq | ddq | tau of a KUKA iiwa 14, every 20th row of a
  longer log; ``t`` from the estimated row spacing as above. The shipped URDF is copied next to
  the log and named in the metadata (``urdf``, relative to the log's folder). The file's torque
  sign is the opposite of the actuation torque (its joint-2 torque anti-correlates with the
  URDF's gravity torque at -0.999), so ``tau`` is negated unless ``flip_tau=False``.

The shared folder is ``$MMGP_SHARED_DATASETS``, else ``<repo>/../shared/datasets``.

Command line: ``python datasets/convert_real.py NAME [NAME...] --out DIR [--skip-missing]``;
NAME may be ``all``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from mmgp.data.outputs import write_table

# Converter name -> folder of the shared datasets it needs.
FOLDERS = {
    "panda_gaz2019": "panda_gaz2019",
    "polydoros_ur10_pickplace": "polydoros_ur10_pickplace",
    "ias_barrett": "ias_nguyen_tuong",
    "ias_sarcos": "ias_nguyen_tuong",
    "ias_sl_barrett": "ias_nguyen_tuong",
    "ias_sl_sarcos": "ias_nguyen_tuong",
    "iiwa14_lasa_subset": "iiwa14_lasa_subset",
}

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
UR_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
             "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
IIWA_JOINTS = [f"iiwa_joint_{i}" for i in range(1, 8)]
UR10_DT = 0.008  # s; diff(q) = 0.008 * dq (least squares on moving rows: 0.00799)
UR10_DDQ_DT = 0.0083  # s; the file's ddq is exactly diff(dq) / 0.0083


class DatasetMissing(FileNotFoundError):
    """The shared dataset folder (or a file in it) is absent."""


def shared_datasets_dir() -> Path:
    """The shared datasets folder: ``$MMGP_SHARED_DATASETS`` or ``<repo>/../shared/datasets``."""
    env = os.environ.get("MMGP_SHARED_DATASETS")
    return Path(env) if env else (REPO.parent / "shared" / "datasets")


def dataset_dir(name: str) -> Path:
    if name not in FOLDERS:
        raise KeyError(f"unknown dataset '{name}'; known: {', '.join(FOLDERS)}")
    return shared_datasets_dir() / FOLDERS[name]


def _need(path: Path) -> Path:
    if not path.exists():
        raise DatasetMissing(f"{path} is absent (set MMGP_SHARED_DATASETS to the shared datasets folder)")
    return path


def _frame(t, q, tau, dq=None, ddq=None) -> pd.DataFrame:
    n = q.shape[1]
    cols = {"t": np.asarray(t, dtype=np.float64)}
    for kind, arr in (("q", q), ("dq", dq), ("ddq", ddq), ("tau", tau)):
        if arr is not None:
            for j in range(n):
                cols[f"{kind}_{j}"] = np.asarray(arr[:, j], dtype=np.float64)
    return pd.DataFrame(cols)


def _write(path: Path, df: pd.DataFrame, *, robot=None, urdf=None, joint_names=None,
           source: str = "", notes: str = "") -> Path:
    meta = {"source": source, "notes": notes}
    if robot is not None:
        meta["robot"] = robot
    if urdf is not None:
        meta["urdf"] = str(urdf)
    if joint_names is not None:
        meta["joint_names"] = json.dumps(list(joint_names))
    write_table(path, df, metadata=meta)
    return path


def estimate_row_spacing(q: np.ndarray, dq: np.ndarray, max_step: float = 0.2) -> float:
    """Seconds between consecutive rows, from diff(q) ~ dt * mean(dq[k], dq[k+1]) (least squares).

    Row pairs whose q jumps by more than ``max_step`` rad (segment boundaries) are left out.
    """
    dqq = np.diff(q, axis=0)
    v = 0.5 * (dq[1:] + dq[:-1])
    ok = np.abs(dqq).max(axis=1) < max_step
    return float((dqq[ok] * v[ok]).sum() / (v[ok] ** 2).sum())


def savgol_ddq(t: np.ndarray, dq: np.ndarray, dt: float = 1e-3, window: int = 41) -> np.ndarray:
    """ddq (T, n) rad/s^2 from dq sampled at irregular times ``t``: Savitzky-Golay on a uniform grid."""
    from scipy.signal import savgol_filter

    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    dq_g = np.stack([np.interp(grid, t, dq[:, j]) for j in range(dq.shape[1])], axis=1)
    dd_g = savgol_filter(dq_g, window, 2, deriv=1, delta=dt, axis=0, mode="interp")
    return np.stack([np.interp(t, grid, dd_g[:, j]) for j in range(dq.shape[1])], axis=1)


# --------------------------------------------------------------------------------------------


def convert_panda_gaz2019(out_dir: Path, ddq: str | None = None) -> list[Path]:
    d = _need(dataset_dir("panda_gaz2019")) / "rbt_log"
    t = np.loadtxt(_need(d / "exciting_traj_time.txt"))
    arrays = {k: np.loadtxt(_need(d / f"exciting_traj_{k}.txt")).reshape(-1, 7)
              for k in ("positions", "velocity", "torques")}
    q, dq, tau = arrays["positions"], arrays["velocity"], arrays["torques"]
    if not (len(t) == len(q) == len(dq) == len(tau)):
        raise ValueError(f"panda_gaz2019: row counts differ: t {len(t)}, q {len(q)}, dq {len(dq)}, tau {len(tau)}")
    acc = None
    notes = "ddq not logged (absent: estimate it)"
    if ddq == "savgol":
        acc = savgol_ddq(t, dq)
        notes = "ddq: Savitzky-Golay derivative of dq (1 ms grid, quadratic, 41 samples)"
    elif ddq is not None:
        raise ValueError(f"ddq must be None or 'savgol', got {ddq!r}")
    return [_write(out_dir / "panda_gaz2019.parquet", _frame(t, q, tau, dq, acc), robot="panda",
                   joint_names=PANDA_JOINTS, source="Gaz et al. RA-L 2019, exciting trajectory 1",
                   notes=notes + "; tau: measured joint torques")]


def convert_polydoros_ur10(out_dir: Path, fix_ddq: bool = True) -> list[Path]:
    from scipy.io import loadmat

    A = loadmat(_need(dataset_dir("polydoros_ur10_pickplace") / "URpickNplace.mat"))["urPicknPlace"]
    A = np.asarray(A, dtype=np.float64)
    q, dq, acc, tau = A[:, 0:6], A[:, 6:12], A[:, 12:18], A[:, 18:24]
    t = np.arange(len(A)) * UR10_DT
    if fix_ddq:
        # The file's ddq is exactly (dq[k] - dq[k-1]) / 0.0083 while q advances by dq * 0.008
        # per row: rescale so that ddq is the backward difference at the true 8 ms step.
        acc = acc * (UR10_DDQ_DT / UR10_DT)
    return [_write(out_dir / "polydoros_ur10_pickplace.parquet", _frame(t, q, tau, dq, acc),
                   robot="ur10", joint_names=UR_JOINTS,
                   source="Polydoros et al. IROS 2015, UR10 pick and place (urPicknPlace)",
                   notes="125 Hz, t synthesised; 5 kg object carried part of the time (when: not stated); "
                         + ("ddq rescaled by 0.0083/0.008 (file used a 8.3 ms step)" if fix_ddq
                            else "ddq as in the file (= diff(dq) / 0.0083)"))]


def convert_ias(name: str, out_dir: Path, drop_test_duplicates: bool = False) -> list[Path]:
    from scipy.io import loadmat

    files = {"ias_barrett": "ias_real_barrett_data.mat", "ias_sarcos": "ias_sarcos_data.mat",
             "ias_sl_barrett": "ias_sl_barrett_data.mat", "ias_sl_sarcos": "ias_sl_sarcos_data.mat"}
    m = loadmat(_need(dataset_dir(name) / files[name]))
    out = []
    train_rows = None
    for split in ("train", "test"):
        X = np.asarray(m[f"X_{split}"], dtype=np.float64)
        Y = np.asarray(m[f"Y_{split}"], dtype=np.float64)
        note = ""
        if split == "train":
            train_rows = {r.tobytes() for r in np.concatenate([X, Y], axis=1)}
        elif drop_test_duplicates:
            keep = np.array([r.tobytes() not in train_rows for r in np.concatenate([X, Y], axis=1)])
            note = f"; {int((~keep).sum())} test rows identical to training rows dropped"
            X, Y = X[keep], Y[keep]
        q, dq, acc = X[:, 0:7], X[:, 7:14], X[:, 14:21]
        dt = estimate_row_spacing(q, dq)
        t = np.arange(len(X)) * dt
        out.append(_write(out_dir / f"{name}_{split}.parquet", _frame(t, q, Y, dq, acc),
                          source=f"Nguyen-Tuong/Seeger/Peters {files[name]} ({split} split)",
                          notes=f"GP only (no robot model); rate not stated: t = row * {dt:.5f} s "
                                f"(row spacing estimated from q and dq){note}"))
    return out


def convert_iiwa14(out_dir: Path, flip_tau: bool = True) -> list[Path]:
    d = _need(dataset_dir("iiwa14_lasa_subset"))
    A = np.loadtxt(_need(d / "gprProcessedActualData.csv"), delimiter=",")
    q, dq, acc, tau = A[:, 0:7], A[:, 7:14], A[:, 14:21], A[:, 21:28]
    if flip_tau:
        # The file's torques are the negative of what the joints must supply (sensor sign
        # convention): -tau matches the shipped URDF's gravity torque with correlation 0.99
        # on joints 2 and 4, +tau anti-correlates.
        tau = -tau
    dt = estimate_row_spacing(q, dq)
    t = np.arange(len(A)) * dt
    out_dir.mkdir(parents=True, exist_ok=True)
    urdf = out_dir / "iiwa14.urdf"
    shutil.copyfile(_need(d / "iiwa14.urdf"), urdf)
    return [urdf, _write(out_dir / "iiwa14_lasa_subset.parquet", _frame(t, q, tau, dq, acc),
                         urdf="iiwa14.urdf", joint_names=IIWA_JOINTS,
                         source="EPFL LASA iiwa 14 subset (Uebersax), every 20th row",
                         notes=f"rate not stated: t = row * {dt:.5f} s (row spacing estimated from q and dq); "
                               + ("tau negated (file sign convention is the opposite of the actuation torque)"
                                  if flip_tau else "tau as in the file (opposite sign convention)"))]


def convert(name: str, out_dir: str | os.PathLike, **options) -> list[Path]:
    """Write the contract log(s) of dataset ``name`` into ``out_dir``; returns the files written.

    Raises :class:`DatasetMissing` when the shared folder or a file of it is absent.
    Options: ``ddq`` (panda_gaz2019: None or "savgol"), ``drop_test_duplicates`` (ias_*),
    ``flip_tau`` (iiwa14_lasa_subset, default True), ``fix_ddq`` (polydoros_ur10_pickplace,
    default True).
    """
    out_dir = Path(out_dir)
    if name not in FOLDERS:
        raise KeyError(f"unknown dataset '{name}'; known: {', '.join(FOLDERS)}")
    _need(dataset_dir(name))
    out_dir.mkdir(parents=True, exist_ok=True)
    if name == "panda_gaz2019":
        return convert_panda_gaz2019(out_dir, ddq=options.get("ddq"))
    if name == "polydoros_ur10_pickplace":
        return convert_polydoros_ur10(out_dir, fix_ddq=options.get("fix_ddq", True))
    if name.startswith("ias_"):
        return convert_ias(name, out_dir, drop_test_duplicates=options.get("drop_test_duplicates", False))
    return convert_iiwa14(out_dir, flip_tau=options.get("flip_tau", True))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("names", nargs="+", metavar="NAME", help=f"one of: {', '.join(FOLDERS)}, or all")
    p.add_argument("--out", required=True, type=Path, help="folder for the Parquet logs")
    p.add_argument("--skip-missing", action="store_true",
                   help="exit 0 with a message when a dataset folder is absent")
    p.add_argument("--ddq", choices=["savgol"], default=None,
                   help="panda_gaz2019: estimate ddq with a Savitzky-Golay filter instead of leaving it out")
    p.add_argument("--drop-test-duplicates", action="store_true",
                   help="ias_*: leave out test rows that also appear in the training split")
    a = p.parse_args(argv)
    names = list(FOLDERS) if a.names == ["all"] else a.names
    unknown = [n for n in names if n not in FOLDERS]
    if unknown:
        print(f"error: unknown dataset(s) {unknown}; known: {', '.join(FOLDERS)}", file=sys.stderr)
        return 2
    status = 0
    for name in names:
        try:
            files = convert(name, a.out, ddq=a.ddq, drop_test_duplicates=a.drop_test_duplicates)
        except DatasetMissing as exc:
            print(f"{name}: skipped: {exc}", file=sys.stderr)
            if not a.skip_missing:
                status = 1
            continue
        for f in files:
            print(f"{name}: wrote {f}")
    return status


if __name__ == "__main__":
    sys.exit(main())
