"""The compensator's rigid-body gravity prior and its refusal of unphysical priors.

References: Pinocchio's computeGeneralizedGravity and computePotentialEnergy (Panda, UR5, a
hand-built tree with prismatic, unaligned and continuous joints), RobotModel.add_payload, and
known payloads put into a stand-in model's torque.
"""
from __future__ import annotations

import json

import numpy as np
import pinocchio as pin
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.compensator import Compensator, RigidBodyPrior, check_passivity, load_compensator
from mmgp.compensator.fit import model_prior
from mmgp.compensator.prior import prior_from_robot
from mmgp.physics.robot import RobotModel

PANDA = [f"panda_joint{i}" for i in range(1, 8)]


def _pinocchio_reference(robot, Q):
    m, d = robot.pin_model, robot.pin_model.createData()
    g = np.array([pin.computeGeneralizedGravity(m, d, robot.configuration(q)) for q in Q])
    V = np.array([pin.computePotentialEnergy(m, d, robot.configuration(q)) for q in Q])
    return g, V


def _hand_built_tree() -> RobotModel:
    """Base -> revolute (unaligned axis) -> prismatic (unaligned) -> continuous; a second branch
    off the first joint with a PZ joint. Random placements and bodies."""
    rng = np.random.default_rng(5)
    model = pin.Model()

    def add(parent, joint, name, lower=None, upper=None):
        place = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3) * 0.3)
        kw = {} if lower is None else {"min_config": np.array([lower]), "max_config": np.array([upper]),
                                       "max_effort": np.array([100.0]), "max_velocity": np.array([10.0])}
        j = model.addJoint(parent, joint, place, name, **kw)
        model.appendBodyToJoint(j, pin.Inertia(float(rng.uniform(0.5, 3)), rng.normal(size=3) * 0.2,
                                               np.diag(rng.uniform(0.01, 0.1, 3))), pin.SE3.Identity())
        model.addBodyFrame(name + "_link", j, pin.SE3.Identity(), 0)
        return j

    axis = lambda: (lambda v: v / np.linalg.norm(v))(rng.normal(size=3))  # noqa: E731
    j1 = add(0, pin.JointModelRevoluteUnaligned(axis()), "j1", -3.0, 3.0)
    j2 = add(j1, pin.JointModelPrismaticUnaligned(axis()), "j2", -0.4, 0.6)
    add(j2, pin.JointModelRUBX(), "j3")
    add(j1, pin.JointModelPZ(), "j4", -0.2, 0.3)
    return RobotModel(model, ["j1", "j2", "j3", "j4"])


@pytest.mark.parametrize("which", ["panda", "ur5", "tree"])
def test_prior_matches_pinocchio(which):
    robot = {"panda": lambda: RobotModel.from_name("panda", PANDA), "ur5": lambda: RobotModel.from_name("ur5"),
             "tree": _hand_built_tree}[which]()
    prior = prior_from_robot(robot)
    if which == "tree":
        assert prior.types == ["revolute", "prismatic", "revolute", "prismatic"]
    rng = np.random.default_rng(0)
    Q = rng.uniform(-3.5, 3.5, (200, robot.n_joints))
    g, V = _pinocchio_reference(robot, Q)
    np.testing.assert_allclose(prior.torque(Q), g, rtol=0, atol=1e-10 * max(1.0, np.abs(g).max()))
    np.testing.assert_allclose(prior.potential(Q), V, rtol=0, atol=1e-10 * max(1.0, np.abs(V).max()))
    # the rigorous bound holds where Pinocchio evaluates it (prismatic joints: inside their limits)
    lo, hi = np.nan_to_num(prior.limits, posinf=50.0, neginf=-50.0)
    Qw = lo + (hi - lo) * rng.random((2000, robot.n_joints))
    Vw = prior.potential(Qw)
    assert prior.potential_lower_bound <= Vw.min() and Vw.max() <= prior.potential_upper_bound


def test_prior_payload_matches_add_payload():
    robot = RobotModel.from_name("panda", PANDA)
    prior = prior_from_robot(robot, payload=(0.7, np.array([0.01, -0.02, 0.21])))
    ref = robot.add_payload("panda_link7", 0.7, [0.01, -0.02, 0.21])
    Q = np.random.default_rng(1).uniform(-2.5, 2.5, (100, 7))
    g, V = _pinocchio_reference(ref, Q)
    np.testing.assert_allclose(prior.torque(Q), g, rtol=0, atol=1e-10 * np.abs(g).max())
    np.testing.assert_allclose(prior.potential(Q), V, rtol=0, atol=1e-10 * np.abs(V).max())


class PandaWithPayload:
    """Stand-in model: Panda gravity with a known payload on panda_link7 (Pinocchio), plus an
    optional constant torque offset, on poses within +-1 rad of a home pose."""

    def __init__(self, mass, com, offset=0.0, n=300, seed=0):
        self.robot = RobotModel.from_name("panda", PANDA)
        self._truth = self.robot.add_payload("panda_link7", mass, com) if mass >= 0 else None
        self.mass, self.com, self.offset = mass, np.asarray(com, float), offset
        home = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
        self.support_q_ = home + np.random.default_rng(seed).uniform(-1, 1, (n, 7))
        self.joint_names_ = PANDA

    def nominal_torque(self, q):
        q = np.atleast_2d(q)
        A = self.robot.regressor(q)[..., -10:-6]
        return self.robot.gravity(q) + A @ np.concatenate([[self.mass], self.mass * self.com]) + self.offset


