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
  * ``compensator``: the exported passive feedforward, fitted to the plant's static torque
    (MuJoCo ``qfrc_bias`` at rest, including the payload) on random configurations, saved to a
    file and evaluated through ``load_compensator`` (numpy) in the 1 kHz loop.

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

Figures: RMS and static tracking error (before the first hit) per variant, min E_in vs -beta_0.
Plots (PNG) go to ``--out``.

    python benchmarks/closed_loop_energy.py --out /tmp/cle [--plants lever,panda] [--support 400]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mmgp.compensator import compensator_from_model, load_compensator
from mmgp.sim import PANDA_JOINTS, REPLICA, Push, build_mjcf, panda_urdf_path, replica_mjcf

HOME = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
G = 9.81


def _mj():
    import mujoco

    return mujoco


def _enable_energy(model):
    mj = _mj()
    model.opt.enableflags |= int(mj.mjtEnableBit.mjENBL_ENERGY)
    return model


class StaticTorqueModel:
    """Stand-in for a trained model: the plant's own static torque (MuJoCo gravity at rest).

    ``nominal_torque(q (T, n)) -> (T, n)`` N*m; ``support_q_`` uniform in ``[lo, hi]``."""

    def __init__(self, mj_model, lo, hi, n, names, seed=0):
        self.m = mj_model
        self.d = _mj().MjData(mj_model)
        rng = np.random.default_rng(seed)
        self.support_q_ = lo + (hi - lo) * rng.random((n, len(lo)))
        self.joint_names_ = list(names)

    def nominal_torque(self, q):
        mj = _mj()
        q = np.atleast_2d(q)
        out = np.empty_like(q)
        for i, qi in enumerate(q):
            self.d.qpos[:] = qi
            self.d.qvel[:] = 0.0
            mj.mj_forward(self.m, self.d)
            out[i] = self.d.qfrc_bias
        return out


def simulate(model, ff, K, q_d, q0, hits, duration, *, friction=None, pot_ff=None):
    """1 kHz loop. ``ff(q) -> (n,)``; ``hits``: list of (Push, body id); returns arrays.

    Work of the external force per step: ``(J^T F) . (q_{k+1} - q_k)`` (F constant over the step).
    """
    mj = _mj()
    d = mj.MjData(model)
    n = model.nv
    dt = model.opt.timestep
    steps = int(round(duration / dt))
    d.qpos[:] = q0
    d.qvel[:] = 0.0
    mj.mj_forward(model, d)
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
            mj.mj_jac(model, d, jacp, None, d.xipos[bid], bid)
            tau_ext += jacp.T @ F
        out["KE"][k], out["PE"][k] = d.energy[1], d.energy[0]
        mj.mj_step(model, d)
        E += float(tau_ext @ (d.qpos - q))
        out["t"][k], out["q"][k], out["P"][k], out["E_in"][k] = t, q, float(tau_ext @ d.qvel), E
    return out


def _hits(model, body, forces, times, frame):
    bid = _mj().mj_name2id(model, _mj().mjtObj.mjOBJ_BODY, body)
    return [(Push(t0=float(t), duration=0.02, body=body, force=tuple(float(x) for x in f), frame=frame), bid)
            for t, f in zip(times, forces)]


