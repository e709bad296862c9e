"""Write the shipped 1-DOF replica recording: mmgp/resources/replica/replica_log.parquet + replica_labels.parquet.

A MuJoCo re-creation of the actuator experiment of Haninger (2016), ch. 5. Reproducible: the files
depend only on the seed (default 0) and the package versions of numpy and mujoco.

Physics (mmgp.sim.REPLICA): one revolute joint about a horizontal axis lifts a 0.73 kg load
(solid sphere, r = 3 cm) on a 0.2 m lever of 0.1 kg (uniform rod); motor armature 1e-3 kg*m^2,
viscous damping 0.01 N*m*s/rad; static torque (0.73*0.2 + 0.1*0.1) * 9.81 * cos(q) = 1.53 cos(q) N*m
(q = 0 lever horizontal, q > 0 lifts). Load-dependent dry friction, as in a Bowden cable:
0.3 + 0.2*|motor torque| N*m, written into MuJoCo's dof_frictionloss every 1 ms step, so MuJoCo's
friction constraint (with no-slip iterations) makes the joint stick. High-gain PD (kp 150 N*m/rad,
kd 3 N*m*s/rad, 2 s of unlogged settling) tracks a slow two-sinusoid reference over about
-0.6..1.3 rad (quasi-static).
Hand-like pushes: a force perpendicular to the lever at the load, 0.3-2 s, sin^2 ramps of
0.1-0.25 s, random sign, peak joint torque 1.5-4 N*m, on roughly a third of the samples.

Logged at 20 Hz (330 samples, 16.5 s): t, q_0 (2^14 counts/rev encoder), tau_0 (motor torque +
N(0, 0.02) N*m). dq and ddq are left out (mmgp estimates them). Metadata: joint_names
["lever_joint"], no robot (there is no URDF).

Labels: t, mode (always 0), disturbed by the contract rule: 1 when the push's joint torque exceeds
3 x 0.02 N*m + 2 x the dry-friction level at that sample, 0 when no push force acts, -1 in between.

Usage: python datasets/make_replica.py [--seed 0] [--out mmgp/resources/replica]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from mmgp.sim import actuator_replica


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-samples", type=int, default=330)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "mmgp" / "resources" / "replica"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rec = actuator_replica(seed=args.seed, n_samples=args.n_samples)
    out = Path(args.out)
    rec.write(out / "replica_log.parquet", out / "replica_labels.parquet")
    counts = rec.labels["disturbed"].value_counts().to_dict()
    print(f"wrote {out}/replica_log.parquet, replica_labels.parquet: {len(rec.t)} samples, "
          f"disturbed 1/0/-1 = {counts.get(1, 0)}/{counts.get(0, 0)}/{counts.get(-1, 0)}, "
          f"{time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
