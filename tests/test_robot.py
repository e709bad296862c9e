"""Tests of mmgp.physics (robot models, inertial helpers, payload identification) against
Pinocchio's own per-sample algorithms and closed identities."""
import numpy as np
import pinocchio as pin
import pytest

from mmgp.errors import InputError
from mmgp.data.logs import read_log, write_log
from mmgp.physics.inertial import transport_matrix
from mmgp.physics.payload import fit_payload
from mmgp.physics.robot import RobotModel, available_robots, load_robot, robot_urdf_path

PANDA_ARM = [f"panda_joint{i}" for i in range(1, 8)]


@pytest.fixture(scope="module")
def panda():
    return RobotModel.from_name("panda", n_joints=7)


def motion(n, T, seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-1.5, 1.5, (T, n)), scale * rng.normal(size=(T, n)),
            scale * rng.normal(size=(T, n)))


def with_payload(robot, link, mass, com, inertia=np.zeros((3, 3))):
    """Pinocchio model with a payload added to the link's parent joint body (test-side, via pin)."""
    model = robot.pin_model.copy()
    frame = model.frames[model.getFrameId(link)]
    model.inertias[frame.parentJoint] = model.inertias[frame.parentJoint] + frame.placement.act(
        pin.Inertia(mass, np.asarray(com, float), np.asarray(inertia, float)))
    return model


def rnea_loop(model, q, dq, ddq):
    data = model.createData()
    return np.array([pin.rnea(model, data, q[t], dq[t], ddq[t]).copy() for t in range(len(q))])


def test_urdf_paths_and_unknown_name():
    assert robot_urdf_path("panda").name == "panda.urdf"
    assert robot_urdf_path("ur10").name == "ur10_robot.urdf"
    for name in ("ur5", "baxter", "talos", "panda"):
        assert name in available_robots() and robot_urdf_path(name).is_file()
    with pytest.raises(InputError) as exc:
        robot_urdf_path("no_such_robot")
    assert "panda" in str(exc.value) and "ur10" in str(exc.value)


def test_panda_reduced_to_arm_matches_full_model(panda):
    assert panda.joint_names == PANDA_ARM and panda.pin_model.nq == 7
    full = pin.buildModelFromUrdf(str(robot_urdf_path("panda")))
    assert full.nq == 9  # the two finger joints exist in the file
    # Locked fingers at 0 with zero finger motion: the full model's arm torques are the reference.
    q, dq, ddq = motion(7, 20, seed=1)
    pad = np.zeros((20, 2))
    ref = rnea_loop(full, np.hstack([q, pad]), np.hstack([dq, pad]), np.hstack([ddq, pad]))[:, :7]
    np.testing.assert_allclose(panda.rnea(q, dq, ddq), ref, rtol=1e-10, atol=1e-10)
    assert abs(pin.computeTotalMass(panda.pin_model) - pin.computeTotalMass(full)) < 1e-12


def test_batched_rnea_and_gravity(panda):
    q, dq, ddq = motion(7, 10_000, seed=2)
    tau = panda.rnea(q, dq, ddq)
    idx = np.random.default_rng(0).choice(10_000, 30, replace=False)
    np.testing.assert_allclose(tau[idx], rnea_loop(panda.pin_model, q[idx], dq[idx], ddq[idx]), atol=1e-12)
    np.testing.assert_allclose(panda.rnea(q[5], dq[5], ddq[5]), tau[5], atol=1e-12)
    # Gravity from a different algorithm: the gradient of the potential energy.
    data = panda.pin_model.createData()
    qs, eps = q[:5], 1e-6
    grad = np.zeros((5, 7))
    for j in range(7):
        e = np.zeros(7)
        e[j] = eps
        grad[:, j] = [(pin.computePotentialEnergy(panda.pin_model, data, x + e)
                       - pin.computePotentialEnergy(panda.pin_model, data, x - e)) / (2 * eps) for x in qs]
    np.testing.assert_allclose(panda.gravity(qs), grad, atol=1e-6)
    M = panda.mass_matrix(qs)
    np.testing.assert_allclose(M @ ddq[0] + panda.rnea(qs, dq[:5], None),
                               panda.rnea(qs, dq[:5], np.tile(ddq[0], (5, 1))), atol=1e-9)