def run_plant(name, args, out_dir):
    mj = _mj()
    rng = np.random.default_rng(args.seed)
    if name == "lever":
        P = REPLICA
        model = _enable_energy(mj.MjModel.from_xml_string(replica_mjcf()))
        nofric = mj.MjModel.from_xml_string(replica_mjcf())
        nofric.dof_frictionloss[:] = 0.0
        lo, hi = np.array([-1.0]), np.array([1.6])
        names = ["lever_joint"]
        q_d = np.array([0.3])
        K_stiff = np.array([20.0])
        L = P["lever_length"]
        m_eff_true = P["load_mass"] * L + P["lever_mass"] * L / 2
        m_eff_nom = 0.5 * L + P["lever_mass"] * L / 2
        rigid = lambda q: np.array([m_eff_nom * G * np.cos(q[0])])
        friction = lambda m, d: m.dof_frictionloss.__setitem__(0, P["friction_c"] + P["friction_beta"] * abs(d.ctrl[0]))
        hits = _hits(model, "load", [(0, 0, 40.0), (0, 0, -30.0), (0, 0, -40.0), (0, 0, 30.0)],
                     [1.0, 1.12, 4.0, 4.12], "body")
        p_min = -m_eff_true * G  # exact: lowest point of the lever's centre of mass (q = -pi/2)
        p_min_how = "exact"
        n_support = min(args.support, 200)
    else:
        urdf = panda_urdf_path()
        payload = {"link": "panda_link8", "mass": 1.5, "com": [0.0, 0.0, 0.12]}
        model = _enable_energy(mj.MjModel.from_xml_string(
            build_mjcf(urdf, PANDA_JOINTS, damping=0.3, payload=payload)))
        nofric = mj.MjModel.from_xml_string(build_mjcf(urdf, PANDA_JOINTS, payload=payload))
        from mmgp.robot import RobotModel

        robot = RobotModel.from_name("panda", PANDA_JOINTS)
        lim_lo, lim_hi = robot.pin_model.lowerPositionLimit.copy(), robot.pin_model.upperPositionLimit.copy()
        lo, hi = np.maximum(HOME - 0.6, lim_lo), np.minimum(HOME + 0.6, lim_hi)
        names = PANDA_JOINTS
        q_d = HOME.copy()
        K_stiff = np.array([150.0, 150.0, 150.0, 150.0, 40.0, 40.0, 15.0])
        rigid = lambda q: robot.gravity(q)
        friction = None
        dirs = rng.standard_normal((4, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        hits = _hits(model, "panda_link7", 60.0 * np.array([dirs[0], -dirs[0], dirs[1], -dirs[1]]),
                     [1.0, 1.08, 4.0, 4.08], "world")
        # sampled minimum of MuJoCo's gravity potential over the joint limits (not rigorous)
        d = mj.MjData(model)
        Qs = lim_lo + (lim_hi - lim_lo) * rng.random((20000, 7))
        pe = []
        for qq in Qs:
            d.qpos[:] = qq
            mj.mj_forward(model, d)
            pe.append(d.energy[0])
        p_min = float(np.min(pe))
        p_min_how = "sampled over the joint limits (20k configurations)"
        n_support = args.support

    t0 = time.perf_counter()
    stand_in = StaticTorqueModel(nofric, lo, hi, n_support, names, seed=args.seed)
    comp = compensator_from_model(stand_in, max_support=n_support, seed=args.seed)
    f = comp.save(out_dir / f"{name}_compensator.npz")
    comp = load_compensator(f)  # the controller uses the exported file
    t_fit = time.perf_counter() - t0
    Qte = lo + (hi - lo) * rng.random((500, len(lo)))
    ref = stand_in.nominal_torque(Qte)
    rms_fit = float(np.sqrt(np.mean((comp.torque(Qte) - ref) ** 2)))
    rms_rigid = float(np.sqrt(np.mean((np.atleast_2d(np.array([rigid(q) for q in Qte])).reshape(ref.shape) - ref) ** 2)))

    ffs = {"none": lambda q: np.zeros(len(q)), "rigid-body": rigid, "compensator": comp.torque}
    q0 = q_d.copy()
    res = {"plant": name, "n_support": n_support, "fit_time_s": t_fit,
           "static_torque_rms_err": {"compensator": rms_fit, "rigid-body": rms_rigid,
                                     "none": float(np.sqrt(np.mean(ref ** 2)))},
           "potential_upper_bound": comp.potential_upper_bound, "p_grav_min": p_min, "p_grav_min_how": p_min_how,
           "runs": {}}
    sims = {}
    first_hit = min(h.t0 for h, _ in hits)
    for imp, K in (("stiffness", K_stiff), ("zero-impedance", np.zeros_like(K_stiff))):
        for ffname, ff in ffs.items():
            if imp == "zero-impedance" and ffname == "none":
                continue  # without any feedforward a zero impedance just lets the arm fall
            s = simulate(model, ff, K, q_d, q0, hits, args.duration, friction=friction)
            sims[(imp, ffname)] = s
            err = s["q"] - q_d
            pre = s["t"] < first_hit
            r = {"rms_err_rad": float(np.sqrt(np.mean(np.sum(err ** 2, 1)))),
                 "static_err_rad": float(np.sqrt(np.sum(err[pre][-1] ** 2))),
                 "max_err_rad": float(np.max(np.linalg.norm(err, axis=1))),
                 "E_in_min_J": float(np.min(s["E_in"])), "E_in_end_J": float(s["E_in"][-1])}
            if ffname == "compensator":
                V0 = comp.potential(q0)
                beta0 = (s["KE"][0] + (s["PE"][0] - p_min) + (comp.potential_upper_bound - V0)
                         + 0.5 * float(np.sum(K * (q0 - q_d) ** 2)))
                r["beta0_J"] = float(beta0)
                r["passive_bound_holds"] = bool(np.min(s["E_in"]) >= -beta0)
                # storage along the run: H = KE + P_grav - V + spring, and E_in >= H - H0 (dissipation)
                H = s["KE"] + s["PE"] - comp.potential(s["q"]) + 0.5 * np.sum(K * (s["q"] - q_d) ** 2, 1)
                r["max_(H-H0)-E_in_J"] = float(np.max(H - H[0] - s["E_in"]))
                s["H"] = H
                s["beta0"] = beta0
            res["runs"][f"{imp}/{ffname}"] = r
    _plot(name, sims, q_d, out_dir)
    return res


def _plot(name, sims, q_d, out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"none": "tab:gray", "rigid-body": "tab:orange", "compensator": "tab:blue"}
    for imp in ("stiffness", "zero-impedance"):
        fig, ax = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
        for (i2, ff), s in sims.items():
            if i2 != imp:
                continue
            ax[0].plot(s["t"], np.linalg.norm(s["q"] - q_d, axis=1), color=colors[ff], label=ff)
            ax[1].plot(s["t"], s["P"], color=colors[ff], label=ff, lw=0.8)
            ax[2].plot(s["t"], s["E_in"], color=colors[ff], label=f"E_in ({ff})")
            if ff == "compensator":
                ax[2].plot(s["t"], s["H"] - s["H"][0], color=colors[ff], ls=":", label="H - H0 (compensator)")
                ax[2].axhline(-s["beta0"], color="k", ls="--", label=f"-beta0 = {-s['beta0']:.1f} J")
        ax[0].set_ylabel("|q - q_d| (rad)")
        ax[1].set_ylabel("port power tau_ext.dq (W)")
        ax[2].set_ylabel("energy (J)")
        ax[2].set_xlabel("t (s)")
        ax[2].set_yscale("symlog", linthresh=0.1)
        for a in ax:
            a.legend(fontsize=8, loc="best")
            a.grid(alpha=0.3)
        ax[0].set_title(f"{name}: {imp}, rubber-mallet hits; E_in must stay above -beta0")
        fig.tight_layout()
        fig.savefig(out_dir / f"{name}_{imp}.png", dpi=110)
        plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="folder for PNG plots, results.json and the exported files")
    ap.add_argument("--plants", default="lever,panda")
    ap.add_argument("--support", type=int, default=400, help="support points of the Panda compensator")
    ap.add_argument("--duration", type=float, default=7.0, help="s per run")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    allres = []
    for plant in args.plants.split(","):
        res = run_plant(plant.strip(), args, out_dir)
        allres.append(res)
        print(f"\n== {plant}: compensator {res['n_support']} support points, fit+export {res['fit_time_s']:.1f} s")
        st = res["static_torque_rms_err"]
        print(f"static torque RMS error over the workspace (N*m): compensator {st['compensator']:.2e}, "
              f"rigid-body model {st['rigid-body']:.2e}, no feedforward {st['none']:.2e}")
        print(f"{'run':30s} {'static err':>11s} {'RMS err':>9s} {'max err':>9s} {'min E_in':>9s} {'-beta0':>8s}")
        for k, r in res["runs"].items():
            b = f"{-r['beta0_J']:8.2f}" if "beta0_J" in r else f"{'':8s}"
            print(f"{k:30s} {r['static_err_rad']:11.2e} {r['rms_err_rad']:9.2e} {r['max_err_rad']:9.2e} "
                  f"{r['E_in_min_J']:9.3f} {b}")
        for k, r in res["runs"].items():
            if "beta0_J" in r:
                print(f"{k}: E_in >= -beta0 holds: {r['passive_bound_holds']}; "
                      f"max (H - H0) - E_in = {r['max_(H-H0)-E_in_J']:.2e} J (<= 0 up to integration error: dissipation)")
    (out_dir / "results.json").write_text(json.dumps(allres, indent=1))
    print(f"\nplots and results.json in {out_dir}")


if __name__ == "__main__":
    main()