def test_model_prior_identifies_the_payload():
    prior = model_prior(PandaWithPayload(0.6, [0.0, 0.01, 0.2]), PandaWithPayload(0.6, [0, 0, 0]).robot, reidentify=False)
    pl = prior.identification["payload"]
    assert pl["mass"] == pytest.approx(0.6, abs=1e-6)
    np.testing.assert_allclose(pl["com"], [0.0, 0.01, 0.2], atol=1e-6)
    assert pl["active_constraints"] == []
    # a "payload" of negative mass (the URDF heavier than the robot): the prior keeps mass >= 0
    neg = PandaWithPayload(-0.7, [0.0, 0.0, 0.1])
    prior = model_prior(neg, neg.robot, reidentify=False)
    pl = prior.identification["payload"]
    assert pl["unconstrained_first_moments"][0] < -0.5
    assert pl["mass"] == pytest.approx(0.0, abs=1e-9) and prior.consistency_problems() == []
    assert prior.masses.min() >= 0


class LighterPanda:
    """Stand-in for a model of a real robot lighter than its URDF: Panda gravity with 0.4 kg taken
    off panda_link4 (a point mass at [0.05, 0.1, 0]) on 400 poses of the whole joint range."""

    def __init__(self):
        self.robot = RobotModel.from_name("panda", PANDA)
        self.truth = self.robot.add_payload("panda_link4", -0.4, [0.05, 0.1, 0.0])
        lo, hi = self.robot.pin_model.lowerPositionLimit, self.robot.pin_model.upperPositionLimit
        self.support_q_ = lo + (hi - lo) * np.random.default_rng(2).random((400, 7))

    def nominal_torque(self, q):
        return self.truth.gravity(np.atleast_2d(q))


def test_model_prior_reidentifies_the_bodies():
    model = LighterPanda()
    full = model_prior(model, model.robot)
    payload_only = model_prior(model, model.robot, reidentify=False)
    assert full.consistency_problems() == [] and full.masses.min() >= 0
    Q = np.random.default_rng(4).uniform(model.robot.pin_model.lowerPositionLimit,
                                         model.robot.pin_model.upperPositionLimit, (300, 7))
    g = model.truth.gravity(Q)
    rms = lambda prior: float(np.sqrt(np.mean((prior.torque(Q) - g) ** 2)))  # noqa: E731
    # a lighter link 4 is no payload on link 7: only the re-identification can explain it
    assert rms(full) < 0.01 * np.sqrt(np.mean(g ** 2)) < rms(payload_only)
    # (gravity fixes only combinations of the masses and first moments, so no single mass is checked)


def _small_compensator(prior, n=7, seed=0):
    rng = np.random.default_rng(seed)
    Z = rng.uniform(-1, 1, (30, n))
    return Compensator("curl-free-wendland", Z, rng.normal(size=(30, n)), np.full(n, 0.8), 0.3, prior=prior)


def test_unphysical_priors_are_refused(tmp_path):
    robot = RobotModel.from_name("panda", PANDA)
    good = prior_from_robot(robot).to_dict()
    bad_cases = {
        "negative mass": dict(good, masses=[*good["masses"][:6], -0.7]),
        "not a rotation": dict(good, rotations=[np.diag([1.0, 1.0, 2.0]).tolist(), *good["rotations"][1:]]),
        "not a unit vector": dict(good, axes=[[0.0, 0.0, 2.0], *good["axes"][1:]]),
        "not finite": dict(good, coms=[[np.nan, 0.0, 0.0], *good["coms"][1:]]),
        "finite limits": dict(good, types=["prismatic", *good["types"][1:]], limits=[[None] * 7, [None] * 7]),
    }
    for why, d in bad_cases.items():
        with pytest.raises(ValueError, match=why):
            RigidBodyPrior.from_dict(d)
    # a file whose prior was edited to a negative mass: load_compensator and the CLI refuse it
    comp = _small_compensator(prior_from_robot(robot))
    path = comp.save(tmp_path / "c.json")
    d = json.loads(path.read_text())
    d["prior"]["masses"][6] = -0.7
    bad = tmp_path / "negative_mass.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="negative mass"):
        load_compensator(bad)
    res = CliRunner().invoke(app, ["check-passivity", str(bad)])
    assert res.exit_code == 2 and "negative mass" in res.output
    ok = CliRunner().invoke(app, ["check-passivity", str(path), "--configs", "20", "--loops", "5"])
    assert ok.exit_code == 0, ok.output
    # an object built around the constructor's check is failed by check_passivity
    comp.prior.masses[6] = -0.7
    res = check_passivity(comp, n_configs=10, n_loops=3, n_storage_samples=200)
    assert not res["passed"] and not res["prior_consistent_pass"]
    assert any("negative mass" in p for p in res["prior_problems"])


def test_compensator_is_the_prior_far_from_its_support():
    robot = RobotModel.from_name("panda", PANDA)
    comp = _small_compensator(prior_from_robot(robot, payload=(0.5, np.array([0, 0, 0.2]))))
    far = np.random.default_rng(3).uniform(2.2, 3.0, (50, 7))  # |u| >= 1.5 from every support point
    tau, rho = comp.torque(far, return_region=True)
    g, V = _pinocchio_reference(robot.add_payload("panda_link7", 0.5, [0, 0, 0.2]), far)
    np.testing.assert_array_equal(tau, comp.prior_torque(far))
    np.testing.assert_allclose(tau, g, rtol=0, atol=1e-10 * np.abs(g).max())
    np.testing.assert_array_equal(rho, 1.0)
    assert np.all(comp.region_distance(far) > 1.0)
    np.testing.assert_array_equal(comp.deviation_torque(far), 0.0)
