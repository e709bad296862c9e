"""FIGAROH head-to-head on the real Staubli TX40 and TIAGo: their split, their metric, their figures.

FIGAROH's figures (``thanhndv212/figaroh-examples``,
``docs/development/log-cholesky-dataset-validation-2026-10-02.md``) come from the runner at their tag
``evidence/12-log-cholesky-2026-10-02``, ``benchmarks/log_cholesky_datasets.py``, which scores with
``metrics`` of figaroh-plus ``docs/development/spikes/log_cholesky_feasibility.py``::

    validation = (Yv @ p - tauv).reshape(nv, -1)
    "heldout_rmse": float(np.sqrt(np.mean(validation**2))),

on the samples ``np.unique(np.linspace(20, N - 21, min(MAX_SAMPLES, N - 40), dtype=int))``
(``MAX_SAMPLES = 240``) of each processed partition of N samples: training rows TX40 0:24750,
TIAGo 921:4149; validation rows TX40 29250:45000, TIAGo 4736:6791 (``mmgp.evaluation.metrics``:
``figaroh_samples``, ``aggregate_rmse``, ``FIGAROH_ROWS``, ``FIGAROH_FIGURES``). Each partition is
processed on its own, as their loaders do (written here from their description, not copied):

* TX40 (``examples/staubli_tx40/utils/staubli_tx40_tools.py``): joint angles from the motor
  encoders (the converter's reduction matrix with the wrist coupling, joint 2 -pi/2, joint 3
  +pi/2); a 5-sample median filter then a zero-phase order-4 Butterworth low-pass at 100 Hz
  (sampling 5 kHz); velocity and acceleration by ``np.gradient`` against ``linspace(0, n * ts, n)``;
  joint torques ``R_tau @ motor torque`` unfiltered; 20 samples cut at each end of every channel.
* TIAGo (their loader at the tag, ``filter_params`` recorded in their results JSON): position and
  logged velocity median + Butterworth filtered with order 4, cutoff 2 Hz, declared sample rate
  500 Hz (the log is 100 Hz: their audit notes it); acceleration by ``np.gradient`` of the
  filtered velocity against the recorded ``t``; effort times gear ratio times motor constant
  (``mmgp.convert``'s constants), torso + 9.81 N/kg x the mass the torso lifts in their URDF
  (``tiago_48_schunk.urdf``, the model they score; its sha256 is checked); no edge cut.

Their nominal figures are reproduced here to 1e-8 (printed as a check: 10.364936 and 3.865181),
so the states and torques below are theirs. Our side, as a user: the training rows written as a
log (TIAGo's torso channel in their convention), ``mmgp diagnose LOG --out DIR`` with default
settings on it (the nominal model: their URDF), then on their validation states the model the
diagnosis writes: MuJoCo inverse dynamics of ``corrected.xml`` (``mmgp.sim.inverse_dynamics``, dry
friction as the diagnosis fits it, frictionloss * tanh(dq / v_s) with its v_s, findings.json
``info.v_s``) plus what MJCF cannot express, as the report tells the user to apply it: a
torque-sensor offset added to the model's torque, an encoder offset subtracted from the angle,
load-dependent friction's beta * |load| * tanh(dq / v_s) with the corrected model's torque as the
load. The row ``found_physics_sign`` applies sign(dq) instead (the law used before 2026-11-28;
half of TX40's validation samples stand still, where the two differ by the whole friction level). The diagnosis's GP stage is a held-out diagnostic, not an exported model, so it
is not scored here.

Printed per robot: FIGAROH's figures beside ours (nominal, with the found physics), the
per-joint RMS error, and the per-joint held-out nMSE (MSE over the variance of the measured
torque) on their 240 validation samples and on every validation sample between the edges.

Usage: python benchmarks/bench_figaroh.py [--robots tx40,tiago] [--out DIR] [--tiago-urdf PATH]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from mmgp.evaluation.metrics import FIGAROH_FIGURES, FIGAROH_ROWS, aggregate_rmse, figaroh_samples, normalised_mse

DATA = Path("/work/shared/datasets")
TX40_DIR, TIAGO_DIR = DATA / "staubli_tx40_figaroh", DATA / "tiago_figaroh"
# sha256 of the inputs FIGAROH's results JSON records (benchmarks/results/log-cholesky-*-pin37.json)
FIGAROH_SHA = {"pos_read_data.csv": "5cc1cecc1024ef0e331d0caba06f689456ab789ec3f1e904599c0a8be5c27bc8",
               "curr_data.csv": "f4592f4ba4db42f5d7625688986be25b575ca34d0504b27979ca6b0276bd3af9",
               "tx40_mdh_modified.urdf": "3d00cbd46279c915d594b1bb4610dbac78d1e99ed27f95de70984bde13486074",
               "tiago_position.csv": "4297a60d434ee89f1f424ad0da8ec65bc00072ac57eb06b94966c0819fc2786d",
               "tiago_velocity.csv": "269f681ca7a9511ac1698bf027ddf601e3fdb49d7d397af4810ec839f136cd69",
               "tiago_effort.csv": "12c635987705efade603426a600f5b315add7f580c720a4b84609dadb9d0a2e9",
               "tiago_48_schunk.urdf": "e4412357e3ea141097acc835d81c4ac477f889ad99b05d2a9818ed9cdf9d12b6"}
TIAGO_URDF = Path(__file__).parent / "data" / "tiago_48_schunk.urdf"
TIAGO_JOINTS = ["torso_lift_joint"] + [f"arm_{i}_joint" for i in range(1, 8)]
TX40_TS = 0.0002  # s (their config)


def checked(path: Path) -> Path:
    """``path`` after checking that it is the file FIGAROH scored (sha256)."""
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != FIGAROH_SHA[path.name]:
        raise SystemExit(f"{path}: sha256 {digest} is not the file FIGAROH scored")
    return path


def median_butter(x: np.ndarray, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """FIGAROH's kinematics filter on (T, n): a 5-sample median, then a zero-phase order-4
    Butterworth low-pass (odd padding of 12 samples)."""
    from scipy import signal

    b, a = signal.butter(4, cutoff_hz / (rate_hz / 2), "low")
    pad = 3 * (max(len(a), len(b)) - 1)
    return np.column_stack([signal.filtfilt(b, a, signal.medfilt(x[:, j], 5), padtype="odd", padlen=pad)
                            for j in range(x.shape[1])])


def tx40_partition(rows: tuple[int, int]) -> dict:
    """FIGAROH's processed TX40 partition: q, dq, ddq (rad, rad/s, rad/s^2), tau (N*m), (N, 6)."""
    from mmgp.convert.datasets.text_sets import tx40_matrix

    a, b = rows
    motor = pd.read_csv(checked(TX40_DIR / "pos_read_data.csv")).to_numpy()[a:b]
    current = pd.read_csv(checked(TX40_DIR / "curr_data.csv")).to_numpy()[a:b]
    R = tx40_matrix()
    q = np.linalg.solve(R, motor.T).T + np.array([0, -np.pi / 2, np.pi / 2, 0, 0, 0])
    t = np.linspace(0.0, len(q) * TX40_TS, len(q))
    q = median_butter(q, 100.0, 1.0 / TX40_TS)
    dq = np.gradient(q, t, axis=0)
    edge = slice(20, -20)
    return {"q": q[edge], "dq": dq[edge], "ddq": np.gradient(dq, t, axis=0)[edge], "tau": (current @ R)[edge]}


