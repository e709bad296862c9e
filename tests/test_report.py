"""Reports people read: report.html beside the JSON, progress bars, --version, help texts, package data.

Each report.html is parsed with the standard library's HTML parser (an independent reader): its
images must decode to the PNG files written beside it, its numbers must be the JSON's, and it must
load nothing from outside itself.
"""
from __future__ import annotations

import base64
import io
import json
import re
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.cli.common import ProgressDisplay, SweepProgress
from mmgp.evaluation.html import HtmlReport, format_value
from mmgp.labelling.convergence import SweepRecord

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "mmgp/resources/replica/replica_log.parquet"
LABELS = ROOT / "mmgp/resources/replica/replica_labels.parquet"
QUICK = "train:\n  max_sweeps: 3\n  min_sweeps: 1\n  average_last: 1\n  fit_iter: 5\n"
runner = CliRunner()


class Page(HTMLParser):
    """What a program reads from a report: images, tables (cells with text and data-value),
    the JSON blocks, and every attribute that could load something from elsewhere."""

    def __init__(self, text: str):
        super().__init__()
        self.images, self.tables, self.json, self.tags, self.external = [], [], {}, [], []
        self._cell = self._pre = None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        for key in ("src", "href", "srcset", "data", "action"):
            if key in a and not str(a[key]).startswith("data:"):
                self.external.append((tag, key, a[key]))
        if tag == "img":
            self.images.append(a)
        elif tag == "table":
            self.tables.append({"kind": a.get("class"), "head": [], "rows": []})
        elif tag == "tr":
            self.tables[-1]["rows"].append([])
        elif tag in ("td", "th"):
            self._cell = {"text": "", "value": a.get("data-value"), "head": tag == "th"}
        elif tag == "pre":
            self._pre = [a.get("id"), ""]

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1]["rows"][-1].append(self._cell)
            self._cell = None
        elif tag == "pre" and self._pre is not None:
            self.json[self._pre[0]] = json.loads(self._pre[1])
            self._pre = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell["text"] += data
        if self._pre is not None:
            self._pre[1] += data

    def table(self, kind: str) -> list[list[dict]]:
        """Body rows of the table of class ``kind``."""
        found = [t for t in self.tables if t["kind"] == kind]
        assert len(found) == 1, [t["kind"] for t in self.tables]
        return [r for r in found[0]["rows"] if r and not r[0]["head"]]

    def key_figures(self) -> dict:
        return {r[0]["text"]: r[1] for r in self.table("key-figures")}


def number(cell: dict) -> float:
    """A numeric cell's exact value; its shown text must be that value rounded."""
    value = float(cell["value"])
    assert cell["text"] == f"{value:.4g}"
    return value


def read_page(path: Path) -> Page:
    page = Page(path.read_text(encoding="utf-8"))
    assert page.external == [] and "script" not in page.tags and "link" not in page.tags
    return page


def embedded_png(img: dict) -> bytes:
    head, data = img["src"].split(",", 1)
    assert head == "data:image/png;base64"
    return base64.b64decode(data)


def png_bytes(tmp_path: Path, name: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2, 2))
    ax.plot([0, 1], [1, 0])
    fig.savefig(tmp_path / name)
    plt.close(fig)
    return tmp_path / name


# --- the builder ---------------------------------------------------------------------------------

def test_builder_embeds_pngs_escapes_text_and_keeps_exact_values(tmp_path):
    png = png_bytes(tmp_path, "line.png")
    data = {"a": 1.0 / 3.0, "b": [1, 2], "nested": {"x": None}}
    page = (HtmlReport("T <1>", subtitle="s & t").section("Figures", "<script>alert(1)</script>")
            .key_figures({"third": 1.0 / 3.0, "count": 7, "flag": True, "missing": None, "nan": float("nan")})
            .figure(png, "a line").figure(png.read_bytes(), "again, from bytes").json(data, "summary"))
    out = page.write(tmp_path / "report.html")
    text = out.read_text()
    assert "<script>" not in text and "&lt;script&gt;" in text and "T &lt;1&gt;" in text
    parsed = read_page(out)
    assert [embedded_png(i) for i in parsed.images] == [png.read_bytes()] * 2
    assert parsed.images[0]["data-file"] == "line.png" and "data-file" not in parsed.images[1]
    figs = parsed.key_figures()
    assert number(figs["third"]) == 1.0 / 3.0 and figs["third"]["text"] == "0.3333"
    assert number(figs["count"]) == 7 and figs["flag"]["text"] == "yes" and figs["missing"]["text"] == "\u2013"
    assert figs["nan"]["text"] == "nan"
    assert parsed.json["summary"] == data
    with pytest.raises(ValueError, match="not a PNG"):
        HtmlReport("x").figure(b"GIF89a....")


