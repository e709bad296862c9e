"""The fleet's time axis (contract 1.2 ``start_time``), honest statuses, units and findings per log.

References are independent of the code under test: log files written here with pyarrow (the
metadata set by hand), times given as literals and converted with the standard library, file
modification times set with ``os.utime``, and the trend figures read back from matplotlib as
the fleet drew them (``Figure.savefig`` is wrapped to keep each figure before it is saved).
"""
from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from pathlib import Path

import matplotlib
import matplotlib.dates as mdates
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.data.logs import read_log
from mmgp.errors import InputError
from mmgp.fleet.drift import flag_drift
from mmgp.physics.robot import RobotModel
from mmgp.sim.concealed import ACTUATOR_URDF
from test_fleet import lever_frame
from test_report import fake_diagnosis, read_page

matplotlib.use("Agg")
runner = CliRunner()
FAST = {"gp": False}
# five copies of one log, recorded at these times (offsets differ on purpose: the table is UTC)
STARTS = ["2026-11-23T09:30:00+00:00", "2026-11-24T11:30:00+02:00", "2026-11-25T04:15:00-05:00",
          "2026-11-26T09:30:00.250000+00:00", "2026-11-27T09:30:00Z"]
UTC = [datetime(2026, 11, 23, 9, 30, tzinfo=timezone.utc), datetime(2026, 11, 24, 9, 30, tzinfo=timezone.utc),
       datetime(2026, 11, 25, 9, 15, tzinfo=timezone.utc),
       datetime(2026, 11, 26, 9, 30, 0, 250000, tzinfo=timezone.utc), datetime(2026, 11, 27, 9, 30, tzinfo=timezone.utc)]
SAME_MTIME = 1_790_000_000  # every copy gets this modification time, as a copy tool may give them


def write_parquet(path: Path, frame: pd.DataFrame, meta: dict, mtime: float | None = SAME_MTIME) -> Path:
    """A log written with pyarrow itself (not the project's writer), its mtime set by hand."""
    table = pa.Table.from_pandas(frame, preserve_index=False)
    pq.write_table(table.replace_schema_metadata({k.encode(): v.encode() for k, v in meta.items()}), path)
    if mtime is not None:
        os.utime(path, (mtime, mtime))
    return path


def lever_copies(folder: Path, starts: list[str | None], n: int = 800) -> list[Path]:
    """Copies of one lever log (Coulomb friction 0.3 N*m), each with its own start_time."""
    (folder / "lever.urdf").write_text(ACTUATOR_URDF)
    frame = lever_frame(RobotModel.from_urdf(folder / "lever.urdf"), seed=4, tau_c=0.3, n=n)
    paths = []
    for i, start in enumerate(starts):
        meta = {"urdf": "lever.urdf", "joint_names": json.dumps(["lever_joint"])}
        if start is not None:
            meta["start_time"] = start
        paths.append(write_parquet(folder / f"copy{i}.parquet", frame, meta))
    return paths


