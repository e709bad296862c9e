"""The corrected model `mmgp diagnose` writes (CONTRACT 1.2): corrected.urdf and corrected.xml.

End to end: a 2-DOF arm recorded in MuJoCo with concealed Coulomb friction and armature on the
shoulder, viscous friction and a spring on the elbow and a payload on the forearm; the command
line diagnoses the log, and the files it writes are held against Pinocchio (the rigid body: the
nominal one plus the payload found) and against the log (MuJoCo's inverse dynamics of
corrected.xml explains most of what the nominal model leaves). Hand-made findings check what the
log cannot: the closed form of a coupled transmission's tendon (CONTRACT section 3), re-identified
bodies, a switching payload, the effects MJCF cannot express, a robot with joints the log lacks.
"""
from __future__ import annotations

import json
import os

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.data.differentiation import SavitzkyGolay, complete_derivatives
from mmgp.data.logs import read_log, write_log
from mmgp.diagnosis.corrected import write_corrected
from mmgp.diagnosis.result import DiagnosisResult
from mmgp.physics.robot import RobotModel
from mmgp.sim import PANDA_JOINTS, build_mjcf, explained_share, friction_velocity, inverse_dynamics, panda_urdf_path
from mmgp.sim import concealed as C

# two links swinging in the vertical x-z plane; a tool behind a fixed joint (merged into the forearm)
ARM2_URDF = """<?xml version="1.0"?>
<robot name="arm2">
  <link name="base"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="upper"/><origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-1.2" upper="1.2" effort="100" velocity="5"/>
  </joint>
  <link name="upper">
    <inertial><origin xyz="0.2 0 0" rpy="0 0 0"/><mass value="2.0"/>
      <inertia ixx="0.002" ixy="0" ixz="0" iyy="0.03" iyz="0" izz="0.03"/></inertial>
  </link>
  <joint name="elbow" type="revolute">
    <parent link="upper"/><child link="fore"/><origin xyz="0.4 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-1.5" upper="1.5" effort="100" velocity="5"/>
  </joint>
  <link name="fore">
    <inertial><origin xyz="0.15 0 0" rpy="0 0.3 0"/><mass value="1.0"/>
      <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.008" iyz="0" izz="0.008"/></inertial>
  </link>
  <joint name="tool_mount" type="fixed">
    <parent link="fore"/><child link="tool"/><origin xyz="0.3 0 0" rpy="0 0 0"/>
  </joint>
  <link name="tool">
    <inertial><origin xyz="0.02 0 0" rpy="0 0 0"/><mass value="0.2"/>
      <inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/></inertial>
  </link>
</robot>
"""
JOINTS = ["shoulder", "elbow"]
# the recording has no pushes and no modes: the learner and the mode test are left out (speed)
CONFIG = "diagnose:\n  separate: none\n  modes: false\n  gp: false\n  plots: false\n"

runner = CliRunner()


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    d = tmp_path_factory.mktemp("corrected")
    urdf = d / "arm2.urdf"
    urdf.write_text(ARM2_URDF)
    # 20 s: long enough for the slow sines to sweep the range (in 7 s a payload looks like offsets)
    spec = {"name": "arm2", "robot": str(urdf), "n_samples": 2000, "rate_hz": 100.0, "effects": [
        C._e("coulomb_friction", "shoulder", tau_c=0.5), C._e("armature", "shoulder", inertia=0.08),
        C._e("viscous_friction", "elbow", b=0.3), C._e("joint_spring", "elbow", k=1.0, q0=0.3),
        C._e("payload", "fore", mass=0.3, com=[0.3, 0.0, 0.0])]}
    rec, _ = C.make_case(spec, seed=0)
    log = write_log(d / "arm2.parquet", rec.t, rec.q, rec.tau, dq=rec.dq, ddq=rec.ddq, urdf="arm2.urdf",
                    joint_names=JOINTS)
    (d / "diagnose.yaml").write_text(CONFIG)
    out = d / "out"
    res = runner.invoke(app, ["diagnose", str(log), "--out", str(out), "--config", str(d / "diagnose.yaml")])
    assert res.exit_code == 0, res.output
    return {"urdf": urdf, "log": log, "out": out, "doc": json.loads((out / "findings.json").read_text())}


