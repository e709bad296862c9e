"""Coupled transmissions: columns against MuJoCo's fixed tendon, the search's sums against a direct
computation, and the diagnosis of MuJoCo recordings with a tendon (and with its look-alike)."""
import mujoco
import numpy as np
import pytest

from mmgp.data.folds import time_block_folds
from mmgp.diagnosis import Diagnoser
from mmgp.diagnosis.selection import FoldGrams
from mmgp.physics import effects as fx
from mmgp.physics.context import build_context
from mmgp.sim import concealed as C
from mmgp.physics.mjcf import coupling_tendon
from mmgp.sim.mjcf import build_mjcf, reduced_pinocchio_model, robot_urdf_path

UR5 = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]


def _mujoco_terms(urdf, tendon, q, dq):
    """MuJoCo's passive force (N*m) and mass matrix with and without the tendon at (q, dq)."""
    out = []
    for t in ([], [tendon]):
        m = mujoco.MjModel.from_xml_string(build_mjcf(urdf, UR5, tendons=[coupling_tendon(x['joint'], x) for x in t]))
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = q, dq
        mujoco.mj_forward(m, d)
        H = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, H)
        out.append((d.qfrc_passive.copy(), H))
    return out


@pytest.mark.parametrize("ratio", [0.8, -1.2])
def test_columns_are_mujocos_fixed_tendon(ratio):
    """Viscous and inertia columns at b, inertia = MuJoCo's tendon damping force (sign flipped:
    the torque the robot must supply) and its mass-matrix term times ddq; the Coulomb column is
    the tanh of the tendon's velocity times J = [1, ratio]."""
    urdf = robot_urdf_path("ur5")
    model = reduced_pinocchio_model(urdf, UR5)
    rng = np.random.default_rng(1)
    q, dq, ddq = rng.uniform(-1, 1, (3, 6)), rng.normal(0, 0.5, (3, 6)), rng.normal(0, 1, (3, 6))
    ctx = build_context(model, q, dq, ddq, v_s=np.full(6, 0.02))
    e = fx.CoupledTransmission(3, 4, ratio)
    sign, visc, inert = e.columns(ctx)
    tendon = {"joint": "wrist_1_joint", "coupled_joint": "wrist_2_joint", "ratio": ratio, "tau_c": 0.0, "b": 0.7,
              "inertia": 0.05}
    for i in range(3):
        (p0, H0), (p1, H1) = _mujoco_terms(urdf, tendon, q[i], dq[i])
        np.testing.assert_allclose(0.7 * visc[i], -(p1 - p0), atol=1e-12)
        np.testing.assert_allclose(0.05 * inert[i], (H1 - H0) @ ddq[i], atol=1e-12)
        w = dq[i, 3] + ratio * dq[i, 4]
        J = np.zeros(6)
        J[[3, 4]] = 1.0, ratio
        np.testing.assert_allclose(sign[i], np.tanh(w / np.hypot(0.02, 0.02 * ratio)) * J, atol=1e-12)
    # the same torques with the joints' roles swapped: tau_c |c|, b c^2, inertia c^2 (closed form)
    p = {"tau_c": 0.3, "b": 0.7, "inertia": 0.05, "ratio": ratio}
    flip = fx.CoupledTransmission(4, 3, 1 / ratio)
    q2 = {"tau_c": 0.3 * abs(ratio), "b": 0.7 * ratio ** 2, "inertia": 0.05 * ratio ** 2, "ratio": 1 / ratio}
    np.testing.assert_allclose(e.torque(p, ctx), flip.torque(q2, ctx), atol=1e-12)
    assert abs(e.canonical().ratio) <= 1.0


