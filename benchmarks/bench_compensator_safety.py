"""Is the exported compensator safe where the robot can go, not only where it was logged? (issue 12)

Three learned models, each trained by ``mmgp.MultimodalGP`` (``--modes 1``, the default
settings) and exported by ``compensator_from_model`` (rigid-body prior with the payload fitted
from the model, Wendland potential GP on the deviation), saved and reloaded from the file:

* simulated Panda, a 0.5 kg payload at the flange, exact rigid body otherwise, ``--samples``
  samples at 100 Hz through ``mmgp.sim.panda_modes(payloads=(0.5,))`` (pushes on);
* simulated UR5, a 0.5 kg payload at ``tool0`` (com 0.05 m out along the tool axis), same
  recording settings (sum-of-sinusoids reference within +-1.2 rad of mid-range, computed torque on
  the payload-free model);
* the real Panda log ``/work/shared/datasets/panda_gaz2019`` converted with ``mmgp convert`` and
  downsampled to 100 Hz by the training settings.

Figures (500 poses drawn uniformly inside the joint limits, seed fixed):

* simulated robots: max |tau_ff - tau_true| per joint (N*m), relative RMS error
  ``sqrt(mean |e|^2) / sqrt(mean |tau_true|^2)``, the distance of the poses from the support in
  the kernel metric; the same figures for the re-identified prior alone, the URDF gravity without
  the payload, the learned model itself (``nominal_torque``) and, with ``--baseline``, the previous
  export (zero-mean RBF potential, no prior); and all but the last again at 500 poses near the data
  (support poses moved by N(0, 0.05^2) rad), where the learned deviation acts;
* real Panda: max |tau_ff - tau_prior| per joint against the file's stated bound on that
  deviation, the valid region (support points, radius, lengthscales), the identified payload.
* ``check_passivity`` of every file, and the refusal of a file whose prior has a negative mass.

    python benchmarks/bench_compensator_safety.py --out /tmp/safety [--samples 10000] [--baseline]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL_PANDA = Path("/work/shared/datasets/panda_gaz2019")
UR5_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint"]


def panda_log(path: Path, n_samples: int, seed: int):
    """Simulated Panda with a 0.5 kg payload (mmgp.sim.panda_modes, one mode, pushes on)."""
    from mmgp.sim import panda_modes

    rec = panda_modes(seed=seed, n_samples=n_samples, payloads=(0.5,))
    rec.write(path)
    return {"robot": "panda", "payload": {"link": "panda_link8", "mass": 0.5, "com": [0.0, 0.0, 0.12]},
            "n_samples": len(rec.t), "pushes": len(rec.info["pushes"])}


def ur5_log(path: Path, n_samples: int, seed: int):
    """Simulated UR5 with a 0.5 kg payload at tool0, tracked by computed torque (Panda gains)."""
    from mmgp.sim import PANDA, load_model, random_link_pushes, reduced_pinocchio_model, robot_urdf_path, simulate
    from mmgp.sim.excitation import sinusoid_reference

    rng = np.random.default_rng(seed)
    urdf = robot_urdf_path("ur5")
    payload = {"link": "tool0", "mass": 0.5, "com": [0.0, 0.0, 0.05]}
    model = load_model(urdf, UR5_JOINTS, payload=payload)
    nominal = load_model(urdf, UR5_JOINTS)
    pm = reduced_pinocchio_model(urdf, UR5_JOINTS)
    duration = n_samples / 100.0
    reference = sinusoid_reference(rng, pm.lowerPositionLimit, pm.upperPositionLimit, max_speed=PANDA["max_speed"])
    pushes = random_link_pushes(rng, duration, ["forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"])
    rec = simulate(model, reference, duration, rate_hz=100.0, kp=PANDA["kp"], kd=PANDA["kd"],
                   controller_model=nominal, gains="acceleration", pushes=pushes,
                   q_resolution=PANDA["q_resolution"], tau_noise=PANDA["tau_noise"], dq_noise=PANDA["dq_noise"],
                   log_dq=True, seed=int(rng.integers(2 ** 31)), robot="ur5", joint_names=UR5_JOINTS)
    rec.write(path)
    return {"robot": "ur5", "payload": payload, "n_samples": len(rec.t), "pushes": len(pushes)}


def real_panda_log(path: Path):
    """The real Panda log through ``python -m mmgp.cli convert``."""
    subprocess.run([sys.executable, "-m", "mmgp.cli", "convert", str(REAL_PANDA), "--out", str(path), "--force"],
                   check=True, capture_output=True, text=True)
    return {"robot": "panda", "source": str(REAL_PANDA)}


def train_model(log: Path, model_dir: Path, rate_hz: float | None, seed: int):
    """``MultimodalGP`` with the default settings, one mode (the log names its robot); saves the model."""
    from mmgp.config import load_settings
    from mmgp.estimator import MultimodalGP

    cfg = load_settings(ROOT / "mmgp" / "resources" / "configs" / "default.yaml", "train", MultimodalGP,
                        n_modes=1, rate_hz=rate_hz, seed=seed)
    t0 = time.perf_counter()
    model = MultimodalGP(**cfg).fit(log)
    model.save(model_dir)
    return {"train_s": time.perf_counter() - t0, "n_sweeps": model.report_.get("n_sweeps"),
            "n_samples_used": int(sum(len(lg.t) for lg in model.logs_))}


def stage_models(out: Path, args) -> dict:
    """Logs and trained models, cached in ``out`` (a second run reuses them)."""
    info = {}
    cases = {"panda_sim": (lambda p: panda_log(p, args.samples, args.seed), None),
             "ur5_sim": (lambda p: ur5_log(p, args.samples, args.seed), None),
             "panda_real": (real_panda_log, 100.0)}
    for name, (make, rate) in cases.items():
        if name not in args.cases:
            continue
        log, mdir = out / f"{name}.parquet", out / f"{name}_model"
        meta_path = out / f"{name}_meta.json"
        if not (mdir / "model.json").is_file():
            t0 = time.perf_counter()
            meta = make(log)
            meta["simulate_s"] = time.perf_counter() - t0
            meta.update(train_model(log, mdir, rate, args.seed))
            meta_path.write_text(json.dumps(meta, indent=1))
            print(f"{name}: {json.dumps(meta)}", flush=True)
        info[name] = json.loads(meta_path.read_text())
    return info


BASELINE_EXPORT = """
import sys
import numpy as np
from mmgp.compensator import compensator_from_model  # the baseline's layout (one module)

