"""Evaluation latency of an exported compensator (7 joints, 1,000 support points) beside Pinocchio.

The compensator is either a file exported by ``mmgp export`` / ``compensator_from_model`` (e.g.
the real-Panda export written by ``bench_compensator_safety.py``), or, by default, a stand-in built
here: the Panda's rigid-body prior plus a Wendland deviation on 1,000 support poses of a smooth
random trajectory within the joint limits, with random weights (the latency does not depend on
their values) and support radii ``--radius`` times the trajectory's span per joint, shrunk to the
export's neighbour budget (100 on average).

Timed in the same run, per call, in CPU time of the calling thread (the machine these benchmarks
run on is shared, and wall time counts the other processes' turns), best of 5 rounds over 256
query poses of each kind ("near": support poses plus N(0, 0.05 rad) noise, where the deviation has
the most neighbours; "uniform": uniform in the joint limits):

* the generated C (``gcc -O2``), a pure C loop: ``<p>_torque(q, tau)`` (prior + deviation + region);
* the same through ctypes (includes the Python call overhead), and numpy (``torque(q)``);
* peer: Pinocchio's ``computeGeneralizedGravity`` on the same robot, from Python, and from C++
  (``g++ -O2`` against the installed Pinocchio; needs Eigen headers: ``--eigen-include DIR`` or
  ``EIGEN_INCLUDE``; skipped with a note when absent).

Also printed: the number of support points within the radius (visited with r < 1) per query, and
the largest |C - numpy| over all queries relative to the torque scale (must be <= 1e-10).

    python benchmarks/bench_compensator_latency.py [--compensator FILE] [--radius 1.0] [--out DIR]
        [--eigen-include DIR]
"""
from __future__ import annotations

import argparse
import ctypes
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from mmgp.compensator import Compensator, load_compensator
from mmgp.compensator.prior import prior_from_robot
from mmgp.gp.gradient_field import neighbour_limited_scale

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]

MAIN_C = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <time.h>
#include "%(stem)s.h"
#include "queries.h"

static double now(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }

int main(void)
{
    double tau[NQJ], sink = 0.0, t0, best[2] = {1e9, 1e9};
    int i, k, rep, calls = %(calls)d;
    for (k = 0; k < 2; ++k)
        for (rep = 0; rep < 5; ++rep) {
            const double *Q = k ? Q_UNIFORM : Q_NEAR;
            t0 = now();
            for (i = 0; i < calls; ++i) { sink += %(stem)s_torque(Q + (i %% NQ) * NQJ, tau); sink += tau[i %% NQJ]; }
            t0 = (now() - t0) / calls;
            if (t0 < best[k]) best[k] = t0;
        }
    printf("%%.4f %%.4f %%g\n", best[0] * 1e6, best[1] * 1e6, sink);
    return 0;
}
"""


def stand_in(radius: float, n: int, seed: int) -> Compensator:
    """Panda prior + a Wendland deviation on ``n`` poses of a smooth random trajectory."""
    from mmgp.physics.robot import RobotModel

    robot = RobotModel.from_name("panda", PANDA_JOINTS)
    lo, hi = robot.pin_model.lowerPositionLimit, robot.pin_model.upperPositionLimit
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 60, n)[:, None]
    w, ph = rng.uniform(0.05, 0.25, (3, 7)) * 2 * np.pi, rng.uniform(0, 2 * np.pi, (3, 7))
    Z = 0.5 * (lo + hi) + 0.35 * (hi - lo) * np.sin(w[None] * t[:, :, None] + ph[None]).mean(1)
    radii = radius * (Z.max(0) - Z.min(0))
    radii *= neighbour_limited_scale(Z / radii, 100)  # the export's default neighbour budget
    return Compensator("curl-free-wendland", Z, rng.normal(size=Z.shape) * 0.1, radii, 0.05,
                       joint_names=PANDA_JOINTS, prior=prior_from_robot(robot, payload=(0.5, np.array([0, 0, 0.2]))))


def _time_per_call(fn, qs, min_time=0.5):
    """Best of 5 rounds, each calling ``fn`` on every row of ``qs`` for about min_time/5 s of this
    thread's CPU time (s/call)."""
    best = np.inf
    for _ in range(5):
        n_calls, t0 = 0, time.thread_time()
        while time.thread_time() - t0 < min_time / 5:
            for q in qs:
                fn(q)
            n_calls += len(qs)
        best = min(best, (time.thread_time() - t0) / n_calls)
    return best


