"""Issue 10, abstention on real robots: what `train` flags on real logs recorded without pushes.

The real identification logs of ../shared/datasets (TIAGo and Staubli TX40 from FIGAROH's
examples, the Panda of Gaz et al. 2019) are excitation trajectories recorded without contact,
so every flagged sample is a false alarm (the issue asks for < 1%). Printed per log, from one
run: the share flagged by mmgp (default settings, one mode) and by one GP + 3 sigma on the same
inputs (baselines.threshold_gp_labels; skipped above --gp3-max samples), the longest flagged
stretch, how many flagged samples have every joint / some joint at rest (|dq| below the
smooth-sign scale v_s: a stuck joint holds any torque within its friction band), which joint's
residual is the largest in standard deviations at the flagged samples (the last sweep's
calibrated predictive), each joint's torque "dead band" share (the most frequent exact reading's
share of the samples: a driver that reports 0 below a threshold), and the seconds.

Usage: python benchmarks/bench_labels_real.py [--logs tiago,tx40,panda] [--gp3-max 9000]
(the full 20,544-sample Panda takes ~8 min; TIAGo ~2 min)
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def run(name: str, tmp: Path, gp3_max: int) -> None:
    from baselines import threshold_gp_labels
    from bench_diagnose_real import convert_log
    from mmgp import MultimodalGP
    from mmgp.data.channels import modal_reading
    from mmgp.diagnosis.separation import runs
    from mmgp.physics.context import smooth_sign_scale

    path = convert_log(name, tmp)
    t0 = time.perf_counter()
    m = MultimodalGP(n_modes=1).fit(path)
    secs = time.perf_counter() - t0
    flags = m.sem_.disturbed_.astype(bool)
    feats, lg = m.features_, m.logs_[0]
    dt = float(np.median(np.diff(lg.t)))
    rest = np.abs(lg.dq) < smooth_sign_scale(lg.dq)[None, :]
    last = m.sem_.last_sweep_
    z = np.abs(feats.Y - last["means"][0]) / np.sqrt(last["vars"][0])
    top = np.bincount(z[flags].argmax(1), minlength=feats.Y.shape[1])   # empty flags: zeros
    print(f"\n=== real {name}: {len(flags)} samples at {1 / dt:.0f} Hz, {feats.Y.shape[1]} joints; mmgp {secs:.0f} s")
    d = m.report_["dissipation"]
    print(f"friction check: {len(d['fits'])} fit(s), worst injecting share per fit "
          f"{[round(f['worst'], 3) for f in d['fits']]}, kept fit {d['chosen'] + 1}")
    longest = max((b - a for a, b in runs(flags)), default=0) * dt
    print(f"mmgp flagged {flags.mean():.2%}; longest flagged stretch {longest:.2f} s; of the "
          f"flagged samples every joint at rest {rest[flags].all(1).mean() if flags.any() else 0:.0%}, "
          f"some joint at rest {rest[flags].any(1).mean() if flags.any() else 0:.0%}")
    print(f"  joint with the largest |z| at the flagged samples (count per joint): {top.tolist()}")
    print(f"  share of samples at each joint's most frequent exact torque reading: "
          f"{[round(modal_reading(lg.tau[:, j])[1], 2) for j in range(lg.tau.shape[1])]}")
    if len(flags) <= gp3_max:
        t0 = time.perf_counter()
        base = threshold_gp_labels(feats.X, feats.Y)
        print(f"one GP + 3 sigma flagged {base.mean():.2%} ({time.perf_counter() - t0:.0f} s)", flush=True)
    else:
        print(f"one GP + 3 sigma: skipped ({len(flags)} samples > --gp3-max {gp3_max})", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="tiago,tx40")
    ap.add_argument("--gp3-max", type=int, default=9000, help="largest log for the exact GP + 3 sigma baseline")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.logs.split(","):
            run(name, Path(tmp), a.gp3_max)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