class Table:  # the model's nominal torque at its distinct support poses, all the export asks for
    def __init__(self, z):
        self.support_q_, self._tau, self.joint_names_ = z["Q"], z["tau"], list(z["names"])
        self._row = {r.tobytes(): k for k, r in enumerate(self.support_q_)}
    def nominal_torque(self, q):
        return self._tau[[self._row[r.tobytes()] for r in np.ascontiguousarray(q)]]

z = np.load(sys.argv[1])
np.save(sys.argv[2], compensator_from_model(Table(z)).torque(z["poses"]))
"""


def baseline_torque(model, poses: np.ndarray, work: Path) -> np.ndarray:
    """tau_ff at ``poses`` of the previous export (/work/baseline: zero-mean RBF potential, no
    prior) of the same model. The baseline cannot read this model format, so it gets the model's
    nominal torque at its distinct support poses (the only inputs its export uses) as a table."""
    import os

    Q = np.unique(np.asarray(model.support_q_, dtype=np.float64), axis=0)
    np.savez(work / "baseline_in.npz", Q=Q, tau=model.nominal_torque(Q), names=np.array(model.joint_names_),
             poses=poses)
    env = {**os.environ, "PYTHONPATH": "/work/baseline"}
    # run from the baseline folder: "python -c" puts the working folder first on sys.path
    subprocess.run([sys.executable, "-c", BASELINE_EXPORT, str(work / "baseline_in.npz"),
                    str(work / "baseline_out.npy")], check=True, env=env, cwd="/work/baseline")
    return np.load(work / "baseline_out.npy")


def mujoco_static_torque(name: str, Q: np.ndarray, meta: dict) -> np.ndarray:
    """The simulated plant's own torque at rest (MuJoCo ``qfrc_bias``, payload included): the truth."""
    import mujoco

    from mmgp.sim import PANDA_JOINTS, load_model, robot_urdf_path

    joints = PANDA_JOINTS if name.startswith("panda") else UR5_JOINTS
    model = load_model(robot_urdf_path(meta["robot"]), joints, payload=meta["payload"])
    data = mujoco.MjData(model)
    out = np.empty_like(Q)
    for k, q in enumerate(Q):
        data.qpos[:], data.qvel[:] = q, 0.0
        mujoco.mj_forward(model, data)
        out[k] = data.qfrc_bias
    return out


