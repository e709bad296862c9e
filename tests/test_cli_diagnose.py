"""`mmgp diagnose` end to end through the command line, on a short concealed MuJoCo case (1-DOF
lever with Coulomb friction 0.3 N*m and external pushes): findings.json per CONTRACT section 2/3,
the concealed effect found against the simulator's truth, atomic --out, clear bad-input errors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mmgp.sim import concealed as C
from mmgp.cli import app
from mmgp.data.logs import write_log

runner = CliRunner()

# CONTRACT section 3: effect -> parameter names
VOCABULARY = {
    "coulomb_friction": {"tau_c"}, "viscous_friction": {"b"}, "load_dependent_friction": {"tau_c", "beta"},
    "armature": {"inertia"}, "joint_spring": {"k", "q0"}, "encoder_offset": {"offset"},
    "torque_offset": {"offset"}, "payload": {"link", "mass", "com"},
}
WHOLE_LOG = {"external_disturbance", "mode_switch"}
NONNEG = {"tau_c", "b", "beta", "inertia", "k", "mass"}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    spec = dict(next(s for s in C.STANDARD_CASES if s["name"] == "actuator_pushes_coulomb"), n_samples=2000)
    rec, truth = C.make_case(spec, seed=2)
    d = tmp_path_factory.mktemp("diag")
    (d / "actuator.urdf").write_text(C.ACTUATOR_URDF)
    names = rec.info["joint_names"]
    # the robot named by the log's metadata (URDF relative to the log's folder) ...
    with_robot = write_log(d / "lever.parquet", rec.t, rec.q, rec.tau, dq=rec.dq, ddq=rec.ddq,
                           urdf="actuator.urdf", joint_names=names)
    # ... and the same samples with no robot anywhere
    bare = write_log(d / "bare.parquet", rec.t, rec.q, rec.tau, dq=rec.dq, ddq=rec.ddq)
    out = d / "out"
    res = runner.invoke(app, ["diagnose", str(with_robot), "--out", str(out)])
    return {"rec": rec, "truth": truth, "dir": d, "log": with_robot, "bare": bare, "out": out, "res": res,
            "names": names}


def test_findings_json_follows_the_contract(case):
    assert case["res"].exit_code == 0, case["res"].output
    doc = json.loads((case["out"] / "findings.json").read_text())
    assert {"findings", "fit"} <= set(doc)
    assert doc["findings"], "the concealed effect was not reported"
    for f in doc["findings"]:
        assert {"effect", "params", "evidence", "explanation"} <= set(f)
        assert isinstance(f["explanation"], str) and f["explanation"]
        if f["effect"] in WHOLE_LOG:
            continue
        assert f["effect"] in VOCABULARY, f["effect"]
        assert set(f["params"]) == VOCABULARY[f["effect"]], (f["effect"], f["params"])
        for k in NONNEG & set(f["params"]):
            assert f["params"][k] >= 0
        if f["effect"] == "payload":
            assert f["link"] == f["params"]["link"]
        else:
            assert f["joint"] in case["names"] or (isinstance(f["joint"], int) and 0 <= f["joint"] < len(case["names"]))
    for stage in ("nominal", "with_physics", "with_physics_and_gp"):
        nm = doc["fit"][stage]["nmse"]
        assert set(nm) == set(case["names"])
        assert all(np.isfinite(v) and v >= 0 for v in nm.values())


def test_concealed_friction_and_pushes_are_found(case):
    assert case["res"].exit_code == 0, case["res"].output
    doc = json.loads((case["out"] / "findings.json").read_text())
    eff = [f for f in doc["findings"] if f["effect"] not in WHOLE_LOG]
    # the simulator's truth: Coulomb friction 0.3 N*m on the lever joint, nothing else
    assert [(f["effect"], f["joint"]) for f in eff] == [("coulomb_friction", "lever_joint")]
    assert eff[0]["params"]["tau_c"] == pytest.approx(0.3, rel=0.1)
    # held-out error falls once the friction is modelled
    fit = doc["fit"]
    assert fit["with_physics"]["nmse"]["lever_joint"] < fit["nominal"]["nmse"]["lever_joint"]
    # pushes: reported as external_disturbance, flagged where the simulator pushed
    dist = [f for f in doc["findings"] if f["effect"] == "external_disturbance"]
    assert len(dist) == 1 and dist[0].get("joint") is None
    lab = pd.read_parquet(case["out"] / "labels.parquet")
    assert list(lab.columns[:3]) == ["t", "mode", "disturbed"]
    rec = case["rec"]
    truth = np.interp(lab["t"], rec.t, rec.labels["disturbed"]).round()
    got = lab["disturbed"].to_numpy() == 1
    assert (got & (truth == 1)).sum() > 0.7 * (truth == 1).sum()
    assert (got & (truth == 0)).sum() < 0.1 * got.sum()
    assert "MultimodalSEM" in dist[0]["evidence"]["method"]
    # the command prints report.md's text from memory: the file less its plot links
    md = (case["out"] / "report.md").read_text()
    printed = case["res"].stdout
    assert md.split("## Plots")[0].rstrip() in printed and "## Plots" not in printed


def test_out_is_written_atomically_and_not_overwritten(case):
    assert case["res"].exit_code == 0, case["res"].output
    out = case["out"]
    before = (out / "findings.json").read_bytes()
    # a non-empty --out is refused without --force (checked before any work: --urdf on a bare log)
    res = runner.invoke(app, ["diagnose", str(case["bare"]), "--urdf", str(case["dir"] / "actuator.urdf"),
                              "--out", str(out)])
    assert res.exit_code == 2
    assert "not empty" in res.output and "--force" in res.output
    assert (out / "findings.json").read_bytes() == before
    # no half-written folders are left next to --out
    assert not [p for p in case["dir"].iterdir() if p.name.startswith(".out.")]


def test_log_without_robot_is_refused_clearly(case, tmp_path):
    out = tmp_path / "nothing"
    res = runner.invoke(app, ["diagnose", str(case["bare"]), "--out", str(out)])
    assert res.exit_code == 2
    assert "--robot" in res.output and "--urdf" in res.output and "bare.parquet" in res.output
    assert not out.exists()


def test_settings_come_from_the_config_section(case, tmp_path):
    """A YAML 'diagnose:' section reaches the Diagnoser: the scan alone separates the pushes
    (no learner), only the listed effects are candidates, no GP stage and no plots; the
    simulator's friction is still found. Unknown keys are refused, naming the file."""
    cfg = tmp_path / "settings.yaml"
    cfg.write_text("train:\n  modes: 1\ndiagnose:\n  gp: false\n  plots: false\n  separate: scan\n"
                   "  effects: [coulomb_friction, viscous_friction]\n")
    out = tmp_path / "out"
    res = runner.invoke(app, ["diagnose", str(case["log"]), "--out", str(out), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "findings.json").read_text())
    eff = [f for f in doc["findings"] if f["effect"] not in WHOLE_LOG]
    assert [(f["effect"], f["joint"]) for f in eff] == [("coulomb_friction", "lever_joint")]
    assert eff[0]["params"]["tau_c"] == pytest.approx(0.3, rel=0.1)
    assert "with_physics_and_gp" not in doc["fit"] and not list(out.glob("*.png"))
    assert doc["info"]["n_candidates"] == 2
    sep = doc["info"]["separation"]
    assert sep["method"] == "robust chi-square scan" and "em_seconds" not in sep
    cfg.write_text("diagnose:\n  gp: false\n  no_such_setting: 3\n")
    res = runner.invoke(app, ["diagnose", str(case["log"]), "--out", str(tmp_path / "x"), "--config", str(cfg)])
    assert res.exit_code == 2
    assert "no_such_setting" in res.output and "settings.yaml" in res.output


