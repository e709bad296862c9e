"""Wrong inputs give warnings and no confident finding: the log's checks (mmgp.physics.plausibility),
the same in train, diagnose and compare, and the diagnosis's answer checks (mmgp.diagnosis.plausibility).

References are independent of the code under test: joint limits and rated torques read from the
Panda URDF's XML, velocities as closed-form derivatives, a log synthesised with Pinocchio's RNEA.
"""
import json
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest

from mmgp.data.logs import RobotLog
from mmgp.diagnosis import Diagnoser
from mmgp.diagnosis.plausibility import MIN_TORQUE_SHARE, check, fit_warnings, implausible
from mmgp.physics.plausibility import degree_warnings, limit_warnings, log_checks, velocity_warnings
from mmgp.physics.robot import RobotModel, robot_urdf_path

NAMES = [f"panda_joint{i}" for i in range(1, 8)]


@pytest.fixture(scope="module")
def panda():
    return RobotModel.from_name("panda", NAMES)


@pytest.fixture(scope="module")
def urdf_limits():
    """(lower, upper, effort) per Panda joint, from the URDF text."""
    root = ET.parse(robot_urdf_path("panda")).getroot()
    lim = {j.get("name"): j.find("limit") for j in root.iter("joint")}
    return np.array([[float(lim[n].get(k)) for k in ("lower", "upper", "effort")] for n in NAMES])


def _trajectory(lims, T=2000, rate=100.0, seed=0):
    """Sinusoids inside the limits with closed-form derivatives."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / rate
    mid, half = lims[:, :2].mean(1), 0.35 * (lims[:, 1] - lims[:, 0]) / 2
    w, ph = rng.uniform(0.4, 1.2, 7), rng.uniform(0, 2 * np.pi, 7)
    q = mid + half * np.sin(w * t[:, None] + ph)
    dq = half * w * np.cos(w * t[:, None] + ph)
    ddq = -half * w ** 2 * np.sin(w * t[:, None] + ph)
    return t, q, dq, ddq


def test_positions_inside_the_limits_pass_and_degrees_fail(panda, urdf_limits):
    t, q, dq, _ = _trajectory(urdf_limits)
    assert limit_warnings(q, panda.pin_model, NAMES) == []
    assert velocity_warnings(t, q, dq, NAMES) == []
    assert degree_warnings(q, NAMES) == []
    assert all("joint limits" in w for w in limit_warnings(np.degrees(q), panda.pin_model, NAMES))
    (deg,) = degree_warnings(np.degrees(q), NAMES)
    assert "degrees" in deg
    # a joint just past its URDF limit on 5% of the samples
    q2 = q.copy()
    q2[:100, 3] = urdf_limits[3, 1] + 0.1
    (w,) = limit_warnings(q2, panda.pin_model, NAMES)
    assert w.startswith("panda_joint4") and "5%" in w


def test_velocities_that_are_not_the_derivative_are_flagged(urdf_limits):
    t, q, dq, _ = _trajectory(urdf_limits)
    assert len(velocity_warnings(t, q, np.degrees(dq), NAMES)) == 7  # deg/s against rad
    noise = np.random.default_rng(1).normal(size=dq.shape)
    assert len(velocity_warnings(t, q, noise, NAMES)) == 7
    swapped = dq[:, [1, 0, 2, 3, 4, 5, 6]]
    assert {w.split(":")[0] for w in velocity_warnings(t, q, swapped, NAMES)} == {"panda_joint1", "panda_joint2"}


def test_fit_and_magnitude_checks(panda, urdf_limits):
    fit = {"nominal": {"nmse": {n: 5.0 for n in NAMES}}, "with_physics": {"nmse": {n: 0.5 for n in NAMES}}}
    warnings, bad = fit_warnings(fit, NAMES)
    assert len(warnings) == 1 and bad == set()  # told, but the found physics predicts well
    fit["with_physics"]["nmse"].update({n: 1.5 for n in NAMES[:4]})
    warnings, bad = fit_warnings(fit, NAMES)
    assert len(warnings) == 5 and bad == set(NAMES)
    fit = {"nominal": {"nmse": {n: 0.3 for n in NAMES}}, "with_physics": {"nmse": {**{n: 0.1 for n in NAMES},
                                                                                    "panda_joint3": 1.4}}}
    assert fit_warnings(fit, NAMES)[1] == {"panda_joint3"}
    # worse than the nominal model but better than the mean: told (real Panda joint 1: 0.44 vs
    # 0.048), nothing withheld; a change within 25% (or 0.01) is not told
    fit = {"nominal": {"nmse": {n: 0.05 for n in NAMES}}, "with_physics": {"nmse": {**{n: 0.055 for n in NAMES},
                                                                                    "panda_joint1": 0.44}}}
    warnings, bad = fit_warnings(fit, NAMES)
    assert bad == set() and [w.split(":")[0] for w in warnings] == ["panda_joint1"]
    assert "worse than the nominal model (nMSE 0.44 vs 0.05)" in warnings[0]
    effort = urdf_limits[0, 2]
    over = {"effect": "torque_offset", "joint": "panda_joint1", "params": {"offset": -(effort + 1)}}
    under = {"effect": "torque_offset", "joint": "panda_joint1", "params": {"offset": -(effort - 1)}}
    assert "rated torque" in implausible(over, panda.pin_model, NAMES)
    assert implausible(under, panda.pin_model, NAMES) is None
    enc = {"effect": "encoder_offset", "joint": "panda_joint7", "params": {"offset": 0.83}}
    assert "encoder offset of 0.83 rad" in implausible(enc, panda.pin_model, NAMES)
    enc["params"]["offset"] = -0.02                 # the size of the validation's concealed offset
    assert implausible(enc, panda.pin_model, NAMES) is None
    total = sum(float(inert.get("value")) for inert in ET.parse(robot_urdf_path("panda")).getroot().iter("mass"))
    heavy = {"effect": "payload", "link": "panda_link7", "params": {"mass": 590.0}}
    assert total < 590 and "payload of 590" in implausible(heavy, panda.pin_model, NAMES)


@pytest.fixture(scope="module")
def friction_log(panda, urdf_limits):
    """A Panda log by Pinocchio's RNEA with 1.5 N*m Coulomb friction on joint 4."""
    t, q, dq, ddq = _trajectory(urdf_limits, T=1500)
    m = panda.pin_model
    d = m.createData()
    tau = np.array([pin.rnea(m, d, q[i], dq[i], ddq[i]) for i in range(len(t))])
    tau[:, 3] += 1.5 * np.tanh(dq[:, 3] / 0.01)
    tau += np.random.default_rng(2).normal(scale=0.02, size=tau.shape)
    return RobotLog("synthetic", t, q, tau, dq=dq, ddq=ddq, metadata={"joint_names": NAMES})


