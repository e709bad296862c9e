"""Converters of the shared real datasets: logs mmgp.io accepts, counts as in SOURCE.md, and
rigid-body sanity against the nominal models where one exists. Skipped per dataset when the
shared folder lacks it."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from mmgp.data.logs import read_log
from mmgp.physics.robot import load_robot

_spec = importlib.util.spec_from_file_location(
    "convert_real", Path(__file__).resolve().parents[1] / "datasets" / "convert_real.py")
cr = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(cr)


def need(name):
    if not cr.dataset_dir(name).is_dir():
        pytest.skip(f"shared dataset folder {cr.dataset_dir(name)} is absent")


def explained(pred, meas):
    """1 - nMSE per joint."""
    return 1.0 - np.mean((pred - meas) ** 2, axis=0) / np.var(meas, axis=0)


def test_panda_gaz2019(tmp_path):
    need("panda_gaz2019")
    (path,) = cr.convert("panda_gaz2019", tmp_path)
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (20544, 7)
    assert log.dq is not None and log.ddq is None
    raw = np.loadtxt(cr.dataset_dir("panda_gaz2019") / "gen_q0.txt")
    np.testing.assert_allclose(log.q[0], raw)  # SOURCE.md: first sample = gen_q0
    assert 20.9 < log.t[-1] - log.t[0] < 21.1
    robot = load_robot(log_path=path)
    assert robot.name == "panda" and robot.n_joints == 7
    ddq = cr.savgol_ddq(log.t, log.dq)
    ev = explained(robot.rnea(log.q, log.dq, ddq), log.tau)
    print("panda nominal RNEA, 1 - nMSE per joint:", np.round(ev, 3))
    assert (ev[:4] > 0.5).all()
    (path2,) = cr.convert("panda_gaz2019", tmp_path / "sg", ddq="savgol")
    np.testing.assert_allclose(read_log(path2).ddq, ddq)


def test_polydoros_ur10(tmp_path):
    need("polydoros_ur10_pickplace")
    (path,) = cr.convert("polydoros_ur10_pickplace", tmp_path)
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (12349, 6)
    np.testing.assert_allclose(np.diff(log.t), 0.008)
    # The 8 ms step: q advances by dq * dt (up to the 1e-4 rounding of q).
    moving = np.abs(log.dq[1:]).max(axis=1) > 0.05
    dq_mid = log.dq[1:][moving]
    dt = np.sum(np.diff(log.q, axis=0)[moving] * dq_mid) / np.sum(dq_mid ** 2)
    assert abs(dt - 0.008) < 2e-5
    # ddq, rescaled by the converter, is the backward difference of dq at that step.
    np.testing.assert_allclose(log.ddq[1:], np.diff(log.dq, axis=0) / 0.008, atol=1e-9)
    (raw,) = cr.convert("polydoros_ur10_pickplace", tmp_path / "raw", fix_ddq=False)
    np.testing.assert_allclose(read_log(raw).ddq[1:], np.diff(log.dq, axis=0) / 0.0083, atol=1e-9)
    robot = load_robot(log_path=path)
    assert robot.name == "ur10"
    # Joint zero/sign conventions: the recording starts and ends at the UR upright home pose,
    # where the nominal model needs almost no shoulder/elbow torque.
    home = robot.gravity(log.q[:400])
    assert np.abs(home[:, 1:3]).max() < 2.0
    tau_rbd = robot.rnea(log.q, log.dq, log.ddq)
    ev = explained(tau_rbd, log.tau)
    corr = [np.corrcoef(tau_rbd[:, j], log.tau[:, j])[0, 1] for j in range(6)]
    print("UR10 nominal RNEA, 1 - nMSE per joint:", np.round(ev, 3), "corr:", np.round(corr, 3))
    # The logged torques are NOT consistent N*m joint torques (see the report): only the sign
    # agreement on the shoulder and elbow is asserted.
    assert corr[1] > 0.1 and corr[2] > 0.1


@pytest.mark.parametrize("name,counts", [("ias_barrett", (12000, 3000)), ("ias_sarcos", (13922, 5569))])
def test_ias_splits(tmp_path, name, counts):
    need(name)
    from scipy.io import loadmat

    train, test = cr.convert(name, tmp_path)
    mat = loadmat(next(cr.dataset_dir(name).glob(f"ias_{'real_barrett' if 'barrett' in name else 'sarcos'}_data.mat")))
    for path, split, n in ((train, "train", counts[0]), (test, "test", counts[1])):
        log = read_log(path)
        assert (log.n_samples, log.n_joints) == (n, 7)
        assert load_robot(log_path=path) is None  # GP only
        X, Y = mat[f"X_{split}"], mat[f"Y_{split}"]
        np.testing.assert_array_equal(np.hstack([log.q, log.dq, log.ddq]), X)
        np.testing.assert_array_equal(log.tau, Y)
    if name == "ias_sarcos":
        _, test2 = cr.convert(name, tmp_path / "dedup", drop_test_duplicates=True)
        assert read_log(test2).n_samples == 5569 - 2785  # SOURCE.md: 2,785 copies of train rows


def test_iiwa14_subset(tmp_path):
    need("iiwa14_lasa_subset")
    files = cr.convert("iiwa14_lasa_subset", tmp_path)
    path = [f for f in files if f.suffix == ".parquet"][0]
    log = read_log(path)
    assert (log.n_samples, log.n_joints) == (750, 7)
    robot = load_robot(log_path=path)  # the URDF next to the log, named in the metadata
    assert robot.urdf_path == tmp_path / "iiwa14.urdf"
    ev = explained(robot.rnea(log.q, log.dq, log.ddq), log.tau)
    print("iiwa14 RNEA (shipped URDF) vs -tau_file, 1 - nMSE per joint:", np.round(ev, 3))
    assert ev[1] > 0.5 and ev[3] > 0.5
    raw = cr.convert("iiwa14_lasa_subset", tmp_path / "raw", flip_tau=False)
    np.testing.assert_array_equal(read_log(raw[1]).tau, -log.tau)


def test_missing_folder_is_skipped_cleanly(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MMGP_SHARED_DATASETS", str(tmp_path / "nowhere"))
    assert cr.main(["panda_gaz2019", "--out", str(tmp_path / "o"), "--skip-missing"]) == 0
    assert "skipped" in capsys.readouterr().err
    assert cr.main(["panda_gaz2019", "--out", str(tmp_path / "o")]) == 1
    assert not (tmp_path / "o").exists()
    with pytest.raises(cr.DatasetMissing):
        cr.convert("iiwa14_lasa_subset", tmp_path / "o")
    assert cr.main(["no_such_set", "--out", str(tmp_path / "o")]) == 2
