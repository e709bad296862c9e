"""Evaluation latency of an exported compensator: 7 joints, 1,000 support points.

Builds a curl-free compensator for the Panda (7 joints), exports it, and times one call of
``tau_ff(q)`` (and ``S(q)``) in
  * Python/numpy (``load_compensator(file).torque(q)``, one configuration per call),
  * C through ctypes (includes the Python call overhead),
  * a pure C loop compiled with ``gcc -O2`` (what a 1 kHz controller pays),
next to the peer figure from the same run: Pinocchio's ``computeGeneralizedGravity`` (the
rigid-body gravity feedforward a controller would otherwise use), called from Python and timed
the same way.

By default the weights come from fitting Panda gravity on 1,000 random configurations
(``--synthetic`` uses random weights instead: the latency does not depend on their values).

    python benchmarks/bench_compensator_latency.py [--support 1000] [--synthetic] [--out DIR]
"""
from __future__ import annotations

import argparse
import ctypes
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from mmgp.compensator import Compensator, compensator_from_model, load_compensator

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]

MAIN_C = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "%(stem)s.h"

static double now(void) { struct timespec t; clock_gettime(CLOCK_MONOTONIC, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }

int main(void)
{
    enum { M = 256, N = %(n)d };
    static double q[M][N];
    double tau[N], sink = 0.0, t0, best_t = 1e9, best_s = 1e9;
    int i, j, rep, calls = %(calls)d;
    srand(1);
    for (i = 0; i < M; ++i) for (j = 0; j < N; ++j)
        q[i][j] = %(lo)s[j] + (%(hi)s[j] - %(lo)s[j]) * (rand() / (double)RAND_MAX);
    for (rep = 0; rep < 5; ++rep) {
        t0 = now();
        for (i = 0; i < calls; ++i) { %(stem)s_torque(q[i %% M], tau); sink += tau[i %% N]; }
        if ((now() - t0) / calls < best_t) best_t = (now() - t0) / calls;
        t0 = now();
        for (i = 0; i < calls; ++i) sink += %(stem)s_storage(q[i %% M]);
        if ((now() - t0) / calls < best_s) best_s = (now() - t0) / calls;
    }
    printf("%%.4f %%.4f %%g\n", best_t * 1e6, best_s * 1e6, sink);
    return 0;
}
"""


class _PandaGravity:
    """Stand-in model: Panda gravity (Pinocchio) on random configurations within the limits."""

    def __init__(self, robot, n, seed=0):
        m = robot.pin_model
        self.lo, self.hi = m.lowerPositionLimit.copy(), m.upperPositionLimit.copy()
        rng = np.random.default_rng(seed)
        self.support_q_ = self.lo + (self.hi - self.lo) * rng.random((n, robot.n_joints))
        self.joint_names_ = robot.joint_names
        self.robot = robot

    def nominal_torque(self, q):
        return self.robot.gravity(q)


def _time_per_call(fn, qs, min_time=0.5):
    """Best of 5 rounds, each calling ``fn`` on every row of ``qs`` for about min_time/5 s (s/call)."""
    best = np.inf
    for _ in range(5):
        n_calls, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < min_time / 5:
            for q in qs:
                fn(q)
            n_calls += len(qs)
        best = min(best, (time.perf_counter() - t0) / n_calls)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--support", type=int, default=1000)
    ap.add_argument("--synthetic", action="store_true", help="random weights instead of a Panda gravity fit")
    ap.add_argument("--out", default=None, help="folder for the exported file and C source (default: temp)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from mmgp.physics.robot import RobotModel

    robot = RobotModel.from_name("panda", PANDA_JOINTS)
    model = _PandaGravity(robot, args.support, seed=args.seed)
    t0 = time.perf_counter()
    if args.synthetic:
        rng = np.random.default_rng(args.seed)
        comp = Compensator("curl-free-rbf", model.support_q_, rng.normal(size=(args.support, 7)),
                           np.full(7, 1.5), 50.0, joint_names=model.joint_names_)
        how = "synthetic weights"
    else:
        comp = compensator_from_model(model, max_support=args.support, seed=args.seed)
        how = "fitted to Panda gravity"
    build_s = time.perf_counter() - t0
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="mmgp_lat_"))
    out.mkdir(parents=True, exist_ok=True)
    f = comp.save(out / "panda_ff.npz")
    comp = load_compensator(f)
    stem = "panda_ff"
    c_path, h_path = comp.write_c(out / stem)
    print(f"compensator: {comp.kind}, {comp.n_joints} joints, {comp.support.shape[0]} support points "
          f"({how}, built in {build_s:.1f} s); file {f} ({f.stat().st_size / 1e3:.0f} kB), C {c_path} "
          f"({c_path.stat().st_size / 1e3:.0f} kB)")

    rng = np.random.default_rng(1)
    qs = model.lo + (model.hi - model.lo) * rng.random((64, 7))

    # Python / numpy
    t_np = _time_per_call(comp.torque, qs)
    t_np_s = _time_per_call(comp.storage, qs)

    # C via ctypes and a pure C loop
    gcc = shutil.which("gcc")
    if gcc is None:
        raise SystemExit("gcc not found: the C timings need it")
    so = out / f"lib{stem}.so"
    subprocess.run([gcc, "-std=c99", "-O2", "-shared", "-fPIC", "-o", str(so), str(c_path), "-lm"], check=True)
    lib = ctypes.CDLL(str(so))
    dp = ctypes.POINTER(ctypes.c_double)
    lib.panda_ff_torque.argtypes = [dp, dp]
    lib.panda_ff_torque.restype = None
    tau = np.zeros(7)
    tau_p = tau.ctypes.data_as(dp)
    qps = [np.ascontiguousarray(q) for q in qs]
    q_ptrs = [q.ctypes.data_as(dp) for q in qps]
    t_ct = _time_per_call(lambda p: lib.panda_ff_torque(p, tau_p), q_ptrs)
    lib.panda_ff_torque(q_ptrs[0], tau_p)
    agree = float(np.max(np.abs(tau - comp.torque(qs[0]))))

    arr = lambda v: "(double[]){" + ", ".join(repr(float(x)) for x in v) + "}"
    main_c = out / "bench_main.c"
    main_c.write_text(MAIN_C % {"stem": stem, "n": 7, "calls": 20000, "lo": arr(model.lo), "hi": arr(model.hi)})
    exe = out / "bench_main"
    subprocess.run([gcc, "-std=c99", "-O2", "-I", str(out), "-o", str(exe), str(main_c), str(c_path), "-lm"],
                   check=True)
    res = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    t_c, t_c_s = float(res[0]), float(res[1])

    # peer: Pinocchio rigid-body gravity from Python
    import pinocchio as pin

    pm, pd = robot.pin_model, robot.pin_model.createData()
    t_pin = _time_per_call(lambda q: pin.computeGeneralizedGravity(pm, pd, q), qs)

    print(f"{'evaluator':46s} {'tau_ff us/call':>15s} {'S us/call':>10s}")
    print(f"{'numpy (load_compensator), one q per call':46s} {t_np * 1e6:15.1f} {t_np_s * 1e6:10.1f}")
    print(f"{'C via ctypes (gcc -O2, incl. call overhead)':46s} {t_ct * 1e6:15.1f} {'':>10s}")
    print(f"{'C, pure loop (gcc -O2)':46s} {t_c:15.2f} {t_c_s:10.2f}")
    print(f"{'peer: Pinocchio computeGeneralizedGravity (py)':46s} {t_pin * 1e6:15.1f} {'':>10s}")
    print(f"C vs numpy max |tau difference| at one q: {agree:.2e} N*m (torque scale {np.max(np.abs(tau)):.1f} N*m)")
    print(f"1 kHz budget: C pure loop uses {t_c / 1000 * 100:.1f}% of a 1 ms cycle "
          f"({'OK' if t_c < 100 else 'TOO SLOW'}: target well under 100 us)")


if __name__ == "__main__":
    main()