@pytest.mark.parametrize("name,n", [("panda", 7), ("ur10", 6)])
def test_regressor_times_parameters_is_rnea(name, n):
    robot = RobotModel.from_name(name, n_joints=n)
    q, dq, ddq = motion(n, 40, seed=3)
    Y = robot.regressor(q, dq, ddq)
    assert Y.shape == (40, n, 10 * robot.n_bodies)
    pi = np.concatenate([robot.pin_model.inertias[j].toDynamicParameters()
                         for j in range(1, robot.pin_model.njoints)])
    np.testing.assert_allclose(Y @ pi, robot.rnea(q, dq, ddq), atol=1e-9)


def test_transport_matches_pinocchio_se3_action():
    rng = np.random.default_rng(4)
    for _ in range(5):
        M = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3))
        inertia = pin.Inertia.Random()
        np.testing.assert_allclose(transport_matrix(M) @ inertia.toDynamicParameters(),
                                   M.act(inertia).toDynamicParameters(), atol=1e-12)


def test_link_regressor_is_the_payload_torque(panda):
    q, dq, ddq = motion(7, 30, seed=5)
    com, inertia = np.array([0.02, -0.01, 0.06]), np.diag([0.01, 0.02, 0.015])
    loaded = with_payload(panda, "panda_hand", 1.3, com, inertia)
    extra = rnea_loop(loaded, q, dq, ddq) - panda.rnea(q, dq, ddq)
    pi_link = pin.Inertia(1.3, com, inertia).toDynamicParameters()  # in the link (hand) frame
    np.testing.assert_allclose(panda.link_regressor(q, dq, ddq, "panda_hand") @ pi_link, extra, atol=1e-10)


@pytest.mark.parametrize("link", ["panda_hand", "panda_link7"])
def test_fit_payload_recovers_point_mass(panda, link):
    q, dq, ddq = motion(7, 300, seed=6)
    com = np.array([0.03, -0.02, 0.08])
    residual = rnea_loop(with_payload(panda, link, 2.5, com), q, dq, ddq) - panda.rnea(q, dq, ddq)
    fit = fit_payload(panda, q, dq, ddq, residual, link)
    assert abs(fit.mass - 2.5) < 1e-6
    np.testing.assert_allclose(fit.com, com, atol=1e-6)
    assert fit.inertia is None and fit.residual_rms < 1e-8
    assert fit.params() == {"link": link, "mass": fit.mass, "com": list(fit.com)}


def test_fit_payload_with_inertia_and_static_data(panda):
    q, dq, ddq = motion(7, 300, seed=7)
    com, inertia = np.array([-0.01, 0.04, 0.05]), np.array([[0.02, 0.001, 0], [0.001, 0.03, 0.002], [0, 0.002, 0.01]])
    loaded = with_payload(panda, "panda_hand", 0.8, com, inertia)
    residual = rnea_loop(loaded, q, dq, ddq) - panda.rnea(q, dq, ddq)
    fit = fit_payload(panda, q, dq, ddq, residual, "panda_hand", fit_inertia=True)
    assert abs(fit.mass - 0.8) < 1e-6
    np.testing.assert_allclose(fit.com, com, atol=1e-6)
    np.testing.assert_allclose(fit.inertia, inertia, atol=1e-6)
    # Static poses only: gravity alone still determines the mass and the com.
    zero = np.zeros_like(q)
    residual = rnea_loop(with_payload(panda, "panda_hand", 0.8, com), q, zero, zero) - panda.gravity(q)
    fit = fit_payload(panda, q, None, None, residual, "panda_hand")
    assert abs(fit.mass - 0.8) < 1e-6
    np.testing.assert_allclose(fit.com, com, atol=1e-6)