def torso_lift_mass(urdf: Path) -> float:
    """kg the TIAGo torso lifts in ``urdf`` (its subtree mass, the other joints at neutral)."""
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    pin.computeSubtreeMasses(model, data)
    return float(data.mass[model.getJointId("torso_lift_joint")])


def tiago_torque(effort: np.ndarray, torso_mass: float) -> np.ndarray:
    """FIGAROH's TIAGo joint effort (N on the torso, N*m on the arm) from the logged effort (T, 8)."""
    from mmgp.convert.datasets.text_sets import GRAVITY, TIAGO_TORQUE_PER_EFFORT

    tau = effort * np.array([TIAGO_TORQUE_PER_EFFORT[j] for j in TIAGO_JOINTS])
    tau[:, 0] += GRAVITY * torso_mass
    return tau


def tiago_tables(rows: tuple[int, int]) -> dict:
    """Rows of the three TIAGo files: t (T,), q, dq, effort (T, 8), columns in TIAGO_JOINTS order."""
    out = {}
    for kind in ("position", "velocity", "effort"):
        df = pd.read_csv(checked(TIAGO_DIR / f"tiago_{kind}.csv")).iloc[rows[0]:rows[1]]
        out["t"] = df["t"].to_numpy(float)
        out[kind] = df[[f"- {j}_{kind}" for j in TIAGO_JOINTS]].to_numpy(float)
    return out


def tiago_partition(rows: tuple[int, int], torso_mass: float) -> dict:
    """FIGAROH's processed TIAGo partition (their filter settings at the tag, see the docstring)."""
    tab = tiago_tables(rows)
    q, dq = (median_butter(tab[k], 2.0, 500.0) for k in ("position", "velocity"))
    return {"q": q, "dq": dq, "ddq": np.gradient(dq, tab["t"], axis=0),
            "tau": tiago_torque(tab["effort"], torso_mass)}


