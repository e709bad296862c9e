"""``mmgp compare`` on the full real Franka Panda log (panda_gaz2019, example-robot-data ``panda``),
run as a user runs it, timed.

Steps (each a child process of this checkout): ``mmgp convert /work/shared/datasets/panda_gaz2019
--out panda.parquet`` (20,544 samples at 1 kHz, ddq estimated by mmgp), then ``mmgp compare
panda.parquet --out DIR`` with its defaults (5 time-block folds, the default gap, at most
``--max-train`` 1,000 training samples per fold, leave-time-block-out hyperparameters). Printed:
the command's wall time, its per-fold progress, the held-out normalised MSE per joint of rigid body
only, GP only and rigid body + GP, and whether rigid body + GP cuts the rigid-body error on every
joint.

Before the one thread policy (``mmgp.threads``) ``mmgp compare`` on this log did not finish in
10 minutes on the shared 2-core machine unless ``OMP_NUM_THREADS=1`` was set by hand (one fold
274 s with two threads vs ~30 s with one); the policy makes the command single-threaded at these
sizes whatever the environment, so this benchmark does not set ``OMP_NUM_THREADS``.

Run: ``python benchmarks/bench_compare_real.py [--out DIR] [--max-train 1000] [--device cpu]``
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

REPO = Path(__file__).resolve().parents[1]
SOURCE = Path("/work/shared/datasets/panda_gaz2019")


def mmgp(args: list[str]) -> tuple[float, str]:
    """``mmgp ARGS`` in a child process with this checkout first on the path: (wall s, stderr)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("OMP_NUM_THREADS", None)            # the command's own policy decides
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "mmgp.cli"] + args, env=env, capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(f"mmgp {' '.join(args)} failed ({run.returncode}):\n{run.stderr}")
    return time.perf_counter() - t0, run.stderr


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=None, help="keep compare.json / compare.png here")
    p.add_argument("--max-train", type=int, default=1000)
    p.add_argument("--device", default="cpu")
    a = p.parse_args(argv)
    if not SOURCE.is_dir():
        print(f"skipped: {SOURCE} not found")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "panda.parquet"
        t_conv, _ = mmgp(["convert", str(SOURCE), "--out", str(log)])
        out = a.out or Path(tmp) / "compare"
        t_cmp, progress = mmgp(["compare", str(log), "--out", str(out), "--max-train", str(a.max_train),
                                "--device", a.device, "--force"])
        res = json.loads((out / "compare.json").read_text())
    print(f"mmgp convert {SOURCE} --out panda.parquet: {t_conv:.1f} s ({res['n_samples']} samples)")
    print(progress.strip())
    print(f"mmgp compare panda.parquet --out DIR --max-train {a.max_train}: finished in {t_cmp:.0f} s "
          f"(fit + predict {res['timings']['fit_predict_s']:.0f} s; load average {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} cores)")
    rb, gp, rbgp = (np.asarray(res["nmse"][m]) for m in ("rigid_body", "gp", "rigid_body_gp"))
    print(f"{'joint':<14}{'rigid body':>12}{'GP only':>10}{'rigid body + GP':>17}")
    for j, name in enumerate(res["joint_names"]):
        print(f"{name:<14}{rb[j]:>12.4f}{gp[j]:>10.4f}{rbgp[j]:>17.4f}  {'cut' if rbgp[j] < rb[j] else 'NOT cut'}")
    print(f"{'mean':<14}{rb.mean():>12.4f}{gp.mean():>10.4f}{rbgp.mean():>17.4f}")
    ok = bool(np.all(rbgp < rb))
    print(f"rigid body + GP below rigid body only on every joint: {'PASS' if ok else 'FAIL'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
