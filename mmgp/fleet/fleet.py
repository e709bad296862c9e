"""The fleet: many logs diagnosed (and optionally trained on) as Ray tasks, one table, drift flags."""
from __future__ import annotations

import json
import math
import re
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

from sklearn.base import BaseEstimator
from sklearn.exceptions import NotFittedError

from ..data.outputs import atomic_write_bytes, jsonable, write_table
from ..errors import InputError
from .drift import flag_drift
from ..threads import usable_cores
from .engine import run_ray, run_serial
from .table import fleet_table
from .work import log_time

LOG_SUFFIXES = (".parquet", ".pq", ".csv")
ENGINES = ("ray", "serial")


def expand_logs(items: Sequence[str | Path]) -> list[Path]:
    """The logs named by ``items``: a file stands for itself (a missing one is reported by its
    task), a folder for its ``*.parquet``/``*.pq``/``*.csv`` files (not recursive; files whose
    name ends in ``labels`` are ground-truth label files, not logs). Order kept, repeats dropped."""
    paths, seen = [], set()
    for item in items:
        item = Path(item)
        if item.is_dir():
            found = sorted(p for p in item.iterdir() if p.is_file() and p.suffix.lower() in LOG_SUFFIXES
                           and not p.stem.lower().endswith("labels"))
            if not found:
                raise InputError(f"no logs ({', '.join(LOG_SUFFIXES)}) in this folder", file=item)
        else:
            found = [item]
        for p in found:
            if p.resolve() not in seen:
                seen.add(p.resolve())
                paths.append(p)
    if not paths:
        raise InputError("no logs given")
    return paths


def _iso(seconds: float) -> str | None:
    return datetime.fromtimestamp(seconds, tz=timezone.utc).isoformat() if math.isfinite(seconds) else None


def _folder_names(logs: list[str]) -> dict[str, str]:
    names: dict[str, str] = {}
    for log in logs:
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(log).stem) or "log"
        name, i = stem, 1
        while name in names.values():
            i += 1
            name = f"{stem}_{i}"
        names[log] = name
    return names


