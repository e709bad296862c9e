"""MuJoCo recording generator: builder vs Pinocchio, friction, labels, determinism, file round trip."""
from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin
import pytest

import mmgp.sim as sim
from mmgp.data.logs import read_labels, read_log

PANDA7 = [f"panda_joint{i}" for i in range(1, 8)]


def _mj_inverse(m, q, v, a):
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qacc[:] = q, v, a
    mujoco.mj_inverse(m, d)
    return d.qfrc_inverse.copy()


def _random_states(nv, k, seed):
    rng = np.random.default_rng(seed)
    return [(rng.uniform(-2, 2, nv), rng.uniform(-2, 2, nv), rng.uniform(-5, 5, nv)) for _ in range(k)]


@pytest.mark.parametrize("robot,joints", [("panda", PANDA7), ("ur5", None)])
def test_mujoco_inverse_dynamics_matches_pinocchio_rnea(robot, joints):
    urdf = sim.robot_urdf_path(robot)
    m = sim.load_model(urdf, joints)
    pm = sim.reduced_pinocchio_model(urdf, joints)
    pd_ = pm.createData()
    assert m.nv == pm.nv
    assert [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, i) for i in range(m.njnt)] == list(pm.names[1:])
    for q, v, a in _random_states(m.nv, 20, 0):
        ref = pin.rnea(pm, pd_, q, v, a)
        assert np.allclose(_mj_inverse(m, q, v, a), ref, rtol=1e-9, atol=1e-9 * (1 + np.abs(ref).max()))


def test_gravity_off_and_payload_match_pinocchio():
    urdf = sim.panda_urdf_path()
    pm = sim.reduced_pinocchio_model(urdf, PANDA7)
    fr = pm.frames[pm.getFrameId("panda_hand")]
    com = np.array([0.01, -0.02, 0.08])
    mass = 1.7
    m = sim.load_model(urdf, PANDA7, payload={"link": "panda_hand", "mass": mass, "com": com.tolist()},
                       gravity=False)
    pm2 = pin.Model(pm)
    pm2.gravity.linear[:] = 0.0
    # Payload in Pinocchio: a 5 cm solid sphere at com (hand frame), added to the hand's parent joint.
    pm2.inertias[fr.parentJoint] = pm2.inertias[fr.parentJoint] + pin.Inertia(
        mass, fr.placement.act(com), np.eye(3) * 0.4 * mass * 0.05 ** 2)
    pd2 = pm2.createData()
    for q, v, a in _random_states(7, 10, 1):
        assert np.allclose(_mj_inverse(m, q, v, a), pin.rnea(pm2, pd2, q, v, a), atol=1e-9)
    # set_payload changes the mass in place: back to the bare robot when 0.
    sim.set_payload(m, 0.0)
    pd_ = pm.createData()
    pm.gravity.linear[:] = 0.0
    for q, v, a in _random_states(7, 5, 2):
        assert np.allclose(_mj_inverse(m, q, v, a), pin.rnea(pm, pd_, q, v, a), atol=1e-6)


def test_joint_extras_add_their_closed_form_torques():
    urdf = sim.panda_urdf_path()
    rng = np.random.default_rng(3)
    arm, damp, k, ref = (rng.uniform(0.05, 0.5, 7), rng.uniform(0.1, 2.0, 7), rng.uniform(1, 20, 7),
                         rng.uniform(-1, 1, 7))
    m0 = sim.load_model(urdf, PANDA7)
    m1 = sim.load_model(urdf, PANDA7, armature=arm, damping=damp, stiffness=k, springref=ref)
    for q, v, a in _random_states(7, 5, 4):
        extra = _mj_inverse(m1, q, v, a) - _mj_inverse(m0, q, v, a)
        # Contract sign conventions: the robot must supply armature*a + b*v + k*(q - q0) more.
        assert np.allclose(extra, arm * a + damp * v + k * (q - ref), atol=1e-9)