def training_log(robot: str, folder: Path, tiago_urdf: Path) -> Path:
    """The training rows as a log a user would diagnose (the converter's output, TIAGo's torso
    channel in FIGAROH's convention), its nominal URDF beside it."""
    from mmgp.convert import convert
    from mmgp.data.logs import read_log, write_log

    src, urdf = (TX40_DIR, checked(TX40_DIR / "tx40_mdh_modified.urdf")) if robot == "tx40" else (TIAGO_DIR, tiago_urdf)
    full = next(Path(p) for p in convert(src, folder / f"{robot}_full.parquet", force=True)
                if str(p).endswith(".parquet"))
    log = read_log(full)
    a, b = FIGAROH_ROWS[robot][0]
    tau = log.tau[a:b].copy()
    if robot == "tiago":
        tau[:, 0] = tiago_torque(tiago_tables((a, b))["effort"], torso_lift_mass(urdf))[:, 0]
    path = folder / f"{robot}_train.parquet"
    (folder / f"{robot}_train.urdf").write_bytes(urdf.read_bytes())
    return write_log(path, log.t[a:b], log.q[a:b], tau, dq=None if log.dq is None else log.dq[a:b],
                     urdf=f"{robot}_train.urdf", joint_names=log.joint_names)


def diagnose(log: Path, out: Path) -> float:
    """``mmgp diagnose LOG --out OUT`` (default settings); its wall time in s."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mmgp.cli", "diagnose", str(log), "--out", str(out), "--quiet", "--force"],
                   check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def found_physics_torque(out: Path, names: list, q, dq, ddq, sign: bool = False) -> np.ndarray:
    """(T, n) torque the diagnosis in ``out`` predicts for the logged states: MuJoCo inverse
    dynamics of corrected.xml, plus the findings MJCF cannot express, applied as the report says;
    dry friction by tanh(dq / v_s) with the diagnosis's v_s (``sign``: by sign(dq))."""
    import mujoco

    from mmgp.sim import inverse_dynamics
    from mmgp.sim.inverse import smooth_sign

    doc = json.loads((out / "findings.json").read_text())
    by = {(f["effect"], f.get("joint")): f["params"] for f in doc["findings"]}
    v_s = np.zeros(len(names)) if sign else np.asarray(doc["info"]["v_s"], dtype=np.float64)
    enc = np.array([by.get(("encoder_offset", j), {}).get("offset", 0.0) for j in names])
    tau = inverse_dynamics(mujoco.MjModel.from_xml_path(str(out / "corrected.xml")), q - enc, dq, ddq, v_s=v_s)
    beta = np.array([by.get(("load_dependent_friction", j), {}).get("beta", 0.0) for j in names])
    tau = tau + beta * np.abs(tau) * smooth_sign(dq, v_s)
    return tau + np.array([by.get(("torque_offset", j), {}).get("offset", 0.0) for j in names])


def nominal_torque(urdf: Path, names: list, q, dq, ddq) -> np.ndarray:
    """(T, n) Pinocchio RNEA of ``urdf`` reduced to ``names`` (other joints at neutral), as FIGAROH's."""
    from mmgp.physics.robot import RobotModel

    return RobotModel.from_urdf(urdf, names).rnea(q, dq, ddq)


def score(parts: dict, models: dict) -> dict:
    """Per model: FIGAROH's aggregate error on their 240 validation samples, per-joint RMS
    error there, and per-joint nMSE there and on every validation sample between the edges."""
    val = parts["val"]
    pick = figaroh_samples(len(val["q"]))
    inner = np.arange(20, len(val["q"]) - 20)
    out = {}
    for name, fn in models.items():
        pred = fn(val["q"], val["dq"], val["ddq"])
        tau = val["tau"]
        out[name] = {"aggregate": aggregate_rmse(tau[pick], pred[pick]),
                     "rms": np.sqrt(np.mean((pred[pick] - tau[pick]) ** 2, axis=0)).tolist(),
                     "nmse_240": normalised_mse(tau[pick], pred[pick]).tolist(),
                     "nmse_all": normalised_mse(tau[inner], pred[inner]).tolist()}
    return out


def identifiability_of(urdf: Path, names: list, part: dict) -> dict:
    """The rigid body's base parameters on FIGAROH's training samples of ``part``: how many of
    the 10 per link the trajectory determines (pivoted QR, ``mmgp.physics.identification``) and
    the base regressor's condition number (columns scaled to unit norm)."""
    import pinocchio as pin

    from mmgp.physics.identification import base_parameters, identifiability
    from mmgp.physics.robot import RobotModel

    model = RobotModel.from_urdf(urdf, names).pin_model
    data = model.createData()
    pick = figaroh_samples(len(part["q"]))
    Y = np.stack([pin.computeJointTorqueRegressor(model, data, part["q"][i], part["dq"][i], part["ddq"][i]).copy()
                  for i in pick])
    base = base_parameters(Y, list(model.names[1:]))
    X = Y.reshape(-1, Y.shape[2]) @ base.regroup.T
    return {"columns": int(Y.shape[2]), "base": len(base.names), "names": base.names,
            "condition_number": identifiability(X.T @ X)["condition_number"]}


