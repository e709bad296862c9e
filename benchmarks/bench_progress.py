"""Progress benchmark (issue 31 item 1): is any stretch of a long command silent for more than 10 s?

Runs ``mmgp train``, ``mmgp diagnose`` and ``mmgp fleet --serial`` as subprocesses on small logs
written to a temporary folder: the shipped 1-DOF demo recording, a simulated Panda log (MuJoCo,
``mmgp.sim.concealed``: Coulomb friction on joint 4 and pushes) and two simulated lever logs for
the fleet. Each command runs *piped* (stdout and stderr are pipes: the plain lines a log file
gets) and/or (``--how``) on a pseudo-terminal (the rich bar). Every line (every redraw of
the bar on a terminal, condensed) is stamped with the seconds since the command started; the
longest gap between two lines and the whole transcript are printed per command.

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python benchmarks/bench_progress.py [--samples 500] [--how piped,terminal]
        [--commands train_demo,train_panda,diagnose_panda,fleet]
"""
from __future__ import annotations

import argparse
import json
import os
import pty
import re
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from mmgp.data.outputs import write_table
from mmgp.resources import demo_files
from mmgp.sim.concealed import ACTUATOR_URDF, J, make_case

LIMIT_S = 10.0
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07|\x1b[()][A-Z0-9]")


def _write(rec, path: Path, metadata: dict) -> None:
    n = rec.q.shape[1]
    cols = {"t": rec.t}
    cols.update({f"q_{j}": rec.q[:, j] for j in range(n)})
    cols.update({f"tau_{j}": rec.tau[:, j] for j in range(n)})
    write_table(path, pd.DataFrame(cols), metadata=metadata)


def make_logs(folder: Path, samples: int) -> dict:
    """The logs the commands read: demo, a Panda log, a folder of two lever logs."""
    spec = {"name": "panda_bench", "robot": "panda", "n_samples": samples, "pushes": True,
            "effects": [{"effect": "coulomb_friction", "joint": J[3], "params": {"tau_c": 1.2}}]}
    rec, _ = make_case(spec, seed=3)
    _write(rec, folder / "panda.parquet", {"robot": "panda", "joint_names": json.dumps(rec.info["joint_names"])})
    fleet = folder / "fleet"
    fleet.mkdir()
    (fleet / "actuator.urdf").write_text(ACTUATOR_URDF)
    for i in range(2):
        spec = {"name": f"lever_{i}", "robot": "actuator", "n_samples": min(samples, 1000),
                "effects": [{"effect": "coulomb_friction", "joint": "lever_joint", "params": {"tau_c": 0.3}}]}
        rec, _ = make_case(spec, seed=1000 + i)
        day = pd.Timestamp("2026-01-01T06:00:00Z") + pd.Timedelta(days=i)
        _write(rec, fleet / f"lever_{i}.parquet", {"urdf": "actuator.urdf", "joint_names": json.dumps(["lever_joint"]),
                                                   "start_time": day.isoformat()})
    return {"demo": demo_files()[0], "panda": folder / "panda.parquet", "fleet": fleet}


def commands(logs: dict, out: Path) -> dict:
    return {"train_demo": ["train", str(logs["demo"]), "--out", str(out / "train_demo")],
            "train_panda": ["train", str(logs["panda"]), "--out", str(out / "train_panda")],
            "diagnose_panda": ["diagnose", str(logs["panda"]), "--out", str(out / "diagnose_panda")],
            "fleet": ["fleet", str(logs["fleet"]), "--serial", "--out", str(out / "fleet")]}


def _env() -> dict:
    return dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="110")


