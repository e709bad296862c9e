"""Wall time of ``mmgp export`` on a large 7-DOF model: the code before the export-time change vs now.

The model: a trained run folder (``--run``), or, with ``--make DIR``, one made here: a 10,000-sample
MuJoCo Panda recording (:func:`mmgp.sim.panda_modes`, 100 Hz, a constant 2 kg payload at
panda_link8, pushes; ``--no-pushes`` for one whose every sample is undisturbed, the largest
support) trained with the default settings (every sample kept: ``rate_hz`` and ``final_support``
null), 4-8 minutes on 2 cores.

Three exports of the same run folder, each a fresh ``python -m mmgp.cli export`` process (imports
included), timed by wall clock and by the process's CPU time (user + system over its threads; on
a shared machine the wall time counts the other processes' turns):

* ``before``: the package as of ``--old-ref`` (default f9f7775, the commit this change started
  from), extracted with ``git archive`` into a temporary folder; it ignores the stored weights.
* ``after``: this checkout, on the run as saved (with the solved GP weights training stores).
* ``after, no stored weights``: this checkout on a copy of the run without them (a model saved
  before the change, or one whose weights no training step solved): the weights are solved at load.

Then tau_ff of the compensator files at the reference's support points and 5,000 uniform points
of its workspace box: the largest deviation from ``before`` (from ``after, no stored weights``
where ``--before-limit`` stopped the old code), in N*m and relative to the largest |tau_ff|. Printed with the machine's load average (the 2 cores are shared: wall times vary with it).

    python benchmarks/bench_export_time.py --run RUN_DIR [--old-ref REF] [--before-limit S] [--keep DIR] [--json OUT]
    python benchmarks/bench_export_time.py --make /tmp/exporttime [--no-pushes]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def make_run(folder: Path, pushes: bool) -> Path:
    """Record a 10,000-sample Panda log with a 2 kg payload and train on it; returns the run folder."""
    from mmgp.sim import panda_modes

    folder.mkdir(parents=True, exist_ok=True)
    tag = "" if pushes else "_nopush"
    log, run = folder / f"panda10k{tag}.parquet", folder / f"run10k{tag}"
    if not log.exists():
        panda_modes(seed=0 if pushes else 1, n_samples=10_000, rate_hz=100.0, payloads=(2.0,), pushes=pushes).write(log)
    if not (run / "model.json").exists():
        subprocess.run([sys.executable, "-m", "mmgp.cli", "train", str(log), "--out", str(run), "--quiet", "--force"],
                       check=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    return run


def without_weights(run: Path, dst: Path) -> Path:
    """A copy of the run's model files without the stored GP weights (as saved before the change)."""
    dst.mkdir(parents=True)
    with np.load(run / "model.npz") as z:
        np.savez(dst / "model.npz", **{k: z[k] for k in z.files if not k.startswith("weights_")})
    meta = json.loads((run / "model.json").read_text())
    meta.pop("gp_weights_sha256", None)
    (dst / "model.json").write_text(json.dumps(meta))
    return dst


def timed_export(code_root: Path, run: Path, out: Path, limit: float | None = None) -> tuple | None:
    """(wall s, CPU s of the process: user + system, all its threads) of ``python -m mmgp.cli export
    RUN --out OUT`` with ``code_root`` first on the path; None when it was stopped after ``limit`` s."""
    env = dict(os.environ, PYTHONPATH=str(code_root))
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    try:
        subprocess.run([sys.executable, "-m", "mmgp.cli", "export", str(run), "--out", str(out), "--force"],
                       check=True, env=env, cwd=code_root, stdout=subprocess.DEVNULL, timeout=limit)
    except subprocess.TimeoutExpired:
        return None
    wall, cpu1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)


def deviation(ref_path: Path, other_path: Path, n: int = 5000) -> tuple[float, float]:
    """(max |tau_ff - tau_ff_ref| N*m, that / max |tau_ff_ref|) at the reference's support and
    ``n`` uniform points of its workspace box."""
    from mmgp import load_compensator

    ref, other = load_compensator(ref_path), load_compensator(other_path)
    lo, hi = ref.bounds
    q = np.concatenate([ref.support, lo + np.random.default_rng(0).random((n, ref.n_joints)) * (hi - lo)])
    a, b = ref.torque(q), other.torque(q)
    dev = float(np.max(np.abs(a - b)))
    return dev, dev / float(np.max(np.abs(a)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, help="a run folder written by 'mmgp train'")
    ap.add_argument("--make", type=Path, help="make the 10,000-sample Panda run in this folder (reused)")
    ap.add_argument("--no-pushes", action="store_true", help="with --make: a log without pushes")
    ap.add_argument("--old-ref", default="f9f7775", help="git ref of the code before the change")
    ap.add_argument("--before-limit", type=float, help="stop the old code's export after this many seconds")
    ap.add_argument("--keep", type=Path, help="copy the compensator files into this folder")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    if (args.run is None) == (args.make is None):
        ap.error("give --run or --make")
    # resolved: each export runs in its code's folder
    run = (args.run if args.run is not None else make_run(args.make, not args.no_pushes)).resolve()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        old_root = tmp / "old"
        old_root.mkdir()
        tar = subprocess.run(["git", "-C", str(ROOT), "archive", args.old_ref, "mmgp"], check=True,
                             capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(old_root)], input=tar, check=True)
        bare = without_weights(run, tmp / "bare")
        with np.load(run / "model.npz") as z:
            n_support, stored = int(z["X_0"].shape[0]), "weights_0" in z.files
        load0 = os.getloadavg()
        times = {"after": timed_export(ROOT, run, tmp / "after.json"),
                 "after, no stored weights": timed_export(ROOT, bare, tmp / "bare.json"),
                 "before": timed_export(old_root, run, tmp / "before.json", args.before_limit)}
        load1 = os.getloadavg()
        # tau_ff against the old code's file, or, where it was stopped, the file of the fresh solve
        ref = "before" if times["before"] is not None else "bare"
        devs = {k: deviation(tmp / f"{ref}.json", tmp / f"{f}.json")
                for k, f in (("after", "after"), ("after, no stored weights", "bare")) if f != ref}
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
            for f in tmp.glob("*.json"):
                shutil.copy(f, args.keep / f.name)
    print(f"run {run}: nominal-mode support {n_support} samples, stored weights: {stored}; "
          f"old code: {args.old_ref}; {os.cpu_count()} cores, load average {load0[0]:.1f} before, "
          f"{load1[0]:.1f} after")
    print(f"tau_ff deviations from the export '{'before' if ref == 'before' else 'after, no stored weights'}'")
    print(f"{'export':<28}{'wall s':>12}{'CPU s':>9}{'max |d tau_ff| N*m':>21}{'relative':>11}")
    for k in ("before", "after", "after, no stored weights"):
        t, d = times[k], devs.get(k)
        cells = f"{'> %.0f' % args.before_limit:>12}{'':>9}" if t is None else f"{t[0]:>12.1f}{t[1]:>9.1f}"
        print(f"{k:<28}{cells}" + ("" if d is None else f"{d[0]:>21.3g}{d[1]:>11.2g}"))
    if args.json:
        args.json.write_text(json.dumps({"run": str(run), "n_support": n_support, "stored_weights": stored,
                                         "old_ref": args.old_ref, "load_average": [load0[0], load1[0]],
                                         "wall_s": times, "deviation_from": ref, "max_tau_ff_deviation": devs}, indent=1))


if __name__ == "__main__":
    main()
