"""The exported feedforward's target at rest, with and without the friction band at rest (issue 10).

``mmgp export`` fits its passive compensator to the model's ``nominal_torque(q)``: the torque at
dq = ddq = 0, averaged over both sliding branches (the centre of the dry-friction band). This
script trains the default model (``rest_band`` on) and the previous default (``rest_band`` off)
on family levers (MuJoCo, ``mmgp.sim.family``; each log's URDF is the rigid-body model) and
compares that target with the lever's true static torque, -G cos q (G = m g c from the lever's
spec), on 200 positions between the 2nd and 98th percentile of the support:

  * RMS and max error (N*m), and the share of positions where the target leaves the true
    friction band (|error| > Coulomb + beta |G cos q|: such a feedforward would move a lever
    that its own friction holds still);
  * the ratio of the RMS errors (band off / band on) per lever, and the worst over levers.

Sets: ``tuning`` (levers 1000-1011, developed on), ``heldout3`` (bench_labels.py's third
held-out levers; their labels were scored once, this target had not been looked at) and
``heldout4`` (the fourth held-out levers, drawn once).

    python benchmarks/bench_rest_target.py [--sets tuning,heldout3] [--cache DIR] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_labels import HELDOUT3_LEVERS, HELDOUT4_LEVERS, TUNING_LEVERS, family_cases  # noqa: E402

SETS = {"tuning": TUNING_LEVERS, "heldout3": HELDOUT3_LEVERS, "heldout4": HELDOUT4_LEVERS}


def target_errors(log: Path, spec: dict, rest_band: bool) -> dict:
    from mmgp import MultimodalGP

    lever, fr = spec["lever"], spec["friction"]
    model = MultimodalGP(rest_band=rest_band, seed=0).fit(log)
    qs = model.support_q_[:, 0]
    q = np.linspace(np.percentile(qs, 2), np.percentile(qs, 98), 200)
    static = -lever["gravity_torque"] * np.cos(q)
    err = model.nominal_torque(q[:, None])[:, 0] - static
    band = fr["coulomb"][0] + fr["beta"][0] * np.abs(static)
    return {"rms": float(np.sqrt(np.mean(err ** 2))), "max": float(np.max(np.abs(err))),
            "outside_band": float(np.mean(np.abs(err) > band)), "band_mean": float(np.mean(band))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="tuning,heldout3")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/mmgp-family-logs"))
    ap.add_argument("--json", type=Path, default=None, help="append one JSON line per lever here")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    print(f"{'set':9} {'lever':13} {'band (N*m)':>10} | {'band on: rms / max / out':>26} | "
          f"{'band off: rms / max / out':>26} | off/on")
    worst = {True: 0.0, False: 0.0}
    for set_name in args.sets.split(","):
        for case in family_cases(SETS[set_name], "lever", args.cache):
            res = {rb: target_errors(case.log, case.info["spec"], rb) for rb in (True, False)}
            for rb in res:
                worst[rb] = max(worst[rb], res[rb]["rms"])
            on, off = res[True], res[False]
            print(f"{set_name:9} {case.name:13} {on['band_mean']:10.3f} | "
                  f"{on['rms']:8.3f} / {on['max']:6.3f} / {on['outside_band']:5.2f} | "
                  f"{off['rms']:8.3f} / {off['max']:6.3f} / {off['outside_band']:5.2f} | "
                  f"{off['rms'] / max(on['rms'], 1e-12):6.1f}", flush=True)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps({"set": set_name, "case": case.name, "band_on": on, "band_off": off}) + "\n")
    print(f"worst RMS over levers: band on {worst[True]:.3f} N*m, band off {worst[False]:.3f} N*m")


if __name__ == "__main__":
    main()
