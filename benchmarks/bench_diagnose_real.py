"""Diagnosis on real robots next to a peer identification on the same held-out split.

For the real Panda (Gaz et al. RA-L 2019), Staubli TX40 and TIAGo logs of
``/work/shared/datasets`` (converted by ``mmgp.convert``), prints the held-out normalised MSE per
joint of the diagnosis' three stages (nominal, with physics, with physics and GP) and of the
peer: plain weighted least squares on the base inertial parameters (the same QR base the
diagnosis uses) plus Coulomb and viscous friction on every joint, joints weighted by their
inverse residual variance (the classic identification recipe; FIGAROH's own pipeline is that
recipe plus its excitation design). The peer is fitted and scored on exactly the diagnosis'
time blocks, samples and valid equations, on the same low-passed residual. For the Panda it also
prints the Coulomb level found per joint beside Gaz et al.'s Coulomb-equivalent level.

Usage: python benchmarks/bench_diagnose_real.py [--logs panda,tx40,tiago] [--out DIR] [--coupling]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mmgp.diagnosis import Diagnoser
from mmgp.diagnosis import stages as st
from mmgp.diagnosis.selection import FoldGrams
from mmgp.physics.effects import build_atoms

ROOT = Path("/work/shared/datasets")
LOGS = {"panda": "panda_gaz2019", "tx40": "staubli_tx40_figaroh", "tiago": "tiago_figaroh"}
# Gaz et al. 2019 friction: A / (1 + exp(-alpha (dq + phi))) - ..., a jump of A between directions
GAZ_A = np.array([0.54615, 0.87224, 0.64068, 1.2794, 0.83904, 0.30301, 0.56489])


def convert_log(name: str, tmp: Path) -> Path:
    from mmgp.convert import convert

    # the converter also writes the files a log names beside it (the TX40's URDF)
    return next(Path(p) for p in convert(ROOT / LOGS[name], tmp / f"{LOGS[name]}.parquet")
                if str(p).endswith(".parquet"))


def peer_errors(d: Diagnoser, log, robot, coupling: bool = False) -> tuple[dict, list[str]]:
    """Held-out normalised MSE per joint of the WLS peer, on the diagnosis' own problem; with
    ``coupling``, also lines on the peer plus a coupled transmission on each adjacent pair."""
    log_p, n_full, smear = st.prepare_log(log, d._differentiator(), d.max_samples)
    prob = st.build_problem(log_p, robot, n_full, smear, effects=d.effects, payload_links=d.payload_links,
                            n_folds=d.n_folds, sign_noise_factor=d.sign_noise_factor, lowpass=d.lowpass,
                            rest_factor=d.rest_factor)
    if not np.array_equal(prob.t, d.labels_["t"] if d.labels_ is not None else prob.t):
        raise RuntimeError("the peer's samples differ from the diagnosis' samples")
    use = np.ones(len(prob.t), bool) if d.labels_ is None else d.labels_["disturbed"] == 0
    effects = [e for e in prob.library if e.name in ("inertial_parameters", "coulomb_friction", "viscous_friction")]
    _, A = build_atoms(effects, prob.ctx)
    nm = wls_nmse(prob, use, A)
    return dict(zip(prob.ctx.joint_names, nm.tolist())), (coupling_scan(prob, use, A, nm) if coupling else [])


def wls_nmse(prob, use: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Held-out nMSE (n,) of weighted least squares on the columns A (T, n, P): joints weighted
    by the inverse variance of an unweighted fit's residual, fitted and scored per time block."""
    A = prob.lowpass(A)
    S = list(range(A.shape[2]))
    g_ols = FoldGrams(A, prob.r, use, prob.folds, W=prob.M)
    w = st.joint_weights((prob.r - A @ g_ols.fit(S, np.ones(prob.ctx.n)))[use], prob.M[use])
    thetas = [g_ols.fit(S, w, k) for k in range(g_ols.K)]
    sq = g_ols.test_errors(S, thetas).sum(0)
    return sq / g_ols.nte.sum(0) / st.torque_variance(prob, use)


def coupled_transmission(ctx, j: int, c: float) -> np.ndarray:
    """Columns (T, n, 3) of a motor whose rotor turns with v = dq[j+1] + c dq[j] (a coupled
    wrist): its Coulomb friction tanh(v / v_s), viscous friction v and rotor inertia dv/dt, acting
    on joint j+1 and, by virtual work, c times on joint j."""
    v = ctx.dq[:, j + 1] + c * ctx.dq[:, j]
    dv = ctx.ddq[:, j + 1] + c * ctx.ddq[:, j]
    cols = np.zeros((ctx.T, ctx.n, 3))
    for p, f in enumerate((np.tanh(v / ctx.v_s[j + 1]), v, dv)):
        cols[:, j, p], cols[:, j + 1, p] = c * f, f
    return cols