def test_corrected_urdf_is_the_nominal_body_plus_the_payload_found(diagnosed):
    out, doc = diagnosed["out"], diagnosed["doc"]
    assert doc["corrected_model"]["written"] is True
    payloads = [f for f in doc["findings"] if f["effect"] == "payload"]
    assert [f["link"] for f in payloads] == ["fore"]
    model = pin.buildModelFromUrdf(str(out / "corrected.urdf"))
    assert list(model.names[1:]) == JOINTS
    nominal = pin.buildModelFromUrdf(str(diagnosed["urdf"]))
    p = payloads[0]["params"]
    # 'fore' is the elbow's body frame: the payload adds in the joint frame as it is
    added = {2: pin.Inertia(p["mass"], np.array(p["com"]), np.zeros((3, 3)))}
    for j in (1, 2):
        want = nominal.inertias[j] + added.get(j, pin.Inertia.Zero())
        got = model.inertias[j]
        assert got.mass == pytest.approx(want.mass, rel=1e-12)
        np.testing.assert_allclose(got.lever, want.lever, atol=1e-12)
        np.testing.assert_allclose(got.inertia, want.inertia, atol=1e-12)
    # MuJoCo compiles corrected.xml with the same bodies and the joint effects found
    mj = mujoco.MjModel.from_xml_path(str(out / "corrected.xml"))
    assert [mj.joint(i).name for i in range(mj.njnt)] == JOINTS
    np.testing.assert_allclose(mj.body_subtreemass[mj.body("upper").id],
                               model.inertias[1].mass + model.inertias[2].mass)
    found = {(f["effect"], f["joint"]): f["params"] for f in doc["findings"] if f.get("joint") in JOINTS}
    assert set(found) == {("coulomb_friction", "shoulder"), ("armature", "shoulder"), ("viscous_friction", "elbow"),
                          ("joint_spring", "elbow")}
    s, e = mj.joint("shoulder").dofadr[0], mj.joint("elbow").dofadr[0]
    assert mj.dof_frictionloss[s] == pytest.approx(found["coulomb_friction", "shoulder"]["tau_c"], rel=1e-12)
    assert mj.dof_armature[s] == pytest.approx(found["armature", "shoulder"]["inertia"], rel=1e-12)
    assert mj.dof_damping[e] == pytest.approx(found["viscous_friction", "elbow"]["b"], rel=1e-12)
    assert mj.jnt_stiffness[mj.joint("elbow").id] == pytest.approx(found["joint_spring", "elbow"]["k"], rel=1e-12)
    q0 = found["joint_spring", "elbow"]["q0"]
    assert mj.qpos_spring[mj.joint("elbow").qposadr[0]] == pytest.approx(q0, rel=1e-12)
    assert mj.dof_frictionloss[e] == mj.dof_damping[s] == 0


def test_corrected_xml_explains_the_nominal_residual(diagnosed):
    """tau - tau_nominal (Pinocchio RNEA of the URDF) against tau - MuJoCo inverse dynamics of
    corrected.xml (dry friction as frictionloss*sign(dq)), on the log with the derivatives
    estimated as the diagnosis estimates them."""
    out = diagnosed["out"]
    log = complete_derivatives(read_log(diagnosed["log"], joint_names=JOINTS), SavitzkyGolay(cv=True))
    tau_nom = RobotModel.from_urdf(diagnosed["urdf"], JOINTS).rnea(log.q, log.dq, log.ddq)
    tau_mj = inverse_dynamics(mujoco.MjModel.from_xml_path(str(out / "corrected.xml")), log.q, log.dq, log.ddq)
    share = explained_share(log.tau, tau_nom, tau_mj)
    assert (share >= 0.8).all(), share
    # the yardstick: MuJoCo's inverse dynamics of the nominal model is Pinocchio's RNEA
    nominal_mj = mujoco.MjModel.from_xml_string(build_mjcf(str(diagnosed["urdf"]), JOINTS))
    np.testing.assert_allclose(inverse_dynamics(nominal_mj, log.q[:200], log.dq[:200], log.ddq[:200]),
                               tau_nom[:200], atol=1e-9)


