"""The shared real datasets through the package converter: logs that read_log accepts, counts as
in SOURCE.md, values against the raw files, and rigid-body sanity against the nominal models.
Skipped per dataset when the shared folder lacks it (no environment variable needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.io import loadmat

from mmgp.convert import convert, read_input
from mmgp.data.differentiation import SavitzkyGolay
from mmgp.data.logs import read_log
from mmgp.errors import InputError
from mmgp.physics.robot import RobotModel, load_robot

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"
SHARED = SHARED if SHARED.is_dir() else Path("/work/shared/datasets")


def folder(name: str) -> Path:
    d = SHARED / name
    if not d.is_dir():
        pytest.skip(f"shared dataset folder {d} is absent")
    return d


def explained(pred, meas):
    """1 - nMSE per joint."""
    return 1.0 - np.mean((pred - meas) ** 2, axis=0) / np.var(meas, axis=0)


def corr(a, b):
    return np.array([np.corrcoef(a[:, j], b[:, j])[0, 1] for j in range(a.shape[1])])


def with_map(tmp_path, text: str) -> Path:
    p = tmp_path / "map.yaml"
    p.write_text(text)
    return p


def test_panda_gaz2019(tmp_path):
    d = folder("panda_gaz2019")
    (path,) = convert(d, tmp_path / "panda.parquet")
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (20544, 7)
    assert log.dq is not None and log.ddq is None
    np.testing.assert_allclose(log.q[0], np.loadtxt(d / "gen_q0.txt"))  # SOURCE.md: first sample = gen_q0
    assert 20.9 < log.t[-1] - log.t[0] < 21.1
    robot = load_robot(log_path=path)
    assert robot.name == "panda" and robot.n_joints == 7
    ddq = SavitzkyGolay(window_s=0.04, order=2)(log.t, log.dq, 1)
    ev = explained(robot.rnea(log.q, log.dq, ddq), log.tau)
    assert (ev[:4] > 0.5).all(), ev


def test_polydoros_ur10(tmp_path):
    d = folder("polydoros_ur10_pickplace")
    (path,) = convert(d, tmp_path / "ur10.parquet")
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (12349, 6)
    np.testing.assert_allclose(np.diff(log.t), 0.008)
    moving = np.abs(log.dq[1:]).max(axis=1) > 0.05  # q advances by dq * 8 ms (to q's 1e-4 rounding)
    dq_mid = log.dq[1:][moving]
    assert abs(np.sum(np.diff(log.q, axis=0)[moving] * dq_mid) / np.sum(dq_mid ** 2) - 0.008) < 2e-5
    np.testing.assert_allclose(log.ddq[1:], np.diff(log.dq, axis=0) / 0.008, atol=1e-9)
    (raw,) = read_input(d, map_path=with_map(tmp_path, "dataset: {fix_ddq: false}\n"))
    np.testing.assert_allclose(raw.ddq[1:], np.diff(log.dq, axis=0) / 0.0083, atol=1e-9)
    robot = load_robot(log_path=path)
    assert robot.name == "ur10"
    assert np.abs(robot.gravity(log.q[:400])[:, 1:3]).max() < 2.0  # starts at the upright home pose
    c = corr(robot.rnea(log.q, log.dq, log.ddq), log.tau)
    assert c[1] > 0.1 and c[2] > 0.1  # the logged torques are not consistent N*m: signs only


@pytest.mark.parametrize("name,file,counts", [("ias_barrett", "ias_real_barrett_data.mat", (12000, 3000)),
                                              ("ias_sarcos", "ias_sarcos_data.mat", (13922, 5569))])
def test_ias_splits(tmp_path, name, file, counts):
    d = folder("ias_nguyen_tuong")
    written = convert(d / file, tmp_path / "out")  # one file of the folder: its two splits
    assert [p.name for p in written] == [f"{name}_test.parquet", f"{name}_train.parquet"]
    mat = loadmat(d / file)
    for split, n in (("train", counts[0]), ("test", counts[1])):
        path = tmp_path / "out" / f"{name}_{split}.parquet"
        log = read_log(path)
        assert (log.n_samples, log.n_joints) == (n, 7)
        assert load_robot(log_path=path) is None  # GP only
        np.testing.assert_array_equal(np.hstack([log.q, log.dq, log.ddq]), mat[f"X_{split}"])
        np.testing.assert_array_equal(log.tau, mat[f"Y_{split}"])
    if name == "ias_sarcos":
        parts = read_input(d / file, map_path=with_map(tmp_path, "dataset: {drop_test_duplicates: true}\n"))
        assert parts[1].n_samples == 5569 - 2785  # SOURCE.md: 2,785 copies of train rows


def test_ias_whole_folder_and_sarcos_gpml(tmp_path):
    parts = read_input(folder("ias_nguyen_tuong"))
    counts = {p.name: p.n_samples for p in parts}
    assert counts == {"ias_barrett_train": 12000, "ias_barrett_test": 3000, "ias_sarcos_train": 13922,
                      "ias_sarcos_test": 5569, "ias_sl_barrett_train": 12000, "ias_sl_barrett_test": 3000,
                      "ias_sl_sarcos_train": 14904, "ias_sl_sarcos_test": 5520}
    with pytest.raises(InputError, match="give --part NAME"):
        convert(folder("ias_nguyen_tuong"), tmp_path / "one.parquet")
    (path,) = convert(folder("ias_nguyen_tuong"), tmp_path / "one.parquet", part="ias_sl_sarcos_test")
    assert read_log(path).n_samples == 5520
    (log,) = read_input(folder("sarcos"))
    A = loadmat(folder("sarcos") / "sarcos_inv_test.mat")["sarcos_inv_test"]
    assert log.n_samples == 4449
    np.testing.assert_array_equal(np.hstack([log.q, log.dq, log.ddq, log.tau]), A)


def test_baxter_trajectories_in_model_order(tmp_path):
    d = folder("polydoros_baxter_forward")
    parts = read_input(d)
    assert len(parts) == 10 and sum(p.n_samples for p in parts) == 19295
    mat = loadmat(d / "BaxterDirectDynamics.mat")
    raw = mat["baxtertraj3"]
    log = parts[2]
    assert log.name == "baxter_traj03" and log.joint_names[:4] == ["left_s0", "left_s1", "left_e0", "left_e1"]
    np.testing.assert_array_equal(log.q, raw[:, [2, 3, 0, 1, 4, 5, 6]])  # file order e0 e1 s0 s1 w0 w1 w2
    np.testing.assert_array_equal(log.tau, raw[:, [16, 17, 14, 15, 18, 19, 20]])
    robot = RobotModel.from_name("baxter", log.joint_names)
    q = np.concatenate([p.q for p in parts])
    tau = np.concatenate([p.tau for p in parts])
    c = corr(robot.gravity(q[::5]), tau[::5])
    assert (c[2:6] > 0.9).all(), c  # e0, e1, w0, w1 follow the nominal gravity torque


def test_staubli_motor_side_to_joints(tmp_path):
    d = folder("staubli_tx40_figaroh")
    (path, urdf) = convert(d, tmp_path / "tx40.parquet")
    assert urdf.name == "tx40.urdf" and urdf.read_bytes() == (d / "tx40_mdh_modified.urdf").read_bytes()
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (45000, 6) and log.dq is None
    np.testing.assert_allclose(np.diff(log.t), 0.0002)
    m = pd.read_csv(d / "pos_read_data.csv").to_numpy()
    cur = pd.read_csv(d / "curr_data.csv").to_numpy()
    r = [32.0, 32.0, 45.0, -48.0, 45.0, 32.0]
    qj = log.q + np.array([0, np.pi / 2, -np.pi / 2, 0, 0, 0])
    motor = qj * r
    motor[:, 5] += r[5] * qj[:, 4]  # motor 6 turns with joints 5 and 6
    np.testing.assert_allclose(motor, m, atol=1e-9)
    # power through the motors = power through the joints, for any joint velocity
    v = np.random.default_rng(0).normal(size=6)
    vm = v * r
    vm[5] += r[5] * v[4]
    np.testing.assert_allclose(log.tau @ v, cur @ vm, rtol=1e-10, atol=1e-9)
    robot = load_robot(log_path=path)
    s = slice(500, -500, 10)
    dq = SavitzkyGolay(window_s=0.04)(log.t, log.q, 1)
    ddq = SavitzkyGolay(window_s=0.04)(log.t, log.q, 2)
    tau_rbd = robot.rnea(log.q[s], dq[s], ddq[s])
    for j, (fv, fs) in enumerate([(8.05, 7.14), (5.53, 8.26), (1.97, 6.34)]):  # TX40_config.yaml
        X = np.c_[tau_rbd[:, j], dq[s, j], np.sign(dq[s, j]), ddq[s, j], np.ones(tau_rbd.shape[0])]
        b = np.linalg.lstsq(X, log.tau[s, j], rcond=None)[0]
        assert 0.8 < b[0] < 1.2 and 0.5 * fv < b[1] < 1.5 * fv and 0.5 * fs < b[2] < 1.5 * fs, (j, b)


def test_tiago_effort_to_torque(tmp_path):
    d = folder("tiago_figaroh")
    (path,) = convert(d, tmp_path / "tiago.parquet")
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (8022, 8)
    assert log.joint_names[0] == "torso_lift_joint"
    robot = load_robot(log_path=path)
    assert robot.name == "tiago"
    ddq = SavitzkyGolay(window_s=0.1)(log.t, log.dq, 1)
    tau_rbd = robot.rnea(log.q, log.dq, ddq)
    slope = np.array([np.polyfit(tau_rbd[:, j], log.tau[:, j], 1)[0] for j in range(8)])
    assert (slope[2:5] > 0.6).all() and (slope[2:5] < 1.3).all(), slope  # arm 2-4 carry the gravity load
    assert abs(log.tau[:, 0].mean() - tau_rbd[:, 0].mean()) < 0.05 * tau_rbd[:, 0].mean()
    (raw,) = read_input(d, map_path=with_map(tmp_path, "dataset: {raw_effort: true}\n"))
    np.testing.assert_array_equal(raw.tau, pd.read_csv(d / "tiago_effort.csv").to_numpy()[:, 1:])


def test_iiwa14_subset(tmp_path):
    d = folder("iiwa14_lasa_subset")
    files = convert(d, tmp_path / "out")
    path = tmp_path / "out" / "iiwa14_lasa_subset.parquet"
    assert sorted(f.name for f in files) == ["iiwa14_lasa_subset.parquet", "iiwa14_lasa_subset.urdf"]
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (750, 7)
    robot = load_robot(log_path=path)  # the URDF next to the log, named in the metadata
    assert robot.urdf_path == tmp_path / "out" / "iiwa14_lasa_subset.urdf"
    ev = explained(robot.rnea(log.q, log.dq, log.ddq), log.tau)
    assert ev[1] > 0.5 and ev[3] > 0.5
    (raw,) = read_input(d, map_path=with_map(tmp_path, "dataset: {flip_tau: false}\n"))
    np.testing.assert_array_equal(raw.tau, -log.tau)
    with pytest.raises(InputError, match="do not apply to iiwa14_lasa_subset"):
        read_input(d, map_path=with_map(tmp_path, "dataset: {fix_ddq: false}\n"))
