"""The public estimator mmgp.MultimodalGP: scikit-learn contract, inputs, persistence, export."""
from __future__ import annotations

import copy
import inspect
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError

from mmgp import InputError, MultimodalGP
from mmgp.data.logs import read_log

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "mmgp/resources/replica/replica_log.parquet"
FAST = dict(max_sweeps=4, min_sweeps=2, average_last=1, fit_iter=10, fit_points=150, max_support=150)


@pytest.fixture(scope="module")
def replica_model():
    return MultimodalGP(**FAST).fit(LOG)


def test_get_params_lists_every_constructor_parameter_and_clone_round_trips():
    sig = inspect.signature(MultimodalGP.__init__)
    names = [p for p in sig.parameters if p != "self"]
    est = MultimodalGP(n_modes="auto", disturbance=False, tol_changed=0.2, block_s=0.0, seed=7)
    params = est.get_params()
    assert sorted(params) == sorted(names)
    defaults = {p: sig.parameters[p].default for p in names}
    expected = dict(defaults, n_modes="auto", disturbance=False, tol_changed=0.2, block_s=0.0, seed=7)
    assert params == expected
    twin = clone(est)
    assert twin is not est and twin.get_params() == params
    assert est.set_params(patience=5, robot="panda") is est
    assert est.get_params()["patience"] == 5 and est.get_params()["robot"] == "panda"
    assert twin.get_params()["patience"] == 3
    # No validation in __init__: a bad value is stored as given, and refused by fit.
    bad = MultimodalGP(n_modes="many")
    assert bad.n_modes == "many"
    with pytest.raises(InputError, match="n_modes"):
        bad.fit(LOG)


def test_clone_of_a_fitted_model_is_unfitted(replica_model):
    twin = clone(replica_model)
    assert not hasattr(twin, "labels_")
    with pytest.raises(NotFittedError):
        twin.predict(np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1)))


def test_unfitted_use_is_a_clear_error(tmp_path):
    est = MultimodalGP()
    z = np.zeros((3, 1))
    for call in (lambda: est.predict(z, z, z), lambda: est.save(tmp_path / "m"), lambda: est.to_compensator(),
                 lambda: est.nominal_torque(z)):
        with pytest.raises(NotFittedError, match="not fitted"):
            call()
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("setting, value", [
    ("n_modes", 0), ("n_modes", 1.5), ("estep", "metropolis"), ("stay_prob", 1.0), ("rate_hz", -5.0),
    ("semiparametric", "both"), ("mean_basis", "linear"), ("max_sweeps", 0), ("patience", 2.5),
    ("tol_changed", 0.0), ("block_s", -1.0), ("mode_smoothing_s", 0.0), ("calibrate", "yes"),
    ("objective", "mse"), ("device", "tpu"), ("seed", "zero"), ("progress", "print"), ("robot", 3.0),
    ("push_s", 0.0), ("gap_s", -1.0), ("push_floor_z", -0.5), ("abstain", 1)])
def test_fit_refuses_a_bad_setting_naming_it(setting, value):
    with pytest.raises(InputError, match=f"'{setting}'"):
        MultimodalGP(**{setting: value}).fit(LOG)


def test_arrays_give_the_labels_of_the_file(replica_model):
    lg = read_log(LOG)
    arrays = dict(t=lg.t, q=lg.q, tau=lg.tau, dq=lg.dq, ddq=lg.ddq)
    copies = {k: None if v is None else v.copy() for k, v in arrays.items()}
    from_arrays = MultimodalGP(**FAST).fit(**arrays)
    pd.testing.assert_frame_equal(from_arrays.labels_, replica_model.labels_, check_exact=True)
    for k, v in arrays.items():       # inputs are never modified
        if v is not None:
            np.testing.assert_array_equal(v, copies[k])
    # One joint may come as (T,) vectors.
    flat = MultimodalGP(**FAST).fit(t=lg.t, q=lg.q[:, 0], tau=lg.tau[:, 0],
                                    dq=None if lg.dq is None else lg.dq[:, 0],
                                    ddq=None if lg.ddq is None else lg.ddq[:, 0])
    pd.testing.assert_frame_equal(flat.labels_, replica_model.labels_, check_exact=True)


