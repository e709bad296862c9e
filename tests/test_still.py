"""An arm holding a pose while a hand pushes it (issue 30): the checks judge what a still robot
can show, the pushes are reported and the payload's mass is found.

The recording is MuJoCo's (``mmgp.sim.held.held_pose``: example-robot-data's UR5 with 2.5 kg on
its flange, held by an impedance controller whose model lacks the payload, pushed by external
forces); the truth is what was put into MuJoCo: the payload, the push spans. The diagnosis runs
from the command line on the log and the URDF without the payload, as a user would.
"""
import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.data.logs import read_log
from mmgp.physics.plausibility import velocity_warnings
from mmgp.sim.held import HELD, held_pose

# the learner's GP stage and plots are left out (speed); pushes, modes and checks as shipped
CONFIG = "diagnose:\n  gp: false\n  plots: false\n"


def _diagnosed(cache: dict, tmp_path_factory, seed: int) -> dict:
    if seed not in cache:
        d = tmp_path_factory.mktemp(f"still{seed}")
        rec = held_pose(seed=seed)
        log = d / "held.parquet"
        rec.write(log)
        (d / "fast.yaml").write_text(CONFIG)
        res = CliRunner().invoke(app, ["diagnose", str(log), "--out", str(d / "out"), "--config",
                                       str(d / "fast.yaml"), "--quiet"])
        assert res.exit_code == 0, res.output
        cache[seed] = {"rec": rec, "log": log, "out": d / "out",
                       "doc": json.loads((d / "out" / "findings.json").read_text())}
    return cache[seed]


@pytest.fixture(scope="module")
def runs():
    return {}


# seed 1: a 2 s push on the shoulder and elbow, on which the library's unphysical masses once
# made the whole rigid body look re-identified instead of the payload; seed 3: pushes held at the
# pose that a switching fit once took for a second payload of 3.67 kg (a false mode switch)
# seed 5: the payload's centre along gravity, which one pose does not determine, was fitted at
# 0.88 m from the few samples a push tilts, and a false spring and encoder offset took its torque
@pytest.fixture(scope="module", params=[0, 1, 3, 5])
def held(runs, tmp_path_factory, request):
    return _diagnosed(runs, tmp_path_factory, request.param)


@pytest.fixture(scope="module")
def held0(runs, tmp_path_factory):
    return _diagnosed(runs, tmp_path_factory, 0)


def test_the_recording_holds_still_between_pushes(held0):
    rec = held0["rec"]
    free = rec.info["push_force"] == 0
    # the truth's own velocities: the arm barely moves unless pushed
    assert np.abs(rec.info["dq_true"][free]).max() < 0.05
    assert 2 <= len(rec.info["push_spans"]) <= 4


def test_no_warning_a_still_robot_cannot_avoid(held):
    doc = held["doc"]
    assert doc["warnings"] == []
    assert doc["withheld_findings"] == []
    # every joint is still on the undisturbed samples: the torque's mean is not what it is judged by
    assert set(doc["fit"]["still_joints"]) == set(held["rec"].info["joint_names"])


def test_the_pushes_are_reported_where_they_were(held):
    doc, truth = held["doc"], held["rec"].info["push_spans"]
    (dist,) = [f for f in doc["findings"] if f["effect"] == "external_disturbance"]
    spans = dist["params"]["spans_s"]
    for a, b in truth:
        found = [(s, e) for s, e in spans if s < b and e > a]
        assert found, (a, b, spans)
        # the push found whole: its reported edges within a tenth of a second of the true ones
        # (the force ramps on and off; a 0.38 s push of seed 5 is reported 0.04 s short each side)
        overlap = sum(min(e, b) - max(s, a) for s, e in found)
        assert overlap > (b - a) - 0.2, (a, b, found)
    # nothing reported far from a push
    assert all(any(s < b + 0.3 and e > a - 0.3 for a, b in truth) for s, e in spans)


def test_the_payload_mass_is_found_and_nothing_else(held):
    doc = held["doc"]
    (pl,) = [f for f in doc["findings"] if f["effect"] == "payload"]
    assert pl["link"] == "wrist_3_link"
    assert pl["params"]["mass"] == pytest.approx(HELD["payload_mass"], rel=0.10)
    # across gravity (this pose's flange points down, wrist_3_link's y up) the centre of mass is
    # found; along gravity it is stated as not determined, not claimed
    com, truth = np.array(pl["params"]["com"]), np.array(held["rec"].info["payload"]["com_wrist_3_link"])
    np.testing.assert_allclose(com[[0, 2]], truth[[0, 2]], atol=0.01)
    (unresolved,) = pl["evidence"]["com_unresolved"]
    assert abs(unresolved["direction"][1]) > 0.99
    assert "does not determine its centre of mass" in pl["explanation"]
    assert {f["effect"] for f in doc["findings"]} == {"payload", "external_disturbance"}


def test_the_location_share_is_of_the_measured_torque(held):
    # the residual's RMS over the logged torque's RMS on the samples the diagnosis used (those
    # not called pushed): a share of the torque (it once divided by a near-zero residual spread).
    # Where the nominal model predicts about nothing it is near 1 either side (wrist_3 of seed 3:
    # the torque is the sensor's noise), so it is checked against the log, not against 1.
    log = read_log(held["log"])
    labels = pd.read_parquet(held["out"] / "labels.parquet")
    rows = np.searchsorted(log.t, labels["t"].to_numpy())
    np.testing.assert_allclose(log.t[rows], labels["t"].to_numpy(), atol=1e-9)
    tau = log.tau[rows][labels["disturbed"].to_numpy() == 0]
    for j, name in enumerate(log.joint_names):
        loc = held["doc"]["location"][name]
        torque_rms = np.sqrt(np.mean(tau[:, j] ** 2))
        assert loc["fraction_of_torque_rms"] == pytest.approx(loc["rms"] / torque_rms, rel=1e-6)
        assert 0.0 <= loc["fraction_of_torque_rms"] < 1.05


def test_velocity_check_judges_the_push_motion_and_still_flags_wrong_velocities(held0):
    log = read_log(held0["log"])
    names = log.joint_names
    assert velocity_warnings(log.t, log.q, log.dq, names) == []
    # the same log with velocities in deg/s, or two joints' velocities swapped, is told
    assert len(velocity_warnings(log.t, log.q, np.degrees(log.dq), names)) == len(names)
    swapped = log.dq[:, [1, 0, 2, 3, 4, 5]]
    assert {w.split(":")[0] for w in velocity_warnings(log.t, log.q, swapped, names)} >= {names[0], names[1]}
