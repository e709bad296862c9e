"""The rigid body re-identified end to end: a MuJoCo recording of a Panda whose middle links are
heavier than its URDF says, diagnosed against that URDF; the corrected model must carry the
re-identified body (physically consistent) and predict the true robot's rigid-body torque."""
import re

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from mmgp.diagnosis import Diagnoser
from mmgp.physics.robot import RobotModel
from mmgp.sim import concealed as C
from mmgp.sim import inverse_dynamics
from mmgp.sim.mjcf import load_model, panda_urdf_path

JOINTS = [f"panda_joint{i}" for i in range(1, 8)]


def _urdfs(folder):
    """(nominal, true) URDF paths: the Panda with its fingers fixed; the true one with link 3 1.5 kg
    heavier and link 4's centre of mass 5 cm further along its x axis (not a payload: the links
    that carry payload candidates are the distal ones)."""
    text = re.sub(r'(<joint name="panda_finger_joint\d" type=")prismatic', r"\1fixed", open(panda_urdf_path()).read())
    nominal, true = folder / "nominal.urdf", folder / "true.urdf"
    nominal.write_text(text)
    m3 = re.search(r'<link name="panda_link3">.*?<mass value="([0-9.e+-]+)"', text, re.S)
    text = text[:m3.start(1)] + repr(float(m3.group(1)) + 1.5) + text[m3.end(1):]
    c4 = re.search(r'<link name="panda_link4">.*?<origin[^>]*xyz="([^"]+)"', text, re.S)
    x, y, z = (float(v) for v in c4.group(1).split())
    true.write_text(text[:c4.start(1)] + f"{x + 0.05} {y} {z}" + text[c4.end(1):])
    return nominal, true


def _pseudo_inertia(p):
    """(4, 4) pseudo-inertia of Pinocchio's parameters p (10,) (Wensing et al. 2018)."""
    inertia = np.array([[p[4], p[5], p[7]], [p[5], p[6], p[8]], [p[7], p[8], p[9]]])
    return np.block([[0.5 * np.trace(inertia) * np.eye(3) - inertia, p[1:4, None]], [p[None, 1:4], p[None, :1]]])


@pytest.fixture(scope="module")
def heavier(tmp_path_factory):
    folder = tmp_path_factory.mktemp("heavier")
    nominal, true = _urdfs(folder)
    rec, _ = C.make_case({"name": "heavier", "robot": str(true), "effects": [], "n_samples": 2000}, seed=2)
    res = Diagnoser(gp=False, plots=False, modes=False).fit(C.recording_to_log(rec), RobotModel.from_urdf(nominal, JOINTS))
    res.report(folder / "out")
    return res, nominal, true, folder / "out"


def test_the_body_is_re_identified_and_written_physically_consistent(heavier):
    res, nominal, true, out = heavier
    assert res.info_["reidentification"]["re_identified"] is True
    found = [f for f in res.findings_ if f["effect"] == "inertial_parameters"]
    assert len(found) == 1 and found[0]["params"]["bodies"]
    # every body of the corrected model is a mass distribution (pseudo-inertia PSD) and MuJoCo loads it
    corrected = pin.buildModelFromUrdf(str(out / "corrected.urdf"))
    for Y in corrected.inertias[1:]:
        assert np.linalg.eigvalsh(_pseudo_inertia(Y.toDynamicParameters())).min() > -1e-9
    mj = mujoco.MjModel.from_xml_path(str(out / "corrected.xml"))
    assert mj.nv == len(JOINTS)


def test_the_corrected_body_predicts_the_true_robot(heavier):
    """Pinocchio on corrected.urdf against MuJoCo on the true robot, on states away from the log
    (random poses, speeds and accelerations): the base parameters are the robot's, not the log's."""
    res, nominal, true, out = heavier
    rng = np.random.default_rng(7)
    lo, hi = (np.array(v)[:7] for v in (pin.buildModelFromUrdf(str(nominal)).lowerPositionLimit,
                                        pin.buildModelFromUrdf(str(nominal)).upperPositionLimit))
    q = rng.uniform(lo, hi, (200, 7))
    dq, ddq = rng.uniform(-0.5, 0.5, (200, 7)), rng.uniform(-1.0, 1.0, (200, 7))
    want = inverse_dynamics(load_model(str(true), JOINTS), q, dq, ddq)

    def rms(urdf):
        m = pin.buildModelFromUrdf(str(urdf))
        d = m.createData()
        return float(np.sqrt(np.mean((np.array([pin.rnea(m, d, *x) for x in zip(q, dq, ddq)]) - want) ** 2)))

    # the trajectory fixes the base parameters only as well as its 2000 noisy samples excite them,
    # and these states lie beyond it: a material cut, not an exact one
    assert rms(out / "corrected.urdf") < 0.5 * rms(nominal)