def test_thinning_to_max_samples_is_said(case, tmp_path):
    """A log longer than max_samples is thinned (after its ends are trimmed where derivatives
    count as estimated), and the progress output says so (docs/training.md, Thinning and
    subsampling); --quiet does not."""
    import re

    n_log = len(case["rec"].t)
    cfg = tmp_path / "settings.yaml"
    cfg.write_text(f"diagnose:\n  gp: false\n  plots: false\n  separate: scan\n  modes: false\n"
                   f"  max_samples: {n_log // 2}\n")
    res = runner.invoke(app, ["diagnose", str(case["log"]), "--out", str(tmp_path / "o"), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    # (a piped progress line, after its clock time and seconds since the start)
    said = re.search(rf"^\d\d:\d\d:\d\d +\d+\.\ds ({n_log // 2:,} of ([\d,]+) samples used: max_samples {n_log // 2})$",
                     res.output, re.M)
    assert said, res.output
    n_read = int(said.group(2).replace(",", ""))
    assert n_log - 100 < n_read <= n_log       # at most the trimmed ends (a few filter lengths) less
    info = json.loads((tmp_path / "o" / "findings.json").read_text())["info"]
    assert (info["n_samples"], info["n_samples_in_log"]) == (n_log // 2, n_read)
    line = said.group(1)
    res = runner.invoke(app, ["diagnose", str(case["log"]), "--out", str(tmp_path / "q"), "--config", str(cfg),
                              "--quiet"])
    assert res.exit_code == 0 and line not in res.output