def test_bad_arrays_are_named():
    lg = read_log(LOG)
    tau = lg.tau.copy()
    tau[7, 0] = np.nan
    with pytest.raises(InputError, match=r"column 'tau', row 7"):
        MultimodalGP().fit(t=lg.t, q=lg.q, tau=tau)
    t = lg.t.copy()
    t[12] = t[11]
    with pytest.raises(InputError, match=r"column 't', row 12"):
        MultimodalGP().fit(t=t, q=lg.q, tau=lg.tau)
    with pytest.raises(InputError, match="column 'tau'"):
        MultimodalGP().fit(t=lg.t, q=lg.q, tau=lg.tau[:-1])
    with pytest.raises(InputError, match="not both"):
        MultimodalGP().fit(LOG, t=lg.t, q=lg.q, tau=lg.tau)
    with pytest.raises(InputError, match="nothing to fit"):
        MultimodalGP().fit()


def test_labels_have_the_contract_columns(replica_model):
    lab = replica_model.labels_
    K = replica_model.n_modes_
    assert list(lab.columns) == ["t", "mode", "disturbed", "p_disturbed"] + [f"p_mode_{k}" for k in range(K)]
    np.testing.assert_array_equal(lab["t"].to_numpy(), read_log(LOG).t)
    np.testing.assert_array_equal(lab["disturbed"].to_numpy(), (replica_model.p_disturbed_ > 0.5).astype(int))
    np.testing.assert_array_equal(lab["mode"].to_numpy(), replica_model.modes_)
    assert replica_model.report_["n_samples"] == len(lab)


def test_two_logs_get_a_log_column(tmp_path):
    lg = read_log(LOG)
    half = lg.n_samples // 2
    first, second = lg.subset(np.arange(half)), lg.subset(np.arange(half, lg.n_samples))
    model = MultimodalGP(**FAST).fit([first, second])
    lab = model.labels_
    assert list(lab.columns[:3]) == ["t", "log", "mode"]
    np.testing.assert_array_equal(lab["log"].to_numpy(), np.repeat([0, 1], [half, lg.n_samples - half]))


def test_save_load_round_trip_predicts_the_same(replica_model, tmp_path):
    rng = np.random.default_rng(0)
    q, dq, ddq = (rng.normal(size=(25, 1)) for _ in range(3))
    replica_model.save(tmp_path / "m")
    back = MultimodalGP.load(tmp_path / "m")
    assert back.get_params() == dict(replica_model.get_params(), progress=None)
    for mode in range(replica_model.n_modes_):
        m0, s0 = replica_model.predict(q, dq, ddq, mode=mode)
        m1, s1 = back.predict(q, dq, ddq, mode=mode)
        np.testing.assert_array_equal(m0, m1)
        np.testing.assert_array_equal(s0, s1)
    np.testing.assert_array_equal(back.predict(q, dq, ddq, return_std=False), replica_model.predict(q, dq, ddq)[0])
    # Format version 1 (written before the estimator existed) still loads.
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    settings = meta.pop("settings")
    settings["modes"] = settings.pop("n_modes")
    for key in ("robot", "block_s", "tol_changed", "patience", "mode_smoothing_s", "calibrate"):
        settings.pop(key)
    meta.update(version=1, config=settings)
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    old = MultimodalGP.load(tmp_path / "m")
    # versions before 4 read the smooth sign without its fade at rest
    as_before = copy.copy(replica_model)
    as_before.sign_fades_ = False
    np.testing.assert_array_equal(old.predict(q, dq, ddq)[0], as_before.predict(q, dq, ddq)[0])
    with pytest.raises(InputError, match="model.json missing"):
        MultimodalGP.load(tmp_path)


def test_predict_refuses_wrong_shapes_and_modes(replica_model):
    z = np.zeros((4, 1))
    with pytest.raises(InputError, match="q must be"):
        replica_model.predict(np.zeros((4, 2)), z, z)
    with pytest.raises(InputError, match="same number of rows"):
        replica_model.predict(z, z[:3], z)
    with pytest.raises(InputError, match="mode"):
        replica_model.predict(z, z, z, mode=replica_model.n_modes_)


