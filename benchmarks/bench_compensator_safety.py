"""Is the exported compensator safe where the robot can go, not only where it was logged? (issue 12)

Three learned models, each trained by ``mmgp.models.trained.train`` (``--modes 1``, the default
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
  the kernel metric, and the same figures for the previous export (zero-mean RBF potential, no
  prior) when ``--baseline`` is given;
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
    """``mmgp.models.trained.train`` with the default settings, one mode; saves the model folder."""
    from mmgp.config import load_config
    from mmgp.models.trained import train
    from mmgp.physics.robot import load_robot

    cfg = load_config(ROOT / "configs" / "default.yaml", modes=1, rate_hz=rate_hz, seed=seed)
    t0 = time.perf_counter()
    res = train([log], cfg, robot=load_robot(log_path=log))
    model_dir.mkdir(parents=True, exist_ok=True)
    res.model.save(model_dir)
    return {"train_s": time.perf_counter() - t0, "n_sweeps": res.report["n_sweeps"],
            "n_samples_used": res.report["n_samples"]}


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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--samples", type=int, default=10000)
    ap.add_argument("--cases", default="panda_sim,ur5_sim,panda_real")
    ap.add_argument("--stage", default="all", choices=["models", "all"])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    args.cases = args.cases.split(",")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stage_models(out, args)


if __name__ == "__main__":
    main()