def run_piped(args: list[str]) -> tuple[list[tuple[float, str, str]], int]:
    """(seconds since start, stream, line) of every line the command wrote, and its exit status."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-P", "-m", "mmgp.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=_env())
    streams = {proc.stdout.fileno(): ("out", proc.stdout, b""), proc.stderr.fileno(): ("err", proc.stderr, b"")}
    lines = []
    while streams:
        ready, _, _ = select.select(list(streams), [], [], 1.0)
        for fd in ready:
            name, f, buf = streams[fd]
            chunk = os.read(fd, 65536)
            now = time.perf_counter() - t0
            if not chunk:
                if buf:
                    lines.append((now, name, buf.decode(errors="replace")))
                del streams[fd]
                continue
            buf += chunk
            *done, buf = buf.split(b"\n")
            lines += [(now, name, d.decode(errors="replace")) for d in done]
            streams[fd] = (name, f, buf)
    return lines, proc.wait()


def run_tty(args: list[str]) -> tuple[list[tuple[float, str, str]], int]:
    """The same on a pseudo-terminal (stdout and stderr both): each distinct screen line, ANSI
    codes removed, stamped when it first appeared (a bar's redraws with new numbers count)."""
    t0 = time.perf_counter()
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-P", "-m", "mmgp.cli", *args], stdout=slave, stderr=slave,
                            env=dict(_env(), TERM="xterm-256color"))
    os.close(slave)
    lines, buf = [], ""
    while True:
        ready, _, _ = select.select([master], [], [], 1.0)
        if not ready:
            if proc.poll() is not None:
                break
            continue
        try:
            chunk = os.read(master, 65536)
        except OSError:
            break
        if not chunk:
            break
        now = time.perf_counter() - t0
        buf += ANSI.sub("", chunk.decode(errors="replace"))
        *done, buf = re.split(r"[\r\n]", buf)
        for d in done:
            if d.strip() and (not lines or d.rstrip() != lines[-1][2]):
                lines.append((now, "tty", d.rstrip()))
    os.close(master)
    return lines, proc.wait()


def longest_gap(lines, end: float | None = None) -> float:
    times = [0.0] + [t for t, _, _ in lines] + ([end] if end is not None else [])
    return max((b - a for a, b in zip(times, times[1:])), default=0.0)


def condensed(lines, every_s: float = 5.0):
    """A terminal transcript without most of the bar's redraws: a line is kept when no line with
    the same text before its numbers was kept in the last ``every_s`` seconds."""
    kept, last = [], {}
    for t, s, line in lines:
        key = re.sub(r"[\d:.\-/━╸╺ ]+", " ", line)[:50]
        if t - last.get(key, -1e9) >= every_s:
            kept.append((t, s, line))
            last[key] = t
    return kept


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=500, help="samples of the simulated Panda log")
    ap.add_argument("--how", default="piped", help="piped, terminal (a pseudo-terminal) or piped,terminal")
    ap.add_argument("--commands", default="train_demo,train_panda,diagnose_panda,fleet")
    a = ap.parse_args()
    summary = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        logs = make_logs(tmp, a.samples)
        print(f"logs: demo {logs['demo'].name}, panda {a.samples} samples (7 DOF), fleet 2 lever logs", flush=True)
        for how, runner in [(h, {"piped": run_piped, "terminal": run_tty}[h]) for h in a.how.split(",")]:
            out = tmp / how
            out.mkdir()
            for name, args in commands(logs, out).items():
                if name not in a.commands.split(","):
                    continue
                t0 = time.perf_counter()
                lines, rc = runner(args)
                total = time.perf_counter() - t0
                gap = longest_gap(lines, total)
                summary.append((name, how, gap, total, rc))
                print(f"\n=== {name} ({how}): mmgp {' '.join(args[:1])} ... exit {rc}, {total:.1f} s, "
                      f"longest gap {gap:.1f} s ===", flush=True)
                for t, s, line in (condensed(lines) if how == "terminal" else lines):
                    print(f"{t:7.1f} {s:3s} | {line}", flush=True)
    print("\ncommand          how       longest gap   total   exit  (gap: between lines, the start and the exit)")
    for name, how, gap, total, rc in summary:
        flag = "" if gap <= LIMIT_S else f"  > {LIMIT_S:.0f} s"
        print(f"{name:16s} {how:9s} {gap:8.1f} s {total:8.1f} s  {rc:3d}{flag}")


if __name__ == "__main__":
    main()
