"""Where the diagnosis stands against a plain least-squares peer on FIGAROH's split and metric.

The peer: ordinary least squares, on FIGAROH's processed training states (6,000 samples evenly
spaced), of the same effect families without re-identifying the body: per joint Coulomb
friction, viscous friction, a torque offset and an armature (on TX40 also the motor-6 columns on
joints 5-6, ratio 1: the converter's encoder matrix), beside the nominal URDF's rigid body.
Ours: ``mmgp diagnose`` with default settings (``bench_figaroh.run``, reused when its output is
in ``--out``), scored as ``bench_figaroh`` scores it. Both are scored with each dry-friction law,
``tanh(dq / v_s)`` (the diagnosis's v_s, findings.json ``info.v_s``; the law it fits) and
``sign(dq)``, on FIGAROH's 240 validation samples, split into samples where some joint stands
still (|dq| < v_s) and the rest.

Then one ingredient at a time, swapped into the peer's fit (peer states at the diagnosis's
samples): the diagnosis's own states (Savitzky-Golay derivatives of the log), its parallel
low-pass, its valid-equation mask (rest left out), its robust (Huber then Tukey) weights (here
refitted without the learner's start), its per-joint weights, non-negativity, the other friction
law, its coupling ratio, the samples it flagged as pushes, and its chosen effect set; and all of
them at once, which reproduces the diagnosis's own refit.

Usage: python benchmarks/bench_figaroh_ceiling.py --out DIR [--robots tx40,tiago]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

import bench_figaroh as bf
from mmgp.evaluation.metrics import FIGAROH_ROWS, aggregate_rmse, figaroh_samples

KIND = {"coulomb_friction": "sign", "viscous_friction": "dq", "armature": "ddq", "torque_offset": "one"}


def peer_set(n: int, robot: str, ratio: float = 1.0) -> list:
    """The peer's effects: (kind, joint) per joint, and the TX40 motor-6 coupling."""
    s = [(k, j) for j in range(n) for k in ("sign", "dq", "one", "ddq")]
    return s + ([("cpl", 5, 4, ratio)] if robot == "tx40" else [])


def ours_set(findings: list, names: list) -> list:
    """The diagnosis's chosen effects in the peer's terms (others, such as a payload, left out)."""
    s = []
    for f in findings:
        if f["effect"] in KIND:
            s.append((KIND[f["effect"]], names.index(f["joint"])))
        elif f["effect"] == "coupled_transmission":
            p = f["params"]
            s.append(("cpl", names.index(f["joint"]), names.index(p["coupled_joint"]), p["ratio"]))
    return s


def columns(S: list, dq, ddq, v_s) -> np.ndarray:
    """(T, n, P) columns of the effects ``S``; dry friction tanh(dq / v_s) (v_s 0: sign)."""
    from mmgp.sim.inverse import smooth_sign

    T, n = dq.shape
    cols = []
    for key in S:
        if key[0] == "cpl":  # the motor turns with w = dq_k + c dq_m: its loss on k, c times on m
            _, k, m, c = key
            w = dq[:, k] + c * dq[:, m]
            for x in (smooth_sign(w, np.hypot(v_s[k], c * v_s[m])), w, ddq[:, k] + c * ddq[:, m]):
                e = np.zeros((T, n))
                e[:, k], e[:, m] = x, c * x
                cols.append(e)
            continue
        kind, j = key
        e = np.zeros((T, n))
        e[:, j] = {"sign": smooth_sign(dq[:, j], v_s[j]), "dq": dq[:, j], "one": 1.0, "ddq": ddq[:, j]}[kind]
        cols.append(e)
    return np.stack(cols, axis=2)


def nonneg_of(S: list) -> np.ndarray:
    return np.concatenate([[True] * 3 if k[0] == "cpl" else [k[0] != "one"] for k in S])