def run(robot: str, folder: Path, tiago_urdf: Path, out_dir: Path | None = None) -> dict:
    urdf = checked(TX40_DIR / "tx40_mdh_modified.urdf") if robot == "tx40" else checked(tiago_urdf)
    mass = torso_lift_mass(urdf) if robot == "tiago" else None
    parts = {k: (tx40_partition(r) if robot == "tx40" else tiago_partition(r, mass))
             for k, r in zip(("train", "val"), FIGAROH_ROWS[robot])}
    log = training_log(robot, folder, urdf)
    out = (out_dir or folder) / f"diagnose_{robot}"
    seconds = diagnose(log, out) if not (out / "findings.json").exists() else float("nan")
    doc = json.loads((out / "findings.json").read_text())
    names = doc.get("joint_names") or (TIAGO_JOINTS if robot == "tiago" else [f"joint_{i}" for i in range(1, 7)])
    res = score(parts, {"nominal": lambda q, dq, ddq: nominal_torque(urdf, names, q, dq, ddq),
                        "with_found_physics": lambda q, dq, ddq: found_physics_torque(out, names, q, dq, ddq),
                        "found_physics_sign": lambda q, dq, ddq: found_physics_torque(out, names, q, dq, ddq, True)})
    return {"robot": robot, "joints": names, "diagnose_s": seconds, "scores": res, "findings": doc["findings"],
            "fit": doc.get("fit"), "out": str(out), "identifiability": identifiability_of(urdf, names, parts["train"]),
            "reidentification": doc.get("info", {}).get("reidentification"),
            "coupling_search": doc.get("info", {}).get("coupling_search")}


def print_run(r: dict) -> None:
    fig, names, sc = FIGAROH_FIGURES[r["robot"]], r["joints"], r["scores"]
    unit = "N*m" if r["robot"] == "tx40" else "(N and N*m mixed, as theirs)"
    print(f"\n{r['robot']}: held-out aggregate torque error on FIGAROH's split and metric, {unit}; "
          f"diagnose {r['diagnose_s']:.0f} s")
    print("  FIGAROH: " + ", ".join(f"{k} {'failed' if v is None else f'{v:.4f}'}" for k, v in fig.items()))
    print("  mmgp:    " + ", ".join(f"{k} {v['aggregate']:.4f}" for k, v in sc.items())
          + f"   (nominal reproduces FIGAROH's {fig['nominal']:.6f}: {sc['nominal']['aggregate']:.6f})")
    print("  findings: " + "; ".join(f"{f['effect']}@{f.get('joint') or f.get('link') or f.get('pair') or ''}"
                                     for f in r["findings"]))
    for key, label in (("rms", "RMS error"), ("nmse_240", "nMSE, 240 samples"), ("nmse_all", "nMSE, all samples")):
        print(f"  {label:<24}" + "".join(f"{n[-13:]:>14}" for n in names))
        for model, v in sc.items():
            print(f"    {model:<22}" + "".join(f"{x:14.4f}" for x in v[key]))
    idf, reid = r["identifiability"], r["reidentification"] or {}
    print(f"  rigid body on FIGAROH's 240 training samples: {idf['base']} base parameters of {idf['columns']}, "
          f"condition number {idf['condition_number']:.3g}; diagnose re-identified it: "
          f"{reid.get('re_identified')} (held-out gain {reid.get('held_out_gain', float('nan')):.3f}, "
          f"p {reid.get('p_value', float('nan')):.2g})")
    for ev in r["coupling_search"] or []:
        print(f"  coupling search: best {ev.get('best')} p {ev.get('best_p_value', float('nan')):.2g} "
              f"(level {ev.get('level', float('nan')):.2g}), pair gain {ev.get('best_pair_gain', float('nan')):.3f}")
    beat = sum(a < b for a, b in zip(sc["with_found_physics"]["nmse_all"], sc["nominal"]["nmse_all"]))
    print(f"  with the found physics beats nominal on {beat}/{len(names)} joints (nMSE, all validation samples)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="tx40,tiago")
    ap.add_argument("--out", type=Path, default=None, help="keep the diagnoses (reused when present) and results.json")
    ap.add_argument("--tiago-urdf", type=Path, default=TIAGO_URDF, help="FIGAROH's tiago_48_schunk.urdf")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for robot in a.robots.split(","):
            rows.append(run(robot.strip(), Path(tmp), a.tiago_urdf, a.out))
            print_run(rows[-1])
    if a.out:
        (a.out / "results.json").write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
