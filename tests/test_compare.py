"""Held-out comparison report (mmgp.compare): folds, the normalised MSE, and a MuJoCo Panda check."""
from __future__ import annotations

import json

import numpy as np
import pytest

import mmgp.sim as sim
from mmgp.evaluation.compare import compare, default_gap, format_compare, write_compare
from mmgp.evaluation.metrics import normalised_mse
from mmgp.data.logs import RobotLog
from mmgp.physics.robot import load_robot
from mmgp.data.differentiation import complete_derivatives
from mmgp.data.folds import time_block_folds

PANDA7 = [f"panda_joint{i}" for i in range(1, 8)]


@pytest.fixture(scope="module", autouse=True)
def _one_torch_thread():
    # The GP fits here are small (N <= 300): on a shared, oversubscribed CPU torch's intra-op
    # threads made this file ~10x slower (measured 214 s vs 16 s). Restored afterwards.
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# ---- normalised MSE -------------------------------------------------------------------------


def test_normalised_mse_perfect_is_zero_and_mean_is_one():
    rng = np.random.default_rng(0)
    y = rng.standard_normal((500, 3)) * [1.0, 10.0, 0.01] + [0.0, 5.0, -3.0]
    assert np.allclose(normalised_mse(y, y), 0.0)
    assert np.allclose(normalised_mse(y, np.broadcast_to(y.mean(0), y.shape)), 1.0)
    # Brute-force definition, column by column.
    p = y + rng.standard_normal(y.shape)
    ref = [np.mean((y[:, j] - p[:, j]) ** 2) / np.var(y[:, j]) for j in range(3)]
    assert np.allclose(normalised_mse(y, p), ref)


# ---- folds ----------------------------------------------------------------------------------


@pytest.mark.parametrize("T,k,gap", [(100, 5, 0), (103, 4, 7), (50, 2, 30), (1000, 5, 41)])
def test_time_block_folds_partition_without_overlap_and_respect_gap(T, k, gap):
    folds = time_block_folds(T, k, gap)
    assert len(folds) == k
    seen = np.concatenate([te for _, te in folds])
    assert np.array_equal(np.sort(seen), np.arange(T))  # every sample is tested exactly once
    for train, test in folds:
        assert np.array_equal(test, np.arange(test[0], test[-1] + 1))  # one contiguous block
        assert not np.intersect1d(train, test).size
        if train.size:
            # Brute force: no training sample within `gap` samples of any test sample ...
            dist = np.abs(train[:, None] - test[None, :]).min()
            assert dist > gap
        # ... and nothing else is withheld from training.
        outside = np.setdiff1d(np.arange(T), test)
        near = outside[np.abs(outside[:, None] - test[None, :]).min(1) <= gap]
        assert np.array_equal(np.sort(np.concatenate([train, near])), outside)