def fit(C, r, W=None, lowpass=None, nonneg=None) -> np.ndarray:
    """argmin sum_tj W (r - C theta)^2 over theta (P,), after ``lowpass`` on r and every column;
    ``nonneg`` (P,) bool: those coefficients >= 0."""
    if lowpass is not None:
        C, r = lowpass(C), lowpass(r)
    sw = np.sqrt(np.ones_like(r) if W is None else W)
    X, y = (C * sw[:, :, None]).reshape(-1, C.shape[2]), (r * sw).reshape(-1)
    keep = np.abs(X).sum(1) > 0
    if nonneg is None:
        return np.linalg.lstsq(X[keep], y[keep], rcond=None)[0]
    lb = np.where(nonneg, 0.0, -np.inf)
    return lsq_linear(X[keep], y[keep], bounds=(lb, np.inf), method="bvls").x


def diagnosis_problem(robot: str, folder: Path, urdf: Path):
    """The diagnosis's problem on the training log (states, filter, mask, robust weights of the
    whole library without the learner's start) and the log's rows of its samples."""
    import mmgp.diagnosis.stages as st
    from mmgp.data.differentiation import SavitzkyGolay
    from mmgp.data.logs import read_log
    from mmgp.physics.robot import load_robot

    path = bf.training_log(robot, folder, urdf)
    rob = load_robot(log_path=path)
    log = read_log(path, n_joints=len(rob.joint_names), joint_names=rob.joint_names)
    t_all = log.t
    log, n_full, smear = st.prepare_log(log, SavitzkyGolay(cv=True), 6000)
    prob = st.build_problem(log, rob, n_full, smear, effects=None, payload_links="auto", sign_noise_factor=3.0,
                            lowpass=True, rest_factor=1.0, n_folds=20)
    lib = st.fit_library(st.without_body(prob), prob.ctx, np.ones(len(prob.t), bool), relinearise=2)
    edge = 20 if robot == "tx40" else 0  # FIGAROH's TX40 partition drops 20 samples at each end
    return prob, lib.weights, np.searchsorted(t_all, prob.t - 1e-9) - edge, st.nominal_weights(prob)


class Validation:
    """FIGAROH's 240 validation samples, their nominal torque and the standstill split."""

    def __init__(self, val: dict, rm, v_s: np.ndarray):
        pick = figaroh_samples(len(val["q"]))
        self.q, self.dq, self.ddq, self.tau = (val[k][pick] for k in ("q", "dq", "ddq", "tau"))
        self.nominal, self.rest = rm.rnea(self.q, self.dq, self.ddq), (np.abs(self.dq) < v_s).any(1)

    def score(self, pred: np.ndarray) -> tuple:
        r = self.rest
        return (aggregate_rmse(self.tau, pred), aggregate_rmse(self.tau[~r], pred[~r]),
                aggregate_rmse(self.tau[r], pred[r]), np.sqrt(((pred - self.tau) ** 2).mean(0)))


def line(label: str, s: tuple) -> None:
    print(f"  {label:<58}{s[0]:8.3f}{s[1]:9.3f}{s[2]:8.3f}   " + " ".join(f"{x:5.2f}" for x in s[3]), flush=True)