def test_format_value_rounds_to_four_significant_digits():
    assert [format_value(v) for v in (123456.0, 0.000123456, 2, False, ["a", 1.5])] == \
        ["1.235e+05", "0.0001235", "2", "no", "a, 1.5"]


# --- the commands' reports ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    (d / "quick.yaml").write_text(QUICK)
    res = runner.invoke(app, ["train", str(LOG), "--out", str(d / "run"), "--config", str(d / "quick.yaml"),
                              "--quiet"])
    assert res.exit_code == 0, res.output
    assert res.stderr == ""                                           # --quiet: no progress at all
    return d / "run"


def test_training_report_shows_the_json_and_the_plots(trained):
    rep = json.loads((trained / "report.json").read_text())
    page = read_page(trained / "report.html")
    by_file = {i["data-file"]: embedded_png(i) for i in page.images}
    assert by_file == {n: (trained / n).read_bytes() for n in ("labels.png", "likelihood_trace.png")}
    figs = page.key_figures()
    assert number(figs["samples"]) == rep["n_samples"] == len(pd.read_parquet(LOG))
    assert number(figs["samples flagged disturbed"]) == rep["disturbance"]["n_disturbed"]
    assert number(figs["EM sweeps"]) == rep["n_sweeps"]
    assert number(figs["training time [s]"]) == rep["timings"]["total_s"]
    rows = page.table("hyperparameters")
    want = [(hp["mode"], j["joint"], j["signal_std"], j["noise_std"]) for hp in rep["hyperparameters"]
            for j in hp["per_joint"]]
    assert [(number(r[0]), r[1]["text"], number(r[2]), number(r[3])) for r in rows] == want
    held = rep["heldout"]["nmse"]            # the replica names no robot: no rigid-body figure
    assert [[c["text"] if c["value"] is None else number(c) for c in r] for r in page.table("heldout")] == \
        [[name, held["model"][j], "\u2013", held["mean"][j]] for j, name in enumerate(rep["heldout"]["joint_names"])]
    assert page.json["report"] == rep


def test_training_report_shows_the_mode_selection(trained, tmp_path):
    from mmgp.evaluation.reports import write_training_report

    rep = json.loads((trained / "report.json").read_text())
    rep["mode_selection"] = {"scores": {"1": -512.25, "2": -498.125, "3": -503.5}, "chosen": 2, "min_mode_s": 4.0,
                             "longest_run_s": {"1": [20.0], "2": [12.5, 6.25], "3": [9.0, 6.0, 1.5]}}
    page = read_page(write_training_report(tmp_path, rep))
    rows = page.table("mode-selection")
    assert [(number(r[0]), number(r[1]), r[2]["text"], r[3]["text"]) for r in rows] == \
        [(1, -512.25, "20", "no"), (2, -498.125, "12.5, 6.25", "yes"), (3, -503.5, "9, 6, 1.5", "no")]
    assert page.images == []                                           # no plots in that folder: none shown


def test_evaluate_adds_its_figures_to_the_report(trained):
    res = runner.invoke(app, ["evaluate", str(trained), "--truth", str(LABELS)])
    assert res.exit_code == 0, res.output
    fig = json.loads((trained / "evaluation.json").read_text())
    page = read_page(trained / "report.html")
    rows = {r[0]["text"]: r for r in page.table("evaluation")}
    assert number(rows["unperturbed correct"][1]) == fig["unperturbed_correct"]
    assert number(rows["perturbed missed"][1]) == fig["perturbed_missed"]
    assert number(rows["unperturbed correct"][2]) == 192 / 235 and number(rows["perturbed missed"][2]) == 14 / 92
    assert page.json["evaluation"] == fig and len(page.images) == 2


def test_compare_report_shows_the_nmse_of_the_json(tmp_path):
    from mmgp.evaluation.compare import write_compare

    rng = np.random.default_rng(0)
    nmse = {m: rng.uniform(0.01, 1.2, 3).tolist() for m in ("rigid_body", "gp", "rigid_body_gp")}
    result = {"log": "x.parquet", "robot": "panda", "joint_names": ["j1", "j2", "j3"], "methods": list(nmse),
              "n_samples": 900, "n_folds": 5, "gap": 11, "gap_s": 0.011, "max_train": 500, "seed": 0,
              "nmse": nmse, "timings": {"total_s": 12.5},
              "gp_improves_rigid_body": [a < b for a, b in zip(nmse["rigid_body_gp"], nmse["rigid_body"])]}
    write_compare(result, tmp_path)
    stored = json.loads((tmp_path / "compare.json").read_text())
    page = read_page(tmp_path / "report.html")
    assert [embedded_png(i) for i in page.images] == [(tmp_path / "compare.png").read_bytes()]
    rows = page.table("nmse")
    for j, name in enumerate(stored["joint_names"]):
        assert rows[j][0]["text"] == name
        assert [number(c) for c in rows[j][1:4]] == [stored["nmse"][m][j] for m in stored["methods"]]
        assert rows[j][4]["text"] == ("yes" if stored["gp_improves_rigid_body"][j] else "no")
    assert [number(c) for c in rows[-1][1:4]] == pytest.approx([sum(v) / 3 for v in stored["nmse"].values()])
    assert page.json["compare"] == stored


