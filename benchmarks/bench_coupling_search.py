"""The coupled-transmission search alone on logs: its wall time, what it finds, its best candidate.

The diagnosis's steps up to the search (``Diagnoser`` defaults: derivatives, the effect library,
the low-pass, the folds), then ``coupling.find_couplings`` on the valid equations without the
multimodal learner's weights (the learner is the slow stage before it and only re-weights
samples). ``--module PATH`` runs another version of ``mmgp/diagnosis/coupling.py`` (e.g. an
older commit's, ``git show REV:mmgp/diagnosis/coupling.py > /tmp/old.py``) on the same problem.

Logs: paths, ``valNN`` (``/work/shared/validation/logs``), or ``tx40`` (the real TX40's training
rows as ``bench_figaroh.py`` writes them, FIGAROH's split). Prints one JSON line per log.

Usage: python benchmarks/bench_coupling_search.py val05 val09 tx40 [--module PATH] [--repeat N]
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VAL = Path("/work/shared/validation/logs")


def log_path(name: str, folder: Path) -> Path:
    """The log file ``name`` stands for (see the module docstring)."""
    if name == "tx40":
        sys.path.insert(0, str(Path(__file__).parent))
        from bench_figaroh import TIAGO_URDF, training_log

        return training_log("tx40", folder, TIAGO_URDF)
    return VAL / f"{name}.parquet" if name.startswith("val") and "/" not in name else Path(name)


def search_module(path: str | None):
    """The coupling module: the package's, or the file ``path`` loaded in its place."""
    if path is None:
        from mmgp.diagnosis import coupling

        return coupling
    spec = importlib.util.spec_from_file_location("mmgp.diagnosis._coupling_alt", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # (dataclasses look their module up there)
    spec.loader.exec_module(mod)
    return mod


def problem(path: Path):
    """The diagnosis problem of ``path`` as ``Diagnoser`` (defaults) builds it before the search."""
    from mmgp.diagnosis import Diagnoser
    from mmgp.diagnosis import stages as st
    from mmgp.diagnosis.pipeline import _read
    from mmgp.physics.robot import load_robot

    d = Diagnoser()
    robot = load_robot(log_path=path)
    log, n_full, smear_s = st.prepare_log(_read(path, robot), d._differentiator(), d.max_samples)
    return d, st.build_problem(log, robot, n_full, smear_s, effects=d.effects, payload_links=d.payload_links,
                               n_folds=d.n_folds, **d._settings("sign_noise_factor", "lowpass", "rest_factor"))


def run(name: str, folder: Path, mod, repeat: int) -> dict:
    from mmgp.diagnosis import stages as st
    from mmgp.threads import limit_threads

    with limit_threads(1, blas_only=True):
        d, prob = problem(log_path(name, folder))
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            _, found, ev = mod.find_couplings(prob, prob.M, st.nominal_weights(prob), alpha=d.alpha, seed=d.seed)
            times.append(time.perf_counter() - t0)
    names = prob.ctx.joint_names
    return {"log": name, "search_s": [round(x, 1) for x in times],
            "found": [{"joint": names[e.index], "coupled": names[e.coupled], "ratio": round(e.ratio, 4)} for e in found],
            "evidence": [{k: v for k, v in e.items() if k != "pairs"} for e in ev]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("logs", nargs="+")
    ap.add_argument("--module", default=None, help="a coupling.py to run instead of the package's")
    ap.add_argument("--repeat", type=int, default=1)
    a = ap.parse_args(argv)
    mod = search_module(a.module)
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.logs:
            print(json.dumps(run(name, Path(tmp), mod, a.repeat), default=float), flush=True)
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
