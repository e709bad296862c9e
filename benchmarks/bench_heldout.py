"""Issue 31 item 2: the held-out score `train` reports (report.json -> heldout), and what it costs.

Trains with default settings on the shipped replica (GP only, and with its URDF as rigid body)
and on real logs of ../shared/datasets (converted as bench_diagnose_real.py does), and prints
each model's held-out normalised MSE per joint (model / rigid body / mean), the training time
and the score's own seconds (mmgp.evaluation.heldout: its share of the training time).

Usage: OMP_NUM_THREADS=1 python benchmarks/bench_heldout.py [--logs replica,replica-urdf,tiago] [--rate-hz R]
(the full TIAGo, 8,022 samples, takes 3-11 min on the shared 2 cores)
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def run(name: str, tmp: Path, rate_hz: float | None) -> None:
    from mmgp import MultimodalGP
    from mmgp.evaluation.heldout import format_heldout
    from mmgp.resources import demo_files, demo_urdf

    kw = {}
    if name.startswith("replica"):
        path = demo_files()[0]
        if name == "replica-urdf":
            kw["robot"] = str(demo_urdf())
    else:
        from bench_diagnose_real import convert_log

        path = convert_log(name, tmp)
    m = MultimodalGP(rate_hz=rate_hz, **kw).fit(path)
    rep, h = m.report_, m.report_["heldout"]
    total, own = rep["timings"]["total_s"], h["seconds"]
    print(f"\n=== {name}: {rep['n_samples']} samples, {len(m.joint_names_)} joints, {rep['n_modes']} mode(s), "
          f"{rep['disturbance']['n_disturbed']} flagged; trained in {total:.1f} s, of which the held-out score "
          f"{own:.2f} s (+{100 * own / (total - own):.1f}% on the rest); fold GP support {h['support']}")
    print(format_heldout(h), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="replica,replica-urdf,tiago")
    ap.add_argument("--rate-hz", type=float, default=None, help="downsample the real logs (MultimodalGP rate_hz)")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.logs.split(","):
            run(name, Path(tmp), None if name.startswith("replica") else a.rate_hz)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