def test_default_gap_covers_the_derivative_window():
    # Independent check: perturb one raw q sample; the Savitzky-Golay derivatives change at most
    # `reach` samples away, and two samples whose estimates share a raw sample are <= 2*reach
    # apart, so the gap must exceed 2*reach.
    for rate in (20.0, 100.0, 1000.0):
        T = 600
        t = np.arange(T) / rate
        q = np.sin(t)[:, None]
        base = complete_derivatives(RobotLog(path="x", t=t, q=q, tau=q))
        q2 = q.copy()
        q2[T // 2] += 1.0
        bumped = complete_derivatives(RobotLog(path="x", t=t, q=q2, tau=q))
        changed = np.flatnonzero((np.abs(bumped.dq - base.dq) > 1e-12).any(1)
                                 | (np.abs(bumped.ddq - base.ddq) > 1e-12).any(1))
        reach = int(np.abs(changed - T // 2).max())
        assert default_gap(t) >= 2 * reach + 1


# ---- MuJoCo Panda with a concealed payload and friction ----------------------------------------


@pytest.fixture(scope="module")
def panda_log():
    urdf = sim.panda_urdf_path()
    friction = np.array([0.5, 0.5, 0.4, 0.4, 0.2, 0.2, 0.15])
    real = sim.load_model(urdf, PANDA7, frictionloss=friction,
                          payload={"link": "panda_link8", "mass": 2.0, "com": [0.0, 0.03, 0.1]})
    nominal = sim.load_model(urdf, PANDA7)
    pm = sim.reduced_pinocchio_model(urdf, PANDA7)
    ref = sim.fourier_reference(np.random.default_rng(5), np.asarray(pm.lowerPositionLimit),
                                np.asarray(pm.upperPositionLimit), period=10.0)
    P = sim.PANDA
    # Three periods: each of three time blocks is one period, so training covers its states.
    rec = sim.simulate(real, ref, 30.0, rate_hz=50.0, kp=P["kp"], kd=P["kd"], controller_model=nominal,
                       q_resolution=P["q_resolution"], tau_noise=P["tau_noise"], dq_noise=P["dq_noise"],
                       seed=1, robot="panda", joint_names=PANDA7)
    log = RobotLog(path="panda_concealed", t=rec.t, q=rec.q, tau=rec.tau, dq=rec.dq,
                   metadata={"joint_names": PANDA7})
    return complete_derivatives(log)


@pytest.fixture(scope="module")
def panda_result(panda_log):
    robot = load_robot("panda", joint_names=PANDA7)
    return compare(panda_log, robot, n_folds=3, max_train=300,
                   gp_options={"max_fit_points": 200, "max_iter": 30})


def test_rigid_body_plus_gp_beats_rigid_body_on_every_joint(panda_result, panda_log):
    r = panda_result
    rb, rbgp = np.array(r["nmse"]["rigid_body"]), np.array(r["nmse"]["rigid_body_gp"])
    print(format_compare(r))
    assert np.all(rbgp < rb), (rb, rbgp)
    assert r["gp_improves_rigid_body"] == [True] * 7
    # The concealed payload and friction are large: the nominal model alone is poor somewhere.
    assert rb.max() > 0.3
    # Rigid-body figures are the nominal RNEA's error, recomputed independently here.
    robot = load_robot("panda", joint_names=PANDA7)
    tau_rbd = robot.rnea(panda_log.q, panda_log.dq, panda_log.ddq)
    assert np.allclose(rb, normalised_mse(panda_log.tau, tau_rbd))


def test_compare_folds_and_output_files(panda_result, panda_log, tmp_path):
    r = panda_result
    T = panda_log.n_samples
    assert r["gap"] == default_gap(panda_log.t)
    blocks = [f["test"] for f in r["folds"]]
    assert blocks[0][0] == 0 and blocks[-1][1] == T
    assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:]))
    for f in r["folds"]:
        lo, hi = f["test"]
        assert f["n_train_available"] == T - min(T, hi + r["gap"]) + max(0, lo - r["gap"])
        assert f["n_train"] == min(300, f["n_train_available"])
    paths = write_compare(r, tmp_path / "out")
    data = json.loads((tmp_path / "out" / "compare.json").read_text())
    assert data["nmse"]["rigid_body_gp"] == pytest.approx(r["nmse"]["rigid_body_gp"])
    png = (tmp_path / "out" / "compare.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in paths] == ["compare.json", "compare.png", "report.html"]


def test_gp_only_without_robot(panda_log):
    short = panda_log.subset(np.arange(0, 600))
    r = compare(short, None, n_folds=2, max_train=60, gp_options={"max_fit_points": 60, "max_iter": 5})
    assert r["methods"] == ["gp"] and "gp_improves_rigid_body" not in r
    assert len(r["nmse"]["gp"]) == 7 and np.all(np.isfinite(r["nmse"]["gp"]))


def test_compare_refuses_missing_derivatives(panda_log):
    with pytest.raises(ValueError, match="complete_derivatives"):
        compare(panda_log.replace(ddq=None), None)