def accuracy(tau, truth) -> dict:
    """Max |error| per joint (N*m) and relative RMS of ``tau`` (T, n) against ``truth`` (T, n)."""
    e = tau - truth
    return {"max_abs_err_per_joint": np.abs(e).max(0).tolist(),
            "rel_rms": float(np.sqrt(np.mean(e ** 2)) / np.sqrt(np.mean(truth ** 2)))}


def evaluate(name: str, out: Path, meta: dict, args) -> dict:
    """Export, reload, check and score one case (module docstring)."""
    from mmgp.compensator import check_passivity, compensator_from_model, load_compensator
    from mmgp.estimator import MultimodalGP

    model = MultimodalGP.load(out / f"{name}_model")
    t0 = time.perf_counter()
    comp = load_compensator(compensator_from_model(model, seed=args.seed).save(out / f"{name}.npz"))
    res = {"export_s": time.perf_counter() - t0, "kind": comp.kind, "n_support": int(comp.support.shape[0]),
           "identification": comp.prior.identification, "radii_rad": comp.lengthscales.tolist(),
           "radius_scale": comp.info.get("radius_scale"),
           "deviation_torque_bound": comp.deviation_torque_bound.tolist(),
           "deviation_sampled_max": comp.deviation_sampled_max.tolist()}
    chk = check_passivity(comp)
    res["check_passivity"] = {k: chk[k] for k in ("passed", "grad_max_rel_err", "loop_max_rel_work",
                                                  "storage_min_sampled", "prior_consistent_pass")}
    robot = model.robot_
    lo, hi = robot.pin_model.lowerPositionLimit, robot.pin_model.upperPositionLimit
    Q = lo + (hi - lo) * np.random.default_rng(args.seed + 12).random((500, robot.n_joints))
    dist = comp.region_distance(Q)
    res["poses"] = {"inside_region": float(np.mean(dist < 1)), "median_region_distance": float(np.median(dist)),
                    "median_rad_to_nearest_support": float(np.median(np.min(np.linalg.norm(
                        Q[:, None] - comp.support[None], axis=2), axis=1)))}
    if name.endswith("_sim"):
        truth = mujoco_static_torque(name, Q, meta)
        res["truth_rms_per_joint"] = np.sqrt(np.mean(truth ** 2, 0)).tolist()
        res["new"] = accuracy(comp.torque(Q), truth)
        res["prior_only"] = accuracy(comp.prior_torque(Q), truth)
        res["urdf_gravity"] = accuracy(robot.gravity(Q), truth)
        res["model_itself"] = accuracy(model.nominal_torque(Q), truth)
        # where the deviation GP acts: 500 of the model's support poses moved by N(0, 0.05^2) rad
        rows = np.random.default_rng(args.seed + 13).choice(len(model.support_q_), 500)
        near = model.support_q_[rows] + np.random.default_rng(args.seed + 14).normal(size=(500, robot.n_joints)) * 0.05
        truth_near = mujoco_static_torque(name, near, meta)
        res["near_data"] = {"inside_region": float(np.mean(comp.region_distance(near) < 1)),
                            **{k: accuracy(tau, truth_near) for k, tau in (
                                ("new", comp.torque(near)), ("prior_only", comp.prior_torque(near)),
                                ("model_itself", model.nominal_torque(near)))}}
        if args.baseline:
            res["baseline"] = accuracy(baseline_torque(model, Q, out), truth)
    else:
        dev = np.abs(comp.deviation_torque(Q))
        near = comp.support + np.random.default_rng(1).normal(size=comp.support.shape) * 0.05
        res["max_abs_deviation_uniform"] = dev.max(0).tolist()
        res["max_abs_deviation_near_data"] = np.abs(comp.deviation_torque(near)).max(0).tolist()
        res["within_rigorous_bound"] = bool(np.all(dev <= comp.deviation_torque_bound))
        res["within_sampled_max"] = bool(np.all(dev <= comp.deviation_sampled_max))
        zero = np.zeros(robot.n_joints)
        res["zero_pose"] = {"tau_ff": comp.torque(zero).tolist(), "prior": comp.prior_torque(zero).tolist(),
                            "region_distance": comp.region_distance(zero)}
        res["refusal"] = refusal(out / f"{name}.npz", out)
    return res