def _replica_static_torque(q):
    P = sim.REPLICA
    L = P["lever_length"]
    return (P["load_mass"] * L + P["lever_mass"] * L / 2) * 9.81 * np.cos(q)


def _hold(q0, ctrl, friction_fn, seconds=1.0):
    m = mujoco.MjModel.from_xml_string(sim.replica_mjcf())
    d = mujoco.MjData(m)
    d.qpos[0] = q0
    for _ in range(int(seconds / m.opt.timestep)):
        d.ctrl[0] = ctrl
        m.dof_frictionloss[0] = friction_fn(ctrl)
        mujoco.mj_step(m, d)
    return d.qpos[0] - q0


def test_static_torque_holds_frictionless_lever():
    for q0 in (-1.0, 0.0, 0.7):
        assert abs(_hold(q0, _replica_static_torque(q0), lambda u: 0.0, 0.5)) < 1e-6


@pytest.mark.parametrize("q0,ctrl", [(0.0, 0.0), (1.0, 0.2), (0.4, 2.5), (-0.8, 0.0)])
def test_load_dependent_friction_holds_or_slips_per_closed_form(q0, ctrl):
    P = sim.REPLICA
    level = lambda u: P["friction_c"] + P["friction_beta"] * abs(u)  # noqa: E731
    imbalance = abs(ctrl - _replica_static_torque(q0))
    drift = _hold(q0, ctrl, level)
    if imbalance < 0.9 * level(ctrl):
        assert abs(drift) < 1e-9
    else:
        assert imbalance > 1.1 * level(ctrl), "test case too close to the friction boundary"
        assert abs(drift) > 1e-2


def test_replica_labels_follow_contract_rule_and_push_torque_closed_form():
    rec = sim.actuator_replica(seed=0)
    info = rec.info
    L = sim.REPLICA["lever_length"]
    # The push force is perpendicular to the lever at the load: joint torque = F * L * profile.
    expected = np.array([sum(p["force"][2] * L * sim.Push(**p).scale(t) for p in info["pushes"]) for t in rec.t])
    assert np.allclose(info["tau_push"][:, 0], expected, atol=1e-9)
    # Friction level the simulation used = 0.3 + 0.2 |motor torque| at that sample.
    assert np.allclose(info["frictionloss"][:, 0], 0.3 + 0.2 * np.abs(info["tau_true"][:, 0]))
    want = []
    for tp, fl, f in zip(info["tau_push"][:, 0], info["frictionloss"][:, 0], info["push_force"]):
        if f == 0.0:
            want.append(0)
        elif abs(tp) > 3 * 0.02 + 2 * fl:
            want.append(1)
        else:
            want.append(-1)
    assert rec.labels["disturbed"].tolist() == want
    counts = rec.labels["disturbed"].value_counts()
    assert counts.get(1, 0) > 20 and counts.get(0, 0) > 100
    assert 0.15 < np.mean(info["push_force"] > 0) < 0.5
    assert (rec.labels["mode"] == 0).all()
    # Logged signals: 2^14-count encoder grid, torque noise of the stated size.
    res = 2 * np.pi / 2 ** 14
    assert np.allclose(rec.q / res, np.round(rec.q / res), atol=1e-6)
    assert 0.012 < np.std(rec.tau - info["tau_true"]) < 0.03
    assert rec.dq is None and rec.ddq is None


def test_replica_obeys_lever_equation_with_friction_inside_its_band():
    rec = sim.actuator_replica(seed=2, n_samples=200)
    P, info = sim.REPLICA, rec.info
    L = P["lever_length"]
    J = (P["armature"] + P["lever_mass"] * L ** 2 / 3 + P["load_mass"] * L ** 2
         + 0.4 * P["load_mass"] * P["load_radius"] ** 2)
    q, dq, ddq = info["q_true"][:, 0], info["dq_true"][:, 0], info["ddq_true"][:, 0]
    friction = (info["tau_true"][:, 0] + info["tau_push"][:, 0] - _replica_static_torque(q)
                - J * ddq - P["damping"] * dq)
    assert np.allclose(friction, -info["tau_constraint"][:, 0], atol=1e-6)
    assert (np.abs(friction) <= info["frictionloss"][:, 0] * (1 + 1e-6) + 1e-9).all()
    # Sliding samples carry the full friction level, opposing the motion.
    sliding = np.abs(dq) > 0.05  # below, MuJoCo's soft friction constraint is not yet saturated
    assert sliding.sum() > 50
    assert np.allclose(friction[sliding], np.sign(dq[sliding]) * info["frictionloss"][sliding, 0], rtol=1e-3,
                       atol=1e-4)