def double_pendulum_arrays(T=300, rate=50.0, seed=0):
    """A 2-DOF log: rigid-body torque of the URDF plus a 0.4 kg point mass at the tip link and
    viscous friction, sampled at 50 Hz, with noise 0.02 N*m."""
    from mmgp.physics.robot import RobotModel

    robot = RobotModel.from_name("double_pendulum")
    t = np.arange(T) / rate
    w = np.array([[1.1, 0.7], [1.9, 1.3]])
    q = np.stack([0.8 * np.sin(w[0, j] * t) + 0.3 * np.sin(w[1, j] * t) for j in range(2)], 1)
    dq = np.stack([0.8 * w[0, j] * np.cos(w[0, j] * t) + 0.3 * w[1, j] * np.cos(w[1, j] * t) for j in range(2)], 1)
    ddq = np.stack([-0.8 * w[0, j] ** 2 * np.sin(w[0, j] * t) - 0.3 * w[1, j] ** 2 * np.sin(w[1, j] * t)
                    for j in range(2)], 1)
    heavy = robot.add_payload(robot.body_names[-1], 0.4, [0.0, 0.0, 0.1])
    tau = heavy.rnea(q, dq, ddq) + 0.05 * dq + 0.02 * np.random.default_rng(seed).normal(size=(T, 2))
    return robot, dict(t=t, q=q, dq=dq, ddq=ddq, tau=tau)


def test_robot_model_round_trip_with_payload_basis(tmp_path):
    robot, arrays = double_pendulum_arrays()
    model = MultimodalGP(robot=robot, **FAST).fit(**arrays)
    assert model.mean_basis_.name == "payload+friction" and model.basis_coef_[0] is not None
    assert model.report_["robot"]["robot"] == "double_pendulum"
    twin = clone(model)                        # the RobotModel setting is copied, not shared
    assert twin.robot is not robot and twin.robot.joint_names == robot.joint_names
    model.save(tmp_path / "m")
    back = MultimodalGP.load(tmp_path / "m")
    assert back.robot == "double_pendulum" and back.robot_.joint_names == robot.joint_names
    q, dq, ddq = arrays["q"][::7], arrays["dq"][::7], arrays["ddq"][::7]
    np.testing.assert_array_equal(back.predict(q, dq, ddq)[0], model.predict(q, dq, ddq)[0])
    # The learned model holds the payload: it predicts the logged torque far better than the URDF.
    err_model = np.abs(model.predict(q, dq, ddq)[0] - arrays["tau"][::7]).mean()
    err_urdf = np.abs(robot.rnea(q, dq, ddq) - arrays["tau"][::7]).mean()
    assert err_model < 0.2 * err_urdf


def test_to_compensator_matches_the_nominal_torque(replica_model):
    comp = replica_model.to_compensator(max_support=150, seed=0)
    Q = replica_model.support_q_
    q = np.linspace(np.percentile(Q, 10), np.percentile(Q, 90), 9)[:, None]
    ref = replica_model.nominal_torque(q)
    noise = replica_model.report_["hyperparameters"][0]["per_joint"][0]["noise_std"]
    assert np.abs(comp.torque(q) - ref).max() < 3 * noise
    h = 1e-6
    np.testing.assert_allclose((comp.storage(q + h) - comp.storage(q - h)) / (2 * h), comp.torque(q)[:, 0],
                               rtol=1e-5, atol=1e-6)


def test_import_mmgp_loads_neither_torch_nor_pinocchio():
    code = ("import sys, mmgp\n"
            "heavy = [m for m in ('torch', 'pinocchio', 'mujoco', 'mmgp.estimator') if m in sys.modules]\n"
            "assert not heavy, heavy\n"
            "print(mmgp.__version__)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stderr
    import mmgp
    from mmgp.compensator.field import load_compensator
    from mmgp.physics.robot import RobotModel, load_robot

    assert res.stdout.strip() == mmgp.__version__
    assert {"MultimodalGP", "Diagnoser", "load_compensator", "read_log", "RobotModel", "load_robot",
            "InputError", "__version__"} <= set(mmgp.__all__)
    assert (mmgp.MultimodalGP, mmgp.load_compensator, mmgp.read_log, mmgp.RobotModel, mmgp.load_robot,
            mmgp.InputError) == (MultimodalGP, load_compensator, read_log, RobotModel, load_robot, InputError)
    with pytest.raises(AttributeError, match="no attribute 'Multimodal'"):
        mmgp.Multimodal