def test_report_tells_how_to_load_it(diagnosed):
    out = diagnosed["out"]
    report = (out / "report.md").read_text()
    assert "## Corrected model" in report
    # the three lines the report gives load both files from the output folder
    lines = diagnosed["doc"]["corrected_model"]["load"]
    assert len(lines) == 3 and all(ln in report for ln in lines)
    scope: dict = {}
    cwd = os.getcwd()
    try:
        os.chdir(out)
        exec("\n".join(lines), scope)
    finally:
        os.chdir(cwd)
    assert scope["mj_model"].nv == 2 and list(scope["pin_model"].names[1:]) == JOINTS
    assert "Corrected model" in (out / "report.html").read_text()


def _hand_findings():
    mode = {"effect": "mode_switch", "joint": None,
            "params": {"n_modes": 2, "per_mode": [{"fraction": 0.3}, {"fraction": 0.7}]}}
    return [
        {"effect": "coupled_transmission", "joint": "elbow",
         "params": {"coupled_joint": "shoulder", "ratio": 0.5, "tau_c": 0.2, "b": 0.1, "inertia": 0.03}},
        {"effect": "load_dependent_friction", "joint": "shoulder", "params": {"tau_c": 0.3, "beta": 0.1}},
        {"effect": "torque_offset", "joint": "elbow", "params": {"offset": 0.2}},
        {"effect": "encoder_offset", "joint": 0, "params": {"offset": 0.01}},
        {"effect": "external_disturbance", "joint": None, "params": {"n_samples": 10}},
        {"effect": "payload", "link": "fore", "mode": 0, "params": {"link": "fore", "mass": 1.0, "com": [0.2, 0, 0]}},
        {"effect": "payload", "link": "fore", "mode": 1,
         "params": {"link": "fore", "mass": 0.4, "com": [0.1, 0, 0.05]}},
        {"effect": "inertial_parameters", "link": None, "params": {"link": None, "base": {}, "delta": {
            "upper": {"mass": 0.2, "com": [0.01, 0.0, 0.0]},
            "fore": {"inertia": [0.001, 0.002, 0.0005, 0.0, 0.0002, 0.0]}}}},
        mode,
    ]


def test_tendon_bodies_and_mode_from_hand_made_findings(tmp_path):
    urdf = tmp_path / "arm2.urdf"
    urdf.write_text(ARM2_URDF)
    out = tmp_path / "out"
    out.mkdir()
    summary = write_corrected(_hand_findings(), urdf, JOINTS, out)
    assert summary["written"] and summary["mode"] == 1
    nominal = pin.buildModelFromUrdf(str(urdf))
    model = pin.buildModelFromUrdf(str(out / "corrected.urdf"))
    Y1, Y2 = nominal.inertias[1], nominal.inertias[2]
    dI = np.array([[0.001, 0.0, 0.0002], [0.0, 0.002, 0.0], [0.0002, 0.0, 0.0005]])
    want = {1: pin.Inertia(Y1.mass + 0.2, Y1.lever + np.array([0.01, 0, 0]), Y1.inertia),
            2: pin.Inertia(Y2.mass, Y2.lever, Y2.inertia + dI)
            + pin.Inertia(0.4, np.array([0.1, 0, 0.05]), np.zeros((3, 3)))}
    for j, w in want.items():
        np.testing.assert_allclose(model.inertias[j].toDynamicParameters(), w.toDynamicParameters(), atol=1e-12)
    # MuJoCo: rigid body (Pinocchio on corrected.urdf) + shoulder friction 0.3 sign(dq_s) + the tendon's
    # closed form: s = dq_e + 0.5 dq_s; (0.2 sign(s) + 0.1 s + 0.03 (ddq_e + 0.5 ddq_s)) on elbow, x0.5 on shoulder
    rng = np.random.default_rng(0)
    q, dq, ddq = rng.uniform(-1, 1, (3, 50, 2))
    mj = mujoco.MjModel.from_xml_path(str(out / "corrected.xml"))
    data = model.createData()
    s, a = dq[:, 1] + 0.5 * dq[:, 0], ddq[:, 1] + 0.5 * ddq[:, 0]
    f = 0.2 * np.sign(s) + 0.1 * s + 0.03 * a
    want_tau = np.array([pin.rnea(model, data, q[t], dq[t], ddq[t]) for t in range(50)])
    want_tau += np.stack([0.3 * np.sign(dq[:, 0]) + 0.5 * f, f], axis=1)
    np.testing.assert_allclose(inverse_dynamics(mj, q, dq, ddq), want_tau, atol=1e-9)
    head = (out / "corrected.xml").read_text().split("<mujoco", 1)[0]
    for word in ("beta", "torque_offset", "encoder_offset", "external_disturbance", "mode_switch", "mode 1",
                 "coupled_transmission"):
        assert word in head, word
    assert sum("mode_switch" in w for w in summary["not_expressed"]) == 1