@pytest.mark.parametrize("T,scattered", [(600, True), (3000, False)])
def test_extended_sums_equal_a_direct_computation(T, scattered):
    """FoldGrams.extended (atoms S of a library plus new columns, only their products computed)
    equals FoldGrams built from those columns directly; with samples left out here and there
    (sums over samples) and in one stretch (sums over runs of samples)."""
    rng = np.random.default_rng(3)
    n = 4
    A = rng.standard_normal((T, n, 6))
    r = rng.standard_normal((T, n))
    use = rng.uniform(size=T) > 0.1 if scattered else ~((np.arange(T) > 0.3 * T) & (np.arange(T) < 0.4 * T))
    W = rng.uniform(size=(T, n))
    folds = time_block_folds(T, 6, gap=4)
    B = np.zeros((T, n, 3))
    B[:, 1], B[:, 3] = rng.standard_normal((T, 3)), rng.standard_normal((T, 3))
    g = FoldGrams(A, r, use, folds, W=W)
    for S in ([0, 2, 5], [1, 4]):
        got = g.extended(S, B)
        want = FoldGrams(np.concatenate([A[:, :, S], B], axis=2), r, use, folds, W=W)
        for name in ("Gall", "call", "Gte", "cte", "Gtr", "ctr", "yte", "nte"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("T,scattered", [(600, True), (3000, False)])
def test_bordered_fits_equal_a_direct_computation(T, scattered):
    """The search's fits and held-out errors of a subset of a library's atoms plus new columns
    (coupling.Bordered: the library's sums weighted once, the new columns' products per candidate)
    equal those of FoldGrams built from those columns directly."""
    from mmgp.diagnosis.coupling import Bordered

    rng = np.random.default_rng(4)
    n = 4
    A = rng.standard_normal((T, n, 6))
    r = rng.standard_normal((T, n))
    use = rng.uniform(size=T) > 0.1 if scattered else np.arange(T) > 0.2 * T
    W = rng.uniform(size=(T, n))
    w = rng.uniform(0.5, 2.0, n)
    folds = time_block_folds(T, 6, gap=4)
    B = np.zeros((T, n, 3))
    B[:, 1], B[:, 3] = rng.standard_normal((T, 3)), rng.standard_normal((T, 3))
    sc = Bordered(FoldGrams(A, r, use, folds, W=W), [5, 0, 2, 3], w)
    prod = sc.products(B)
    for at in ([0, 1, 2, 3], [1, 3], []):
        want = FoldGrams(np.concatenate([A[:, :, [[5, 0, 2, 3][i] for i in at]], B], axis=2), r, use, folds, W=W)
        P = list(range(want.P))
        np.testing.assert_allclose(sc.fit(prod, at), want.fit(P, w), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(sc.cv_errors(prod, at), want.cv_errors(P, w), rtol=1e-8, atol=1e-10)


def _diagnose(effects, n_samples=2000):
    spec = {"name": "ur5_wrist", "robot": "ur5", "effects": effects, "n_samples": n_samples}
    rec, truth = C.make_case(spec, seed=2)
    # the coupling is searched before the pushes and modes: those stages are left out for time
    d = Diagnoser(gp=False, plots=False, separate="none", modes=False)
    return d.fit(C.recording_to_log(rec), C.nominal_robot(spec)).findings_


@pytest.mark.parametrize("ratio,tau_c,b,inertia", [(0.8, 0.5, 0.3, 0.02), (-1.2, 0.4, 0.2, 0.01)])
def test_finds_a_mujoco_tendon_and_no_per_joint_friction(ratio, tau_c, b, inertia):
    """A fixed tendon q4 + ratio q5 of a UR5's wrist with frictionloss, damping and armature: one
    coupled_transmission with the tendon's ratio, friction and damping within 10% (a ratio over 1
    reported the other way round: 1/ratio, tau_c |ratio|, b ratio^2, inertia ratio^2), and no
    per-joint friction or armature on the wrist."""
    f = _diagnose([{"effect": "coupled_transmission", "joint": "wrist_1_joint",
                    "params": {"coupled_joint": "wrist_2_joint", "ratio": ratio, "tau_c": tau_c, "b": b,
                               "inertia": inertia}}])
    (ct,) = [x for x in f if x["effect"] == "coupled_transmission"]
    k, m, s = ("wrist_1_joint", "wrist_2_joint", 1.0) if abs(ratio) <= 1 else ("wrist_2_joint", "wrist_1_joint", ratio)
    p = ct["params"]
    assert (ct["joint"], p["coupled_joint"]) == (k, m)
    assert p["ratio"] == pytest.approx(ratio / s ** 2, rel=0.1)
    assert p["tau_c"] == pytest.approx(tau_c * abs(s), rel=0.1)
    assert p["b"] == pytest.approx(b * s ** 2, rel=0.1)
    assert p["inertia"] == pytest.approx(inertia * s ** 2, rel=0.25)
    lo, hi = ct["evidence"]["params_interval"]["ratio"]
    assert lo <= p["ratio"] <= hi
    per_joint = [x for x in f if x["effect"] in ("coulomb_friction", "viscous_friction", "load_dependent_friction",
                                                  "armature")]
    assert per_joint == []


def test_per_joint_friction_on_two_wrist_joints_is_no_coupling():
    """The look-alike: Coulomb friction of its own on each of two wrist joints is named as such,
    not as a coupling."""
    f = _diagnose([{"effect": "coulomb_friction", "joint": "wrist_1_joint", "params": {"tau_c": 0.5}},
                   {"effect": "coulomb_friction", "joint": "wrist_2_joint", "params": {"tau_c": 0.4}}])
    assert not [x for x in f if x["effect"] == "coupled_transmission"]
    got = {x["joint"]: x["params"]["tau_c"] for x in f if x["effect"] == "coulomb_friction"}
    assert got == pytest.approx({"wrist_1_joint": 0.5, "wrist_2_joint": 0.4}, rel=0.1)


def test_a_payload_is_no_shoulder_coupling():
    """A 3 kg payload on a UR5's last link (nothing coupled) is named a payload, not a coupled
    motor: its torque on the shoulder, which per-joint friction cannot fit, is what a coupling's
    columns could take (validation val09 with the payloads out of the search's context; this
    trajectory's best candidate, 0-2, cuts 37% of its pair's error at p 0.003)."""
    f = _diagnose([{"effect": "payload", "link": "wrist_3_link", "params": {"mass": 3.0, "com": [0.0, 0.1, 0.02]}}])
    assert not [x for x in f if x["effect"] == "coupled_transmission"]
    (pl,) = [x for x in f if x["effect"] == "payload"]
    assert pl["params"]["mass"] == pytest.approx(3.0, rel=0.1)




def test_a_payloads_rotational_inertia_is_no_coupling():
    """A 3 kg payload on a UR5's last link with an extended body's rotational inertia (0.03, 0.03,
    0.01 kg*m^2 about its centre of mass; the diagnosis's payload is a point mass), nothing
    coupled: no coupling. An inertia term on two joints at a fixed ratio fits much of what the
    point mass leaves (the best candidate beats the per-joint effects at the family's level), but
    a motor dissipates, and its friction columns add nothing here."""
    f = _diagnose([{"effect": "payload", "link": "wrist_3_link",
                    "params": {"mass": 3.0, "com": [0.0, 0.1, 0.02], "inertia": [0.03, 0.03, 0.01]}}], n_samples=6000)
    assert not [x for x in f if x["effect"] == "coupled_transmission"]
    (pl,) = [x for x in f if x["effect"] == "payload"]
    assert pl["params"]["mass"] == pytest.approx(3.0, rel=0.1)

def test_a_coupled_motor_beside_the_coupled_joints_own_motor():
    """A coupled wrist as the Staubli TX40's: a motor turning with wrist_1 + 0.8 wrist_2 (a MuJoCo
    fixed tendon with frictionloss, damping, armature) and wrist_2's own motor, whose friction
    outweighs the coupled motor's there as on the TX40 (Coulomb 1.24 times, viscous 2.07 times:
    the TX40's joint 5 against its motor 6). The coupling is found with its ratio and friction
    within 10%, and wrist_2's own friction beside it within 10%: a coupling tried only in place
    of both joints' friction has to carry wrist_2's own as well, and loses to per-joint friction."""
    f = _diagnose([{"effect": "coupled_transmission", "joint": "wrist_1_joint",
                    "params": {"coupled_joint": "wrist_2_joint", "ratio": 0.8, "tau_c": 0.5, "b": 0.3,
                               "inertia": 0.02}},
                   {"effect": "coulomb_friction", "joint": "wrist_2_joint", "params": {"tau_c": 0.62}},
                   {"effect": "viscous_friction", "joint": "wrist_2_joint", "params": {"b": 0.62}}])
    (ct,) = [x for x in f if x["effect"] == "coupled_transmission"]
    p = ct["params"]
    assert (ct["joint"], p["coupled_joint"]) == ("wrist_1_joint", "wrist_2_joint")
    assert p["ratio"] == pytest.approx(0.8, rel=0.1)
    assert p["tau_c"] == pytest.approx(0.5, rel=0.1)
    assert p["b"] == pytest.approx(0.3, rel=0.1)
    own = {x["effect"]: x["params"] for x in f if x.get("joint") == "wrist_2_joint"}
    assert own["coulomb_friction"]["tau_c"] == pytest.approx(0.62, rel=0.1)
    assert own["viscous_friction"]["b"] == pytest.approx(0.62, rel=0.1)
    assert not [x for x in f if x.get("joint") == "wrist_1_joint" and x["effect"] != "coupled_transmission"]
