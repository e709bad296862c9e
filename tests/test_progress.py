"""Progress of long commands (issue 31 item 1): plain timestamped lines when piped with a
heartbeat, so no stretch is silent for long; a bar with a total on a terminal; nothing with
--quiet. The library reports its stages through :mod:`mmgp.progress`, never printing itself."""
from __future__ import annotations

import io
import re
import time

from typer.testing import CliRunner

from mmgp import progress
from mmgp.cli import app
from mmgp.cli.common import ProgressDisplay
from mmgp.resources import demo_files, demo_urdf

runner = CliRunner()
LOG = demo_files()[0]
QUICK = "train:\n  max_sweeps: 6\n  min_sweeps: 2\n  average_last: 1\n  fit_iter: 10\n"
STAMP = re.compile(r"^\d\d:\d\d:\d\d +(\d+\.\d)s (.*)$")


def stamped(stderr: str) -> list[tuple[float, str]]:
    """(seconds since the start, text) of every progress line; each must carry the stamp."""
    out = []
    for line in stderr.splitlines():
        m = STAMP.match(line)
        assert m, f"a piped progress line without its time: {line!r}"
        out.append((float(m.group(1)), m.group(2)))
    return out


def piped(buf: io.StringIO, **kw) -> ProgressDisplay:
    from rich.console import Console

    return ProgressDisplay(console=Console(file=buf, force_terminal=False, width=200), **kw)


def test_heartbeat_speaks_during_a_silent_stage_and_library_reports_are_lines():
    buf = io.StringIO()
    with piped(buf, heartbeat_s=0.2) as shown:
        shown.stage("slow work", None)
        progress.report("inner step")
        time.sleep(0.9)
    lines = stamped(buf.getvalue())
    texts = [t for _, t in lines]
    assert texts[:2] == ["slow work", "inner step"]
    assert any(t.startswith("  still inner step (") for t in texts[2:]), texts
    times = [0.0] + [s for s, _ in lines]
    assert max(b - a for a, b in zip(times, times[1:])) < 0.8
    progress.report("after the display closed")      # no listener left: nothing, no error
    assert "after the display closed" not in buf.getvalue()


def test_quiet_display_prints_nothing_and_does_not_listen():
    buf = io.StringIO()
    with piped(buf, quiet=True, heartbeat_s=0.05) as shown:
        shown.stage("x", 3)
        progress.report("y")
        time.sleep(0.2)
    assert buf.getvalue() == ""


def test_diagnose_bar_has_a_total_that_follows_the_library_stages():
    from rich.console import Console

    from mmgp.diagnosis.pipeline import STAGES

    buf = io.StringIO()
    with ProgressDisplay(console=Console(file=buf, force_terminal=True, width=150)) as shown:
        assert shown._current().description == "starting"       # never an empty line before the first stage
        shown.stage("diagnose", len(STAGES) + 1, follow="diagnosis")
        progress.report("diagnosis: selecting effects", work="diagnosis", done=5, total=len(STAGES))
        task = shown._current()
        assert (task.total, task.completed) == (len(STAGES) + 1, 5)
        progress.report("EM start: one GP on all 10 samples")      # other reports leave the count
        assert shown._current().completed == 5
    assert f"[6/{len(STAGES) + 1}]" in buf.getvalue()


def test_piped_train_has_no_long_gap_and_the_heartbeat_fires_in_a_slow_stage(tmp_path, monkeypatch):
    import mmgp.evaluation.heldout as heldout

    score = heldout.heldout_score

    def slow_score(model, **kw):
        out = score(model, **kw)                          # reports "held-out score: ..." first
        time.sleep(1.5)                                   # then says nothing for a while
        return out

    monkeypatch.setattr(heldout, "heldout_score", slow_score)
    monkeypatch.setenv("MMGP_HEARTBEAT_S", "0.3")
    for var in ("FORCE_COLOR", "TTY_COMPATIBLE"):
        monkeypatch.delenv(var, raising=False)
    cfg = tmp_path / "quick.yaml"
    cfg.write_text(QUICK)
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "o"), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    lines = stamped(res.stderr)
    texts = [t for _, t in lines]
    assert "reading and differentiating log 1 of 1" in texts and "EM start: one GP on all 330 samples" in texts
    assert any(t.startswith("  sweep   0") for t in texts) and "held-out score: 5 time blocks" in texts
    assert any(t.startswith("  still held-out score") for t in texts), texts
    times = [0.0] + [s for s, _ in lines]
    assert max(b - a for a, b in zip(times, times[1:])) < 10.0, lines


def test_quiet_train_prints_nothing_on_stderr(tmp_path, monkeypatch):
    monkeypatch.setenv("MMGP_HEARTBEAT_S", "0.05")
    cfg = tmp_path / "quick.yaml"
    cfg.write_text(QUICK)
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "o"), "--config", str(cfg), "--quiet"])
    assert res.exit_code == 0, res.output
    assert [line for line in res.stderr.splitlines() if not line.startswith("warning: ")] == []


def test_piped_diagnose_counts_its_stages(tmp_path, monkeypatch):
    from mmgp.diagnosis.pipeline import STAGES

    for var in ("FORCE_COLOR", "TTY_COMPATIBLE"):
        monkeypatch.delenv(var, raising=False)
    cfg = tmp_path / "d.yaml"
    cfg.write_text("diagnose:\n  gp: false\n  plots: false\n")
    res = runner.invoke(app, ["diagnose", str(LOG), "--urdf", str(demo_urdf()), "--out", str(tmp_path / "o"),
                              "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    n = len(STAGES) + 1
    texts = [t for _, t in stamped(res.stderr)]
    assert texts[0] == f"diagnose ({n} steps)", texts
    counted = [int(m.group(1)) for t in texts if (m := re.search(rf"\[(\d+)/{n}\]$", t))]
    assert counted[0] == 1 and counted[-1] == n and counted == sorted(counted), texts
