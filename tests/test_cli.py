"""End-to-end checks of the command line on the shipped replica (a few seconds each)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.evaluation.metrics import classification_figures
from mmgp.data.logs import read_labels

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "mmgp/resources/replica/replica_log.parquet"
LABELS = ROOT / "mmgp/resources/replica/replica_labels.parquet"
runner = CliRunner()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "run"
    res = runner.invoke(app, ["train", str(LOG), "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    return out


def test_train_writes_contract_outputs(trained):
    lab = pd.read_parquet(trained / "labels.parquet")
    assert list(lab.columns[:4]) == ["t", "mode", "disturbed", "p_disturbed"]
    assert "p_mode_0" in lab.columns
    assert len(lab) == len(pd.read_parquet(LOG))
    assert set(lab["disturbed"].unique()) <= {0, 1}
    assert ((lab["p_disturbed"] >= 0) & (lab["p_disturbed"] <= 1)).all()
    # Thresholded posterior and label agree.
    assert ((lab["p_disturbed"] > 0.5).astype(int) == lab["disturbed"]).all()
    rep = json.loads((trained / "report.json").read_text())
    for key in ("hyperparameters", "disturbance", "switching_prior", "likelihood_trace", "timings"):
        assert key in rep
    assert rep["n_samples"] == len(lab)
    assert (trained / "labels.png").stat().st_size > 1000
    assert (trained / "likelihood_trace.png").stat().st_size > 1000


def test_train_far_above_source_on_replica(trained):
    # The source classified 81.7% of unperturbed samples correctly and missed 15.2% of pushes.
    pred = pd.read_parquet(trained / "labels.parquet")
    fig = classification_figures(pred, read_labels(LABELS, t=pred["t"].to_numpy()))
    assert fig["unperturbed_correct"] > 192 / 235
    assert fig["perturbed_missed"] < 14 / 92


def test_evaluate_writes_figures_matching_library(trained):
    res = runner.invoke(app, ["evaluate", str(trained), "--truth", str(LABELS)])
    assert res.exit_code == 0, res.output
    fig = json.loads((trained / "evaluation.json").read_text())
    pred = pd.read_parquet(trained / "labels.parquet")
    truth = read_labels(LABELS, t=pred["t"].to_numpy())
    d = truth["disturbed"].to_numpy()
    p = pred["disturbed"].to_numpy()
    judged = d != -1
    assert fig["n_judged"] == judged.sum()
    assert fig["n_ambiguous_left_out"] == (~judged).sum()
    assert fig["perturbed_missed"] == pytest.approx(((p == 0) & (d == 1)).sum() / (d == 1).sum())
    assert fig["unperturbed_correct"] == pytest.approx(((p == 0) & (d == 0)).sum() / (d == 0).sum())


def test_predict_matches_reloaded_model(trained, tmp_path):
    out = tmp_path / "pred.parquet"
    res = runner.invoke(app, ["predict", str(trained), str(LOG), "--out", str(out)])
    assert res.exit_code == 0, res.output
    df = pd.read_parquet(out)
    assert list(df.columns) == ["t", "tau_hat_0", "tau_std_0"]
    tau = pd.read_parquet(LOG)["tau_0"].to_numpy()
    lab = pd.read_parquet(trained / "labels.parquet")
    nominal = lab["disturbed"].to_numpy() == 0
    # On undisturbed samples the nominal mode predicts the logged torque to within a few std.
    z = np.abs(tau - df["tau_hat_0"].to_numpy()) / df["tau_std_0"].to_numpy()
    assert np.median(z[nominal]) < 2.0
    assert (df["tau_std_0"] > 0).all()


def test_export_and_check_passivity(trained, tmp_path):
    f = tmp_path / "comp.json"
    res = runner.invoke(app, ["export", str(trained), "--out", str(f), "--c", str(tmp_path / "comp")])
    assert res.exit_code == 0, res.output
    import mmgp

    comp = mmgp.load_compensator(f)
    q = np.linspace(-0.5, 1.2, 7)[:, None]
    h = 1e-6
    fd = (comp.storage(q + h) - comp.storage(q - h)) / (2 * h)
    assert np.allclose(fd, comp.torque(q)[:, 0], rtol=1e-5, atol=1e-6)
    res = runner.invoke(app, ["check-passivity", str(f)])
    assert res.exit_code == 0 and "passed: True" in res.output


def test_bad_input_gives_one_located_error_and_exit_2(tmp_path):
    df = pd.read_parquet(LOG)
    df.loc[5, "tau_0"] = np.nan
    bad = tmp_path / "bad.csv"
    df.to_csv(bad, index=False)
    before = bad.read_bytes()
    out = tmp_path / "out"
    res = runner.invoke(app, ["train", str(bad), "--out", str(out), "--quiet"])
    assert res.exit_code == 2
    assert "tau_0" in res.output and "row 5" in res.output and str(bad) in res.output
    assert not out.exists()
    assert bad.read_bytes() == before


def test_nonempty_out_refused_without_force(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    res = runner.invoke(app, ["train", str(LOG), "--out", str(out), "--quiet"])
    assert res.exit_code == 2 and "--force" in res.output
    assert (out / "keep.txt").read_text() == "precious"


def test_bad_config_key_is_refused(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("modez: 2\n")
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "o"), "--config", str(cfg)])
    assert res.exit_code == 2 and "modez" in res.output


def test_unavailable_device_is_a_clear_error(tmp_path, monkeypatch):
    # The same check on every machine: CUDA is made unavailable, as on a CPU-only one.
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for args in (["train", str(LOG), "--out", str(tmp_path / "o"), "--device", "cuda", "--quiet"],
                 ["compare", str(LOG), "--out", str(tmp_path / "c"), "--device", "cuda"]):
        res = runner.invoke(app, args)
        assert res.exit_code == 2 and "cuda" in res.output
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:") and "cuda" in lines[0], res.stderr
        assert res.stdout == ""
    assert not (tmp_path / "o").exists() and not (tmp_path / "c").exists()


def test_python_and_command_line_give_identical_labels(trained):
    """The estimator called from Python and `mmgp train` on the same log and settings."""
    from mmgp import MultimodalGP

    model = MultimodalGP().fit(LOG)
    cli = pd.read_parquet(trained / "labels.parquet")
    pd.testing.assert_frame_equal(model.labels_, cli, check_exact=True)
    rep = json.loads((trained / "report.json").read_text())
    assert rep["disturbance"]["n_disturbed"] == int(model.labels_["disturbed"].sum())


def test_bad_yaml_is_one_line_naming_file_and_line(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("train:\n  n_modes: 2\n  seed: [0, 1\n")
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "o"), "--config", str(cfg), "--quiet"])
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and str(cfg) in lines[0] and "line 3" in lines[0], res.stderr
    cfg.write_text("train:\n  n_mode: 2\n")
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "o"), "--config", str(cfg), "--quiet"])
    assert res.exit_code == 2 and "n_mode" in res.stderr and "n_modes" in res.stderr


def planted_two_mode_log(path, T=480, rate=20.0, seed=0):
    """1-DOF log whose torque jumps by 1 N*m in two stretches of 5.5 s (mode 1), noise 0.05 N*m;
    every stretch of either mode lasts >= 4 s (a mode lasts: ``min_mode_s``)."""
    from mmgp.data.logs import write_log

    t = np.arange(T) / rate
    q = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)
    mode = (((t >= 4) & (t < 9.5)) | ((t >= 14) & (t < 19.5))).astype(int)
    tau = np.sin(1.5 * q) + 1.0 * mode + 0.05 * np.random.default_rng(seed).normal(size=T)
    write_log(path, t, q[:, None], tau[:, None])
    return mode


def test_modes_auto_picks_the_planted_two_modes(tmp_path):
    from sklearn.metrics import adjusted_rand_score

    log = tmp_path / "two.parquet"
    mode = planted_two_mode_log(log)
    out = tmp_path / "auto"
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("train:\n  max_sweeps: 8\n  fit_iter: 20\n")
    res = runner.invoke(app, ["train", str(log), "--out", str(out), "--modes", "auto", "--no-disturbance",
                              "--config", str(cfg), "--quiet"])
    assert res.exit_code == 0, res.output
    rep = json.loads((out / "report.json").read_text())
    assert rep["mode_selection"]["chosen"] == 2 and set(rep["mode_selection"]["scores"]) == {"1", "2", "3"}
    assert rep["n_modes"] == 2 and rep["config"]["max_sweeps"] == 8 and rep["config"]["n_modes"] == "auto"
    assert "--modes auto: 2 mode(s); 3 rejected:" in res.output, res.output
    lab = pd.read_parquet(out / "labels.parquet")
    assert {"p_mode_0", "p_mode_1"} <= set(lab.columns) and "p_mode_2" not in lab.columns
    assert adjusted_rand_score(mode, lab["mode"]) >= 0.9


def test_demo_end_to_end(tmp_path, trained):
    out = tmp_path / "demo"
    out.mkdir()
    (out / ".mmgp-demo").write_text("an earlier demo run\n")     # the demo may replace its own output
    (out / "stale.txt").write_text("from the earlier run")
    res = runner.invoke(app, ["demo", "--out", str(out)])
    assert res.exit_code == 0, res.output
    for name in ("labels.parquet", "report.json", "evaluation.json", "model.json", "model.npz", "labels.png",
                 "likelihood_trace.png"):
        assert (out / name).is_file(), name
    assert not (out / "stale.txt").exists()
    # The demo trains with the defaults on the shipped log: the labels of `mmgp train`.
    pred = pd.read_parquet(out / "labels.parquet")
    pd.testing.assert_frame_equal(pred, pd.read_parquet(trained / "labels.parquet"), check_exact=True)
    # Its figures, against counts made here from the shipped truth.
    fig = json.loads((out / "evaluation.json").read_text())
    d = read_labels(LABELS, t=pred["t"].to_numpy())["disturbed"].to_numpy()
    p = pred["disturbed"].to_numpy()
    assert fig["unperturbed_correct"] == pytest.approx(((p == 0) & (d == 0)).sum() / (d == 0).sum())
    assert fig["perturbed_missed"] == pytest.approx(((p == 0) & (d == 1)).sum() / (d == 1).sum())
    assert f"{fig['unperturbed_correct']:.3f}" in res.stdout and "0.817" in res.stdout
    # Another folder is not replaced without --force.
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("precious")
    res = runner.invoke(app, ["demo", "--out", str(other)])
    assert res.exit_code == 2 and (other / "keep.txt").read_text() == "precious"


def _digest(path: Path) -> str:
    import hashlib
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_every_command_refuses_to_write_over_or_around_its_inputs(trained, tmp_path):
    """Each command hands its inputs to the writer: an output that is an input, or a folder that
    holds one, is refused with exit 2 before any work, and the inputs stay byte for byte."""
    import shutil

    logs = tmp_path / "logs"
    logs.mkdir()
    log = logs / "replica.parquet"
    shutil.copy(LOG, log)
    urdf = logs / "lever.urdf"
    shutil.copy(ROOT / "mmgp/resources/replica/replica_lever.urdf", urdf)
    before = {p: _digest(p) for p in [log, urdf, trained / "model.json", trained / "model.npz"]}
    attempts = {
        "train into the log's folder": ["train", str(log), "--out", str(logs), "--force", "--quiet"],
        "diagnose into the log's folder": ["diagnose", str(log), "--urdf", str(urdf), "--out", str(logs), "--force"],
        "compare into the URDF's folder": ["compare", str(log), "--urdf", str(urdf), "--out", str(logs), "--force"],
        "predict over the log": ["predict", str(trained), str(log), "--out", str(log), "--force"],
        "predict over the model": ["predict", str(trained), str(log), "--out", str(trained / "model.npz"), "--force"],
        "export over the model": ["export", str(trained), "--out", str(trained / "model.json"), "--force"],
    }
    for what, argv in attempts.items():
        res = runner.invoke(app, argv)
        assert res.exit_code == 2, (what, res.output)
        assert "input" in res.output.lower(), (what, res.output)
    assert {p: _digest(p) for p in before} == before
    assert sorted(p.name for p in logs.iterdir()) == ["lever.urdf", "replica.parquet"]


def test_train_says_why_modes_auto_stopped():
    from mmgp.cli.train import _selection

    short = {"mode_selection": {"scores": {"1": -10.0, "2": 5.0}, "longest_run_s": {"1": [21.0], "2": [3.6, 0.7]},
                                "min_mode_s": 4.0, "chosen": 1}}
    assert _selection(short) == (" --modes auto: 1 mode(s); 2 rejected: one of its modes lasted at most 0.7 s in "
                                 "one stretch (< min_mode_s 4.0 s).")
    lower = {"mode_selection": {"scores": {"1": -10.0, "2": -12.5}, "longest_run_s": {"1": [21.0], "2": [9.0, 8.0]},
                                "min_mode_s": 4.0, "chosen": 1}}
    assert _selection(lower) == " --modes auto: 1 mode(s); 2 rejected: scored lower (-12.5 vs -10.0)."
    lower["mode_selection"]["abandoned"] = {"1": False, "2": True}
    assert _selection(lower) == (" --modes auto: 1 mode(s); 2 rejected: scored lower (-12.5 vs -10.0); stopped early, "
                                 "one of its modes held nowhere for 4.0 s in one stretch.")
    assert _selection({"mode_selection": None}) == ""



def test_summary_says_why_the_flags_differ_from_the_last_sweep():
    from mmgp.cli.train import _flags_note

    trace = [{"n_disturbed": 487}]
    abstained = {"likelihood_trace": trace, "disturbance": {"n_disturbed": 0, "abstained": True, "n_by_scan": 0}}
    assert "487" in _flags_note(abstained) and "none is flagged" in _flags_note(abstained)
    averaged = {"likelihood_trace": trace, "disturbance": {"n_disturbed": 470, "abstained": False, "n_by_scan": 3}}
    assert "487" in _flags_note(averaged) and "scan's (3)" in _flags_note(averaged)
    same = {"likelihood_trace": trace, "disturbance": {"n_disturbed": 487, "abstained": False}}
    assert _flags_note(same) == "" and _flags_note({"likelihood_trace": [], "disturbance": {"n_disturbed": 0}}) == ""


def test_summary_names_the_sweep_kept_when_the_sweeps_cycle():
    from mmgp.cli.train import _flags_note

    trace = [{"n_disturbed": n, "log_marginal": lm} for n, lm in [(379, 85603.6), (7, 86375.6), (2507, 46996.8),
                                                                  (432, 23090.0)]]
    rep = {"likelihood_trace": trace, "labels_from_sweep": 1,
           "disturbance": {"n_disturbed": 0, "abstained": True, "n_by_scan": 0}}
    note = _flags_note(rep)
    assert "did not converge" in note and "sweep 1's" in note and "86375.6" in note and "23090.0" in note
    # what follows is about the kept sweep (7 in the disturbance state), not the last (432)
    assert "held 7 samples" in note and "none is flagged" in note


def test_train_message_names_the_starts_and_a_better_fit_that_injects_energy():
    from mmgp.cli.train import _dissipation

    rep = {"dissipation": {"fits": [
        {"start": "stuck-aware", "log_marginal": 18075.7, "worst": 0.21, "p_value": 0.001, "physical": False},
        {"start": "every-sample", "log_marginal": 14919.8, "worst": 0.15, "p_value": 0.002, "physical": False},
        {"start": "swapped labels", "log_marginal": 12087.7, "worst": 0.01, "p_value": 0.6, "physical": True}],
        "chosen": 2, "physical": True, "runner_up_gap": 12087.7 - 18075.7}}
    text = _dissipation(rep)
    assert "both starts (stuck-aware 18075.7, every-sample 14919.8 log marginal)" in text
    assert "refitted 1 time(s)" in text and "kept fit 3 (swapped labels)" in text
    assert "a fit whose friction injects energy 5988.0 higher, not kept" in text
    rep["dissipation"]["fits"] = rep["dissipation"]["fits"][1:]
    rep["dissipation"].update(chosen=0, runner_up_gap=14919.8 - 12087.7)
    rep["dissipation"]["fits"][0]["physical"] = True
    assert _dissipation(rep).endswith("(log marginal 14919.8, the runner-up 2832.1 lower).")