def _diagnose(log, robot):
    return Diagnoser(gp=False, plots=False, modes=False, separate="none").fit(log, robot).result_


def test_right_inputs_find_the_friction_without_warnings(panda, friction_log):
    res = _diagnose(friction_log, panda)
    assert res.warnings == []
    assert ("coulomb_friction", "panda_joint4") in {(f["effect"], f.get("joint")) for f in res.findings}


def test_torque_share_is_the_effects_torque_over_the_joints_spread(panda, friction_log):
    """The finding's torque share against its own closed form: 1.5 N*m * RMS(tanh(dq / v_s)) over
    the joint torque's standard deviation (the diagnosis low-passes both; within 5%)."""
    res = _diagnose(friction_log, panda)
    f = next(f for f in res.findings if f["effect"] == "coulomb_friction" and f["joint"] == "panda_joint4")
    tau_c, vs = f["params"]["tau_c"], res.info["v_s"][3]
    want = tau_c * np.sqrt(np.mean(np.tanh(friction_log.dq[:, 3] / vs) ** 2)) / friction_log.tau[:, 3].std()
    assert f["evidence"]["torque_share"] == pytest.approx(want, rel=0.05)
    assert f["evidence"]["torque_share"] > MIN_TORQUE_SHARE


def test_findings_too_small_to_name_are_withheld_without_a_warning(panda, urdf_limits):
    t, q, dq, ddq = _trajectory(urdf_limits, T=300)
    fit = {"nominal": {"nmse": {n: 0.1 for n in NAMES}}, "with_physics": {"nmse": {n: 0.01 for n in NAMES}}}
    small = {"effect": "armature", "joint": "panda_joint1", "params": {"inertia": 0.009},
             "evidence": {"torque_share": 0.6 * MIN_TORQUE_SHARE}}
    big = {"effect": "armature", "joint": "panda_joint2", "params": {"inertia": 0.09},
           "evidence": {"torque_share": 1.5 * MIN_TORQUE_SHARE}}
    log = RobotLog("synthetic", t, q, np.zeros_like(q), dq=dq)
    kept, withheld, warnings = check([small, big], fit, NAMES, panda.pin_model, log_checks(log, NAMES, panda))
    assert kept == [big] and warnings == []
    assert [w["joint"] for w in withheld] == ["panda_joint1"]
    assert "0.3% of the joint torque's spread" in withheld[0]["withheld_because"]


