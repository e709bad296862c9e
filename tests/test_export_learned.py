"""Export of a model learned by ``mmgp.model.train``: the user's path train -> export -> save -> load.

References: the trained model's own prediction (torch GP, a different code path from the numpy
evaluator of the file), finite differences of the exported storage, zero (storage lower bound),
the replica lever's gravity and dry-friction band, and, for a MuJoCo two-link arm, the
closed-form gravity torque of the arm.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import mmgp
from mmgp.compensator import check_passivity, compensator_from_model
from mmgp import MultimodalGP

REPLICA_LOG = Path(__file__).resolve().parents[1] / "mmgp" / "resources" / "replica" / "replica_log.parquet"


@pytest.fixture(scope="module")
def replica(tmp_path_factory):
    res = MultimodalGP(max_sweeps=15, seed=0).fit(REPLICA_LOG)
    comp = compensator_from_model(res, max_support=200, seed=0)
    path = comp.save(tmp_path_factory.mktemp("exp") / "replica.npz")
    return res, mmgp.load_compensator(path)


def test_replica_export_matches_model(replica):
    res, comp = replica
    assert comp.kind == "curl-free-wendland" and comp.prior is None  # no robot: zero mean
    lo, hi = res.support_q_.min(), res.support_q_.max()
    q = np.linspace(lo, hi, 400)[:, None]
    ref = res.nominal_torque(q)
    # The export has to be invisible next to what the model itself can resolve: its learned noise
    # std (about 0.017 N*m here, the torque sensor's 0.02). 1% of it is far below anything a
    # controller could notice, and far above the interpolant's error (a few 1e-6 N*m).
    noise = res.report_["hyperparameters"][0]["per_joint"][0]["noise_std"]
    assert 0.005 < noise < 0.05
    err = np.max(np.abs(comp.torque(q) - ref))
    assert err < 0.01 * noise, err


def test_replica_export_holds_the_lever_still(replica):
    """Physics reference: the replica lever's gravity torque is (m_load L + m_lever L / 2) g cos q
    and its dry friction is c + beta |motor torque| (mmgp.sim.REPLICA). A torque tau
    holds the lever at rest iff |tau - gravity| <= c + beta |tau|, so the learned torque at rest
    must lie in that band (without gravity it would leave it by up to 5x)."""
    from mmgp.sim import REPLICA as P

    res, comp = replica
    q = np.linspace(res.support_q_.min(), res.support_q_.max(), 400)
    gravity = (P["load_mass"] * P["lever_length"] + P["lever_mass"] * P["lever_length"] / 2) * 9.81 * np.cos(q)
    tau = comp.torque(q[:, None])[:, 0]
    assert np.all(np.abs(tau - gravity) <= P["friction_c"] + P["friction_beta"] * np.abs(tau))


def test_replica_storage_gradient_is_torque(replica):
    _, comp = replica
    q = np.linspace(-3.0, 4.0, 701)
    h = 1e-5
    fd = (comp.storage(q[:, None] + h) - comp.storage(q[:, None] - h)) / (2 * h)
    tau = comp.torque(q[:, None])[:, 0]
    # central difference: truncation h^2 |tau''| / 6 ~ 1e-10, rounding eps |S| / h ~ 1e-10 N*m
    assert np.max(np.abs(fd - tau)) <= 1e-6 * np.max(np.abs(tau))


def test_replica_storage_nonnegative(replica):
    _, comp = replica
    l = comp.lengthscales[0]
    lo, hi = comp.bounds[0, 0] - 20 * l, comp.bounds[1, 0] + 20 * l
    S = comp.storage(np.linspace(lo, hi, 20001)[:, None])
    assert np.all(np.isfinite(S))
    assert S.min() >= 0.0
    # the lower bound is not vacuous: the storage comes within the bound's slack of zero
    assert S.min() < 1e-2 * (comp.potential_upper_bound - comp.potential_lower_bound)


# -- two joints: a MuJoCo two-link arm in a vertical plane ---------------------------------------
L1, L2, M1, M2, G = 0.25, 0.2, 0.6, 0.4, 9.81


def _arm_xml() -> str:
    # point-like masses at the link ends, so the gravity torque has a short closed form
    return f"""<mujoco><compiler angle="radian"/>
  <option timestep="0.001" gravity="0 0 -{G}" integrator="Euler"><flag contact="disable"/></option>
  <worldbody><body name="l1"><joint name="j1" type="hinge" axis="0 -1 0" damping="0.02" armature="1e-3"/>
    <inertial pos="{L1} 0 0" mass="{M1}" diaginertia="1e-4 1e-4 1e-4"/>
    <body name="l2" pos="{L1} 0 0"><joint name="j2" type="hinge" axis="0 -1 0" damping="0.02" armature="1e-3"/>
      <inertial pos="{L2} 0 0" mass="{M2}" diaginertia="1e-4 1e-4 1e-4"/></body></body></worldbody>
  <actuator><motor joint="j1"/><motor joint="j2"/></actuator></mujoco>"""


def _arm_gravity(q):
    c1, c12 = np.cos(q[:, 0]), np.cos(q[:, 0] + q[:, 1])
    return np.stack([G * (M1 * L1 * c1 + M2 * (L1 * c1 + L2 * c12)), G * M2 * L2 * c12], axis=1)


def test_two_joint_learned_export_is_passive(tmp_path):
    import mujoco

    from mmgp.sim import simulate

    model = mujoco.MjModel.from_xml_string(_arm_xml())
    w, a, c = 2 * np.pi / np.array([13.0, 7.0]), np.array([0.9, 1.0]), np.array([0.3, -0.4])

    def reference(t):
        return c + a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t)

    rec = simulate(model, reference, 15.0, rate_hz=20.0, kp=40.0, kd=1.5, tau_noise=0.01,
                   q_resolution=2 * np.pi / 2 ** 14, log_dq=False, joint_names=["j1", "j2"], seed=1, settle=1.0)
    log = tmp_path / "arm.parquet"
    rec.write(log)
    res = MultimodalGP(max_sweeps=10, seed=0).fit(log)
    assert not res.disturbed_.any()  # a push-free log: the learner abstains
    comp = compensator_from_model(res, max_support=150, seed=0)
    comp = mmgp.load_compensator(comp.save(tmp_path / "arm.json"))
    assert comp.kind == "curl-free-wendland" and comp.n_joints == 2

    chk = check_passivity(comp)
    assert chk["passed"], chk
    assert chk["grad_max_rel_err"] < 1e-6 and chk["loop_max_rel_work"] < 1e-9

    # Independent reference: the arm's gravity torque. Inside the box the data cover, the learned
    # feedforward must carry it (peak 3.2 N*m; the residual is the PD loop's quasi-static error,
    # tracking forces and the model's curl that the gradient projection removes; this model has no
    # robot, so between the passes of the Lissajous trajectory the compactly supported potential
    # reverts towards its zero prior: 1.9 % and 8.1 % here with the deterministic EM's evenly spaced
    # support, 3.2 % and 6.9 % with the earlier random support, 1.0 % and 2.7 % with the Gaussian kernel).
    rng = np.random.default_rng(0)
    lo, hi = comp.bounds
    Q = lo + 0.15 * (hi - lo) + 0.7 * (hi - lo) * rng.random((300, 2))
    g = _arm_gravity(Q)
    rel = np.sqrt(np.mean((comp.torque(Q) - g) ** 2, axis=0)) / np.sqrt(np.mean(g ** 2, axis=0))
    assert np.all(rel < 0.1), rel
