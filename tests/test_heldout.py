"""The held-out score `mmgp train` reports (report.json -> heldout), against references outside it:
a log whose torque is a known function (rigid body + payload + viscous friction + Gaussian
noise of known spread), the rigid body's and the mean's figures computed by hand, the fold split
checked pair by pair, and what `mmgp train` writes and prints on the shipped replica."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mmgp import MultimodalGP
from mmgp.data.differentiation import SavitzkyGolay
from mmgp.data.folds import default_gap, time_block_folds
from test_estimator import double_pendulum_arrays

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "mmgp/resources/replica/replica_log.parquet"
NOISE = 0.02                      # N*m, the synthetic log's torque noise (test_estimator's log)
VISCOUS = 0.05                    # N*m*s/rad, its viscous friction (not in the URDF)


def double_pendulum_log(T=1000, rate=50.0, seed=0):
    """A 2-DOF log at 50 Hz: the URDF's rigid body with a 0.4 kg point mass at the tip link,
    viscous friction VISCOUS and Gaussian noise of NOISE N*m; exact dq and ddq (nothing estimated)."""
    return double_pendulum_arrays(T=T, rate=rate, seed=seed)


@pytest.fixture(scope="module")
def known():
    robot, arrays = double_pendulum_log()
    # One mode, no disturbance mode: every sample is undisturbed and scored.
    model = MultimodalGP(robot=robot, disturbance=False, fit_points=400, fit_iter=30).fit(**arrays)
    return robot, arrays, model, model.report_["heldout"]


def test_every_sample_of_a_log_without_pushes_is_scored(known):
    _, arrays, _, h = known
    T = len(arrays["t"])
    assert h["n_scored"] == T and h["n_disturbed_left_out"] == 0 and h["n_unscored"] == 0
    assert "undisturbed" in h["scored"] and h["n_folds"] == 5


def test_the_model_is_scored_at_the_noise_floor(known):
    # Out of fold, the best any model can do is the noise: nMSE = NOISE^2 / var(tau) per joint.
    _, arrays, _, h = known
    floor = NOISE ** 2 / arrays["tau"].var(0)
    model = np.array(h["nmse"]["model"])
    assert np.all(model > 0.7 * floor) and np.all(model < 2.0 * floor), (model, floor)


def test_the_rigid_body_figure_is_the_known_terms_share(known):
    # What the URDF misses is the payload, the viscous friction and the noise, all known here.
    robot, a, _, h = known
    miss = a["tau"] - robot.rnea(a["q"], a["dq"], a["ddq"])
    by_hand = (miss ** 2).mean(0) / a["tau"].var(0)
    np.testing.assert_allclose(h["nmse"]["rigid_body"], by_hand, rtol=1e-9)
    assert np.all(by_hand > 100 * np.array(h["nmse"]["model"]))


def test_the_mean_figure_is_each_blocks_training_mean(known):
    # By hand: block k predicted by the mean torque of the samples more than `gap` from it.
    _, a, _, h = known
    tau, T, gap = a["tau"], len(a["t"]), h["gap"]
    edges = np.linspace(0, T, 6).round().astype(int)
    sq = np.zeros(2)
    for lo, hi in zip(edges[:-1], edges[1:]):
        i = np.arange(T)
        train = (i < lo - gap) | (i >= hi + gap)
        sq += ((tau[lo:hi] - tau[train].mean(0)) ** 2).sum(0)
    np.testing.assert_allclose(h["nmse"]["mean"], sq / T / tau.var(0), rtol=1e-9)
    assert np.all(np.array(h["nmse"]["mean"]) >= 1.0)       # the pooled mean is the best constant


@pytest.mark.parametrize("T, n_folds, gap", [(50, 5, 0), (101, 5, 3), (330, 5, 11), (997, 4, 26)])
def test_no_test_sample_is_within_the_gap_of_a_training_sample(T, n_folds, gap):
    folds = time_block_folds(T, n_folds, gap)
    assert np.array_equal(np.sort(np.concatenate([te for _, te in folds])), np.arange(T))
    for train, test in folds:
        assert np.all(np.diff(test) == 1)                       # contiguous
        assert np.abs(train[:, None] - test[None, :]).min() > gap
        assert len(train) == T - len(test) - min(gap, test[0]) - min(gap, T - 1 - test[-1])


def test_the_gap_keeps_derivative_windows_apart():
    # Raw positions moved inside a test block change no training sample's estimated derivatives
    # when the gap is the window's length (what heldout uses with estimated derivatives: 0.5 s).
    rng = np.random.default_rng(1)
    t = np.arange(600) / 100.0
    q = np.sin(t)[:, None] + 0.01 * rng.normal(size=(600, 1))
    sg = SavitzkyGolay(window_s=0.5)
    gap = default_gap(t, 0.5)
    for train, test in time_block_folds(len(t), 5, gap):
        moved = q.copy()
        moved[test] += rng.normal(size=(len(test), 1))
        for deriv in (1, 2):
            np.testing.assert_allclose(sg(t, moved, deriv)[train], sg(t, q, deriv)[train], atol=1e-9)


def test_train_writes_and_prints_the_heldout_score(tmp_path):
    from mmgp.cli import app

    (tmp_path / "quick.yaml").write_text("train:\n  max_sweeps: 3\n  min_sweeps: 1\n  average_last: 1\n  fit_iter: 5\n")
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["train", str(LOG), "--out", str(out), "--config", str(tmp_path / "quick.yaml"),
                                   "--quiet"])
    assert res.exit_code == 0, res.output
    rep = json.loads((out / "report.json").read_text())
    h = rep["heldout"]
    assert h["joint_names"] == rep["joint_names"] and h["nmse"]["rigid_body"] is None     # no robot in the log
    assert h["n_scored"] + h["n_disturbed_left_out"] + h["n_unscored"] == rep["n_samples"]
    assert h["n_disturbed_left_out"] == rep["disturbance"]["n_disturbed"]
    assert 0.0 < h["nmse"]["model"][0] < 1.0 < h["nmse"]["mean"][0]
    assert rep["timings"]["heldout_s"] == h["seconds"]
    assert "held-out normalised MSE" in res.stdout
    row = next(line.split() for line in res.stdout.splitlines() if line.startswith(rep["joint_names"][0]))
    assert [float(row[1]), row[2], float(row[3])] == [pytest.approx(h["nmse"]["model"][0], rel=1e-3), "-",
                                                      pytest.approx(h["nmse"]["mean"][0], rel=1e-3)]
