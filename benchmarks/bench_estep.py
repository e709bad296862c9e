"""Issue 2: compare the two E-steps (joint FFBS vs single-site Gibbs) on the same data.

For each 1-DOF replica seed: classification figures, sweeps to convergence and wall time of
each E-step; the better one is the default (configs/default.yaml: estep).

Usage: python benchmarks/bench_estep.py [--seeds 0 1 2 3 4 5]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mmgp.config import load_settings
from mmgp.evaluation.metrics import classification_figures
from mmgp.data.logs import read_labels
from mmgp import MultimodalGP
from mmgp.sim import actuator_replica


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    args = ap.parse_args()
    table = {"ffbs": [], "gibbs": []}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            rec = actuator_replica(seed=seed)
            log, lab = Path(tmp) / f"l{seed}.parquet", Path(tmp) / f"b{seed}.parquet"
            rec.write(log, lab)
            for estep in table:
                t0 = time.perf_counter()
                res = MultimodalGP(estep=estep).fit(log)
                secs = time.perf_counter() - t0
                pred = res.labels_
                f = classification_figures(pred, read_labels(lab, t=pred["t"].to_numpy()))
                table[estep].append((f["accuracy"], f["unperturbed_correct"], f["perturbed_missed"],
                                     res.report_["n_sweeps"], int(res.report_["converged"]), secs))
                print(f"seed {seed} {estep:5s}: accuracy {f['accuracy']:.3f} unperturbed correct "
                      f"{f['unperturbed_correct']:.3f} perturbed missed {f['perturbed_missed']:.3f} "
                      f"sweeps {res.report_['n_sweeps']} converged {res.report_['converged']} {secs:.1f} s", flush=True)
    print(f"\n{'E-step':<8}{'accuracy':>10}{'unpert. correct':>17}{'pert. missed':>14}{'sweeps':>8}{'converged':>11}{'seconds':>9}")
    for estep, rows in table.items():
        a = np.array(rows, dtype=float)
        print(f"{estep:<8}{a[:, 0].mean():>10.3f}{a[:, 1].mean():>17.3f}{a[:, 2].mean():>14.3f}"
              f"{a[:, 3].mean():>8.1f}{a[:, 4].mean():>11.2f}{a[:, 5].mean():>9.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