def test_a_dead_band_torque_channel_is_warned_about_and_findings_kept(panda, urdf_limits):
    t, q, dq, ddq = _trajectory(urdf_limits, T=300)
    fit = {"nominal": {"nmse": {n: 0.1 for n in NAMES}}, "with_physics": {"nmse": {n: 0.01 for n in NAMES}}}
    big = {"effect": "armature", "joint": "panda_joint2", "params": {"inertia": 0.09},
           "evidence": {"torque_share": 1.5 * MIN_TORQUE_SHARE}}
    tau = np.sin(np.arange(300)[:, None] * 0.05 + np.arange(7)[None, :])
    tau[:, 6] = np.where(np.abs(tau[:, 6]) < 0.8, -0.0, tau[:, 6])     # joint 7: 0 below 0.8 N*m (as -0.0)
    log = RobotLog("synthetic", t, q, tau, dq=dq)
    kept, withheld, warnings = check([big], fit, NAMES, panda.pin_model, log_checks(log, NAMES, panda))
    assert kept == [big] and withheld == []
    assert len(warnings) == 1 and warnings[0].startswith(f"{NAMES[6]}: the torque reads exactly 0 on ")


@pytest.mark.parametrize("wrong", ["degrees", "swapped", "noise", "robot"])
def test_wrong_inputs_give_warnings_and_no_finding(panda, friction_log, wrong):
    log, robot = friction_log, panda
    if wrong == "degrees":
        log = log.replace(q=np.degrees(log.q), dq=np.degrees(log.dq), ddq=np.degrees(log.ddq))
    elif wrong == "swapped":
        perm = [0, 1, 3, 2, 4, 5, 6]
        log = log.replace(q=log.q[:, perm], dq=log.dq[:, perm], ddq=log.ddq[:, perm], tau=log.tau[:, perm])
    elif wrong == "noise":
        rng = np.random.default_rng(3)
        log = log.replace(dq=rng.normal(size=log.dq.shape), ddq=rng.normal(size=log.dq.shape),
                          tau=rng.normal(scale=5.0, size=log.tau.shape))
    else:
        robot = RobotModel.from_name("xarm7", n_joints=7)
        log = log.replace(metadata={})
    res = _diagnose(log, robot)
    assert res.warnings, wrong
    assert res.findings == [] and res.to_dict()["warnings"] == res.warnings


# ---------------------------------------------------------------------------------------------
# One set of log checks for every command (issue 31 item 3): train, diagnose and compare give
# the same warnings in the same words, in their reports and on stderr.

def test_degree_detector_against_spans_written_here():
    """Joints spanning 0.1, 0.2, 0.5 and 3.0 rad logged in degrees span 5.73, 11.5, 28.6 and 172
    (two turns are 12.57 rad): the last two are flagged, the first two pass (too small to tell);
    the same joints in radians, and one spinning 12 rad (under two turns), pass."""
    s = np.linspace(0.0, 1.0, 50)[:, None]
    q = s * np.array([0.1, 0.2, 0.5, 3.0])
    names = ["a", "b", "c", "d"]
    assert degree_warnings(q, names) == []
    assert degree_warnings(np.c_[q, 12.0 * s], names + ["e"]) == []
    (w,) = degree_warnings(np.degrees(q), names)
    assert w.startswith("c, d: the positions span more than two turns (172); angles in degrees?")


def test_log_checks_against_the_urdf_and_closed_form_velocities(panda, urdf_limits):
    t, q, dq, _ = _trajectory(urdf_limits, T=400)
    tau = np.zeros_like(q)
    assert log_checks(RobotLog("x", t, q, tau, dq=dq), NAMES, panda) == ([], [])
    # logged velocities in deg/s while the positions are in rad: every joint told; estimated
    # velocities are not checked
    suspect, notes = log_checks(RobotLog("x", t, q, tau, dq=np.degrees(dq)), NAMES, panda)
    assert len(suspect) == 7 and all("time derivative" in w for w in suspect) and notes == []
    est = RobotLog("x", t, q, tau, dq=np.degrees(dq), dq_estimated=True)
    assert log_checks(est, NAMES, panda) == ([], [])
    # without a robot the limits are not checked, degrees still are
    suspect, _ = log_checks(RobotLog("x", t, np.degrees(q), tau), NAMES, None)
    assert len(suspect) == 1 and "degrees" in suspect[0]