def _c_array(name, a) -> str:
    return f"static const double {name}[{a.size}] = {{" + ", ".join(repr(float(x)) for x in a.ravel()) + "};\n"


def time_c(comp, out: Path, queries: dict, stem: str = "ff") -> tuple[dict, float]:
    """Pure C loop timings (us/call) per query kind, and max |C - numpy| / torque scale."""
    c_path, _ = comp.write_c(out / stem)
    gcc = shutil.which("gcc")
    (out / "queries.h").write_text(f"#define NQ {len(queries['near'])}\n#define NQJ {comp.n_joints}\n"
                                   + _c_array("Q_NEAR", queries["near"]) + _c_array("Q_UNIFORM", queries["uniform"]))
    (out / "bench_main.c").write_text(MAIN_C % {"stem": stem, "calls": 20000})
    exe = out / "bench_main"
    subprocess.run([gcc, "-std=c99", "-O2", "-I", str(out), "-o", str(exe), str(out / "bench_main.c"), str(c_path),
                    "-lm"], check=True)
    near, uniform, _ = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    so = out / f"lib{stem}.so"
    subprocess.run([gcc, "-std=c99", "-O2", "-shared", "-fPIC", "-o", str(so), str(c_path), "-lm"], check=True)
    lib = ctypes.CDLL(str(so))
    dp = ctypes.POINTER(ctypes.c_double)
    fn = getattr(lib, f"{stem}_torque")
    fn.argtypes, fn.restype = [dp, dp], ctypes.c_double
    Q = np.concatenate(list(queries.values()))
    ref, tau = comp.torque(Q), np.zeros(comp.n_joints)
    worst = 0.0
    for q, r in zip(Q, ref):
        qc = np.ascontiguousarray(q)
        fn(qc.ctypes.data_as(dp), tau.ctypes.data_as(dp))
        worst = max(worst, float(np.max(np.abs(tau - r))))
    ptrs = [np.ascontiguousarray(q) for q in queries["near"]]
    tp = tau.ctypes.data_as(dp)
    t_ct = _time_per_call(lambda q: fn(q.ctypes.data_as(dp), tp), ptrs)
    return {"near": float(near), "uniform": float(uniform), "ctypes_near": t_ct * 1e6}, worst / np.abs(ref).max()


PIN_CPP = r"""
#include <pinocchio/multibody.hpp>
#include <pinocchio/algorithm/rnea.hpp>
#include <cstdio>
#include <ctime>
#include "queries.h"
static double now() { timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }
int main() {
  pinocchio::Model m;
%(build)s
  pinocchio::Data d(m);
  double sink = 0, best = 1e9;
  for (int rep = 0; rep < 5; ++rep) {
    double t0 = now();
    for (int i = 0; i < 20000; ++i)
      sink += pinocchio::computeGeneralizedGravity(m, d, Eigen::Map<const Eigen::VectorXd>(Q_UNIFORM + (i %% NQ) * NQJ, NQJ))[1];
    double t = (now() - t0) / 20000;
    if (t < best) best = t;
  }
  std::printf("%%.4f %%g\n", best * 1e6, sink);
}
"""


def _pinocchio_model_cpp(pm) -> str:
    """C++ statements rebuilding the reduced Pinocchio model ``pm`` (joint types, placements, inertias)."""
    lines = []
    mat = lambda M: "(Eigen::Matrix3d() << " + ", ".join(repr(float(x)) for x in np.ravel(M)) + ").finished()"  # noqa: E731
    vec = lambda v: f"Eigen::Vector3d({', '.join(repr(float(x)) for x in v)})"  # noqa: E731
    for j in range(1, pm.njoints):
        name = pm.joints[j].shortname()
        if name not in ("JointModelRX", "JointModelRY", "JointModelRZ"):
            raise ValueError(f"the C++ peer handles RX/RY/RZ joints only, not {name}")
        P, inertia = pm.jointPlacements[j], pm.inertias[j]
        lines.append(f"  {{ auto j = m.addJoint({pm.parents[j]}, pinocchio::{name}(), "
                     f"pinocchio::SE3({mat(P.rotation)}, {vec(P.translation)}), \"j{j}\");\n"
                     f"    m.appendBodyToJoint(j, pinocchio::Inertia({float(inertia.mass)!r}, {vec(inertia.lever)}, "
                     f"{mat(inertia.inertia)}), pinocchio::SE3::Identity()); }}")
    return "\n".join(lines)