def fake_diagnosis(values: dict):
    """A stand-in for the diagnosis (seconds per log): Coulomb friction per log from ``values``."""
    def diagnose_log(log, robot, settings):
        tau_c = values[Path(log.path).name]
        finding = {"effect": "coulomb_friction", "joint": "lever_joint", "params": {"tau_c": tau_c},
                   "evidence": {"params_std": {"tau_c": 0.01}}}
        return [finding], {"findings": [finding]}

    return diagnose_log


def test_fleet_report_shows_drift_logs_and_trends(tmp_path, monkeypatch):
    from mmgp.data.outputs import write_table
    from mmgp.sim.concealed import ACTUATOR_URDF

    (tmp_path / "lever.urdf").write_text(ACTUATOR_URDF)
    values = {}
    for i, tau_c in enumerate([1.0, 1.0, 1.01, 1.5]):
        t = np.arange(200) / 100.0
        frame = pd.DataFrame({"t": t, "q_0": np.sin(t), "tau_0": np.cos(t)})
        write_table(tmp_path / f"L{i}.parquet", frame,
                    metadata={"urdf": "lever.urdf", "log_time": f"2026-01-0{i + 1}T00:00:00Z"})
        values[f"L{i}.parquet"] = tau_c
    monkeypatch.setattr("mmgp.fleet.work.diagnose_log", fake_diagnosis(values))
    monkeypatch.setenv("TTY_COMPATIBLE", "1")                          # the progress bar, as on a terminal
    out = tmp_path / "out"
    res = runner.invoke(app, ["fleet", *map(str, sorted(tmp_path.glob("L*.parquet"))), "--out", str(out),
                              "--serial", "--baseline", "2"])
    assert res.exit_code == 0, res.output
    assert "fleet: logs" in res.stderr and "4/4" in res.stderr and "ETA" in res.stderr
    assert f"Wrote {out}/report.html" in res.stdout
    summary = json.loads((out / "fleet.json").read_text())
    drift = json.loads((out / "drift.json").read_text())
    page = read_page(out / "report.html")
    figs = page.key_figures()
    assert number(figs["logs"]) == summary["n_logs"] == 4 and number(figs["failed"]) == 0
    assert number(figs["drifting series"]) == drift["n_drifting"] == 1
    (row,) = page.table("drift")
    assert [c["text"] for c in row[:5]] == ["drift", summary["logs"][0]["robot"], "coulomb_friction", "lever_joint",
                                            "tau_c"]
    assert row[5]["text"] == str(tmp_path / "L3.parquet") and number(row[6]) == 1.5
    (series,) = drift["series"]
    assert number(row[7]) == series["baseline"]["lo"] and number(row[8]) == series["baseline"]["hi"]
    assert [r[0]["text"] for r in page.table("logs")] == [s["log"] for s in summary["logs"]]
    assert {i["data-file"]: embedded_png(i) for i in page.images} == \
        {n: (out / "trends" / n).read_bytes() for n in summary["trends"]}
    assert page.json["fleet"] == summary and page.json["drift"] == drift


# --- progress -----------------------------------------------------------------------------------

def record(sweep: int, modes: int) -> SweepRecord:
    return SweepRecord(sweep, -10.0, -9.0, 0.1, 3, [10] * modes, 0.01)