@pytest.fixture(scope="module")
def panda_files(panda, urdf_limits, tmp_path_factory):
    """A Panda log by Pinocchio's RNEA (q and tau only: the commands estimate the derivatives),
    the same in degrees, and with joints 3 and 4 swapped; each run through train, diagnose and
    compare (settings that keep each run to seconds)."""
    from typer.testing import CliRunner

    from mmgp.cli import app
    from mmgp.data.logs import write_log

    d = tmp_path_factory.mktemp("plausible")
    t, q, dq, ddq = _trajectory(urdf_limits, T=250)
    m = panda.pin_model
    data = m.createData()
    tau = np.array([pin.rnea(m, data, q[i], dq[i], ddq[i]) for i in range(len(t))])
    tau += np.random.default_rng(4).normal(scale=0.05, size=tau.shape)
    perm = [0, 1, 3, 2, 4, 5, 6]
    cfg = d / "fast.yaml"
    cfg.write_text("train:\n  semiparametric: none\n  mean_basis: none\n"
                   "diagnose:\n  gp: false\n  plots: false\n  modes: false\n  separate: none\n")
    out = {"q": q}
    noise = np.random.default_rng(5).normal(scale=0.02, size=tau.shape)
    out["tau"] = tau
    for name, qq, tt in (("rad", q, tau), ("deg", np.degrees(q), tau), ("swapped", q[:, perm], tau[:, perm]),
                         ("noise", q, noise)):
        log = write_log(d / f"{name}.parquet", t, qq, tt, joint_names=NAMES)
        runs = {}
        for cmd, extra in (("train", ["--modes", "1", "--no-disturbance"]), ("diagnose", []),
                           ("compare", ["--max-train", "40"])):
            o = d / f"{name}-{cmd}"
            args = [cmd, str(log), "--robot", "panda", "--out", str(o), "--quiet"] + extra
            if cmd != "compare":
                args += ["--config", str(cfg)]
            res = CliRunner().invoke(app, args)
            assert res.exit_code == 0, (cmd, res.output)
            doc = {"train": "report.json", "diagnose": "findings.json", "compare": "compare.json"}[cmd]
            printed = [ln[len("warning: "):] for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
            runs[cmd] = (json.loads((o / doc).read_text())["warnings"], printed)
        out[name] = runs
    return out


def _is_fit_warning(w: str) -> bool:
    """A warning of a command's held-out fit (its own figures, after the log's checks)."""
    return w.startswith("the nominal model predicts") or "the held-out torque better than its mean" in w


def _all_same(runs):
    """The log's warnings, asserting that each command wrote and printed them alike and that they
    come first (each command's checks of its own held-out fit come after them)."""
    (train, train_printed), (diag, diag_printed), (comp, comp_printed) = (runs[c] for c in
                                                                         ("train", "diagnose", "compare"))
    assert train == train_printed and comp == comp_printed and diag == diag_printed
    logs = [[w for w in ws if not _is_fit_warning(w)] for ws in (train, comp)]
    assert logs[0] == logs[1] == train[:len(logs[0])] == comp[:len(logs[0])] == diag[:len(logs[0])]
    return logs[0]


def test_an_unmodified_log_gets_no_log_warning(panda_files):
    runs = panda_files["rad"]
    assert _all_same(runs) == []
    assert runs["train"][0] == runs["compare"][0] == []     # nor a fit warning
    assert not [w for w in runs["diagnose"][0] if "degrees" in w or "joint limits" in w]


def test_a_log_in_degrees_gets_the_same_warning_from_every_command(panda_files, urdf_limits):
    warnings = _all_same(panda_files["deg"])
    span = np.degrees(panda_files["q"]).max(0) - np.degrees(panda_files["q"]).min(0)   # every joint: 40 to 118 deg
    assert (span > 4 * np.pi).all()
    deg = [w for w in warnings if "degrees" in w]
    assert deg == [f"{', '.join(NAMES)}: the positions span more than two turns ({span.max():.3g}); angles in "
                   "degrees? (the log must hold radians)"]
    # and every joint outside its URDF limits
    assert sorted(w.split(":")[0] for w in warnings if "joint limits" in w) == NAMES


def test_swapped_joints_are_told_by_every_command(panda_files, urdf_limits):
    warnings = _all_same(panda_files["swapped"])
    # joint 3's positions in joint 4's column: the share beyond joint 4's URDF limits (+- 0.05 rad)
    q4 = panda_files["q"][:, 2]
    lo, hi = urdf_limits[3, :2]
    share = np.mean((q4 < lo - 0.05) | (q4 > hi + 0.05))
    assert share > 0.01
    assert [w for w in warnings if w.startswith("panda_joint4:")] == [
        f"panda_joint4: the logged position leaves the model's joint limits [{lo:.3g}, {hi:.3g}] rad on "
        f"{100 * share:.0f}% of the samples (range {q4.min():.3g} to {q4.max():.3g}): wrong robot model, joint "
        "order or units"]


def test_a_robotless_demo_log_in_degrees_is_told_by_train(tmp_path):
    """The shipped 1-DOF replica (no robot model) with its angle in degrees: train names the
    joint; as shipped, nothing."""
    from typer.testing import CliRunner

    from mmgp.cli import app
    from mmgp.data.logs import read_log, write_log
    from mmgp.resources import demo_files

    lg = read_log(demo_files()[0])
    q = lg.q[:, 0]
    assert lg.joint_names == ["lever_joint"] and np.degrees(np.ptp(q)) > 4 * np.pi > np.ptp(q)
    path = write_log(tmp_path / "deg.parquet", lg.t, np.degrees(lg.q), lg.tau, joint_names=lg.joint_names)
    res = CliRunner().invoke(app, ["train", str(path), "--modes", "1", "--no-disturbance", "--out",
                                   str(tmp_path / "m"), "--quiet"])
    assert res.exit_code == 0, res.output
    want = (f"lever_joint: the positions span more than two turns ({np.degrees(np.ptp(q)):.3g}); angles in "
            "degrees? (the log must hold radians)")
    assert json.loads((tmp_path / "m" / "report.json").read_text())["warnings"] == [want]
    assert f"warning: {want}" in res.stderr


def test_fit_warnings_against_the_line_of_the_mean():
    """Held-out nMSE 1 is the torque's own mean: the nominal model beyond it on most joints is
    told (as another robot's model, or as a URDF far from the robot when the learnt model predicts
    those joints), a joint no model predicts is told, a learnt model short of samples is not."""
    from mmgp.physics.plausibility import fit_warnings as log_fit_warnings

    names = ["a", "b", "c"]
    assert log_fit_warnings(names, [1.2, 0.9, 0.5], [0.1, 0.1, 0.1]) == []          # 1 of 3 is not most
    w = log_fit_warnings(names, [1.2, 3.0, 0.5], [0.1, 0.2, 0.1])
    assert w == ["the nominal model predicts the torque worse than its mean on 2 of 3 joints (held-out nMSE up to 3), "
                 "and the learnt model predicts them (nMSE up to 0.2): the URDF is far from this robot (its inertial "
                 "parameters, friction or a payload), or it is another robot's model"]
    w = log_fit_warnings(names, [1.2, 3.0, 0.5], [0.1, 1.5, 0.1])
    assert len(w) == 2 and w[0].endswith("a wrong robot model, joint order or units, or a URDF far from the robot")
    assert w[1].startswith("b: neither the nominal model (nMSE 3) nor the learnt model (nMSE 1.5) predicts")
    assert log_fit_warnings(names, [0.01, 0.02, 0.5], [1.3, 0.1, 0.1]) == []     # the nominal predicts joint a
    assert log_fit_warnings(names, None, [1.3, 0.1, None])[0].startswith("a: the learnt model (nMSE 1.3) does not")


def test_a_log_of_noise_is_told_by_every_command(panda_files):
    """White noise of 0.02 N*m for torque: the nominal model's held-out error is beyond the
    torque's mean by about the RNEA torque's (Pinocchio's) variance over the noise's, above 5 on
    every joint, and every command says so."""
    spread = panda_files["tau"].std(0)
    assert (1 + (spread / 0.02) ** 2 > 5).all()
    for cmd in ("train", "diagnose", "compare"):
        warnings, printed = panda_files["noise"][cmd]
        assert warnings == printed
        nominal = [w for w in warnings if w.startswith("the nominal model predicts")]
        assert len(nominal) == 1 and "on 7 of 7 joints" in nominal[0], (cmd, warnings)
