"""Issue 10: are pushes on proximal links and light pushes found? Panda logs with an exact model.

Each log is a family Panda draw (mmgp.sim.family, its motion, controller and sensor noise) with
the concealed physics removed (no friction, no payload: the URDF is the exact model) and its pushes
replaced by pushes of ``--force`` N (uniform in the range, random direction) on the links of
``--links`` (cycled, one link per push), ~20% of the time. ``mmgp`` (``MultimodalGP`` defaults)
labels it; printed per log and per pushed link: unperturbed correct, perturbed missed (the
contract's rule: significant samples must be flagged, clean ones not) and, with ``--zscores``,
on missed / found significant / clean samples the medians of: per-joint |z| under the last
sweep's nominal predictive (``z_``), the largest joint's |z| (``zmax_``), the true push torque
in predictive standard deviations (``pushz_``) and the predictive std in N*m (``std_``): where
the evidence of a missed push sits. ``--dump DIR`` keeps the last sweep's arrays per log (npz).
``--controller ctc`` forces computed torque, ``--noise`` one torque noise std on every joint.

Usage: python benchmarks/bench_push_links.py [--seeds 0,1] [--links 2,4,7] [--force 8,25]
       [--rate 100] [--seconds 40] [--controller ctc] [--noise 0.05] [--zscores] [--dump DIR]
       [--cache DIR] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def link_coms(links) -> dict:
    """Centre of mass (3,) of each Panda link number in ``links``, in the link's frame, m."""
    import mujoco

    from mmgp.sim.family import ARMS
    from mmgp.sim.mjcf import load_model, robot_urdf_path

    model = load_model(robot_urdf_path("panda"), ARMS["panda"]["joints"])
    return {k: model.body_ipos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"panda_link{k}")].tolist()
            for k in links}


def push_spec(seed: int, links, force, rate: float, seconds: float, fraction: float = 0.2, controller=None,
              noise=None):
    """A family Panda spec of ``seed`` without concealed physics, pushes on ``links`` (link numbers
    1-7) of ``force`` = (lo, hi) N at the link's centre of mass, covering about ``fraction`` of the
    time; ``controller`` "ctc" forces computed torque (None: the draw's)."""
    from mmgp.sim.family import draw

    spec = draw(seed, "panda", max_samples=int(rate * seconds))
    rng = np.random.default_rng([seed, 0x70757368])
    n = len(spec.joint_names)
    spec.rate_hz, spec.duration, spec.payload = float(rate), float(seconds), None
    if controller == "ctc" and spec.controller["type"] != "ctc":
        wn, n_j = 20.0, len(spec.joint_names)
        spec.controller = {"type": "ctc", "kp": [wn ** 2] * n_j, "kd": [2 * wn] * n_j}
    if noise is not None:
        spec.sensor["tau_noise"] = [float(noise)] * len(spec.joint_names)
    coms = link_coms(links)
    spec.friction = {"coulomb": [0.0] * n, "beta": [0.0] * n, "viscous": [0.0] * n}
    pushes, t, i = [], rng.uniform(1.0, 3.0), 0
    while True:
        d = float(rng.uniform(0.5, 2.0))
        if t + d > seconds - 0.5:
            break
        u = rng.standard_normal(3)
        pushes.append({"t0": float(t), "duration": d, "body": f"panda_link{links[i % len(links)]}",
                       "force": (u / np.linalg.norm(u) * rng.uniform(*force)).tolist(), "torque": [0.0] * 3,
                       "point": coms[links[i % len(links)]], "frame": "world", "ramp": float(rng.uniform(0.1, 0.4) * d)})
        t += d + d * (1 - fraction) / fraction * rng.uniform(0.5, 1.5)
        i += 1
    spec.pushes = pushes
    return spec