def decomposition(robot, parts, prob, W_rob, rows, jw, V, S_ours, ratio, pushes, v_s, rm) -> None:
    """The swaps (module docstring), each scored with both friction laws."""
    F, n = parts["train"], V.tau.shape[1]
    pick = np.unique(np.linspace(20, len(F["q"]) - 21, 6000).astype(int))
    fig = {k: (F["q"][i], F["dq"][i], F["ddq"][i], F["tau"][i]) for k, i in (("F", pick), ("F@D", rows))}
    fig = {k: (dq, ddq, tau - rm.rnea(q, dq, ddq)) for k, (q, dq, ddq, tau) in fig.items()}
    fig["D"] = (prob.ctx.dq, prob.ctx.ddq, prob.tau - prob.ctx.tau_rbd)
    M, S_peer = prob.M, peer_set(n, robot)
    Wp = np.repeat((~pushes)[:, None].astype(float), n, axis=1)
    swaps = [("peer: FIGAROH states, 6000 samples", "F", S_peer, {}),
             ("  at the diagnosis's 6000 samples", "F@D", S_peer, {}),
             ("  + the diagnosis's states (SG derivatives)", "D", S_peer, {}),
             ("  + parallel low-pass", "F@D", S_peer, {"lowpass": prob.lowpass}),
             ("  + valid-equation mask (rest out)", "F@D", S_peer, {"W": M}),
             ("  + robust weights (x mask)", "F@D", S_peer, {"W": W_rob}),
             ("  + per-joint weights", "F@D", S_peer, {"W": np.broadcast_to(jw, M.shape)}),
             ("  + non-negative", "F@D", S_peer, {"nonneg": True}),
             (f"  + the coupling ratio {ratio:.3f}", "F@D", peer_set(n, robot, ratio), {}),
             (f"  + samples flagged as pushes out ({pushes.mean():.0%})", "F@D", S_peer, {"W": Wp}),
             ("  + the diagnosis's chosen effects", "F@D", S_ours, {}),
             ("all of the above (the diagnosis's refit)", "D", S_ours,
              {"lowpass": prob.lowpass, "W": W_rob * Wp * jw, "nonneg": True})]
    for law, vs in (("tanh(dq/v_s)", v_s), ("sign(dq)", np.zeros(n))):
        print(f"  -- fitted and scored with {law}")
        for label, data, S, kw in swaps:
            dq, ddq, r = fig[data]
            th = fit(columns(S, dq, ddq, vs), r, kw.get("W"), kw.get("lowpass"), nonneg_of(S) if kw.get("nonneg") else None)
            line(label, V.score(V.nominal + columns(S, V.dq, V.ddq, vs) @ th))


def run(robot: str, out: Path, folder: Path) -> None:
    import pandas as pd

    from mmgp.physics.robot import RobotModel

    r = bf.run(robot, folder, bf.TIAGO_URDF, out)
    d = Path(r["out"])
    doc = json.loads((d / "findings.json").read_text())
    names, v_s = r["joints"], np.asarray(doc["info"]["v_s"])
    urdf = bf.checked(bf.TX40_DIR / "tx40_mdh_modified.urdf") if robot == "tx40" else bf.checked(bf.TIAGO_URDF)
    rm = RobotModel.from_urdf(urdf, names)
    mass = bf.torso_lift_mass(urdf) if robot == "tiago" else None
    parts = {k: (bf.tx40_partition(rw) if robot == "tx40" else bf.tiago_partition(rw, mass))
             for k, rw in zip(("train", "val"), FIGAROH_ROWS[robot])}
    V = Validation(parts["val"], rm, v_s)
    print(f"\n{robot}: held-out aggregate error on FIGAROH's 240 validation samples ({V.rest.mean():.0%} with a joint "
          f"standing still, |dq| < v_s); FIGAROH's best {min(v for v in bf.FIGAROH_FIGURES[robot].values() if v):.3f}")
    print(f"  {'':<58}{'all':>8}{'moving':>9}{'still':>8}   per-joint RMS")
    line("nominal", V.score(V.nominal))
    for law, sign in (("tanh(dq/v_s)", False), ("sign(dq)", True)):
        line(f"mmgp diagnose, corrected.xml, {law}", V.score(bf.found_physics_torque(d, names, V.q, V.dq, V.ddq, sign)))
    S_ours = ours_set(doc["findings"], names)
    ratio = next((k[3] for k in S_ours if k[0] == "cpl"), 1.0)
    prob, W_rob, rows, jw = diagnosis_problem(robot, folder, urdf)
    labels = d / "labels.parquet"
    pushes = pd.read_parquet(labels)["disturbed"].to_numpy(bool) if labels.exists() else np.zeros(len(prob.t), bool)
    decomposition(robot, parts, prob, W_rob, rows, jw, V, S_ours, ratio, pushes, v_s, rm)


def main(argv=None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="tx40,tiago")
    ap.add_argument("--out", type=Path, required=True, help="the diagnoses (bench_figaroh's layout; reused when present)")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for robot in a.robots.split(","):
            run(robot.strip(), a.out, Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())
