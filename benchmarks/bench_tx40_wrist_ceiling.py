"""How low can any model take the real TX40's wrist error on FIGAROH's validation rows?

Issue 30 asks for held-out nMSE < 0.05 on wrist joints 5 and 6 of the real TX40 (FIGAROH's
validation rows 29250:45000, nMSE = MSE over the variance of the measured torque, every sample
between the edges, as ``bench_figaroh.score``'s ``nmse_all``). This script measures the ceiling
of that line, on FIGAROH's processed partitions (``bench_figaroh.tx40_partition``), four ways:

1. **Noise floor**: the part of each joint's measured torque no function of the state can
   predict, estimated from the torque alone: the variance of its second difference / 6 (white
   noise's; smooth torque contributes ~nothing at 5 kHz), over the torque's variance.
2. **Physics, trained on the training rows** (0:24750, the realistic ceiling of what a diagnosis
   can name): ordinary least squares of the whole library at once: the rigid body's 60 inertial
   columns (Pinocchio's regressor; least squares takes the base combination), per joint Coulomb
   ``tanh(dq / v_s)``, viscous, offset and armature, the motor-6 coupling on joints 5-6 (ratio 1,
   the encoder matrix's), with v_s the diagnosis's rule (3 x the velocity's difference noise).
3. **The same library fitted on the validation rows themselves** (in-sample: an oracle no
   held-out model can beat with these physics), also with the torque shifted against the states
   by up to +-20 ms (a lag between current and the zero-phase filtered states).
4. **A black box**: scikit-learn's HistGradientBoostingRegressor per joint on (q, dq, ddq) of all
   joints plus the nominal torque, trained on the training rows, and (oracle) trained on the
   odd tenths of the validation rows and scored on the even tenths.

Printed per joint: nominal, each ceiling, and the diagnosis's figure from the last
``bench_figaroh`` run (benchmarks/README: 0.258 / 0.183 on joints 5 / 6).

Usage: python benchmarks/bench_tx40_wrist_ceiling.py
"""
from __future__ import annotations

import sys

import numpy as np

import bench_figaroh as bf
from bench_figaroh_ceiling import columns, peer_set
from mmgp.evaluation.metrics import FIGAROH_ROWS, normalised_mse


def noise_floor(tau: np.ndarray) -> np.ndarray:
    """(n,) white-noise variance of each column (second difference / 6) over its variance."""
    return np.diff(tau, 2, axis=0).var(0) / 6.0 / tau.var(0)


def regressor(rm, q, dq, ddq, stride: int) -> np.ndarray:
    """(T', n, 60) Pinocchio joint-torque regressor of every ``stride``-th sample."""
    import pinocchio as pin

    data = rm.pin_model.createData()
    return np.stack([pin.computeJointTorqueRegressor(rm.pin_model, data, rm.configuration(q[i]), dq[i], ddq[i]).copy()
                     for i in range(0, len(q), stride)])


def library(rm, part, v_s, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """(columns (T', n, P), torque minus nominal (T', n)) on every ``stride``-th sample."""
    q, dq, ddq, tau = (part[k][::stride] for k in ("q", "dq", "ddq", "tau"))
    # per joint Coulomb tanh(dq / v_s), viscous, offset, armature, and the motor-6 coupling (ratio 1)
    C = np.concatenate([regressor(rm, q, dq, ddq, 1), columns(peer_set(dq.shape[1], "tx40"), dq, ddq, v_s)], axis=2)
    return C, tau


def lstsq(C: np.ndarray, y: np.ndarray) -> np.ndarray:
    X, t = C.reshape(-1, C.shape[2]), y.reshape(-1)
    scale = np.maximum(np.abs(X).max(0), 1e-12)
    return np.linalg.lstsq(X / scale, t, rcond=1e-10)[0] / scale


def lag_scan(C: np.ndarray, tau: np.ndarray, shifts=(-100, -50, -20, -10, 10, 20, 50, 100)) -> dict:
    """In-sample fits of the library with the torque shifted by each of ``shifts`` samples
    against the states (0.2 ms each): the best per joint, if a lag between the current and the
    filtered states were what the wrists miss."""
    best = np.full(tau.shape[1], np.inf)
    for s in shifts:
        Cs, ys = (C[:-s], tau[s:]) if s > 0 else (C[-s:], tau[:s])
        best = np.minimum(best, normalised_mse(ys, Cs @ lstsq(Cs, ys)))
    return {f"  same, torque shifted {min(shifts)}..{max(shifts)} samples, best per joint": best}


def black_box(train: dict, val: dict, nominal_tr, nominal_va) -> np.ndarray:
    from sklearn.ensemble import HistGradientBoostingRegressor

    def feats(p, nom):
        return np.column_stack([p["q"], p["dq"], p["ddq"], nom])

    Xtr, Xva = feats(train, nominal_tr), feats(val, nominal_va)
    pred = np.zeros_like(val["tau"])
    for j in range(val["tau"].shape[1]):
        m = HistGradientBoostingRegressor(max_iter=300, random_state=0).fit(Xtr, train["tau"][:, j])
        pred[:, j] = m.predict(Xva)
    return pred


def main() -> int:
    from mmgp.data.statistics import difference_noise_sd
    from mmgp.physics.robot import RobotModel

    urdf = bf.checked(bf.TX40_DIR / "tx40_mdh_modified.urdf")
    names = [f"joint_{i}" for i in range(1, 7)]
    rm = RobotModel.from_urdf(urdf, names)
    tr, va = (bf.tx40_partition(r) for r in FIGAROH_ROWS["tx40"])
    inner = np.arange(20, len(va["q"]) - 20)
    va = {k: v[inner] for k, v in va.items()}
    v_s = 3.0 * difference_noise_sd(tr["dq"])
    nom_va = rm.rnea(va["q"], va["dq"], va["ddq"])
    rows = {"nominal": normalised_mse(va["tau"], nom_va), "noise floor": noise_floor(va["tau"])}

    C_tr, y_tr = library(rm, tr, v_s, stride=4)
    C_va, y_va = library(rm, va, v_s, stride=1)
    th = lstsq(C_tr, y_tr)
    rows["physics library, trained on training rows"] = normalised_mse(va["tau"], C_va @ th)
    th_in = lstsq(C_va, y_va)
    rows["physics library, fitted on the validation rows"] = normalised_mse(va["tau"], C_va @ th_in)
    rows.update(lag_scan(C_va, y_va))

    nom_tr = rm.rnea(tr["q"], tr["dq"], tr["ddq"])
    rows["gradient boosting, trained on training rows"] = normalised_mse(va["tau"], black_box(tr, va, nom_tr, nom_va))
    tenth = (np.arange(len(inner)) * 10 // len(inner)) % 2 == 1
    half = {k: v[tenth] for k, v in va.items()}
    other = {k: v[~tenth] for k, v in va.items()}
    rows["gradient boosting, validation odd tenths -> even tenths"] = normalised_mse(
        other["tau"], black_box(half, other, nom_va[tenth], nom_va[~tenth]))

    print(f"TX40 held-out nMSE per joint on FIGAROH's validation rows ({len(inner)} samples); line: joints 5, 6 < 0.05")
    print(f"  {'':<58}" + "".join(f"{n:>9}" for n in names))
    for label, v in rows.items():
        print(f"  {label:<58}" + "".join(f"{x:9.4f}" for x in v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
