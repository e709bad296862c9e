"""FIGAROH's held-out metric (hand computations and the sample indices their results JSON records),
and an MJCF of a URDF whose link inertia misses the triangle inequality (MuJoCo loads it; the
moments moved as the closed form says)."""
import mujoco
import numpy as np
import pytest

from mmgp.evaluation.metrics import aggregate_rmse, figaroh_samples
from mmgp.physics.mjcf import build_mjcf, loadable_inertia


def test_aggregate_rmse_by_hand():
    """Errors 0, -2, -3, 0 (two joints x two samples): sqrt((4 + 9) / 4) = 1.8028; the two
    joints pooled, not averaged per joint (per joint: 2.1213 and 0)."""
    tau = np.array([[1.0, 2.0], [3.0, 4.0]])
    pred = np.array([[1.0, 0.0], [0.0, 4.0]])
    assert aggregate_rmse(tau, pred) == pytest.approx(np.sqrt(13.0 / 4.0), rel=1e-15)
    assert aggregate_rmse(tau, pred) == pytest.approx(1.8027756377319946, rel=1e-12)
    with pytest.raises(ValueError):
        aggregate_rmse(tau, pred[:1])


@pytest.mark.parametrize("n,head,tail", [
    # FIGAROH's selected_processed_indices (benchmarks/results/log-cholesky-*-pin37.json)
    (24710, [20, 123, 226, 329, 432, 536], [24585, 24689]),     # TX40 training
    (15710, [20, 85, 151, 216, 282, 347], [15623, 15689]),      # TX40 validation
    (2055, [20, 28, 36, 45, 53, 62], [2025, 2034]),             # TIAGo validation
])
def test_samples_are_figarohs(n, head, tail):
    s = figaroh_samples(n)
    assert len(s) == 240
    assert s[:len(head)].tolist() == head and s[-2:].tolist() == tail


def test_short_partitions():
    """Fewer than 240 samples between the 20-sample edges: every one of them; none: an error."""
    assert figaroh_samples(100).tolist() == list(range(20, 80))
    with pytest.raises(ValueError):
        figaroh_samples(40)


def _rotation(seed: int) -> np.ndarray:
    Q, R = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return Q * np.sign(np.diag(R))


def test_loadable_inertia_closed_form():
    """Principal moments 0.1, 0.12, 0.27 (short by 0.05) in a rotated frame: each moved by a third
    of the shortfall (the least-norm change), the principal axes kept; a point mass: moments at
    the floor mass x 1e-8 m^2; a valid inertia untouched."""
    R = _rotation(4)
    fixed, note = loadable_inertia(R @ np.diag([0.1, 0.12, 0.27]) @ R.T, 2.0)
    d = 0.05 / 3
    np.testing.assert_allclose(fixed, R @ np.diag([0.1 + d, 0.12 + d, 0.27 - d]) @ R.T, atol=1e-10)
    assert "0.05" in note
    point, note = loadable_inertia(np.zeros((3, 3)), 0.2)
    np.testing.assert_allclose(point, np.eye(3) * 0.2e-8, rtol=1e-12)
    assert "floored" in note
    ok = R @ np.diag([0.1, 0.12, 0.2]) @ R.T
    got, note = loadable_inertia(ok, 1.0)
    assert note is None and np.array_equal(got, 0.5 * (ok + ok.T))


URDF = """<?xml version="1.0"?>
<robot name="bad_inertia">
  <link name="base"/>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="l1"/><origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="5"/>
  </joint>
  <link name="l1">
    <inertial><origin xyz="0.1 0 0" rpy="0.3 0.2 0.1"/><mass value="1.0"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.012" iyz="0" izz="0.027"/></inertial>
  </link>
  <joint name="j2" type="revolute">
    <parent link="l1"/><child link="l2"/><origin xyz="0.2 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="5"/>
  </joint>
  <link name="l2">
    <inertial><origin xyz="0.05 0 0" rpy="0 0 0"/><mass value="0.2"/>
      <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>
  </link>
</robot>
"""


def test_mjcf_of_a_urdf_whose_inertia_mujoco_refuses(tmp_path):
    """MuJoCo refuses the URDF's links as written (balanceinertia off): l1 misses the triangle
    inequality, l2 is a point mass. The MJCF build_mjcf writes loads, MuJoCo's principal moments
    are the closed form's, the comment names both links, and MuJoCo's inverse dynamics matches
    Pinocchio's RNEA of the URDF to the size of the change."""
    import pinocchio as pin

    path = tmp_path / "bad.urdf"
    path.write_text(URDF)
    with pytest.raises(ValueError, match="A \\+ B >= C"):
        mujoco.MjModel.from_xml_path(str(path))
    xml = build_mjcf(str(path), ["j1", "j2"])
    head = xml.split("<mujoco")[0]
    assert "body l1" in head and "body l2" in head
    m = mujoco.MjModel.from_xml_string(xml)
    d = 0.005 / 3
    np.testing.assert_allclose(np.sort(m.body_inertia[1]), [0.01 + d, 0.012 + d, 0.027 - d], rtol=1e-9)
    np.testing.assert_allclose(m.body_inertia[2], [0.2e-8] * 3, rtol=1e-9)
    model = pin.buildModelFromUrdf(str(path))
    q, dq, ddq = np.array([0.3, -0.5]), np.array([0.7, 0.2]), np.array([1.1, -0.4])
    data = mujoco.MjData(m)
    data.qpos[:], data.qvel[:], data.qacc[:] = q, dq, ddq
    mujoco.mj_inverse(m, data)
    # the moved moments change the torque by at most |ddq| times the change (2 d on j1's axis)
    np.testing.assert_allclose(data.qfrc_inverse, pin.rnea(model, model.createData(), q, dq, ddq),
                               atol=2 * d * 1.2)