def test_friction_law_is_the_fitted_tanh_with_its_velocity_scale(tmp_path):
    """corrected.xml carries the velocity scale v_s the diagnosis fitted its friction with, and
    MuJoCo's inverse dynamics of it follows tau_c tanh(dq / v_s) (a tendon: tanh(w / v_w), v_w from
    its joints' v_s), held against Pinocchio's RNEA plus that closed form; at a standstill whose
    velocity reads 1e-15 rad/s the friction adds nothing, where sign(dq) would add its whole level."""
    urdf = tmp_path / "arm2.urdf"
    urdf.write_text(ARM2_URDF)
    findings = [{"effect": "coulomb_friction", "joint": "shoulder", "params": {"tau_c": 0.3}},
                {"effect": "coupled_transmission", "joint": "elbow",
                 "params": {"coupled_joint": "shoulder", "ratio": 0.5, "tau_c": 0.2, "b": 0.0, "inertia": 0.0}}]
    v_s = {"shoulder": 0.05, "elbow": 0.02}
    assert write_corrected(findings, urdf, JOINTS, tmp_path, v_s)["written"]
    mj = mujoco.MjModel.from_xml_path(str(tmp_path / "corrected.xml"))
    np.testing.assert_allclose(friction_velocity(mj), [0.05, 0.02], rtol=1e-15)
    rng = np.random.default_rng(1)
    q, ddq = rng.uniform(-1, 1, (2, 40, 2))
    dq = rng.uniform(-0.1, 0.1, (40, 2))  # within a few v_s, where tanh and sign differ
    dq[:10] = rng.choice([-1e-15, 1e-15], (10, 2))  # a filtered standstill
    model = pin.buildModelFromUrdf(str(tmp_path / "corrected.urdf"))
    data = model.createData()
    rigid = np.array([pin.rnea(model, data, q[t], dq[t], ddq[t]) for t in range(40)])
    w = dq[:, 1] + 0.5 * dq[:, 0]
    f = 0.2 * np.tanh(w / np.hypot(0.02, 0.5 * 0.05))
    want = rigid + np.stack([0.3 * np.tanh(dq[:, 0] / 0.05) + 0.5 * f, f], axis=1)
    tau = inverse_dynamics(mj, q, dq, ddq)
    np.testing.assert_allclose(tau, want, atol=1e-9)
    np.testing.assert_allclose(tau[:10], rigid[:10], atol=1e-9)
    # v_s = 0 is the former law, sign(dq): the standstill then carries the whole level
    at_rest = inverse_dynamics(mj, q[:10], dq[:10], ddq[:10], v_s=0.0) - rigid[:10]
    np.testing.assert_allclose(np.abs(at_rest[:, 0] - 0.5 * 0.2 * np.sign(w[:10])), 0.3, atol=1e-9)