def test_determinism_by_seed():
    a, b, c = sim.actuator_replica(seed=5, n_samples=120), sim.actuator_replica(seed=5, n_samples=120), \
        sim.actuator_replica(seed=6, n_samples=120)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.tau, b.tau)
    assert a.labels.equals(b.labels)
    assert not np.array_equal(a.tau, c.tau)


def test_panda_modes_torque_is_payload_dynamics_and_round_trips(tmp_path):
    rec = sim.panda_modes(seed=1, n_samples=1250, rate_hz=50.0)  # 25 s: at least one payload switch
    info = rec.info
    modes = rec.labels["mode"].to_numpy()
    assert set(modes) == {0, 1}
    # Independent check: actuator torque + push torque = Pinocchio RNEA of the robot carrying the
    # payload of the labelled mode, at the true state and MuJoCo's acceleration.
    urdf = sim.panda_urdf_path()
    pm = sim.reduced_pinocchio_model(urdf, PANDA7)
    fr = pm.frames[pm.getFrameId("panda_link8")]
    models = []
    for mass in info["payloads"]:
        mk = pin.Model(pm)
        mk.inertias[fr.parentJoint] = mk.inertias[fr.parentJoint] + pin.Inertia(
            mass, fr.placement.act(np.array(sim.PANDA["payload_com"])), np.eye(3) * 0.4 * mass * 0.05 ** 2)
        models.append((mk, mk.createData()))
    for i in range(0, len(rec.t), 7):
        mk, dk = models[modes[i]]
        ref = pin.rnea(mk, dk, info["q_true"][i], info["dq_true"][i], info["ddq_true"][i])
        assert np.allclose(info["tau_true"][i] + info["tau_push"][i], ref, atol=1e-6)
    # Labels: contract rule with zero friction -> 3 x torque noise.
    big = (np.abs(info["tau_push"]) > 3 * sim.PANDA["tau_noise"]).any(axis=1)
    want = np.where(info["push_force"] == 0, 0, np.where(big, 1, -1))
    assert np.array_equal(rec.labels["disturbed"].to_numpy(), want)
    assert (want == 1).sum() > 50

    rec.write(tmp_path / "log.parquet", tmp_path / "labels.parquet")
    log = read_log(tmp_path / "log.parquet")
    assert log.metadata["robot"] == "panda" and log.joint_names == PANDA7
    assert np.array_equal(log.t, rec.t) and np.array_equal(log.q, rec.q)
    assert np.array_equal(log.dq, rec.dq) and np.array_equal(log.tau, rec.tau) and log.ddq is None
    lab = read_labels(tmp_path / "labels.parquet", t=log.t)
    assert np.array_equal(lab["mode"].to_numpy(), modes)
    assert np.array_equal(lab["disturbed"].to_numpy(), rec.labels["disturbed"].to_numpy())


def test_shipped_replica_is_the_seed0_recording(tmp_path):
    rec = sim.actuator_replica(seed=0)
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "mmgp" / "resources" / "replica"
    log = read_log(shipped / "replica_log.parquet")
    assert "robot" not in log.metadata and log.joint_names == ["lever_joint"]
    assert log.dq is None
    assert np.allclose(log.q, rec.q) and np.allclose(log.tau, rec.tau) and np.allclose(log.t, rec.t)
    lab = read_labels(shipped / "replica_labels.parquet", t=log.t)
    assert np.array_equal(lab["disturbed"].to_numpy(), rec.labels["disturbed"].to_numpy())