class Fleet(BaseEstimator):
    """Diagnose every log of a fleet (and with ``train`` also train on it), each as one task.

    Parameters (stored unchanged; checked in :meth:`fit`):
    ``robot`` / ``urdf``: nominal model for every log (else each log's metadata names it);
    ``train``: also run the training per log; ``engine``: ``"ray"`` (tasks on Ray) or
    ``"serial"`` (one after another in this process, no Ray needed); ``address``: Ray cluster
    address (None: a local Ray on this machine); ``workers``: tasks in flight at once (local
    default: the cores available); ``baseline``: first logs per robot that define the drift
    baseline (see :mod:`mmgp.fleet.drift`); ``diagnosis_settings`` / ``train_settings``: dicts
    passed to the diagnosis (``Diagnoser`` settings) and the training (``MultimodalGP`` settings).

    Learned: ``logs_`` (paths), ``outcomes_`` (per log: findings, errors, seconds), ``table_``
    (the fleet table, see :mod:`mmgp.fleet.table`, with ``drift``), ``drift_`` (drift.json),
    ``seconds_`` (wall time of the run, Ray's start included), ``timings_`` (``ray_start_s``).
    """

    def __init__(self, robot: str | None = None, urdf: str | Path | None = None, train: bool = False,
                 engine: str = "ray", address: str | None = None, workers: int | None = None,
                 baseline: int = 5, diagnosis_settings: dict | None = None, train_settings: dict | None = None):
        vars(self).update({k: v for k, v in locals().items() if k != "self"})  # stored unchanged

    def _check(self) -> None:
        if self.robot is not None and self.urdf is not None:
            raise InputError("give either a robot name or a URDF, not both")
        if self.engine not in ENGINES:
            raise InputError(f"engine must be one of {ENGINES}, got {self.engine!r}")
        if self.workers is not None and int(self.workers) < 1:
            raise InputError(f"--workers must be at least 1, got {self.workers}")
        if int(self.baseline) < 1:
            raise InputError(f"--baseline must be at least 1 log, got {self.baseline}")

    def _job(self, path: Path) -> dict:
        # the time is read here, before any task runs: a malformed start_time is bad input of the
        # whole run (one error, exit 2), not a failed row found after minutes of diagnosis
        seconds, source = log_time(path)
        return {"path": str(path.resolve()), "name": str(path), "log_time": seconds, "log_time_source": source,
                "robot": self.robot,
                "urdf": None if self.urdf is None else str(Path(self.urdf).resolve()), "train": bool(self.train),
                "diagnosis_settings": self.diagnosis_settings, "train_settings": self.train_settings}

    def fit(self, logs: Sequence[str | Path], progress=None) -> "Fleet":
        """Run every log (files or folders, see :func:`expand_logs`). ``progress(done, total,
        outcome)`` is called as each log finishes. A log that fails is reported, never raised."""
        self._check()
        self.logs_ = expand_logs(logs)
        jobs = [self._job(p) for p in self.logs_]
        t0 = time.perf_counter()
        self.timings_ = {}
        if self.engine == "serial":
            self.outcomes_ = run_serial(jobs, progress)
        else:
            self.outcomes_ = run_ray(jobs, address=self.address, workers=self.workers, progress=progress,
                                     timings=self.timings_)
        self.seconds_ = time.perf_counter() - t0
        self.table_, self.drift_ = flag_drift(fleet_table(self.outcomes_), int(self.baseline))
        return self

    def _fitted(self) -> None:
        if not hasattr(self, "table_"):
            raise NotFittedError("this Fleet has not run yet: call fit(logs) first")

    def summary(self) -> dict:
        """Run-level facts: engine, workers, wall time, and per log its time, status and seconds."""
        self._fitted()
        folders = _folder_names([o["log"] for o in self.outcomes_])
        workers = 1 if self.engine == "serial" else (self.workers or (usable_cores() if self.address is None
                                                                       else None))
        logs = [{"log": o["log"], "folder": f"logs/{folders[o['log']]}", "robot": o["robot"],
                 "log_time": _iso(o["log_time"]), "log_time_source": o["log_time_source"],
                 "n_findings": None if o["findings"] is None else len(o["findings"]),
                 "error": o["error"], "seconds": o["seconds"]} for o in self.outcomes_]
        return {"engine": self.engine, "address": self.address, "workers": workers, "seconds": self.seconds_,
                "ray_start_seconds": self.timings_.get("ray_start_s"),
                "n_logs": len(logs), "n_failed": sum(o["error"] is not None for o in self.outcomes_), "logs": logs}

    def write(self, out_dir) -> Path:
        """Write ``fleet.parquet``, ``drift.json``, ``fleet.json`` (the summary), ``trends/*.png``,
        ``report.html`` (all of these on one self-contained page) and per log ``logs/<name>/`` (``findings.json``; ``train/`` with the model, labels and
        report when training; ``error.txt`` when it failed) into the folder ``out_dir``."""
        from .plots import plot_trends
        from .report import write_fleet_report

        self._fitted()
        out = Path(out_dir)
        write_table(out / "fleet.parquet", self.table_)
        atomic_write_bytes(out / "drift.json", json.dumps(jsonable(self.drift_), indent=2).encode())
        summary = self.summary()
        summary["trends"] = plot_trends(self.table_, self.drift_, out / "trends")
        atomic_write_bytes(out / "fleet.json", json.dumps(jsonable(summary), indent=2).encode())
        write_fleet_report(out, summary, self.drift_, {o["log"]: o["findings"] for o in self.outcomes_})
        for o, s in zip(self.outcomes_, summary["logs"]):
            _write_log_outputs(out / s["folder"], o)
        return out


def _write_log_outputs(folder: Path, outcome: dict) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    if outcome["diagnosis"] is not None:
        atomic_write_bytes(folder / "findings.json", json.dumps(jsonable(outcome["diagnosis"]), indent=2).encode())
    if outcome["training"] is not None:
        train = folder / "train"
        train.mkdir()
        for name, data in outcome["training"]["files"].items():
            atomic_write_bytes(train / name, data)
        atomic_write_bytes(train / "report.json", json.dumps(outcome["training"]["report"], indent=2).encode())
    if outcome["error"] is not None:
        text = outcome["error"] + "\n" + outcome.get("traceback", "")
        atomic_write_bytes(folder / "error.txt", text.encode())
