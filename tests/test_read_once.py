"""Each command opens each of its logs once (issue 32): the robot is found in the RobotLog the
command read, and the diagnosis, the training and the comparison use that RobotLog. Counted at
the libraries' own openers (pyarrow's ParquetFile, read_table, read_schema, read_metadata;
Python's open), so every way into a file counts, whatever mmgp function takes it."""
from __future__ import annotations

import builtins
import io
import os
import shutil
from collections import Counter
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from mmgp.cli import app

ROOT = Path(__file__).resolve().parents[1]
REPLICA = ROOT / "mmgp/resources/replica"
runner = CliRunner()
FAST_TRAIN = "train:\n  max_sweeps: 2\n  min_sweeps: 1\n  average_last: 1\n  fit_iter: 5\n"


@pytest.fixture
def opened(monkeypatch):
    """Counter of the files opened for reading, by resolved path."""
    seen: Counter = Counter()

    def note(target):
        if isinstance(target, (str, os.PathLike)):
            seen[str(Path(target).resolve())] += 1

    real_init, real_open = pq.ParquetFile.__init__, io.open

    def parquet_file(self, source, *a, **k):
        note(source)
        return real_init(self, source, *a, **k)

    def counted(real):
        def reader(source, *a, **k):
            note(source)
            return real(source, *a, **k)
        return reader

    def open_(file, mode="r", *a, **k):
        if not any(c in mode for c in "wax+"):
            note(file)
        return real_open(file, mode, *a, **k)

    monkeypatch.setattr(pq.ParquetFile, "__init__", parquet_file)
    for name in ("read_table", "read_schema", "read_metadata"):  # these open a path themselves
        monkeypatch.setattr(pq, name, counted(getattr(pq, name)))
    monkeypatch.setattr(io, "open", open_)
    monkeypatch.setattr(builtins, "open", open_)
    return seen


@pytest.fixture
def lever(tmp_path):
    """The replica log naming its URDF in its metadata (so the robot is found in the log), and
    the same log as CSV (no metadata: the URDF is given)."""
    log = tmp_path / "lever.parquet"
    shutil.copy(REPLICA / "replica_lever.urdf", tmp_path / "lever.urdf")
    table = pq.read_table(REPLICA / "replica_log.parquet")
    meta = dict(table.schema.metadata or {}, urdf=b"lever.urdf")
    pq.write_table(table.replace_schema_metadata(meta), log)
    csv = tmp_path / "lever.csv"
    pd.read_parquet(log).to_csv(csv, index=False)
    config = tmp_path / "fast.yaml"
    config.write_text(FAST_TRAIN)
    return {"log": log, "csv": csv, "urdf": tmp_path / "lever.urdf", "config": config, "dir": tmp_path}


def _run(args):
    res = runner.invoke(app, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res


@pytest.mark.parametrize("kind", ["log", "csv"])
def test_train_and_predict_open_their_log_once(lever, opened, kind):
    log, out = lever[kind], lever["dir"] / f"model_{kind}"
    robot = [] if kind == "log" else ["--urdf", lever["urdf"]]
    _run(["train", log, "--out", out, "--config", lever["config"], "--quiet", *robot])
    assert opened[str(log.resolve())] == 1
    opened.clear()
    _run(["predict", out, log, "--out", lever["dir"] / f"pred_{kind}.parquet"])
    assert opened[str(log.resolve())] == 1


def test_diagnose_and_compare_open_their_log_once(lever, opened):
    log = lever["log"]
    _run(["diagnose", log, "--out", lever["dir"] / "diag", "--quiet"])
    assert opened[str(log.resolve())] == 1
    opened.clear()
    _run(["compare", log, "--out", lever["dir"] / "cmp", "--max-train", "60", "--quiet"])
    assert opened[str(log.resolve())] == 1


def test_a_fleet_task_opens_its_log_once(lever, opened):
    """The task (diagnosis and training) reads the log once; the driver reads each log's
    start_time before any task runs (a malformed one is the whole run's bad input), from the
    Parquet footer: two opens per log in all."""
    from mmgp.fleet.work import process_log

    log = lever["log"]
    job = {"path": str(log), "name": "lever", "log_time": 0.0, "log_time_source": "mtime", "train": True,
           "diagnosis_settings": {"gp": False},
           "train_settings": {"max_sweeps": 2, "min_sweeps": 1, "average_last": 1, "fit_iter": 5}}
    outcome = process_log(job)
    assert outcome["error"] is None and outcome["training"] is not None
    assert opened[str(log.resolve())] == 1
    opened.clear()
    _run(["fleet", log, "--out", lever["dir"] / "fleet", "--serial", "--quiet"])
    assert opened[str(log.resolve())] == 2