def test_joints_the_log_lacks_are_fixed_where_the_diagnosis_held_them(tmp_path):
    """Panda: the fingers are not logged; the corrected URDF loads with the 7 arm joints and the
    bodies of mmgp's reduced model (fingers merged at their neutral position)."""
    write_corrected([], panda_urdf_path(), PANDA_JOINTS, tmp_path)
    model = pin.buildModelFromUrdf(str(tmp_path / "corrected.urdf"))
    reduced = RobotModel.from_name("panda", PANDA_JOINTS).pin_model
    assert list(model.names[1:]) == list(PANDA_JOINTS)
    for j in range(1, model.njoints):
        np.testing.assert_allclose(model.inertias[j].toDynamicParameters(), reduced.inertias[j].toDynamicParameters(),
                                   atol=1e-12)
        assert model.jointPlacements[j].isApprox(reduced.jointPlacements[j])


def test_without_a_urdf_nothing_is_written_and_the_report_says_so(tmp_path):
    res = DiagnosisResult(findings=[], fit={}, location={}, joint_names=JOINTS)
    res.write(tmp_path)
    assert not (tmp_path / "corrected.urdf").exists() and not (tmp_path / "corrected.xml").exists()
    doc = json.loads((tmp_path / "findings.json").read_text())
    assert doc["corrected_model"]["written"] is False
    assert "no URDF" in (tmp_path / "report.md").read_text()


def test_combined_velocity_scale_is_the_root_sum_of_squares():
    # closed form: a motor at w = dq_k + c dq_m with independent noises v_k, v_m has noise hypot(v_k, c v_m)
    import math

    from mmgp.physics.context import combined_velocity_scale

    assert math.isclose(combined_velocity_scale([1.0, -0.7], [0.03, 0.05]), math.hypot(0.03, 0.035), rel_tol=1e-12)
    J = np.array([[1.0, 0.5, 0.0], [0.0, 2.0, -1.0]])
    np.testing.assert_allclose(combined_velocity_scale(J, [0.1, 0.2, 0.3]),
                               [math.hypot(0.1, 0.1), math.hypot(0.4, 0.3)], rtol=1e-12)


def test_whole_identified_bodies_are_written_or_named_when_not_physical(tmp_path):
    """``bodies`` (the consistent fit's bodies whole): a physical one lands in corrected.urdf as
    Pinocchio builds it from mass, com and inertia; one whose inertia about its com is not
    positive (a held pose's fit) is named and the nominal body kept, without an exception."""
    urdf = tmp_path / "arm2.urdf"
    urdf.write_text(ARM2_URDF)
    bad = {"mass": 1.5, "com": [0.1, 0.0, 0.0], "inertia": [0.001, -0.004, 0.001, 0.0, 0.0, 0.0]}
    good = {"mass": 2.2, "com": [0.05, 0.01, -0.02], "inertia": [0.01, 0.02, 0.015, 0.001, -0.002, 0.0005]}
    finding = {"effect": "inertial_parameters", "link": None,
               "params": {"link": None, "base": {}, "delta": {}, "bodies": {"upper": good, "fore": bad}}}
    out = tmp_path / "out"
    out.mkdir()
    summary = write_corrected([finding], urdf, JOINTS, out)
    nominal = pin.buildModelFromUrdf(str(urdf))
    model = pin.buildModelFromUrdf(str(out / "corrected.urdf"))
    v = good["inertia"]
    I = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    want = pin.Inertia(good["mass"], np.array(good["com"]), I).toDynamicParameters()
    np.testing.assert_allclose(model.inertias[1].toDynamicParameters(), want, atol=1e-12)
    np.testing.assert_allclose(model.inertias[2].toDynamicParameters(), nominal.inertias[2].toDynamicParameters(),
                               atol=1e-12)
    assert any("fore" in w and "not physical" in w for w in summary["not_expressed"])
    mujoco.MjModel.from_xml_path(str(out / "corrected.xml"))
