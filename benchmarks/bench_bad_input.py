"""Issue 31: a bad path or column answers in under a second.

Times, as whole processes (median of ``--runs``): ``mmgp train|diagnose|compare`` on a missing
file and on a log without its torque column, beside ``mmgp --version`` (the floor: Python and
the command-line parser) and the import that the commands paid before answering until
2026-11-27 (``import mmgp.estimator``: torch and scikit-learn), from the same run.

Usage: python benchmarks/bench_bad_input.py [--runs 5]
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd


def wall(cmd: list[str], runs: int) -> tuple[float, int]:
    times, code = [], 0
    for _ in range(runs):
        t0 = time.perf_counter()
        code = subprocess.run(cmd, capture_output=True).returncode
        times.append(time.perf_counter() - t0)
    return statistics.median(times), code


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    mmgp = [shutil.which("mmgp") or sys.executable, *([] if shutil.which("mmgp") else ["-m", "mmgp.cli"])]
    with tempfile.TemporaryDirectory() as tmp:
        no_tau = Path(tmp) / "no_tau.parquet"
        pd.DataFrame({"t": np.arange(30) * 0.01, "q_0": np.zeros(30)}).to_parquet(no_tau)
        rows = [("mmgp --version (floor)", mmgp + ["--version"]),
                ("import mmgp.estimator (paid before)", [sys.executable, "-c", "import mmgp.estimator"])]
        for command in ("train", "diagnose", "compare"):
            for what, path in (("missing file", Path(tmp) / "nope.parquet"), ("no tau_0 column", no_tau)):
                rows.append((f"mmgp {command}: {what}", mmgp + [command, str(path), "--out", str(Path(tmp) / "o")]))
        print(f"{'command':<40}{'median s':>10}{'exit':>6}")
        for name, cmd in rows:
            secs, code = wall(cmd, a.runs)
            print(f"{name:<40}{secs:>10.2f}{code:>6}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
