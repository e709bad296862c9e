"""How training scales with the number of samples: ``MultimodalGP(n_modes=1, disturbance=False)``
(the EM-free path) fitted and then predicting 2,000 new samples, at growing N.

Data: a 7-DOF Panda trajectory (example-robot-data ``panda``), torques from the rigid-body model
plus viscous and Coulomb friction, 0.05 N*m noise, ``--rate`` Hz; the GP learns the residual on
top of the rigid-body prior exactly as ``mmgp train`` does with a robot. Each size runs in its own
process, so the peak resident memory (ru_maxrss) is that size's alone. Up to 16,000 samples the
rule picks the exact GP on every sample; above, SGPR with 2,000 inducing inputs (memory
O(M^2 + M * chunk) whatever N).

Run: ``python benchmarks/bench_train_scale.py [--sizes 2000,5000,10000,20000] [--device cpu]``

On a machine without Pinocchio (a GPU machine), write the trajectory here first with
``--save-data FILE --sizes ...`` (it stores the rigid-body torque beside the measured one) and run
there with ``--data FILE``: the GP is then fitted, without a robot model, on the measured torque
minus the stored rigid-body torque (the residual ``mmgp train`` learns on top of its prior), and
nMSE is computed on the full torque, as above.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def trajectory(T: int, rate: float, seed: int = 0):
    """t (T,), q, tau (T, 7) of a smooth multi-sine Panda trajectory with friction and noise."""
    from mmgp.physics.robot import load_robot

    rng = np.random.default_rng(seed)
    robot = load_robot(robot="panda", n_joints=7)
    t = np.arange(T) / rate
    f = rng.uniform(0.05, 0.4, (3, 7))
    ph = rng.uniform(0, 2 * np.pi, (3, 7))
    amp = rng.uniform(0.2, 0.6, (3, 7))
    w = 2 * np.pi * f
    q = sum(amp[i] * np.sin(w[i] * t[:, None] + ph[i]) for i in range(3))
    dq = sum(amp[i] * w[i] * np.cos(w[i] * t[:, None] + ph[i]) for i in range(3))
    ddq = sum(-amp[i] * w[i] ** 2 * np.sin(w[i] * t[:, None] + ph[i]) for i in range(3))
    tau = robot.rnea(q, dq, ddq) + 0.3 * dq + 0.4 * np.tanh(dq / 0.02) + 0.05 * rng.standard_normal(q.shape)
    return t, q, dq, ddq, tau


def save_data(path: str, T: int, rate: float) -> None:
    """The trajectory of T samples and its rigid-body torque, for a machine without Pinocchio."""
    from mmgp.physics.robot import load_robot

    t, q, dq, ddq, tau = trajectory(T, rate)
    np.savez(path, t=t, q=q, dq=dq, ddq=ddq, tau=tau, tau_rb=load_robot(robot="panda", n_joints=7).rnea(q, dq, ddq))


def one_size(N: int, device: str, rate: float, data: str | None = None) -> dict:
    """Fit and predict at N samples in this process; returns the figures."""
    from mmgp import MultimodalGP

    if data is None:
        t, q, dq, ddq, tau = trajectory(N + 2000, rate)
        prior, robot = np.zeros_like(tau), "panda"
    else:
        z = np.load(data)
        if len(z["t"]) < N + 2000:
            raise SystemExit(f"{data} holds {len(z['t'])} samples; {N + 2000} needed")
        t, q, dq, ddq, tau, prior = (z[k][: N + 2000] for k in ("t", "q", "dq", "ddq", "tau", "tau_rb"))
        robot = None
    tr, te = slice(0, N), slice(N, N + 2000)
    model = MultimodalGP(n_modes=1, disturbance=False, robot=robot, device=device, fit_points=1000)
    t0 = time.perf_counter()
    model.fit(t=t[tr], q=q[tr], tau=tau[tr] - prior[tr], dq=dq[tr], ddq=ddq[tr])
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    mean, std = model.predict(q[te], dq[te], ddq[te])
    mean = mean + prior[te]
    t_pred = time.perf_counter() - t0
    nmse = ((mean - tau[te]) ** 2).mean(0) / tau[te].var(0)
    return {"N": N, "kind": model.gp_kinds_[0], "fit_s": t_fit, 
            "predict_2000_s": t_pred, "nmse_mean": float(nmse.mean()),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="2000,5000,10000,20000")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--data", default=None, help="trajectory file written by --save-data (no Pinocchio needed)")
    ap.add_argument("--save-data", default=None, help="write the trajectory for the largest size and stop")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.save_data:
        save_data(a.save_data, max(int(x) for x in a.sizes.split(",")) + 2000, a.rate)
        return 0
    if a.one is not None:
        print(json.dumps(one_size(a.one, a.device, a.rate, a.data)))
        return 0
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; device {a.device}")
    print(f"{'N':>7} {'GP':>6} {'fit s':>8} {'predict 2000 s':>15} {'nMSE mean':>10} "
          f"{'peak RSS MB':>12}")
    for N in (int(x) for x in a.sizes.split(",")):
        env = dict(os.environ, PYTHONPATH=str(REPO))
        extra = ["--data", a.data] if a.data else []
        run = subprocess.run([sys.executable, __file__, "--one", str(N), "--device", a.device, "--rate", str(a.rate)]
                             + extra, capture_output=True, text=True, env=env)
        if run.returncode != 0:
            print(f"{N:>7} failed: {run.stderr.strip().splitlines()[-1] if run.stderr.strip() else run.returncode}")
            continue
        r = json.loads(run.stdout.strip().splitlines()[-1])
        print(f"{r['N']:>7} {r['kind']:>6} {r['fit_s']:>8.1f} {r['predict_2000_s']:>15.1f} "
              f"{r['nmse_mean']:>10.4f} {r['peak_rss_mb']:>12.0f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
