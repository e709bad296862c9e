"""MuJoCo is optional (extra ``mmgp[sim]``): the core imports and trains with it missing.

The check runs in a fresh interpreter in which a meta-path finder refuses ``mujoco``, as on a
machine where ``pip install mmgp`` did not install it: every module outside ``mmgp.sim`` imports,
``python -m mmgp.cli train`` learns from the shipped demo log, and ``mmgp.sim`` itself fails with
the one message that names the extra.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd

import mmgp

ROOT = Path(mmgp.__file__).resolve().parents[1]

_CHILD = textwrap.dedent("""
    import importlib, importlib.abc, json, runpy, sys
    from pathlib import Path

    class RefuseMujoco(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "mujoco" or name.startswith("mujoco."):
                raise ImportError("No module named 'mujoco' (refused by the test)")
            return None

    sys.meta_path.insert(0, RefuseMujoco())
    root, out, config, log = (Path(a) for a in sys.argv[1:5])
    report = {"imported": [], "sim_error": None}
    for f in sorted((root / "mmgp").rglob("*.py")):
        rel = f.relative_to(root).with_suffix("")
        if rel.parts[:2] == ("mmgp", "sim") or rel.name == "__main__":
            continue  # the optional package; __main__ runs the command line when imported
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        importlib.import_module(name)
        report["imported"].append(name)
    try:
        import mmgp.sim  # noqa: F401
    except ImportError as exc:
        report["sim_error"] = str(exc)
    sys.argv = ["mmgp", "train", str(log), "--out", str(out), "--config", str(config), "--quiet"]
    try:
        runpy.run_module("mmgp.cli", run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as exc:
        code = exc.code or 0
    report["exit_code"] = code
    report["mujoco_loaded"] = "mujoco" in sys.modules
    print("REPORT " + json.dumps(report))
""")


def test_core_imports_and_trains_with_mujoco_refused(tmp_path):
    from mmgp.resources import demo_files

    log, _ = demo_files()
    config = tmp_path / "short.yaml"
    config.write_text("train:\n  max_sweeps: 2\n  min_sweeps: 1\n")
    out = tmp_path / "trained"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(ROOT), str(out), str(config), str(log)],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("REPORT ")]
    assert proc.returncode == 0 and lines, proc.stderr[-3000:]
    report = json.loads(lines[-1][len("REPORT "):])
    n_modules = sum(1 for f in (ROOT / "mmgp").rglob("*.py")
                    if "sim" not in f.relative_to(ROOT).parts[:2] and f.stem != "__main__")
    assert len(report["imported"]) == n_modules
    assert {"mmgp.cli", "mmgp.labelling.sem", "mmgp.diagnosis", "mmgp.compensator"} <= set(report["imported"])
    assert report["sim_error"] is not None and "mmgp[sim]" in report["sim_error"]
    assert report["exit_code"] == 0, proc.stderr[-3000:]
    assert not report["mujoco_loaded"]
    labels = pd.read_parquet(out / "labels.parquet")
    assert len(labels) == len(pd.read_parquet(log)) == 330
    assert set(labels["disturbed"].unique()) <= {0, 1}


_GP_ONLY_CHILD = textwrap.dedent("""
    import importlib.abc, json, sys
    import numpy as np

    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("pinocchio", "example_robot_data", "mujoco"):
                raise ImportError("No module named " + name + " (refused by the test)")
            return None

    sys.meta_path.insert(0, Refuse())
    from mmgp import MultimodalGP
    from mmgp.data.logs import write_log
    rng = np.random.default_rng(0)
    t = np.arange(400) * 0.01
    q = np.stack([np.sin(t), np.cos(0.7 * t)], 1)
    tau = 2.0 * np.sin(q) + 0.01 * rng.standard_normal(q.shape)
    write_log(sys.argv[1], t, q, tau)
    model = MultimodalGP(n_modes=1, disturbance=False, fit_points=200).fit([sys.argv[1]])
    dq = np.stack([np.cos(t), -0.7 * np.sin(0.7 * t)], 1)
    ddq = np.stack([-np.sin(t), -0.49 * np.cos(0.7 * t)], 1)
    mean, _ = model.predict(q[5::40], dq[5::40], ddq[5::40])
    print("REPORT " + json.dumps({"err": float(np.abs(mean - 2.0 * np.sin(q[5::40])).max()),
                                  "pinocchio": "pinocchio" in sys.modules}))
""")


def test_gp_only_training_needs_no_pinocchio(tmp_path):
    """A log that names no robot trains (GP only) where Pinocchio cannot be imported, e.g. a GPU
    machine without it; the fit recovers the closed-form torque 2 sin(q) it was generated from."""
    run = subprocess.run([sys.executable, "-c", _GP_ONLY_CHILD, str(tmp_path / "log.parquet")],
                         capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"))
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads(next(x for x in run.stdout.splitlines() if x.startswith("REPORT "))[7:])
    assert not report["pinocchio"]
    assert report["err"] < 0.05