def test_fit_payload_weights_select_a_mode_and_mass_stays_non_negative(panda):
    q, dq, ddq = motion(7, 400, seed=8)
    com = np.array([0.0, 0.0, 0.1])
    nominal = panda.rnea(q, dq, ddq)
    on = rnea_loop(with_payload(panda, "panda_hand", 3.0, com), q, dq, ddq) - nominal
    off = rnea_loop(with_payload(panda, "panda_hand", -0.5, com), q, dq, ddq) - nominal  # lighter than nominal
    half = np.arange(400) < 200
    residual = np.where(half[:, None], on, off)
    fit = fit_payload(panda, q, dq, ddq, residual, "panda_hand", weights=half.astype(float))
    assert abs(fit.mass - 3.0) < 1e-6 and fit.n_samples == 200
    # A lighter-than-nominal hand: no non-negative point mass explains it (a tiny one far away
    # can trade first moment against rotational inertia, hence "small", not zero).
    fit = fit_payload(panda, q, dq, ddq, residual, "panda_hand", weights=(~half).astype(float))
    assert 0.0 <= fit.mass < 0.01
    # Ten parameters: a convex problem with one bound; compare with scipy's bounded solver.
    from scipy.optimize import lsq_linear

    fit = fit_payload(panda, q, dq, ddq, off, "panda_hand", fit_inertia=True)
    assert fit.mass == 0.0
    A = panda.link_regressor(q, dq, ddq, "panda_hand").reshape(-1, 10)
    ref = lsq_linear(A, off.reshape(-1), bounds=([0] + [-np.inf] * 9, np.inf), method="bvls", tol=1e-14)
    ref_rms = np.sqrt(np.mean((A @ ref.x - off.reshape(-1)) ** 2))
    assert ref.x[0] < 1e-9 and fit.residual_rms <= ref_rms * (1 + 1e-9)


def test_fit_payload_uncertainty_matches_monte_carlo(panda):
    q, dq, ddq = motion(7, 150, seed=9, scale=0.5)
    com = np.array([0.02, 0.0, 0.1])
    clean = rnea_loop(with_payload(panda, "panda_hand", 1.5, com), q, dq, ddq) - panda.rnea(q, dq, ddq)
    rng = np.random.default_rng(10)
    masses, stds = [], []
    for _ in range(40):
        fit = fit_payload(panda, q, dq, ddq, clean + 0.2 * rng.normal(size=clean.shape), "panda_hand")
        masses.append(fit.mass)
        stds.append(fit.mass_std)
    spread, claimed = np.std(masses, ddof=1), np.mean(stds)
    print(f"mass std: Monte Carlo {spread:.4f} kg, reported {claimed:.4f} kg")
    assert 0.7 < spread / claimed < 1.4
    assert abs(np.mean(masses) - 1.5) < 3 * spread / np.sqrt(40) + 1e-3


