"""Real Franka Emika Panda: rigid-body model alone vs GP alone vs rigid-body + GP on the residual.

Data: the exciting-trajectory log of Gaz et al. (RA-L 2019), /work/shared/datasets/panda_gaz2019
(rbt_log/exciting_traj_{time,positions,velocity,torques}.txt, 20,544 samples at ~1 kHz, 21 s;
each file reshape(-1, 7)). ddq: Savitzky-Golay derivative of the logged dq (mmgp.signals,
default 0.05 s window, on the real jittered time stamps). The series is then thinned to ~``--rate``
Hz by picking the sample nearest each tick (neighbouring 1 kHz rows carry no new information).

Rigid-body model: mmgp.robot.RobotModel.from_name("panda", n_joints=7): example-robot-data's nominal URDF
inertials, no friction, no motor inertia. Evaluation: 5 contiguous time blocks
(mmgp.signals.time_block_folds, ``--gap-s`` seconds dropped from training on each side of the
test block); per joint nMSE = MSE / variance of the held-out torques, pooled over the folds.
GP: mmgp.gp.sparse.make_gp (exact below 3,000 training samples), inputs [q, dq, ddq].

Run: python benchmarks/bench_panda_semiparametric.py [--rate 100] [--gap-s 0.2]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

ROOT = "/work/shared/datasets/panda_gaz2019/rbt_log"


def load(rate: float):
    from mmgp.data.differentiation import SavitzkyGolay

    read = lambda k: np.loadtxt(os.path.join(ROOT, f"exciting_traj_{k}.txt"))  # noqa: E731
    t = read("time")
    q, dq, tau = (read(k).reshape(-1, 7) for k in ("positions", "velocity", "torques"))
    ddq = SavitzkyGolay()(t, dq, 1)
    ticks = np.arange(t[0], t[-1], 1.0 / rate)
    idx = np.unique(np.clip(np.searchsorted(t, ticks), 0, len(t) - 1))
    return t[idx], q[idx], dq[idx], ddq[idx], tau[idx]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--gap-s", type=float, default=0.2)
    ap.add_argument("--folds", type=int, default=5)
    a = ap.parse_args()

    from mmgp.gp.sparse import make_gp
    from mmgp.physics.robot import RobotModel
    from mmgp.data.folds import time_block_folds

    t, q, dq, ddq, tau = load(a.rate)
    robot = RobotModel.from_name("panda", n_joints=7)  # the log has no finger joints
    t0 = time.perf_counter()
    tau_rbd = robot.rnea(q, dq, ddq)
    t_rbd = time.perf_counter() - t0
    X = np.concatenate([q, dq, ddq], 1)
    T = len(t)
    gap = int(round(a.gap_s * a.rate))
    print(f"panda_gaz2019: {T} samples at ~{a.rate:.0f} Hz over {t[-1] - t[0]:.1f} s; {a.folds} time-block folds, "
          f"gap {gap} samples; robot {robot}", flush=True)
    preds = {k: np.zeros_like(tau) for k in ("rigid-body only", "GP only", "rigid-body + GP")}
    times = {"rigid-body only": t_rbd, "GP only": 0.0, "rigid-body + GP": t_rbd}
    for k, (tr, te) in enumerate(time_block_folds(T, a.folds, gap)):
        preds["rigid-body only"][te] = tau_rbd[te]
        t0 = time.perf_counter()
        gp = make_gp(len(tr)).fit(X[tr], tau[tr])
        preds["GP only"][te] = gp.predict(X[te], return_std=False)
        times["GP only"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        gp_r = make_gp(len(tr)).fit(X[tr], tau[tr] - tau_rbd[tr])
        preds["rigid-body + GP"][te] = tau_rbd[te] + gp_r.predict(X[te], return_std=False)
        times["rigid-body + GP"] += time.perf_counter() - t0
        print(f"  fold {k}: train {len(tr)}, test {len(te)} ({type(gp).__name__})", flush=True)
    # pooled over folds: each fold's error normalised by that fold's torque variance, then averaged
    folds = time_block_folds(T, a.folds, gap)
    print(f"{'model':>18s} | {'time s':>7s} | nMSE per joint (mean over folds of MSE/var(held-out tau))")
    res = {}
    for name, p in preds.items():
        v = np.mean([((p[te] - tau[te]) ** 2).mean(0) / tau[te].var(0) for _, te in folds], 0)
        res[name] = v
        print(f"{name:>18s} | {times[name]:7.1f} | [" + " ".join(f"{x:.4f}" for x in v) + f"] mean {v.mean():.4f}")
    cut = res["rigid-body + GP"] < res["rigid-body only"]
    print(f"rigid-body + GP beats rigid-body only on {cut.sum()}/7 joints; beats GP only on "
          f"{(res['rigid-body + GP'] < res['GP only']).sum()}/7 joints")


if __name__ == "__main__":
    main()
