"""Closed-loop demonstration: impedance control with the exported feedforward, rubber-mallet test.

Plants (MuJoCo, the independent "real" robots of ``mmgp.sim``):
  * the 1-DOF actuator replica lever (``replica_mjcf``: 0.73 kg load on a 0.2 m lever, dry friction
    growing with the motor torque, set every step as in ``actuator_replica``),
  * the 7-DOF Panda (``build_mjcf``) with a 1.5 kg payload at the flange and joint damping
    0.3 N*m*s/rad, around a home pose.

Feedforward variants, each with the same impedance ``tau = ff(q) + K (q_d - q)`` (no controller
damping: a "pure stiffness", and ``K = 0``: "zero impedance"):
  * ``none``: no feedforward,
  * ``rigid-body``: the nominal rigid-body model alone (Panda: Pinocchio gravity without the
    payload; lever: the nominal CAD lever with a 0.5 kg load instead of 0.73 kg),
  * ``learned``: the exported passive feedforward of a model LEARNED by mmgp, exactly as a user
    gets it: a MuJoCo recording of the same plant (lever: ``actuator_replica(seed)``, 330 samples
    at 20 Hz, quasi-static with pushes; Panda: ``mmgp.sim.simulate`` with the payload, exciting
    sum-of-sinusoids motion within +-0.6 rad of the home pose, back at rest there every 5 s, under
    computed torque on the payload-free model, pushes, sensor noise, 100 Hz), written as a contract log,
    ``mmgp.MultimodalGP`` (lever: no robot; Panda: ``load_robot(robot="panda")``, so the GP
    learns the residual on top of the rigid-body model), ``compensator_from_model(result)``
    (whose target is the library's own ``MultimodalGP.nominal_torque``: GP averaged over both
    friction signs, payload mean and rigid-body part included), ``.save``, ``mmgp.load_compensator``
    (numpy) in the 1 kHz loop; "learned model (before export)" is ``nominal_torque`` itself
    (static torque figures only),
  * ``stand-in``: the same export applied to the plant's exact static torque (MuJoCo
    ``qfrc_bias`` at rest, including the payload) on random configurations: what the export does
    to a perfect model.

Rubber-mallet test: 20 ms sin^2 force pulses at fixed times, in pairs: a hit, then an opposite hit
shortly after that catches the rebound and takes energy out (lever: 40 N then 30 N at the load,
t = 1, 1.12, 4, 4.12 s; Panda: 60 N along a random direction and back at panda_link7's centre of
mass, t = 1, 1.08, 4, 4.08 s). Port power ``P = tau_ext . dq`` with
``tau_ext = J^T F``; energy into the robot ``E_in(t) = int P dt`` (work of F over each step's
displacement). With the feedforward ``tau_ff = grad V``, the closed loop has storage
``H = KE + P_grav(q) - V(q) + K |q - q_d|^2 / 2`` and ``dH/dt <= P``, so
``E_in(t) >= H(t) - H(0) >= -(H(0) - inf H)``. The bound printed and drawn is
``beta_0 = KE_0 + (P_grav(q0) - P_grav_min) + (V_upper - V(q0)) + K |q0 - q_d|^2 / 2`` with
``V_upper`` the compensator's rigorous upper bound and ``P_grav_min`` exact for the lever and the
sampled minimum over the joint limits for the Panda (MuJoCo's own potential-energy figure).

Figures: static torque error against the plant's exact static torque, RMS and static tracking
error (before the first hit) per variant, the time the pose holds (|q - q_d| <= 0.05 rad), min E_in
vs -beta_0, max (H - H0) - E_in (re-checked at a 4x finer step where it exceeds 1 mJ). Plots (PNG),
the recordings, the exported compensators and results.json go to ``--out``.

    python benchmarks/closed_loop_energy.py --out /tmp/cle [--plants lever,panda] [--support 400]
        [--panda-samples 2000] [--max-sweeps 15]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import mujoco
import numpy as np

import mmgp
from mmgp.compensator import compensator_from_model, load_compensator
from mmgp import MultimodalGP
from mmgp.config import load_settings
from mmgp.physics.robot import RobotModel, load_robot
from mmgp.sim import PANDA, PANDA_JOINTS, REPLICA, Push, actuator_replica, load_model, panda_urdf_path, replica_mjcf
from mmgp.sim import simulate as record

HOME = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
G = 9.81
ENVELOPE_S = 5.0  # s, Panda training reference: back at rest at the home pose this often


def _enable_energy(model):
    model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    return model


class StaticTorqueModel:
    """Stand-in for a trained model: the plant's own static torque (MuJoCo gravity at rest).

    ``nominal_torque(q (T, n)) -> (T, n)`` N*m; ``support_q_`` uniform in ``[lo, hi]``."""

    def __init__(self, mj_model, lo, hi, n, names, seed=0):
        self.m = mj_model
        self.d = mujoco.MjData(mj_model)
        rng = np.random.default_rng(seed)
        self.support_q_ = lo + (hi - lo) * rng.random((n, len(lo)))
        self.joint_names_ = list(names)

    def nominal_torque(self, q):
        q = np.atleast_2d(q)
        out = np.empty_like(q)
        for i, qi in enumerate(q):
            self.d.qpos[:] = qi
            self.d.qvel[:] = 0.0
            mujoco.mj_forward(self.m, self.d)
            out[i] = self.d.qfrc_bias
        return out


def panda_recording(urdf, payload, lo, hi, n_samples, seed):
    """Training log of the Panda plant (payload, damping 0.3) around the home pose: (T, 7) at 100 Hz.

    Reference per joint: 3 sinusoids of 0.05-0.4 Hz centred in ``[lo, hi]`` filling 90% of the half
    range, times an envelope ``sin^2(pi t / ENVELOPE_S)`` so that the arm comes back to rest at the
    centre (the pose the impedance will hold) every ``ENVELOPE_S`` s, peak speed <= 0.8 rad/s; computed torque on the payload-free model (the nominal model
    a user would have), gains, noise and encoder of :data:`mmgp.sim.PANDA`. Pushes as in
    ``panda_modes``: 10-40 N in a random world direction at a random link among panda_link3..7,
    0.3-2 s long, every 1.5-5 s.
    """
    rng = np.random.default_rng(seed)
    model = load_model(urdf, PANDA_JOINTS, damping=0.3, payload=payload)
    nominal = load_model(urdf, PANDA_JOINTS)
    centre, half = 0.5 * (lo + hi), 0.45 * (hi - lo)
    w = 2 * np.pi * rng.uniform(0.05, 0.4, (7, 3))
    a = rng.uniform(0.3, 1.0, (7, 3))
    a *= (half / a.sum(1))[:, None]
    ph = rng.uniform(0, 2 * np.pi, (7, 3))
    we = np.pi / ENVELOPE_S
    # |d/dt (e x)| <= |x'| + |e'| |x| with e = sin^2 <= 1, |e'| <= we
    a *= np.minimum(1.0, PANDA["max_speed"] / ((a * w).sum(1) + we * a.sum(1)))[:, None]

    def reference(t):
        x = w * t + ph
        s, c = np.sin(x), np.cos(x)
        e, de, dde = np.sin(we * t) ** 2, we * np.sin(2 * we * t), 2 * we * we * np.cos(2 * we * t)
        p, dp, ddp = (a * s).sum(1), (a * w * c).sum(1), -(a * w * w * s).sum(1)
        return centre + e * p, de * p + e * dp, dde * p + 2 * de * dp + e * ddp

    duration = n_samples / 100.0
    pushes, t = [], rng.uniform(1.0, 3.0)
    while True:
        d = rng.uniform(0.3, 2.0)
        if t + d > duration:
            break
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        pushes.append(Push(t0=float(t), duration=float(d), body=f"panda_link{int(rng.integers(3, 8))}",
                           force=tuple(float(x) for x in u * rng.uniform(10.0, 40.0)),
                           ramp=float(rng.uniform(0.1, 0.25))))
        t += d + rng.uniform(1.5, 5.0)
    return record(model, reference, duration, rate_hz=100.0, kp=PANDA["kp"], kd=PANDA["kd"],
                  controller_model=nominal, gains="acceleration", pushes=pushes,
                  q_resolution=PANDA["q_resolution"], tau_noise=PANDA["tau_noise"], dq_noise=PANDA["dq_noise"],
                  log_dq=True, seed=int(rng.integers(2 ** 31)), robot="panda", joint_names=PANDA_JOINTS)


def learned_compensator(name, rec, args, out_dir, max_support):
    """Write ``rec`` as a contract log, train with mmgp, export, save and load back. Returns
    (compensator as loaded from the file, the fitted MultimodalGP, timings dict)."""
    log = out_dir / f"{name}_log.parquet"
    rec.write(log)
    cfg = load_settings(Path(__file__).resolve().parents[1] / "configs" / "default.yaml", "train", MultimodalGP,
                        max_sweeps=args.max_sweeps, seed=args.seed)
    robot = None if name == "lever" else load_robot(robot="panda", log_path=log)
    t0 = time.perf_counter()
    result = MultimodalGP(robot=robot, **cfg).fit(log)
    t1 = time.perf_counter()
    (out_dir / f"{name}_model").mkdir(exist_ok=True)
    result.save(out_dir / f"{name}_model")
    comp = compensator_from_model(result, max_support=max_support, seed=args.seed)
    f = comp.save(out_dir / f"{name}_learned_compensator.npz")
    t2 = time.perf_counter()
    return mmgp.load_compensator(f), result, {"train_s": t1 - t0, "export_s": t2 - t1}


def simulate(model, ff, K, q_d, q0, hits, duration, *, friction=None):
    """1 kHz loop. ``ff(q) -> (n,)``; ``hits``: list of (Push, body id); returns arrays.

    Work of the external force per step: ``(J^T F) . (q_{k+1} - q_k)`` (F constant over the step).
    """
    d = mujoco.MjData(model)
    n = model.nv
    dt = model.opt.timestep
    steps = int(round(duration / dt))
    d.qpos[:] = q0
    d.qvel[:] = 0.0
    mujoco.mj_forward(model, d)
    out = {k: np.zeros(steps) for k in ("t", "P", "E_in", "KE", "PE")}
    out["q"] = np.zeros((steps, n))
    jacp = np.zeros((3, n))
    E = 0.0
    for k in range(steps):
        t = k * dt
        q = d.qpos.copy()
        d.ctrl[:] = ff(q) + K * (q_d - q)
        if friction is not None:
            friction(model, d)
        d.xfrc_applied[:] = 0.0
        tau_ext = np.zeros(n)
        for push, bid in hits:
            s = push.scale(t)
            if s == 0.0:
                continue
            F = s * np.asarray(push.force, dtype=float)
            if push.frame == "body":
                F = d.xmat[bid].reshape(3, 3) @ F
            d.xfrc_applied[bid, :3] += F
            mujoco.mj_jac(model, d, jacp, None, d.xipos[bid], bid)
            tau_ext += jacp.T @ F
        out["KE"][k], out["PE"][k] = d.energy[1], d.energy[0]
        mujoco.mj_step(model, d)
        E += float(tau_ext @ (d.qpos - q))
        out["t"][k], out["q"][k], out["P"][k], out["E_in"][k] = t, q, float(tau_ext @ d.qvel), E
    return out


def _hits(model, body, forces, times, frame):
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    return [(Push(t0=float(t), duration=0.02, body=body, force=tuple(float(x) for x in f), frame=frame), bid)
            for t, f in zip(times, forces)]


def lever_plant(args, rng) -> dict:
    """The replica lever: plant, impedance, mallet hits, nominal model, training recording."""
    P = REPLICA
    model = _enable_energy(mujoco.MjModel.from_xml_string(replica_mjcf()))
    nofric = mujoco.MjModel.from_xml_string(replica_mjcf())
    nofric.dof_frictionloss[:] = 0.0
    L = P["lever_length"]
    m_eff_true = P["load_mass"] * L + P["lever_mass"] * L / 2
    m_eff_nom = 0.5 * L + P["lever_mass"] * L / 2
    rec = actuator_replica(args.seed)
    return {
        "model": model, "nofric": nofric, "lo": np.array([-1.0]), "hi": np.array([1.6]), "names": ["lever_joint"],
        "q_d": np.array([0.3]), "K": np.array([20.0]),
        "rigid": lambda q: np.array([m_eff_nom * G * np.cos(q[0])]),
        "friction": lambda m, d: m.dof_frictionloss.__setitem__(0, P["friction_c"] + P["friction_beta"] * abs(d.ctrl[0])),
        "hits": _hits(model, "load", [(0, 0, 40.0), (0, 0, -30.0), (0, 0, -40.0), (0, 0, 30.0)],
                      [1.0, 1.12, 4.0, 4.12], "body"),
        "p_min": -m_eff_true * G,  # exact: lowest point of the lever's centre of mass (q = -pi/2)
        "p_min_how": "exact", "n_support": min(args.support, 200), "rec": rec,
        "rec_how": f"actuator_replica(seed={args.seed}): {len(rec.t)} samples at 20 Hz",
    }


def panda_plant(args, rng) -> dict:
    """The Panda with a 1.5 kg payload and joint damping: as :func:`lever_plant`."""
    urdf = panda_urdf_path()
    payload = {"link": "panda_link8", "mass": 1.5, "com": [0.0, 0.0, 0.12]}
    model = _enable_energy(load_model(urdf, PANDA_JOINTS, damping=0.3, payload=payload))
    robot = RobotModel.from_name("panda", PANDA_JOINTS)
    lim_lo, lim_hi = robot.pin_model.lowerPositionLimit.copy(), robot.pin_model.upperPositionLimit.copy()
    lo, hi = np.maximum(HOME - 0.6, lim_lo), np.minimum(HOME + 0.6, lim_hi)
    dirs = rng.standard_normal((4, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = _hits(model, "panda_link7", 60.0 * np.array([dirs[0], -dirs[0], dirs[1], -dirs[1]]),
                 [1.0, 1.08, 4.0, 4.08], "world")
    # sampled minimum of MuJoCo's gravity potential over the joint limits (not rigorous)
    d = mujoco.MjData(model)
    pe = []
    for qq in lim_lo + (lim_hi - lim_lo) * rng.random((20000, 7)):
        d.qpos[:] = qq
        mujoco.mj_forward(model, d)
        pe.append(d.energy[0])
    rec = panda_recording(urdf, payload, lo, hi, args.panda_samples, args.seed)
    return {
        "model": model, "nofric": load_model(urdf, PANDA_JOINTS, payload=payload),
        "lo": lo, "hi": hi, "names": PANDA_JOINTS, "q_d": HOME.copy(),
        "K": np.array([150.0, 150.0, 150.0, 150.0, 40.0, 40.0, 15.0]), "rigid": lambda q: robot.gravity(q),
        "friction": None, "hits": hits, "p_min": float(np.min(pe)),
        "p_min_how": "sampled over the joint limits (20k configurations)", "n_support": args.support, "rec": rec,
        "rec_how": (f"mmgp.sim.simulate, payload 1.5 kg, damping 0.3, {len(rec.t)} samples at 100 Hz, "
                    f"{len(rec.info['pushes'])} pushes"),
    }


def static_torque_errors(plant, torques, stand_in, learned, rng) -> tuple[dict, np.ndarray, np.ndarray]:
    """RMS of |tau(q) - exact static torque| (N*m) per feedforward, on uniform points of the part of
    the workspace box the learned model's data cover (outside it the learned feedforward fades to
    zero by design), on 500 training positions and at q_d. Returns (errors, box low, box high)."""
    lo, hi, rec = plant["lo"], plant["hi"], plant["rec"]
    blo, bhi = np.maximum(lo, learned.bounds[0]), np.minimum(hi, learned.bounds[1])
    Qbox = blo + (bhi - blo) * rng.random((500, len(lo)))
    Qtraj = rec.info["q_true"][rng.choice(len(rec.t), min(500, len(rec.t)), replace=False)]
    static = {}
    for where, Q in (("box", Qbox), ("trajectory", Qtraj), ("q_d", plant["q_d"][None])):
        ref = stand_in.nominal_torque(Q)
        static[where] = {k: float(np.sqrt(np.mean(np.sum((np.asarray(f(Q)).reshape(Q.shape) - ref) ** 2, 1))))
                         for k, f in torques.items()}
    return static, blo, bhi


def _storage(s, comp, K, q_d):
    """Closed-loop storage H = KE + P_grav - V + K |q - q_d|^2 / 2 (J) along a run."""
    return s["KE"] + s["PE"] - comp.potential(s["q"]) + 0.5 * np.sum(K * (s["q"] - q_d) ** 2, 1)


def passivity_figures(plant, s, ff, K, comp, duration) -> dict:
    """beta0 and the passivity checks of one run with an exported feedforward ``comp``."""
    q_d, model = plant["q_d"], plant["model"]
    q0 = q_d.copy()
    beta0 = (s["KE"][0] + (s["PE"][0] - plant["p_min"]) + (comp.potential_upper_bound - comp.potential(q0))
             + 0.5 * float(np.sum(K * (q0 - q_d) ** 2)))
    H = _storage(s, comp, K, q_d)
    s["H"], s["beta0"] = H, beta0
    r = {"beta0_J": float(beta0), "passive_bound_holds": bool(np.min(s["E_in"]) >= -beta0),
         "min_(beta0+E_in)_J": float(np.min(beta0 + s["E_in"])), "max_(H-H0)-E_in_J": float(np.max(H - H[0] - s["E_in"]))}
    if r["max_(H-H0)-E_in_J"] > 1e-3:
        # dH/dt <= P holds for the continuous system; a positive gap means the 1 ms semi-implicit
        # Euler step did not conserve energy (fast motion, steep torque). Re-run with a 4x finer
        # step (feedforward evaluated at every step) to tell.
        dt = model.opt.timestep
        model.opt.timestep = dt / 4
        try:
            s4 = simulate(model, ff, K, q_d, q0, plant["hits"], duration, friction=plant["friction"])
        finally:
            model.opt.timestep = dt
        H4 = _storage(s4, comp, K, q_d)
        r.update({"recheck_dt_s": dt / 4, "recheck_max_(H-H0)-E_in_J": float(np.max(H4 - H4[0] - s4["E_in"])),
                  "recheck_E_in_min_J": float(np.min(s4["E_in"]))})
    return r


def tracking_figures(plant, s, ff, duration) -> dict:
    """Tracking error (rad), time the pose holds, port energy and peak speed/torque of one run."""
    err = s["q"] - plant["q_d"]
    pre = s["t"] < min(h.t0 for h, _ in plant["hits"])
    far = np.linalg.norm(err, axis=1) > 0.05
    return {"rms_err_rad": float(np.sqrt(np.mean(np.sum(err ** 2, 1)))),
            "static_err_rad": float(np.sqrt(np.sum(err[pre][-1] ** 2))),
            "max_err_rad": float(np.max(np.linalg.norm(err, axis=1))),
            # how long the impedance holds the pose: first time |q - q_d| exceeds 0.05 rad
            "t_leave_0.05rad_s": float(s["t"][np.argmax(far)] if np.any(far) else duration),
            "E_in_min_J": float(np.min(s["E_in"])), "E_in_end_J": float(s["E_in"][-1]),
            "max_speed_rad_s": float(np.max(np.linalg.norm(np.diff(s["q"], axis=0), axis=1))
                                     / plant["model"].opt.timestep),
            "max_ff_torque_Nm": float(np.max(np.abs(np.array([ff(q) for q in s["q"][::20]]))))}


def run_plant(name, args, out_dir):
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    plant = (lever_plant if name == "lever" else panda_plant)(args, rng)
    rec, n_support = plant["rec"], plant["n_support"]
    t_rec = time.perf_counter() - t0
    print(f"[{name}] recording: {plant['rec_how']} ({t_rec:.1f} s)", flush=True)

    learned, result, t_learn = learned_compensator(name, rec, args, out_dir, n_support)
    print(f"[{name}] trained {result.report_['n_sweeps']} sweeps in {t_learn['train_s']:.1f} s, "
          f"exported in {t_learn['export_s']:.1f} s", flush=True)

    t0 = time.perf_counter()
    stand_in = StaticTorqueModel(plant["nofric"], plant["lo"], plant["hi"], n_support, plant["names"], seed=args.seed)
    comp = compensator_from_model(stand_in, max_support=n_support, seed=args.seed)
    comp = load_compensator(comp.save(out_dir / f"{name}_standin_compensator.npz"))
    t_fit = time.perf_counter() - t0
    print(f"[{name}] stand-in exported in {t_fit:.1f} s", flush=True)

    rigid = plant["rigid"]
    torques = {"learned": learned.torque, "learned model (before export)": result.nominal_torque,
               "stand-in": comp.torque, "rigid-body": lambda Q: np.array([rigid(q) for q in Q]).reshape(Q.shape),
               "none": np.zeros_like}
    static, blo, bhi = static_torque_errors(plant, torques, stand_in, learned, rng)
    ffs = {"none": lambda q: np.zeros(len(q)), "rigid-body": rigid, "learned": learned.torque, "stand-in": comp.torque}
    comps = {"learned": learned, "stand-in": comp}
    res = {"plant": name, "recording": plant["rec_how"], "recording_s": t_rec,
           "n_train_samples": int(result.report_["n_samples"]), "n_sweeps": int(result.report_["n_sweeps"]),
           "train_s": t_learn["train_s"], "export_s": t_learn["export_s"],
           "learned_n_support": int(learned.support.shape[0]),
           "learned_workspace_bounds": learned.bounds.tolist(),
           "learned_train_rmse_vs_model": learned.info.get("train_rmse_per_joint"),
           "stand_in_n_support": n_support, "stand_in_fit_s": t_fit,
           "static_torque_test_box": [blo.tolist(), bhi.tolist()],
           "static_torque_err": static,
           "potential_upper_bound": {k: c.potential_upper_bound for k, c in comps.items()},
           "storage_sampled_min": {k: c.storage_sampled_min for k, c in comps.items()},
           "p_grav_min": plant["p_min"], "p_grav_min_how": plant["p_min_how"], "runs": {}}
    sims = {}
    for imp, K in (("stiffness", plant["K"]), ("zero-impedance", np.zeros_like(plant["K"]))):
        for ffname, ff in ffs.items():
            if imp == "zero-impedance" and ffname == "none":
                continue  # without any feedforward a zero impedance just lets the arm fall
            s = simulate(plant["model"], ff, K, plant["q_d"], plant["q_d"].copy(), plant["hits"], args.duration,
                         friction=plant["friction"])
            sims[(imp, ffname)] = s
            r = tracking_figures(plant, s, ff, args.duration)
            if ffname in comps:
                r.update(passivity_figures(plant, s, ff, K, comps[ffname], args.duration))
            res["runs"][f"{imp}/{ffname}"] = r
    _plot(name, sims, plant["q_d"], out_dir)
    return res


def _plot(name, sims, q_d, out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"none": "tab:gray", "rigid-body": "tab:orange", "learned": "tab:blue", "stand-in": "tab:green"}
    for imp in ("stiffness", "zero-impedance"):
        fig, ax = plt.subplots(3, 1, figsize=(9, 10), sharex=True)
        for (i2, ff), s in sims.items():
            if i2 != imp:
                continue
            lw = 1.6 if ff == "learned" else 0.9
            ax[0].plot(s["t"], np.linalg.norm(s["q"] - q_d, axis=1), color=colors[ff], label=ff, lw=lw)
            ax[1].plot(s["t"], s["P"], color=colors[ff], label=ff, lw=0.8)
            ax[2].plot(s["t"], s["E_in"], color=colors[ff], label=f"E_in ({ff})", lw=lw)
            if "H" in s:
                ax[2].plot(s["t"], s["H"] - s["H"][0], color=colors[ff], ls=":", label=f"H - H0 ({ff})")
                ax[2].axhline(-s["beta0"], color=colors[ff], ls="--", lw=0.9,
                              label=f"-beta0 ({ff}) = {-s['beta0']:.1f} J")
        ax[0].set_ylabel("|q - q_d| (rad)")
        ax[0].set_yscale("log")
        ax[1].set_ylabel("port power tau_ext.dq (W)")
        ax[2].set_ylabel("energy (J)")
        ax[2].set_xlabel("t (s)")
        ax[2].set_yscale("symlog", linthresh=0.1)
        for a in ax:
            a.legend(fontsize=7, loc="best")
            a.grid(alpha=0.3)
        ax[0].set_title(f"{name}: {imp}, rubber-mallet hits; E_in must stay above -beta0")
        fig.tight_layout()
        fig.savefig(out_dir / f"{name}_{imp}.png", dpi=110)
        plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="folder for PNG plots, results.json, logs and exported files")
    ap.add_argument("--plants", default="lever,panda")
    ap.add_argument("--support", type=int, default=400, help="support points of the Panda compensators")
    ap.add_argument("--panda-samples", type=int, default=2000, help="samples of the Panda training log (100 Hz)")
    ap.add_argument("--max-sweeps", type=int, default=15, help="EM sweeps of MultimodalGP")
    ap.add_argument("--duration", type=float, default=7.0, help="s per run")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    allres = []
    t_all = time.perf_counter()
    for plant in args.plants.split(","):
        res = run_plant(plant.strip(), args, out_dir)
        allres.append(res)
        print(f"\n== {plant}: training log {res['recording']}; mmgp train {res['n_sweeps']} sweeps "
              f"{res['train_s']:.1f} s, export {res['export_s']:.1f} s ({res['learned_n_support']} support points)")
        print("static torque error against the plant's exact static torque, RMS of |error| (N*m):")
        st = res["static_torque_err"]
        print(f"  {'feedforward':32s} {'box':>9s} {'training q':>10s} {'at q_d':>9s}")
        for k in st["box"]:
            print(f"  {k:32s} {st['box'][k]:9.2e} {st['trajectory'][k]:10.2e} {st['q_d'][k]:9.2e}")
        print(f"{'run':38s} {'static err':>10s} {'RMS err':>9s} {'max err':>9s} {'t>0.05':>6s} {'min E_in':>9s} {'-beta0':>9s} "
              f"{'min(b0+E)':>10s} {'max dH-E':>9s}")
        for k, r in res["runs"].items():
            x = (f"{-r['beta0_J']:9.2f} {r['min_(beta0+E_in)_J']:10.3f} {r['max_(H-H0)-E_in_J']:9.1e}"
                 if "beta0_J" in r else "")
            print(f"{k:38s} {r['static_err_rad']:10.2e} {r['rms_err_rad']:9.2e} {r['max_err_rad']:9.2e} "
                  f"{r['t_leave_0.05rad_s']:6.2f} "
                  f"{r['E_in_min_J']:9.3f} {x}")
        for k, r in res["runs"].items():
            if "beta0_J" in r:
                print(f"{k}: E_in >= -beta0 holds: {r['passive_bound_holds']}; "
                      f"max (H - H0) - E_in = {r['max_(H-H0)-E_in_J']:.2e} J (<= 0 up to integration error); "
                      f"max speed {r['max_speed_rad_s']:.2g} rad/s, max |tau_ff| {r['max_ff_torque_Nm']:.3g} N*m")
                if "recheck_dt_s" in r:
                    print(f"    re-run at dt = {r['recheck_dt_s'] * 1e3:.2f} ms: max (H - H0) - E_in = "
                          f"{r['recheck_max_(H-H0)-E_in_J']:.2e} J, min E_in {r['recheck_E_in_min_J']:.3f} J")
    (out_dir / "results.json").write_text(json.dumps(allres, indent=1))
    print(f"\nplots, logs, compensators and results.json in {out_dir} ({time.perf_counter() - t_all:.0f} s)")


if __name__ == "__main__":
    main()
