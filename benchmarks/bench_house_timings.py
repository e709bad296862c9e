"""Issue 32's timings: `mmgp diagnose` on a 10,000-sample 7-DOF log and `mmgp train` on val06, with
the code before the house work and after it, in one run.

Each side runs from its own detached checkout (``git worktree add``) as a whole command-line
process (`python -c "...mmgp.cli.main()"` with the checkout first on ``sys.path``, one thread),
the two sides interleaved repeat by repeat so that the machine's load falls on both alike.
Prints each command's wall time per side (minimum over the repeats) and after / before.

The logs are ``../shared/validation``'s: val11 (Panda, 10,000 samples at 100 Hz, pushes) for
``diagnose`` and val06 (Panda, 15,000 samples, two payload modes) for ``train --modes 2``.
Between the two revisions other issues changed what the commands compute (labelling, diagnosis),
so the ratio is the tree's, not the house work's alone.

Usage: python benchmarks/bench_house_timings.py [--before REV] [--after REV] [--repeats N] [--only diagnose,train]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOGS = Path("/work/shared/validation/logs")
#: the commit before the first change made for issue 32 (1b7ae4c, "One robust scale ...")
BEFORE = "1b7ae4c^"


def commands(out: Path) -> dict[str, list[str]]:
    return {"diagnose": ["diagnose", str(LOGS / "val11.parquet"), "--out", str(out / "diagnose"), "--force", "--quiet"],
            "train": ["train", str(LOGS / "val06.parquet"), "--modes", "2", "--out", str(out / "train"), "--force",
                      "--quiet"]}


def run(tree: Path, args: list[str]) -> float:
    code = (f"import sys; sys.path.insert(0, {str(tree)!r}); import mmgp; "
            f"assert mmgp.__file__.startswith({str(tree)!r}); from mmgp.cli import main; "
            "sys.argv[0] = 'mmgp'; sys.exit(main())")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, *args], check=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default=BEFORE)
    ap.add_argument("--after", default="HEAD")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--only", default="diagnose,train")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="mmgp-house-") as tmp:
        tmp = Path(tmp)
        trees = {}
        for side, rev in (("before", a.before), ("after", a.after)):
            trees[side] = tmp / side
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(trees[side]), rev], check=True)
        try:
            times = {(c, s): [] for c in a.only.split(",") for s in trees}
            for _ in range(a.repeats):
                for name in a.only.split(","):
                    for side, tree in trees.items():
                        times[name, side].append(run(tree, commands(tmp / f"out-{side}")[name]))
                        print(f"{name:9s} {side:6s} {times[name, side][-1]:8.1f} s", flush=True)
            for name in a.only.split(","):
                b, f = min(times[name, "before"]), min(times[name, "after"])
                print(f"{name}: before ({a.before}) {b:.1f} s, after ({a.after}) {f:.1f} s, after / before {f / b:.2f}")
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)


if __name__ == "__main__":
    main()