def make_log(seed, links, force, rate, seconds, cache: Path, controller=None, noise=None):
    """(log path, labels (T,) int, tau_push (T, n), pushed link per sample (0 none))."""
    from mmgp.sim.family import record, write_scenario

    stem = f"pl{seed}_l{''.join(map(str, links))}_f{force[0]:g}-{force[1]:g}_r{rate:g}_s{seconds:g}{'_' + controller if controller else ''}{f'_n{noise:g}' if noise else ''}"
    log, side = cache / f"{stem}.parquet", cache / f"{stem}.truth.npz"
    if not (log.is_file() and side.is_file()):
        spec = push_spec(seed, links, force, rate, seconds, controller=controller, noise=noise)
        rec = record(spec)
        write_scenario(rec, cache, stem)
        link = np.zeros(len(rec.t), int)
        for p in spec.pushes:
            link[(rec.t > p["t0"]) & (rec.t < p["t0"] + p["duration"])] = int(p["body"][-1])
        np.savez(side, labels=rec.labels["disturbed"].to_numpy(), tau_push=rec.info["tau_push"], link=link)
    z = np.load(side)
    return log, z["labels"], z["tau_push"], z["link"]


def run_one(log, labels, link, tau_push, zscores: bool, dump: str | None = None) -> dict:
    """Fit the default ``MultimodalGP`` on ``log`` and score its labels against ``labels`` (T,)
    (1 significant, 0 clean, -1 ambiguous); ``link`` (T,) the pushed link (0 none), ``tau_push``
    (T, n) the true push torque, N*m."""
    from mmgp.estimator import MultimodalGP

    t0 = time.perf_counter()
    model = MultimodalGP(seed=0).fit(str(log))
    sec = time.perf_counter() - t0
    sem = model.sem_
    flagged = sem.disturbed_.astype(bool)
    clean, sig = labels == 0, labels == 1
    row = {"log": Path(log).stem, "seconds": round(sec, 1), "sweeps": int(sem.n_sweeps_),
           "unperturbed_correct": round(float((~flagged[clean]).mean()), 3),
           "perturbed_missed": round(float((~flagged[sig]).mean()), 3), "n_significant": int(sig.sum()),
           "sigma_d": np.round(np.sqrt(sem.sigma_d_), 3).tolist()}
    row["missed_by_link"] = {int(k): round(float((~flagged[sig & (link == k)]).mean()), 3)
                             for k in np.unique(link[sig]) if k}
    if zscores and sem.last_sweep_ is not None:
        ls = sem.last_sweep_
        z = np.abs(model.features_.Y - ls["means"][0]) / np.sqrt(ls["vars"][0]) if hasattr(model, "features_") else None
        if z is not None and z.shape[0] == len(labels):
            snr = np.abs(tau_push) / np.sqrt(ls["vars"][0])
            for name, sel in (("missed", sig & ~flagged), ("found", sig & flagged), ("clean", clean)):
                if sel.any():
                    row["z_" + name] = np.round(np.median(z[sel], 0), 2).tolist()
                    row["zmax_" + name] = round(float(np.median(z[sel].max(1))), 2)
                    row["pushz_" + name] = np.round(np.median(snr[sel], 0), 2).tolist()
                    row["std_" + name] = np.round(np.median(np.sqrt(ls["vars"][0][sel]), 0), 3).tolist()
    if dump and sem.last_sweep_ is not None:
        np.savez(Path(dump) / f"{Path(log).stem}.npz", Y=model.features_.Y, X=model.features_.X,
                 mean=sem.last_sweep_["means"][0], var=sem.last_sweep_["vars"][0], p=sem.p_disturbed_,
                 labels=labels, link=link, calib=sem.last_sweep_["calib"], sigma_d=sem.sigma_d_)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--links", default="2,4,7")
    ap.add_argument("--force", default="8,25")
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--controller", default=None, help="ctc: computed torque on every log (default: the draw's)")
    ap.add_argument("--noise", type=float, default=None, help="torque noise std on every joint, N*m (default: the draw's)")
    ap.add_argument("--zscores", action="store_true")
    ap.add_argument("--dump", default=None, help="folder for the last sweep's arrays per log (npz)")
    ap.add_argument("--cache", default="/tmp/bench_push_links")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    links = [int(x) for x in a.links.split(",")]
    force = tuple(float(x) for x in a.force.split(","))
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in (int(s) for s in a.seeds.split(",")):
        log, labels, tau_push, link = make_log(seed, links, force, a.rate, a.seconds, cache, a.controller, a.noise)
        row = run_one(log, labels, link, tau_push, a.zscores, a.dump)
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(json.dumps({"worst_unperturbed_correct": min(r["unperturbed_correct"] for r in rows),
                      "worst_perturbed_missed": max(r["perturbed_missed"] for r in rows),
                      "mean_perturbed_missed": round(float(np.mean([r["perturbed_missed"] for r in rows])), 3)}))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