@pytest.fixture
def drawn(monkeypatch):
    """Every figure the fleet saves, kept as drawn."""
    from matplotlib.figure import Figure

    figures, save = [], Figure.savefig

    def keep(self, *args, **kwargs):
        figures.append(self)
        return save(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def x_dates(ax) -> list[datetime]:
    line = ax.get_lines()[0]  # the errorbar's data line
    return [mdates.num2date(x) for x in mdates.date2num(line.get_xdata())]


def test_five_copies_are_placed_at_their_start_time(tmp_path, drawn, monkeypatch):
    from mmgp.fleet import work

    diagnose = work.diagnose_log  # the real diagnosis, without its GP stage (seconds per log)
    monkeypatch.setattr(work, "diagnose_log", lambda log, robot, settings: diagnose(log, robot, FAST))
    paths = lever_copies(tmp_path, STARTS, n=600)
    assert len({os.stat(p).st_mtime for p in paths}) == 1  # the file times cannot tell them apart
    out = tmp_path / "out"
    res = runner.invoke(app, ["fleet", *map(str, paths), "--out", str(out), "--serial", "--baseline", "3"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(out / "fleet.parquet")
    for path, when in zip(paths, UTC):
        rows = table[table["log"] == str(path)]
        assert (rows["log_time"] == pd.Timestamp(when)).all() and (rows["log_time_source"] == "start_time").all()
    friction = table[table["param"] == "tau_c"]
    assert len(friction) == 5 and (friction["unit"] == "N*m").all()
    # the trend plot's x data are the logs' own times, on an axis of days, not years
    (fig,) = [f for f in drawn if "coulomb_friction" in f._suptitle.get_text()]
    ax = next(a for a in fig.axes if a.get_title().startswith("tau_c"))
    assert x_dates(ax) == UTC
    lo, hi = (mdates.num2date(x) for x in ax.get_xlim())
    assert lo < UTC[0] and hi > UTC[-1] and (hi - lo).days < 6
    assert isinstance(ax.xaxis.get_major_formatter(), mdates.ConciseDateFormatter)
    assert ax.get_ylabel() == "tau_c [N*m]" and ax.get_xlabel() == "log time (UTC)"
    assert ax.get_title() == "tau_c: steady"  # identical copies, compared with a baseline of 3
    # the page: each log's time and its source, and each log's findings
    page = read_page(out / "report.html")
    logs = {r[0]["text"]: r for r in page.table("logs")}
    for path, when in zip(paths, UTC):
        assert logs[str(path)][2]["text"] == when.isoformat() and logs[str(path)][3]["text"] == "start_time"
    findings = page.table("findings")
    for path in paths:
        mine = [r for r in findings if r[0]["text"] == str(path)]
        assert any(r[2]["text"] == "coulomb_friction" and "N*m" in r[4]["text"] for r in mine)


def test_a_log_without_start_time_is_timed_by_its_mtime_and_says_so(tmp_path, monkeypatch):
    (tmp_path / "lever.urdf").write_text(ACTUATOR_URDF)
    frame = pd.DataFrame({"t": np.arange(200) / 100.0, "q_0": np.sin(np.arange(200) / 100.0), "tau_0": 0.1})
    timed = write_parquet(tmp_path / "timed.parquet", frame, {"urdf": "lever.urdf", "start_time": STARTS[0]})
    untimed = write_parquet(tmp_path / "untimed.parquet", frame, {"urdf": "lever.urdf"}, mtime=1_795_000_000.5)
    monkeypatch.setattr("mmgp.fleet.work.diagnose_log", fake_diagnosis({"timed.parquet": 1.0, "untimed.parquet": 1.0}))
    out = tmp_path / "out"
    res = runner.invoke(app, ["fleet", str(timed), str(untimed), "--out", str(out), "--serial"])
    assert res.exit_code == 0, res.output
    assert "1 log(s) without start_time in their metadata: placed in time by file mtime" in res.output
    table = pd.read_parquet(out / "fleet.parquet").set_index("log")
    assert table.loc[str(untimed), "log_time"] == pd.Timestamp(datetime.fromtimestamp(1_795_000_000.5, timezone.utc))
    assert table.loc[str(untimed), "log_time_source"] == "mtime"
    assert table.loc[str(timed), "log_time_source"] == "start_time"
    text = (out / "report.html").read_text()
    assert "1 of 2 log(s) have no time in their metadata and are placed by mtime: " + str(untimed) in text


@pytest.mark.parametrize("bad, why", [("27/11/2026 09:30", "not an ISO 8601 time"),
                                      ("2026-11-27T09:30:00", "has no UTC offset")])
def test_a_malformed_start_time_is_one_error_naming_file_and_key(tmp_path, bad, why):
    good, wrong = lever_copies(tmp_path, [STARTS[0], bad], n=200)
    out = tmp_path / "out"
    res = runner.invoke(app, ["fleet", str(good), str(wrong), "--out", str(out), "--serial"])
    assert res.exit_code == 2
    (line,) = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert str(wrong) in line and "metadata 'start_time'" in line and repr(bad) in line and why in line
    assert not out.exists()
    with pytest.raises(InputError, match="start_time"):  # every command reads the key the same way
        read_log(wrong)


def planted(n_logs: int) -> pd.DataFrame:
    """A fleet table: one robot, one steady parameter in ``n_logs`` daily logs."""
    return pd.DataFrame([{"log": f"L{i}", "robot": "r1", "log_time": pd.Timestamp("2026-03-01", tz="UTC")
                          + pd.Timedelta(days=i), "log_time_source": "start_time", "effect": "viscous_friction",
                          "joint": "j1", "param": "b", "value": 0.3, "lo": 0.29, "hi": 0.31, "unit": "N*m*s/rad",
                          "error": None} for i in range(n_logs)])


def test_only_a_comparison_says_steady():
    _, few = flag_drift(planted(3), baseline=5)
    (s,) = few["series"]
    assert s["status"] == "no baseline" and "3 log(s)" in s["reason"] and "needs 5" in s["reason"]
    assert few["robots_without_baseline"] == ["r1"] and few["n_steady"] == 0 and few["n_no_baseline"] == 1
    _, exact = flag_drift(planted(5), baseline=5)
    (s,) = exact["series"]
    assert s["status"] == "not compared" and "none comes after them" in s["reason"]
    _, enough = flag_drift(planted(6), baseline=5)
    assert enough["series"][0]["status"] == "steady" and enough["robots_without_baseline"] == []


def test_the_page_says_why_nothing_was_compared(tmp_path, monkeypatch, drawn):
    paths = lever_copies(tmp_path, STARTS[:3], n=200)
    monkeypatch.setattr("mmgp.fleet.work.diagnose_log", fake_diagnosis({p.name: 0.3 for p in paths}))
    out = tmp_path / "out"
    res = runner.invoke(app, ["fleet", *map(str, paths), "--out", str(out), "--serial"])  # baseline 5
    assert res.exit_code == 0, res.output
    assert "NO BASELINE for lever: fewer than 5 log(s)" in res.output
    drift = json.loads((out / "drift.json").read_text())
    assert [s["status"] for s in drift["series"]] == ["no baseline"]
    page = read_page(out / "report.html")
    (row,) = page.table("series")
    assert row[0]["text"] == "no baseline" and "needs 5" in row[5]["text"]
    assert "Nothing was compared" in (out / "report.html").read_text()
    (fig,) = drawn
    assert fig.axes[0].get_title() == "tau_c: no baseline"
    # a single log's panel spans hours around it, not years
    (tmp_path / "one").mkdir()
    one = lever_copies(tmp_path / "one", [STARTS[1]], n=200)
    monkeypatch.setattr("mmgp.fleet.work.diagnose_log", fake_diagnosis({"copy0.parquet": 0.3}))
    res = runner.invoke(app, ["fleet", str(one[0]), "--out", str(tmp_path / "out1"), "--serial"])
    assert res.exit_code == 0, res.output
    ax = drawn[-1].axes[0]
    lo, hi = (mdates.num2date(x) for x in ax.get_xlim())
    assert x_dates(ax) == [UTC[1]] and lo < UTC[1] < hi and (hi - lo).total_seconds() <= 3 * 3600