def coupling_scan(prob, use: np.ndarray, A: np.ndarray, base: np.ndarray) -> list[str]:
    """The peer plus one coupled transmission, each adjacent pair and ratio c = +-1: a line per
    pair and ratio, its joints' held-out nMSE beside the peer's."""
    ctx, lines = prob.ctx, []
    for j in range(ctx.n - 1):
        for c in (1.0, -1.0):
            nm = wls_nmse(prob, use, np.concatenate([A, coupled_transmission(ctx, j, c)], 2))
            pair = f"{ctx.joint_names[j]}-{ctx.joint_names[j + 1]}"
            lines.append(f"  coupled transmission {pair}, c {c:+.0f}: joint {j} {base[j]:.4f} -> {nm[j]:.4f}, "
                         f"joint {j + 1} {base[j + 1]:.4f} -> {nm[j + 1]:.4f}; others' mean "
                         f"{np.delete(base, [j, j + 1]).mean():.4f} -> {np.delete(nm, [j, j + 1]).mean():.4f}")
    return lines


def run(name: str, tmp: Path, out: Path | None, coupling: bool = False) -> dict:
    from mmgp.data.logs import read_log
    from mmgp.physics.robot import load_robot

    path = convert_log(name, tmp)
    robot = load_robot(log_path=path)
    log = read_log(path, joint_names=robot.joint_names)
    t0 = time.perf_counter()
    d = Diagnoser(plots=out is not None).fit(log, robot)
    sec = time.perf_counter() - t0
    if out is not None:
        d.report(out / name)
    peer, coupled = peer_errors(d, log, robot, coupling)
    stages = {k: v["nmse"] for k, v in d.fit_stages_.items() if isinstance(v, dict)}
    stages["peer_wls"] = peer
    names = list(peer)
    print(f"\n{name} ({LOGS[name]}, {log.n_samples} samples, diagnosis {sec:.0f} s)")
    print("  findings: " + "; ".join(f"{f['effect']}@{f.get('joint') or f.get('link')}" for f in d.findings_))
    for w in d.result_.warnings:
        print("  WARNING:", w)
    print(f"  {'held-out nMSE':<22}" + "".join(f"{j[-12:]:>13}" for j in names))
    for k, v in stages.items():
        print(f"  {k:<22}" + "".join(f"{v[j]:13.4f}" for j in names))
    for k in ("with_physics", "with_physics_and_gp"):
        if k in stages:
            nom = sum(stages[k][j] < stages["nominal"][j] for j in names)
            beat = sum(stages[k][j] < peer[j] for j in names)
            print(f"  {k}: beats nominal on {nom}/{len(names)} joints, beats the peer on {beat}/{len(names)}")
    print("\n".join(coupled), end="\n" if coupled else "", flush=True)
    row = {"log": name, "seconds": sec, "stages": stages, "findings": d.findings_, "warnings": d.result_.warnings}
    if name == "panda":
        row["friction"] = panda_friction(d.findings_, names)
    return row


def panda_friction(findings: list, names: list) -> dict:
    """Coulomb level per joint against Gaz et al.'s Coulomb-equivalent level A/2."""
    ours = np.full(len(names), np.nan)
    for f in findings:
        if f["effect"] in ("coulomb_friction", "load_dependent_friction") and f.get("joint") in names:
            ours[names.index(f["joint"])] = f["params"]["tau_c"]
    ref = GAZ_A / 2
    rel = np.abs(ours - ref) / ref
    ok = int(np.sum(rel <= 0.25))
    print("  Coulomb level ours      :", np.array2string(ours, precision=3))
    print("  Gaz et al. A/2          :", np.array2string(ref, precision=3))
    print(f"  friction found on {int(np.isfinite(ours).sum())}/7 joints, within 25% of Gaz on {ok}/7")
    return {"ours": ours.tolist(), "gaz": ref.tolist(), "within_25pct": ok}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", default="panda,tx40,tiago")
    ap.add_argument("--out", type=Path, default=None, help="write each diagnosis' report here")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--coupling", action="store_true",
                    help="also score the peer plus a coupled transmission on each adjacent joint pair")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run(name, Path(tmp), a.out, a.coupling) for name in a.logs.split(",")]
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
