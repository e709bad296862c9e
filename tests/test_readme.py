"""The README's Python example runs as written, and what it computes is checked against references
outside mmgp: the recording's ground-truth labels, the lever's closed-form static torque, finite
differences of the exported potential, and the contract's effect vocabulary."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
# Static torque of the shipped replica (datasets/make_replica.py): (0.73 * 0.2 + 0.1 * 0.1) * 9.81 * cos(q).
STATIC_GAIN = (0.73 * 0.2 + 0.1 * 0.1) * 9.81


def readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1, "the README holds exactly one Python example"
    return blocks[0]


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    folder = tmp_path_factory.mktemp("readme")
    namespace: dict = {"__name__": "__readme__"}
    cwd = Path.cwd()
    try:
        import os
        os.chdir(folder)
        exec(compile(readme_example(), "README.md", "exec"), namespace)
    finally:
        os.chdir(cwd)
    return folder, namespace


def test_example_uses_only_the_public_api():
    code = readme_example()
    assert "from mmgp." not in code and "import mmgp." not in code
    import mmgp
    used = set(re.findall(r"\bmmgp\.(\w+)", code))
    assert used <= set(mmgp.__all__), used - set(mmgp.__all__)


def test_labels_agree_with_the_recordings_ground_truth(ran):
    _, ns = ran
    truth = pd.read_parquet(ns["truth"])
    labels = ns["labels"]
    assert list(labels.columns[:4]) == ["t", "mode", "disturbed", "p_disturbed"]
    judged = truth["disturbed"].to_numpy() != -1
    true_d = truth["disturbed"].to_numpy()[judged]
    pred_d = labels["disturbed"].to_numpy()[judged]
    assert np.mean(pred_d[true_d == 0] == 0) >= 0.9      # unperturbed correct
    assert np.mean(pred_d[true_d == 1] == 0) <= 0.1      # perturbed missed


def test_prediction_and_feedforward_follow_the_recording(ran):
    folder, ns = ran
    truth = pd.read_parquet(ns["truth"])
    clean = truth["disturbed"].to_numpy() == 0
    states = ns["states"]
    # Where no push acted, the logged torque is the lever's plus noise (0.02 N*m): most clean
    # samples lie inside the prediction's 3-std band, and the band is not vacuous (below the
    # cable's dry-friction level of 0.3 N*m and more).
    inside = np.abs(states.tau[clean, 0] - ns["mean"][clean, 0]) <= 3 * ns["std"][clean, 0]
    assert inside.mean() >= 0.9
    assert np.median(ns["std"][clean, 0]) < 0.3
    q = ns["q"][:, 0]
    static = STATIC_GAIN * np.cos(q)
    # The feedforward is the static torque up to the cable's dry friction (0.3 + 0.2 |tau| N*m,
    # either sign), which the position-only field averages.
    band = 0.3 + 0.2 * np.abs(static)
    ff = ns["feedforward"]
    assert (folder / "replica_feedforward.npz").is_file()
    assert np.all(np.abs(ff.torque(ns["q"])[:, 0] - static) <= band)
    h = 1e-5
    fd = (ff.potential(ns["q"] + h) - ff.potential(ns["q"] - h)) / (2 * h)
    np.testing.assert_allclose(ff.torque(ns["q"])[:, 0], fd, atol=1e-6)


def test_diagnosis_holds_the_log_against_the_lever_and_writes_its_report(ran):
    folder, ns = ran
    vocabulary = set(re.findall(r"^\| `(\w+)` \|", (ROOT / "docs" / "contract.md").read_text(), flags=re.M))
    assert {"coulomb_friction", "payload", "joint_spring"} <= vocabulary
    out = folder / "replica_diagnosis"
    findings = json.loads((out / "findings.json").read_text())
    assert (out / "report.md").is_file()
    assert all(f["effect"] in vocabulary for f in findings["findings"])
    assert len(findings["findings"]) == len(ns["diagnosis"].findings_)
    found = {f["effect"]: f for f in findings["findings"]}
    # The recording's cable friction is 0.3 + 0.2 |tau| N*m (datasets/make_replica.py) and about a
    # third of its samples are pushed: both must be named, the friction's parameters within 25%.
    friction = found["load_dependent_friction"]
    assert friction["joint"] == "lever_joint"
    assert friction["params"]["tau_c"] == pytest.approx(0.3, rel=0.25)
    assert friction["params"]["beta"] == pytest.approx(0.2, rel=0.25)
    spans = found["external_disturbance"]["params"]["spans_s"]
    truth = pd.read_parquet(ns["truth"])
    log = ns["mmgp"].read_log(ns["log"])
    in_span = np.zeros(len(log.t), bool)
    for a, b in spans:
        in_span |= (log.t >= a - 1e-9) & (log.t <= b + 1e-9)
    pushed = truth["disturbed"].to_numpy() == 1
    assert in_span[pushed].mean() >= 0.8 and in_span[truth["disturbed"].to_numpy() == 0].mean() <= 0.1
    # The nominal residual the diagnosis located (outside the push spans it left out) is the log
    # minus the closed-form lever torque (inertia and velocity terms are small on this slow recording).
    rms = np.sqrt(np.mean((log.tau[~in_span, 0] - STATIC_GAIN * np.cos(log.q[~in_span, 0])) ** 2))
    assert findings["location"]["lever_joint"]["rms"] == pytest.approx(rms, rel=0.05)
