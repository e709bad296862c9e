"""Payload identification benchmarks (mmgp.physics.payload.fit_payload on tau - RNEA(nominal)).

Parts (``--part``, default all):

* ``sim``: MuJoCo Panda carrying a known payload (welded to ``panda_link8``, a solid 5 cm
  sphere of the given mass), computed-torque tracking of a periodic exciting trajectory on the
  payload-free model, logged with a 19-bit encoder, dq noise 0.005 rad/s, tau noise 0.05 N*m;
  ddq estimated by mmgp (Savitzky-Golay). Must-show: mass within 5 %, com within 1 cm. Peer
  figure: the same fit from MuJoCo's true, noise-free signals (what the data could give at best).
* ``modes``: mmgp.sim.panda_modes (payload switching 0 / 2 kg, with pushes): per-mode fit
  weighted by the true mode labels (pushed samples left out by the true labels), and by the
  modes and disturbance flags of mmgp's multimodal EM (``mmgp.MultimodalGP``, n_modes=2,
  semiparametric residual).
* ``ur10``: the real UR10 pick-and-place log (polydoros_ur10_pickplace, authors: a 5 kg object):
  what the logged torques can and cannot say about a payload at ``tool0``.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_payload.py [--part sim|modes|ur10|all] [--no-em]``
(one torch thread: much faster on a shared CPU; the EM of ``modes`` took 470-580 s on 2 busy cores).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import mmgp.sim as sim
from mmgp.data.logs import RobotLog, read_log
from mmgp.physics.inertial import point_mass_parameters
from mmgp.physics.payload import fit_payload
from mmgp.physics.robot import load_robot
from mmgp.data.differentiation import SavitzkyGolay, complete_derivatives

PANDA7 = [f"panda_joint{i}" for i in range(1, 8)]
np.set_printoptions(precision=3, suppress=True, linewidth=160)


def exciting_reference(rng, lower, upper, period=12.0, n_harm=5, max_speed=1.0, fill=0.35):
    """Periodic Fourier-series exciting trajectory (base period ``period`` s) inside the limits."""
    return sim.fourier_reference(rng, lower, upper, period, n_harm=n_harm, fill=fill, max_amp=1.2,
                                 max_speed=max_speed, decay=0.5)


def record_payload(mass, com, *, seed=0, duration=36.0, rate_hz=100.0, link="panda_link8"):
    urdf = sim.panda_urdf_path()
    real = sim.load_model(urdf, PANDA7, payload={"link": link, "mass": mass, "com": list(com)})
    nominal = sim.load_model(urdf, PANDA7)
    pm = sim.reduced_pinocchio_model(urdf, PANDA7)
    ref = exciting_reference(np.random.default_rng(seed), np.asarray(pm.lowerPositionLimit),
                             np.asarray(pm.upperPositionLimit))
    P = sim.PANDA
    return sim.simulate(real, ref, duration, rate_hz=rate_hz, kp=P["kp"], kd=P["kd"], controller_model=nominal,
                        q_resolution=P["q_resolution"], tau_noise=P["tau_noise"], dq_noise=P["dq_noise"],
                        seed=seed + 1, robot="panda", joint_names=PANDA7)


ID_WINDOW_S = 0.2  # s, Savitzky-Golay window for identification (see part_sim)


def _fit_log(robot, rec, window_s, link="panda_link8"):
    log = complete_derivatives(RobotLog(path="sim", t=rec.t, q=rec.q, tau=rec.tau, dq=rec.dq),
                               SavitzkyGolay(window_s=window_s))
    res = log.tau - robot.rnea(log.q, log.dq, log.ddq)
    return fit_payload(robot, log.q, log.dq, log.ddq, res, link)


def part_sim() -> bool:
    """Known payloads. The residual tau - RNEA(q, dq, ddq_est) holds -M(q) (ddq_est - ddq): noise
    that is correlated with the regressor (which is built from the same ddq_est), so noisy
    accelerations bias the fit (errors in variables). mmgp's default derivative window
    (max(5 samples, 0.05 s)) leaves ~0.3 rad/s^2 of noise at 100 Hz with 0.005 rad/s dq noise; a
    0.2 s window (still far shorter than the trajectory's fastest period, 2.4 s) removes the bias.
    Both are printed; the must-show is judged on the 0.2 s window."""
    print("== Simulated Panda, known payload on panda_link8 (MuJoCo, computed torque, noisy log) ==")
    robot = load_robot("panda", joint_names=PANDA7)
    cases = [(0.5, (0.0, 0.0, 0.05)), (2.0, (0.0, 0.03, 0.10)), (3.0, (0.05, -0.02, 0.15)),
             (1.2, (-0.04, 0.06, 0.08))]
    ok_all = ok_default = True
    print(f"columns: fit with a {ID_WINDOW_S} s derivative window | fit with mmgp's default window | "
          "oracle (MuJoCo's true noise-free signals)")
    print(f"{'truth m':>7} {'truth com [m]':>20} | {'fit m':>6} {'err %':>5} {'fit com':>22} {'err cm':>6} | "
          f"{'m':>6} {'err %':>5} {'err cm':>6} | {'m':>6} {'err %':>5} {'err cm':>6} | pass")
    for i, (m, c) in enumerate(cases):
        rec = record_payload(m, c, seed=10 + i)
        c = np.asarray(c)
        fits = [_fit_log(robot, rec, ID_WINDOW_S), _fit_log(robot, rec, None)]
        qi, vi, ai = rec.info["q_true"], rec.info["dq_true"], rec.info["ddq_true"]
        fits.append(fit_payload(robot, qi, vi, ai, rec.info["tau_true"] - robot.rnea(qi, vi, ai), "panda_link8"))
        em = [100 * abs(f.mass - m) / m for f in fits]
        ec = [100 * np.linalg.norm(f.com - c) for f in fits]
        ok = em[0] < 5.0 and ec[0] < 1.0
        ok_all &= ok
        ok_default &= em[1] < 5.0 and ec[1] < 1.0
        print(f"{m:7.2f} {str(np.round(c, 3)):>20} | {fits[0].mass:6.3f} {em[0]:5.2f} {str(np.round(fits[0].com, 4)):>22} "
              f"{ec[0]:6.3f} | {fits[1].mass:6.3f} {em[1]:5.2f} {ec[1]:6.3f} | {fits[2].mass:6.3f} {em[2]:5.2f} "
              f"{ec[2]:6.3f} | {'yes' if ok else 'NO'}  (mass std {fits[0].mass_std:.4f} kg)")
    print(f"must-show (mass within 5 %, com within 1 cm, every case, {ID_WINDOW_S} s window): "
          f"{'PASS' if ok_all else 'FAIL'}; with the default window: {'pass' if ok_default else 'fail'}")
    # The same payload fitted on panda_hand (a fixed frame 0.107 m further along z, turned -45 deg
    # about z): checks that a frame other than the parent body works.
    m, c = 2.0, (0.0, 0.03, 0.10)
    rec = record_payload(m, c, seed=11)
    fr8 = robot.pin_model.frames[robot.pin_model.getFrameId("panda_link8")].placement
    frh = robot.pin_model.frames[robot.pin_model.getFrameId("panda_hand")].placement
    c_hand = frh.actInv(fr8.act(np.asarray(c)))
    fh = _fit_log(robot, rec, ID_WINDOW_S, link="panda_hand")
    print(f"same 2 kg payload fitted on panda_hand: mass {fh.mass:.3f} kg, com {np.round(fh.com, 4)} "
          f"(truth in hand frame {np.round(c_hand, 4)}, error {100 * np.linalg.norm(fh.com - c_hand):.3f} cm)")
    return ok_all


def part_modes(run_em: bool = True) -> None:
    print("\n== Per-mode payload: mmgp.sim.panda_modes (payload 0 / 2 kg at panda_link8, com [0, 0, 0.12]) ==")
    from sklearn.metrics import adjusted_rand_score

    robot = load_robot("panda", joint_names=PANDA7)
    t0 = time.perf_counter()
    rec = sim.panda_modes(seed=0, n_samples=5000, rate_hz=100.0, payloads=(0.0, 2.0), pushes=True)
    print(f"recorded {len(rec.t)} samples in {time.perf_counter() - t0:.1f} s; "
          f"{int((rec.labels['disturbed'] != 0).sum())} samples pushed (label != 0)")
    # Identification derivatives: the 0.2 s window of part_sim (the default window's noisy ddq
    # biases the com by centimetres; printed once for comparison).
    raw = RobotLog(path="modes", t=rec.t, q=rec.q, tau=rec.tau, dq=rec.dq)
    log = complete_derivatives(raw, SavitzkyGolay(window_s=ID_WINDOW_S))
    res = log.tau - robot.rnea(log.q, log.dq, log.ddq)
    mode = rec.labels["mode"].to_numpy()
    clean = rec.labels["disturbed"].to_numpy() == 0
    truth = {0: 0.0, 1: 2.0}
    print(f"{'weights':<48}{'mode':>5}{'mass kg':>9}{'truth':>7}{'com [m]':>24}{'samples':>9}")
    for k in (0, 1):
        for name, w in (("true mode labels, pushes left out", (mode == k) & clean),
                        ("true mode labels, pushes kept", mode == k)):
            f = fit_payload(robot, log.q, log.dq, log.ddq, res, "panda_link8", weights=w.astype(float))
            print(f"{name:<48}{k:>5}{f.mass:>9.3f}{truth[k]:>7.1f}{str(np.round(f.com, 3)):>24}{f.n_samples:>9}")
    ld = complete_derivatives(raw)
    f = fit_payload(robot, ld.q, ld.dq, ld.ddq, ld.tau - robot.rnea(ld.q, ld.dq, ld.ddq), "panda_link8",
                    weights=((mode == 1) & clean).astype(float))
    print(f"{'(same, pushes left out, default deriv. window)':<48}{1:>5}{f.mass:>9.3f}{2.0:>7.1f}"
          f"{str(np.round(f.com, 3)):>24}{f.n_samples:>9}")
    print("(com of a ~0 kg mode is meaningless: mass * com is what the data determine)")
    if not run_em:
        return
    from mmgp import MultimodalGP

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "modes.parquet"
        rec.write(path)
        t0 = time.perf_counter()
        tr = MultimodalGP(n_modes=2, semiparametric="residual", rate_hz=20.0, seed=0, robot=robot).fit(path)
        dt_em = time.perf_counter() - t0
    lg = tr.logs_[0]
    sem = tr.sem_
    # The EM ran on the 20 Hz rows; pick the matching truth rows.
    rows = np.searchsorted(rec.t, lg.t)
    ari = adjusted_rand_score(mode[rows][clean[rows]], sem.labels_[clean[rows]])
    print(f"EM (MultimodalGP, n_modes=2, residual, 20 Hz: {len(lg.t)} samples): {dt_em:.0f} s, "
          f"mode ARI vs truth {ari:.3f}, {int(sem.disturbed_.sum())} flagged disturbed")
    # Payload fits on the EM's rows, with the identification derivatives of the full-rate log.
    q, dq, ddq, r = log.q[rows], log.dq[rows], log.ddq[rows], res[rows]
    for k in range(sem.p_mode_.shape[1]):
        # Posterior averages can stray a rounding error outside [0, 1].
        w = np.clip(sem.p_mode_[:, k], 0, 1) * np.clip(1.0 - sem.p_disturbed_, 0, 1)
        f = fit_payload(robot, q, dq, ddq, r, "panda_link8", weights=w)
        share = np.bincount(mode[rows][sem.labels_ == k], minlength=2) / max(1, (sem.labels_ == k).sum())
        print(f"EM mode {k} (weights p_mode * (1 - p_disturbed)): mass {f.mass:.3f} kg, com {np.round(f.com, 3)}; "
              f"its samples: {100 * share[0]:.0f} % true mode 0, {100 * share[1]:.0f} % true mode 1")
    for k in (0, 1):
        w = ((mode[rows] == k) & clean[rows]).astype(float)
        f = fit_payload(robot, q, dq, ddq, r, "panda_link8", weights=w)
        print(f"peer: same 20 Hz rows, true labels, pushes left out, mode {k}: mass {f.mass:.3f} kg, "
              f"com {np.round(f.com, 3)}")


def _runs(mask: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return [(a, b) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)) if b - a >= min_len]


def part_ur10() -> None:
    print("\n== UR10 pick-and-place (polydoros_ur10_pickplace), payload at tool0; authors: 5 kg ==")
    from mmgp.convert import convert
    from mmgp.errors import InputError

    try:
        with tempfile.TemporaryDirectory() as tmp:
            (path,) = convert(REPO.parent / "shared" / "datasets" / "polydoros_ur10_pickplace",
                              Path(tmp) / "ur10.parquet")
            log = read_log(path)
            robot = load_robot(log_path=path)
    except InputError as exc:
        print(f"skipped: {exc}")
        return
    tau = log.tau
    tau_rbd = robot.rnea(log.q, log.dq, log.ddq)
    names = robot.joint_names
    one_kg = robot.link_regressor(log.q, log.dq, log.ddq, "tool0") @ point_mass_parameters(1.0, np.zeros(3))

    print("1) Whole log, per joint: tau = k * tau_rbd(nominal) + c (least squares)")
    print(f"{'joint':<22}{'k':>9}{'c N*m':>9}{'corr':>8}{'R2':>8}{'std tau':>9}{'std rbd':>9}")
    r2s, corrs = [], []
    for j in range(6):
        A = np.c_[tau_rbd[:, j], np.ones(len(tau))]
        (k, c), *_ = np.linalg.lstsq(A, tau[:, j], rcond=None)
        r2 = 1 - np.var(tau[:, j] - A @ [k, c]) / np.var(tau[:, j])
        r2s.append(r2)
        corrs.append(np.corrcoef(tau[:, j], tau_rbd[:, j])[0, 1])
        print(f"{names[j]:<22}{k:>9.3f}{c:>9.2f}{np.corrcoef(tau[:, j], tau_rbd[:, j])[0, 1]:>8.3f}{r2:>8.3f}"
              f"{tau[:, j].std():>9.2f}{tau_rbd[:, j].std():>9.2f}")

    print("\n2) Static holds (all joints still, >= 2 s). A payload at tool0 adds m * (1 kg torque); the arm's own")
    print("   gravity is the nominal g. Holds at the same pose in the two cycles: the torque difference / 1 kg torque")
    print("   is the mass carried in one hold minus the other, per joint (should agree across joints).")
    # wrist_3's dq reads a constant ~0.03 rad/s while q does not change: judge stillness on q.
    still = np.zeros(len(tau), bool)
    dqq = np.abs(np.diff(log.q, axis=0)).max(1)
    still[1:] = dqq < 1e-4
    holds = _runs(still, int(2.0 / 0.008))
    info = []
    for a, b in holds:
        a, b = a + 25, b - 25  # keep off the stops' transients
        qm = log.q[a:b].mean(0)
        info.append((a, b, qm, tau[a:b].mean(0), robot.gravity(qm), one_kg[a:b].mean(0)))
        print(f"  {a * 0.008:6.1f}-{b * 0.008:5.1f} s  tau[0:4] {tau[a:b].mean(0)[:4]}  nominal g[0:4] "
              f"{robot.gravity(qm)[:4]}  1 kg@tool0[1:4] {one_kg[a:b].mean(0)[1:4]}")
    pairs, implied = [], []
    for i in range(len(info)):
        for k in range(i + 1, len(info)):
            if np.abs(info[i][2] - info[k][2]).max() < 0.02 and np.abs(info[i][5][1:4]).max() > 1.0:
                pairs.append((i, k))
    for i, k in pairs:
        d = info[k][3] - info[i][3]
        mj = d[1:4] / info[i][5][1:4]
        implied.append(mj)
        print(f"  pose at {info[i][0] * 0.008:.0f} s vs {info[k][0] * 0.008:.0f} s: torque difference[0:4] {d[:4]}; "
              f"implied mass difference per joint (shoulder_lift, elbow, wrist_1): {mj} kg")
    if pairs:
        print("  (shoulder_pan has no gravity torque, yet its holding torque also differs between the holds.)")

    print("\n3) Per moving segment (the stretches between the holds above), payload at tool0 fitted:")
    print("   a) on tau - tau_rbd as logged (tau taken as N*m joint torque);")
    print("   b) on (tau - c)/k - tau_rbd with the whole-log k, c of part 1 (joints with k > 0.05 only);")
    print("   c) on tau itself, i.e. IF tau were the joint torque minus the controller's payload-free model")
    print("      (a residual): fit_payload on tau, and per joint tau_j = m_j * (1 kg torque)_j + c_j.")
    in_hold = np.zeros(len(tau), bool)
    for a, b in holds:
        in_hold[a:b] = True
    segs = _runs(~in_hold, int(1.5 / 0.008))
    kc = np.array([np.linalg.lstsq(np.c_[tau_rbd[:, j], np.ones(len(tau))], tau[:, j], rcond=None)[0]
                   for j in range(6)])
    use = kc[:, 0] > 0.05
    print(f"{'segment s':>14}{'a) m kg':>9}{'a) com':>22}{'b) m kg':>9}{'c) m kg':>9}{'c) com':>22}"
          f"{'c) m_j lift':>12}{'c) m_j elbow':>13}")
    masses = []
    for a, b in segs:
        sl = slice(a, b)
        fa = fit_payload(robot, log.q[sl], log.dq[sl], log.ddq[sl], tau[sl] - tau_rbd[sl], "tool0")
        scaled = (tau[sl] - kc[:, 1]) / np.where(use, kc[:, 0], 1.0) - tau_rbd[sl]
        w = np.broadcast_to(use.astype(float), scaled.shape)
        fb = fit_payload(robot, log.q[sl], log.dq[sl], log.ddq[sl], scaled, "tool0", weights=w)
        fc = fit_payload(robot, log.q[sl], log.dq[sl], log.ddq[sl], tau[sl], "tool0")
        mj = [np.linalg.lstsq(np.c_[one_kg[sl, j], np.ones(b - a)], tau[sl, j], rcond=None)[0][0] for j in (1, 2)]
        masses.append((fa.mass, fb.mass, fc.mass, *mj))
        print(f"{a * 0.008:6.1f}-{b * 0.008:6.1f}{fa.mass:>9.2f}{str(np.round(fa.com, 2)):>22}{fb.mass:>9.2f}"
              f"{fc.mass:>9.2f}{str(np.round(fc.com, 2)):>22}{mj[0]:>12.2f}{mj[1]:>13.2f}")
    masses = np.array(masses).reshape(-1, 5)
    if len(masses):
        print("spread over segments (kg): " + ", ".join(
            f"{lab} {masses[:, i].min():.1f}..{masses[:, i].max():.1f}"
            for i, lab in enumerate(["a)", "b)", "c) fit_payload", "c) lift", "c) elbow"])))
    print("\nConclusion (UR10):")
    print(f"- The logged torques are not N*m joint torques of the nominal UR10: |corr| with RNEA <= "
          f"{np.max(np.abs(corrs)):.2f} and R2 of a per-joint scale + offset <= {np.max(r2s):.2f} on every joint; "
          f"the scales (shoulder {kc[1, 0]:.2f}, elbow {kc[2, 0]:.2f}) are far from 1 and the wrist ones are "
          "meaningless (the nominal wrist torques are ~0).")
    if implied:
        big = np.array(implied)
        spans = "; ".join(f"pose {i + 1}: {b.min():.1f}..{b.max():.1f} kg" for i, b in enumerate(big))
        print(f"- Repeated holds at the same pose imply mass changes of {spans}, depending on the joint (if tau were "
              "a residual): the joints do not agree, "
              "and the gravity-free shoulder_pan joint shifts as much, so static friction/offsets dominate.")
    if len(masses):
        print(f"- Moving segments give {masses[:, 0].min():.1f}..{masses[:, 0].max():.1f} kg (as logged), "
              f"{masses[:, 1].min():.1f}..{masses[:, 1].max():.1f} kg (rescaled), "
              f"{masses[:, 2].min():.1f}..{masses[:, 2].max():.1f} kg (tau as residual): no reading gives a mass that "
              "is consistent across segments and joints, and none singles out segments carrying ~5 kg.")
    print("- So the file cannot confirm or refute the stated 5 kg; a payload cannot be identified from it without "
          "knowing what the torque column is (current? filtered? which offsets and signs?).")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--part", choices=["sim", "modes", "ur10", "all"], default="all")
    p.add_argument("--no-em", action="store_true", help="modes: skip the EM run (true labels only)")
    a = p.parse_args(argv)
    ok = True
    if a.part in ("sim", "all"):
        ok = part_sim()
    if a.part in ("modes", "all"):
        part_modes(run_em=not a.no_em)
    if a.part in ("ur10", "all"):
        part_ur10()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