def test_progress_bar_with_eta_on_a_terminal_lines_elsewhere_nothing_when_quiet():
    from rich.console import Console

    outputs = {}
    for name, quiet, terminal in (("terminal", False, True), ("pipe", False, False), ("quiet", True, True)):
        buf = io.StringIO()
        with ProgressDisplay(quiet, console=Console(file=buf, force_terminal=terminal, width=120)) as shown:
            sweeps = SweepProgress(shown, limit=4)
            for rec in [record(0, 1), record(1, 1), record(0, 2), record(1, 2), record(2, 2)]:
                sweeps(rec)
        outputs[name] = buf.getvalue()
    term = outputs["terminal"]
    assert "ETA" in term and "EM, 1 mode(s)" in term and "EM, 2 mode(s)" in term
    assert "2/2" in term and "3/3" in term                            # stages that end early show as complete
    assert "now trying 2" in term and "\x1b[" in term
    # piped: each line after its clock time and seconds since the start ("23:59:03   33.8s "),
    # a line per stage and per sweep
    pipe = [re.sub(r"^\d\d:\d\d:\d\d +\d+\.\ds ", "", line) for line in outputs["pipe"].splitlines()]
    assert all(re.match(r"\d\d:\d\d:\d\d +\d+\.\ds ", line) for line in outputs["pipe"].splitlines())
    assert len(pipe) == 8 and "\x1b[" not in outputs["pipe"] and "ETA" not in outputs["pipe"]
    assert pipe[0] == "EM, 1 mode(s) (4 steps)" and pipe[1].startswith("  sweep   0")
    assert pipe[3] == "  --modes auto: 1 mode(s) done; now trying 2" and pipe[4] == "EM, 2 mode(s) (4 steps)"
    assert outputs["quiet"] == ""


def test_train_progress_shows_on_a_terminal_only(tmp_path, monkeypatch):
    cfg = tmp_path / "quick.yaml"
    cfg.write_text(QUICK)
    for var in ("FORCE_COLOR", "TTY_COMPATIBLE"):
        monkeypatch.delenv(var, raising=False)
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "pipe"), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert "sweep   0" in res.stderr and "\x1b[" not in res.stderr and "ETA" not in res.stderr
    monkeypatch.setenv("TTY_COMPATIBLE", "1")                          # rich: treat the output as a terminal
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "tty"), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert "ETA" in res.stderr and "EM, 1 mode(s)" in res.stderr and "sweep   0" in res.stderr


# --- version, help, package data ----------------------------------------------------------------

def test_version_flag_prints_the_packaged_version():
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and res.stdout == f"mmgp {version}\n"
    assert runner.invoke(app, ["version"]).stdout == f"{version}\n"


def commands(group, prefix=()):
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):                                    # a group (typer may bring its own click)
            yield from commands(cmd, prefix + (name,))
        else:
            yield prefix + (name,), cmd


def test_every_option_and_argument_of_every_command_has_help():
    root = typer.main.get_command(app)
    found = list(commands(root))
    assert len(found) >= 13 and ("config", "show") in [p for p, _ in found]
    missing = [(" ".join(path), p.name) for path, cmd in found for p in cmd.params
               if not (getattr(p, "help", None) or "").strip()]
    assert missing == []
    assert all((cmd.help or "").strip() for _, cmd in found)
    assert all((p.help or "").strip() for p in root.params)             # --version


def test_configs_and_demo_data_are_package_data_in_one_copy():
    from mmgp.resources import config_file, config_files, demo_files

    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    resources = ROOT / "mmgp/resources"
    shipped = {p for g in globs["mmgp.resources"] for p in resources.glob(g)}
    assert set(config_files().values()) | set(demo_files()) <= shipped
    assert set(config_files()) == {"default", "panda_modes"}
    for name, path in config_files().items():                           # the top-level folder is the same files
        assert (ROOT / "configs" / path.name).samefile(path)
    res = runner.invoke(app, ["config", "show", "panda_modes"])
    assert res.exit_code == 0 and res.stdout == config_file("panda_modes.yaml").read_text()
    res = runner.invoke(app, ["config", "show", "nope"])
    assert res.exit_code == 2 and "default, panda_modes" in res.stderr


def test_training_report_shows_each_fit_of_the_friction_check(trained, tmp_path):
    from mmgp.evaluation.reports import write_training_report

    rep = json.loads((trained / "report.json").read_text())
    rep["dissipation"] = {"fits": [{"start": "stuck-aware", "worst": 0.371, "p_value": 5.3e-6, "log_marginal": -102.5,
                                    "physical": False},
                                   {"start": "swapped labels", "worst": 0.0, "p_value": 1.0, "log_marginal": 68.625,
                                    "physical": True}],
                          "chosen": 1, "physical": True, "runner_up_gap": 171.125}
    page = read_page(write_training_report(tmp_path, rep))
    rows = page.table("dissipation")
    assert [(number(r[0]), r[1]["text"], number(r[2]), r[3]["text"], number(r[4]), r[5]["text"], r[6]["text"])
            for r in rows] == [(1, "stuck-aware", 0.371, "5.3e-06", -102.5, "no", "no"),
                               (2, "swapped labels", 0, "1", 68.625, "yes", "yes")]