def test_joint_order_and_count_errors(tmp_path):
    swapped = PANDA_ARM.copy()
    swapped[1], swapped[2] = swapped[2], swapped[1]
    with pytest.raises(InputError, match="panda_joint3.*panda_joint2|order"):
        RobotModel.from_name("panda", swapped)
    with pytest.raises(InputError, match="panda_joint99"):
        RobotModel.from_name("panda", PANDA_ARM[:6] + ["panda_joint99"])
    with pytest.raises(InputError, match="10 joints"):
        RobotModel.from_name("panda", n_joints=10)
    with pytest.raises(InputError, match="6 joint names|7 joints"):
        RobotModel.from_name("panda", PANDA_ARM[:6], n_joints=7)
    arm = RobotModel.from_name("panda", PANDA_ARM)
    with pytest.raises(InputError, match="different order"):
        arm.check_log(7, swapped)
    with pytest.raises(InputError, match="6 joints"):
        arm.check_log(6)
    # Baxter: the first 7 movable joints (head + one arm) are not one chain.
    with pytest.raises(InputError, match="ambiguous"):
        RobotModel.from_name("baxter", n_joints=7)
    left = ["left_s0", "left_s1", "left_e0", "left_e1", "left_w0", "left_w1", "left_w2"]
    assert RobotModel.from_name("baxter", left).joint_names == left

    # Contract rules through a log's metadata; the urdf path is relative to the log's folder.
    rng = np.random.default_rng(0)
    t, q = np.arange(20) * 0.01, rng.normal(size=(20, 7))
    log = write_log(tmp_path / "a.parquet", t, q, q, robot="panda", joint_names=PANDA_ARM)
    assert load_robot(log_path=log).joint_names == PANDA_ARM
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "robot.urdf").write_bytes(robot_urdf_path("panda").read_bytes())
    log2 = write_log(sub / "b.parquet", t, q, q, urdf="robot.urdf")
    assert load_robot(log_path=log2).urdf_path == sub / "robot.urdf"
    assert load_robot(log_path=read_log(log2)).urdf_path == sub / "robot.urdf"  # a RobotLog works too
    log3 = write_log(tmp_path / "c.parquet", t, q[:, :6], q[:, :6], robot="ur10",
                     joint_names=["shoulder_lift_joint", "shoulder_pan_joint", "elbow_joint",
                                  "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"])
    with pytest.raises(InputError, match="c.parquet.*order"):
        load_robot(log_path=log3)
    with pytest.raises(InputError, match="not in the robot model"):
        load_robot(log_path=log, robot="ur10")  # the flag wins, the log's panda joint names stay
    with pytest.raises(InputError, match="b.parquet.*7 joints"):
        load_robot(log_path=log2, robot="ur10")
    assert load_robot(log_path=write_log(tmp_path / "d.parquet", t, q, q)) is None


def test_continuous_joints_match_revolute_twin():
    cont = RobotModel.from_name("double_pendulum_continuous")
    rev = RobotModel.from_name("double_pendulum")
    assert cont.continuous_joints == cont.joint_names and cont.pin_model.nq == 4
    assert rev.continuous_joints == []
    q, dq, ddq = motion(2, 25, seed=11)
    q = q * 3.0  # beyond +-pi too: the cos/sin form must wrap
    np.testing.assert_allclose(cont.rnea(q, dq, ddq), rev.rnea(q, dq, ddq), atol=1e-10)
    np.testing.assert_allclose(cont.regressor(q, dq, ddq), rev.regressor(q, dq, ddq), atol=1e-10)


def test_ur10_joints_and_gravity():
    ur = RobotModel.from_name("ur10")
    assert ur.joint_names == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                              "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
    assert ur.continuous_joints == []
    model, data = ur.pin_model, ur.pin_model.createData()
    g = np.array([0.0, 0.0, -9.81])
    for q in np.random.default_rng(12).uniform(-np.pi, np.pi, (5, 6)):
        pin.forwardKinematics(model, data, q)
        # Closed form on a serial chain: joint k holds the moment of the weights of links k..n
        # about its axis (a_k, through p_k): tau_k = -a_k . sum_i (c_i - p_k) x m_i g.
        ref = np.zeros(6)
        for k in range(1, 7):
            axis = {"X": 0, "Y": 1, "Z": 2}[model.joints[k].shortname()[-1]]
            a = data.oMi[k].rotation[:, axis]
            p = data.oMi[k].translation
            for i in range(k, 7):
                c = data.oMi[i].act(model.inertias[i].lever)
                ref[k - 1] -= a @ np.cross(c - p, model.inertias[i].mass * g)
        np.testing.assert_allclose(ur.gravity(q), ref, atol=1e-9)
    # Upright home pose of the UR convention: the shoulder holds almost nothing.
    upright = ur.gravity(np.array([0, -np.pi / 2, 0, -np.pi / 2, 0, 0]))
    assert abs(upright[1]) < 0.05 * abs(ur.gravity(np.zeros(6))[1])
