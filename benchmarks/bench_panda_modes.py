"""Issue 2 must-show: 7-DOF Panda (MuJoCo, example-robot-data model) with two payload modes
(0 and 2 kg at the flange) plus pushes, 5,000 samples.

Prints mmgp's mode adjusted Rand index and disturbed-class F1 (targets >= 0.9 each), the whole
SEM's wall time (target < 3 min on 2 cores) and peak memory, beside the baselines on the same
data (one GP + 3-sigma threshold; trimmed GP).

Usage: python benchmarks/bench_panda_modes.py [--seeds 0 1 2] [--samples 5000] [--no-baselines]
"""
from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from baselines import threshold_gp_labels, trimmed_gp_labels
from mmgp.config import load_settings
from mmgp.evaluation.metrics import classification_figures
from mmgp.data.logs import read_labels
from mmgp import MultimodalGP
from mmgp.physics.robot import load_robot
from mmgp.sim import panda_modes


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--samples", type=int, default=5000)
    ap.add_argument("--estep", default="ffbs")
    ap.add_argument("--config", default=None)
    ap.add_argument("--no-baselines", action="store_true")
    args = ap.parse_args()
    rows = {}
    for seed in args.seeds:
        print(f"\n=== seed {seed} ===", flush=True)
        rows[seed] = run_seed(args, seed)
    print("\nseed   mode ARI   disturbed F1   SEM s")
    for seed, (ari, f1, secs) in rows.items():
        print(f"{seed:4d}   {ari:8.3f}   {f1:12.3f}   {secs:5.0f}")
    ok = all(ari >= 0.9 and f1 >= 0.9 and secs < 180 for ari, f1, secs in rows.values())
    print(f"targets on every seed (ARI >= 0.9, F1 >= 0.9, SEM < 180 s): {'MET' if ok else 'NOT MET'}")
    return 0


def run_seed(args, seed):
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        rec = panda_modes(seed=seed, n_samples=args.samples)
        log, lab = Path(tmp) / "panda.parquet", Path(tmp) / "panda_labels.parquet"
        rec.write(log, lab)
        print(f"generated {args.samples} samples in {time.perf_counter() - t0:.1f} s", flush=True)
        cfg = load_settings(args.config, "train", MultimodalGP, n_modes=2, estep=args.estep)
        robot = load_robot(log_path=log)
        t0 = time.perf_counter()
        res = MultimodalGP(robot=robot, **cfg,
                           progress=lambda r: print(f"  sweep {r.sweep} changed {r.changed:.3f} disturbed {r.n_disturbed} "
                                                    f"modes {r.mode_sizes} {r.seconds:.1f} s", flush=True)).fit(log)
        secs = time.perf_counter() - t0
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        pred = res.labels_
        truth = read_labels(lab, t=pred["t"].to_numpy())
        ours = classification_figures(pred, truth)
        print(f"\nmmgp (K=2 + disturbance, {res.report_['n_sweeps']} sweeps): mode ARI {ours['mode_adjusted_rand_index']:.3f}, "
              f"disturbed F1 {ours['disturbed_f1']:.3f} (precision {ours['disturbed_precision']:.3f}, recall "
              f"{ours['disturbed_recall']:.3f}); judged {ours['n_judged']}, ambiguous left out {ours['n_ambiguous_left_out']}")
        print(f"whole pipeline (load, derivatives, RNEA, SEM) {secs:.1f} s; SEM {res.report_['timings']['total_s']:.1f} s; "
              f"peak RSS {peak_mb:.0f} MB")
        if not args.no_baselines:
            X, Y = res.features_.X, res.features_.Y
            for name, fn in (("GP + 3-sigma threshold", threshold_gp_labels), ("trimmed GP", trimmed_gp_labels)):
                t1 = time.perf_counter()
                d = fn(X, Y)
                p = pred.copy()
                p["disturbed"] = d.astype(int)
                p["mode"] = 0
                f = classification_figures(p, truth)
                print(f"baseline {name}: disturbed F1 {f['disturbed_f1']:.3f} (precision {f['disturbed_precision']:.3f}, "
                      f"recall {f['disturbed_recall']:.3f}); modes: none (ARI {f['mode_adjusted_rand_index']:.3f}); "
                      f"{time.perf_counter() - t1:.1f} s")
        return ours["mode_adjusted_rand_index"], ours["disturbed_f1"], res.report_["timings"]["total_s"]


if __name__ == "__main__":
    raise SystemExit(main())