def time_pinocchio_cpp(pm, out: Path, eigen: str | None) -> float | None:
    """us/call of computeGeneralizedGravity in C++, or None without Eigen headers or g++."""
    import pinocchio

    gxx = shutil.which("g++")
    if not eigen or gxx is None or not Path(eigen, "Eigen").is_dir():
        return None
    # the installed package's prefix (include/, lib/): the folder "cmeel.prefix" above the module
    prefix = next(p for p in Path(pinocchio.__file__).resolve().parents if p.name == "cmeel.prefix")
    (out / "pin.cpp").write_text(PIN_CPP % {"build": _pinocchio_model_cpp(pm)})
    exe = out / "pin_bench"
    subprocess.run([gxx, "-O2", "-std=c++17", "-DNDEBUG", "-DBOOST_MPL_CFG_NO_PREPROCESSED_HEADERS",
                    "-DBOOST_MPL_LIMIT_LIST_SIZE=30", "-DBOOST_MPL_LIMIT_VECTOR_SIZE=30", f"-I{prefix / 'include'}",
                    f"-I{eigen}", f"-I{out}", str(out / "pin.cpp"), "-o", str(exe), f"-L{prefix / 'lib'}",
                    "-lpinocchio_default", f"-Wl,-rpath,{prefix / 'lib'}"], check=True)
    return float(subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--compensator", default=None, help="exported compensator file (default: the stand-in)")
    ap.add_argument("--radius", type=float, default=1.0, help="stand-in support radii, times the span")
    ap.add_argument("--support", type=int, default=1000)
    ap.add_argument("--out", default=None, help="folder for the generated sources (default: temp)")
    ap.add_argument("--eigen-include", default=os.environ.get("EIGEN_INCLUDE"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from mmgp.physics.robot import RobotModel

    robot = RobotModel.from_name("panda", PANDA_JOINTS)
    comp = load_compensator(args.compensator) if args.compensator else stand_in(args.radius, args.support, args.seed)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="mmgp_lat_"))
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    lo, hi = robot.pin_model.lowerPositionLimit, robot.pin_model.upperPositionLimit
    queries = {"near": comp.support[rng.integers(comp.support.shape[0], size=256)] + rng.normal(size=(256, 7)) * 0.05,
               "uniform": lo + (hi - lo) * rng.random((256, 7))}
    c, agree = time_c(comp, out, queries)
    t_np = _time_per_call(comp.torque, queries["near"][:32])
    import pinocchio as pin

    pm, pd = robot.pin_model, robot.pin_model.createData()
    t_pin = _time_per_call(lambda q: pin.computeGeneralizedGravity(pm, pd, q), queries["uniform"])
    t_cpp = time_pinocchio_cpp(pm, out, args.eigen_include)
    nb = {k: np.sum(np.sum(((Q[:, None] - comp.support[None]) / comp.lengthscales) ** 2, 2) < 1, 1)
          for k, Q in queries.items()}
    print(f"compensator: {comp.kind}, {comp.n_joints} joints, {comp.support.shape[0]} support points, prior "
          f"{comp.prior is not None}, radii {np.array2string(comp.lengthscales, precision=2)} rad "
          f"({args.compensator or f'stand-in, radius {args.radius} x span'})")
    for k in nb:
        print(f"  {k:8s} queries: support points within the radius: mean {nb[k].mean():.1f}, max {nb[k].max()}; "
              f"inside the region {np.mean(nb[k] > 0):.2f}")
    print(f"{'evaluator (us per call)':52s} {'near':>8s} {'uniform':>8s}")
    print(f"{'C pure loop, gcc -O2: tau_ff (prior + deviation)':52s} {c['near']:8.2f} {c['uniform']:8.2f}")
    print(f"{'C via ctypes (incl. Python call overhead)':52s} {c['ctypes_near']:8.2f}")
    print(f"{'numpy load_compensator(...).torque(q)':52s} {t_np * 1e6:8.1f}")
    print(f"{'peer: Pinocchio computeGeneralizedGravity, Python':52s} {'':8s} {t_pin * 1e6:8.2f}")
    print(f"{'peer: Pinocchio computeGeneralizedGravity, C++ -O2':52s} {'':8s} "
          + (f"{t_cpp:8.2f}" if t_cpp is not None else "  (no Eigen headers: --eigen-include)"))
    print(f"C vs numpy: max |tau difference| / torque scale = {agree:.2e} over {sum(map(len, queries.values()))} poses")


if __name__ == "__main__":
    main()
