"""Comparison report on the real Franka Panda log (panda_gaz2019, example-robot-data ``panda``).

Held-out normalised MSE per joint of rigid-body only (nominal URDF, RNEA), GP only and rigid-body
+ GP (GP on tau - tau_rbd), through :mod:`mmgp.compare` exactly as ``mmgp compare`` runs it:
read the log, complete the derivatives with mmgp's defaults (ddq from the logged dq), time-block
folds with the default gap. Must-show: rigid-body + GP cuts the rigid-body error on every joint.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_compare_real.py [--out DIR] [--folds 5] [--max-train 2000]
[--fit-points 400]`` (about 510 s with the defaults, 140 s with ``--max-train 600 --fit-points 300
--iters 40``, on 2 busy CPU cores).
The shared datasets folder is ``<repo>/../shared/datasets``.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "datasets"

from mmgp.convert import convert  # noqa: E402
from mmgp.errors import InputError  # noqa: E402
from mmgp.evaluation.compare import compare, format_compare, write_compare
from mmgp.data.logs import read_log
from mmgp.physics.robot import load_robot
from mmgp.data.differentiation import complete_derivatives


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=None, help="write compare.json/compare.png here")
    p.add_argument("--folds", type=int, default=5)
    p.add_argument("--max-train", type=int, default=2000)
    p.add_argument("--fit-points", type=int, default=400, help="samples used to fit GP hyperparameters")
    p.add_argument("--iters", type=int, default=60, help="L-BFGS iterations of the hyperparameter fit")
    p.add_argument("--device", default="cpu")
    a = p.parse_args(argv)
    try:
        tmp = tempfile.TemporaryDirectory()
        (path,) = convert(SHARED / "panda_gaz2019", Path(tmp.name) / "panda_gaz2019.parquet")
    except InputError as exc:
        print(f"skipped: {exc}")
        return 0
    log = read_log(path)
    robot = load_robot(log_path=path)
    log = complete_derivatives(log)
    print(f"{path.name}: {log.n_samples} samples, {log.t[-1] - log.t[0]:.1f} s, robot {robot.name}; "
          f"ddq estimated: {log.ddq_estimated}")
    t0 = time.perf_counter()
    res = compare(log, robot, n_folds=a.folds, max_train=a.max_train,
                  gp_options={"max_fit_points": a.fit_points, "max_iter": a.iters, "device": a.device},
                  progress=lambda m: print("  " + m, flush=True))
    print(f"compare: {time.perf_counter() - t0:.0f} s")
    print(format_compare(res))
    rb, gp, rbgp = (np.asarray(res["nmse"][m]) for m in ("rigid_body", "gp", "rigid_body_gp"))
    print("\nper joint: error cut by the GP (rigid body -> rigid body + GP), and GP only for reference")
    for j, name in enumerate(res["joint_names"]):
        print(f"  {name:<14} {rb[j]:.4f} -> {rbgp[j]:.4f}  ({100 * (1 - rbgp[j] / rb[j]):5.1f} % less; "
              f"GP only {gp[j]:.4f})  {'cut' if rbgp[j] < rb[j] else 'NOT cut'}")
    ok = bool(np.all(rbgp < rb))
    print(f"must-show (rigid body + GP below rigid body only on every joint): {'PASS' if ok else 'FAIL'}")
    print(f"rigid body + GP below GP only on {int((rbgp < gp).sum())} of {len(gp)} joints")
    if a.out is not None:
        for f in write_compare(res, a.out):
            print(f"wrote {f}")
    tmp.cleanup()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
