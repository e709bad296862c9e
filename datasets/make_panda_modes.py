"""Write a simulated Panda recording with payload modes and pushes: OUT/panda_modes_log.parquet and
OUT/panda_modes_labels.parquet.

MuJoCo model built from example-robot-data's panda.urdf via Pinocchio (mmgp.sim.build_mjcf), fingers
locked, 1 kHz computed-torque tracking (payload-free controller model, kp 2500 1/s^2, kd 100 1/s) of a
sum of 4 sinusoids per joint (0.04-0.25 Hz, 70% of each joint range, <= 0.8 rad/s). A 5 cm sphere
at panda_link8 (com [0, 0, 0.12] m) switches between the --payloads masses in 8-20 s segments
(labels: mode = index into --payloads). Pushes: 10-40 N world forces at a random link among
panda_link3..7, 0.3-2 s, every 1.5-5 s. Logged at --rate Hz: q (19-bit encoder), dq (+N(0, 0.005)
rad/s), tau (+N(0, 0.05) N*m); metadata robot="panda", joint_names. Labels' disturbed column follows
the contract rule (3 x torque noise + 2 x dry friction; friction is zero unless --frictionloss).

Usage: python datasets/make_panda_modes.py OUT [--seed 0] [--n-samples 5000] [--rate 100]
       [--payloads 0 2] [--no-pushes] [--frictionloss F]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from mmgp.sim import panda_modes


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-samples", type=int, default=5000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--payloads", type=float, nargs="+", default=[0.0, 2.0])
    ap.add_argument("--no-pushes", action="store_true")
    ap.add_argument("--frictionloss", type=float, default=None, help="dry friction of every joint, N*m")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rec = panda_modes(seed=args.seed, n_samples=args.n_samples, rate_hz=args.rate, payloads=tuple(args.payloads),
                      pushes=not args.no_pushes, frictionloss=args.frictionloss)
    out = Path(args.out)
    rec.write(out / "panda_modes_log.parquet", out / "panda_modes_labels.parquet")
    counts = rec.labels["disturbed"].value_counts().to_dict()
    print(f"wrote {out}/panda_modes_log.parquet, panda_modes_labels.parquet: {len(rec.t)} samples, "
          f"modes {rec.labels['mode'].value_counts().sort_index().to_dict()}, "
          f"disturbed 1/0/-1 = {counts.get(1, 0)}/{counts.get(0, 0)}/{counts.get(-1, 0)}, "
          f"{time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