def refusal(path: Path, out: Path) -> dict:
    """A copy of the file with the payload body's mass made negative: load and the CLI must refuse."""
    from typer.testing import CliRunner

    from mmgp.cli import app
    from mmgp.compensator import load_compensator

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays.pop("meta")))
    meta["prior"]["masses"][-1] = -0.7
    bad = out / "negative_mass.npz"
    np.savez(bad, meta=np.array(json.dumps(meta)), **arrays)
    try:
        load_compensator(bad)
        loaded = "loaded (WRONG)"
    except ValueError as exc:
        loaded = f"refused: {exc}"
    cli = CliRunner().invoke(app, ["check-passivity", str(bad)])
    return {"load_compensator": loaded, "check_passivity_exit_code": cli.exit_code, "cli_output": cli.output.strip()}


def report(results: dict) -> None:
    f = lambda a, p=2: "[" + ", ".join(f"{x:.{p}f}" for x in a) + "]"  # noqa: E731
    for name, r in results.items():
        pl = r["identification"]["payload"]
        print(f"\n== {name}: {r['kind']}, {r['n_support']} support points, export {r['export_s']:.0f} s; "
              f"payload {pl['mass']:.4f} kg at {f(pl['com'], 4)} m (free fit m = {pl['unconstrained_first_moments'][0]:.4f}"
              f" kg; active {pl['active_constraints']}); re-identified masses "
              f"{f(r['identification'].get('reidentified', {}).get('masses', [float('nan')]), 3)} (URDF "
              f"{f(r['identification']['nominal_masses'], 3)}) kg; decision {r['identification'].get('reidentify_decision')}")
        print(f"   radii (rad) {f(r['radii_rad'])} (scale {r['radius_scale']}); 500 uniform poses: inside the region "
              f"{r['poses']['inside_region']:.3f}, median region distance {r['poses']['median_region_distance']:.2f}, "
              f"median distance to the nearest support pose {r['poses']['median_rad_to_nearest_support']:.2f} rad")
        print(f"   check_passivity: {r['check_passivity']}")
        for k in ("new", "prior_only", "urdf_gravity", "model_itself", "baseline"):
            if k in r:
                print(f"   {k:12s} max |tau - truth| per joint {f(r[k]['max_abs_err_per_joint'], 3)} N*m, "
                      f"relative RMS {r[k]['rel_rms']:.4f}")
        if "near_data" in r:
            nd = r["near_data"]
            print(f"   near the data (500 support poses + N(0, 0.05^2) rad; inside the region {nd['inside_region']:.3f}):")
            for k in ("new", "prior_only", "model_itself"):
                print(f"     {k:12s} max |tau - truth| per joint {f(nd[k]['max_abs_err_per_joint'], 3)} N*m, "
                      f"relative RMS {nd[k]['rel_rms']:.4f}")
        if "max_abs_deviation_uniform" in r:
            print(f"   max |tau_ff - tau_prior| at the 500 poses {f(r['max_abs_deviation_uniform'], 3)}; near the data "
                  f"{f(r['max_abs_deviation_near_data'])}")
            print(f"   stated bounds: rigorous {f(r['deviation_torque_bound'], 1)}; sampled max "
                  f"{f(r['deviation_sampled_max'])}; within both: {r['within_rigorous_bound']}, {r['within_sampled_max']}")
            z = r["zero_pose"]
            print(f"   zero pose: tau_ff {f(z['tau_ff'])}, prior {f(z['prior'])}, region distance {z['region_distance']:.2f}")
            print(f"   negative-mass file: {r['refusal']['load_compensator'][:120]}; check-passivity exit "
                  f"{r['refusal']['check_passivity_exit_code']}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--samples", type=int, default=10000)
    ap.add_argument("--cases", default="panda_sim,ur5_sim,panda_real")
    ap.add_argument("--stage", default="all", choices=["models", "all"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--baseline", action="store_true", help="also score the previous export (/work/baseline)")
    args = ap.parse_args()
    args.cases = args.cases.split(",")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info = stage_models(out, args)
    if args.stage == "models":
        return
    results = {name: dict(evaluate(name, out, info[name], args), training=info[name]) for name in info}
    (out / "results.json").write_text(json.dumps(results, indent=1))
    report(results)
    print(f"\nresults.json, compensator files and models in {out}")


if __name__ == "__main__":
    main()
