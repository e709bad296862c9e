"""Fleet benchmark: `mmgp fleet` on generated logs, one after another vs on Ray, and the drift flag.

50 logs of the 1-DOF actuator lever (MuJoCo, ``mmgp.sim.concealed``: a 0.73 kg load on a 0.2 m
lever, Coulomb friction in the simulator, torque noise, velocities estimated from positions),
one per day from 2026-01-01 (``start_time`` in each log's metadata), each on its own random
trajectory. The friction is 0.3 N*m up to log ``start - 1`` and then rises by ``slope`` N*m per
log (gearbox wear): log ``start`` has 0.3 + slope. The same command runs twice in this process's
environment, ``--serial`` and on a local Ray with ``--workers`` (default: every core), and the
wall times of both (Python start, imports and Ray's start included) and their ratio are printed,
with the fleet's own task time from ``fleet.json``. Then: which logs the drift flag names for the
friction, against the planted start.

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python benchmarks/bench_fleet.py [--logs 50] [--start 30]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from mmgp.data.outputs import write_table
from mmgp.threads import usable_cores
from mmgp.sim.concealed import ACTUATOR_URDF, make_case

BASE_TAU_C = 0.3


def planted_tau_c(i: int, start: int, slope: float) -> float:
    """The simulator's Coulomb friction in log ``i`` (N*m)."""
    return BASE_TAU_C if i < start else BASE_TAU_C + slope * (i - start + 1)


def generate(folder: Path, n_logs: int, start: int, slope: float, samples: int) -> None:
    (folder / "actuator.urdf").write_text(ACTUATOR_URDF)
    for i in range(n_logs):
        spec = {"name": f"lever_{i:02d}", "robot": "actuator", "n_samples": samples,
                "effects": [{"effect": "coulomb_friction", "joint": "lever_joint",
                             "params": {"tau_c": planted_tau_c(i, start, slope)}}]}
        rec, _ = make_case(spec, seed=1000 + i)
        cols = {"t": rec.t, "q_0": rec.q[:, 0], "tau_0": rec.tau[:, 0]}
        if rec.dq is not None:
            cols["dq_0"] = rec.dq[:, 0]
        day = pd.Timestamp("2026-01-01T06:00:00Z") + pd.Timedelta(days=i)
        write_table(folder / f"lever_{i:02d}.parquet", pd.DataFrame(cols),
                    metadata={"urdf": "actuator.urdf", "joint_names": json.dumps(["lever_joint"]),
                              "start_time": day.isoformat()})


def run_fleet(logs: Path, out: Path, extra: list[str]) -> float:
    """Wall seconds of one `mmgp fleet` run (a fresh Python: imports and Ray's start included)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "mmgp.cli", "fleet", str(logs), "--out", str(out), "--force", *extra]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    print(done.stdout.strip())
    return seconds


def drift_check(out: Path, n_logs: int, start: int) -> dict:
    """Logs (by index) the drift flag names for the friction, against the planted start."""
    report = json.loads((out / "drift.json").read_text())
    (series,) = [s for s in report["series"] if s["effect"] == "coulomb_friction" and s["param"] == "tau_c"]
    flagged = sorted(int(Path(p).stem.split("_")[-1]) for p in series["flagged_logs"])
    first = int(Path(series["first_log"]).stem.split("_")[-1]) if series.get("first_log") else None
    return {"flagged": flagged, "first": first, "false_flags": [i for i in flagged if i < start],
            "missed": [i for i in range(start, n_logs) if i not in flagged], "baseline": series.get("baseline")}


def compare_tables(a: Path, b: Path) -> float:
    """Largest difference between the two runs' parameter values (same logs, same findings?)."""
    ta, tb = (pd.read_parquet(p / "fleet.parquet").sort_values(["log", "effect", "joint", "param"]) for p in (a, b))
    keys = ["log", "effect", "param"]
    if not ta[keys].reset_index(drop=True).equals(tb[keys].reset_index(drop=True)):
        return float("inf")
    return float(np.nanmax(np.abs(ta["value"].to_numpy() - tb["value"].to_numpy())))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=50)
    ap.add_argument("--start", type=int, default=30, help="first log with more friction")
    ap.add_argument("--slope", type=float, default=0.01, help="N*m more friction per log from --start on")
    ap.add_argument("--samples", type=int, default=2000, help="samples per log (200 Hz)")
    ap.add_argument("--workers", type=int, default=None, help="Ray workers (default: the cores available)")
    args = ap.parse_args()
    workers = args.workers or usable_cores()
    with tempfile.TemporaryDirectory(prefix="mmgp-bench-fleet-") as tmp:
        tmp = Path(tmp)
        logs = tmp / "logs"
        logs.mkdir()
        t0 = time.perf_counter()
        generate(logs, args.logs, args.start, args.slope, args.samples)
        print(f"generated {args.logs} logs x {args.samples} samples in {time.perf_counter() - t0:.0f} s; "
              f"friction {BASE_TAU_C} N*m, +{args.slope} N*m per log from log {args.start}")
        print(f"cores available: {usable_cores()}; load average before: {os.getloadavg()}")
        serial = run_fleet(logs, tmp / "serial", ["--serial"])
        print(f"load average: {os.getloadavg()}")
        on_ray = run_fleet(logs, tmp / "ray", ["--workers", str(workers)])
        print(f"load average after: {os.getloadavg()}")
        runs = {k: json.loads((tmp / k / "fleet.json").read_text()) for k in ("serial", "ray")}
        print(f"\nserial loop: {serial:.1f} s wall ({runs['serial']['seconds']:.1f} s in the fleet's run)")
        print(f"Ray, {workers} workers: {on_ray:.1f} s wall ({runs['ray']['seconds']:.1f} s in the fleet's run, "
              f"of which {runs['ray']['ray_start_seconds']:.1f} s starting Ray)")
        print(f"speed-up (serial / Ray, wall): {serial / on_ray:.2f}x")
        med = {k: float(np.median([lg["seconds"] for lg in r["logs"]])) for k, r in runs.items()}
        print(f"median seconds per log inside its task: serial {med['serial']:.2f}, Ray {med['ray']:.2f}")
        print(f"largest difference between the two tables' values: {compare_tables(tmp / 'serial', tmp / 'ray'):.3g}")
        check = drift_check(tmp / "ray", args.logs, args.start)
        print(f"\ndrift (Ray run): baseline interval {check['baseline']}")
        print(f"flagged logs: {check['flagged']}")
        print(f"first flagged: {check['first']} (planted start {args.start}); flagged before the start: "
              f"{check['false_flags']}; not flagged from the start on: {check['missed']}")
        ok = check["first"] == args.start and not check["false_flags"] and not check["missed"]
        print("drift flagged at the right logs" if ok else "drift NOT flagged exactly at the planted logs")


if __name__ == "__main__":
    main()
