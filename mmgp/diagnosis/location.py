"""Where the nominal residual concentrates: per joint, the region of the trajectory whose
residual RMS is largest relative to the joint's overall residual RMS."""
from __future__ import annotations

import numpy as np


def locate(r: np.ndarray, q, dq, ddq, tau, tau_rbd, t, v_s, joint_names) -> dict:
    """Where the residual ``r`` (T, n) concentrates, per joint: the region (of five candidates:
    near-zero velocity, high load, a position quintile, high acceleration, a time fifth) whose
    residual RMS is largest relative to the joint's overall residual RMS. ``fraction_of_torque_rms``
    is the residual RMS over the measured torque's (``tau``): the nominal torque's can be ~0 (a
    joint the model gives no load), and the share then reads absurdly large."""
    out = {}
    T = r.shape[0]
    for j, jn in enumerate(joint_names):
        rj = r[:, j]
        rms = float(np.sqrt(np.mean(rj ** 2))) + 1e-300
        regions = {}
        slow = np.abs(dq[:, j]) < 2 * v_s[j]
        if 20 <= slow.sum() <= T - 20:
            regions["near zero velocity (|dq| < 2 v_s)"] = slow
        hi = np.abs(tau_rbd[:, j]) > np.quantile(np.abs(tau_rbd[:, j]), 0.8)
        regions["high load (top 20% |tau_rbd|)"] = hi
        acc = np.abs(ddq[:, j]) > np.quantile(np.abs(ddq[:, j]), 0.8)
        regions["high acceleration (top 20% |ddq|)"] = acc
        qe = np.quantile(q[:, j], [0, .2, .4, .6, .8, 1])
        for a, b in zip(qe[:-1], qe[1:]):
            regions[f"q in [{a:.2f}, {b:.2f}] rad"] = (q[:, j] >= a) & (q[:, j] <= b)
        te = np.linspace(0, T, 6).astype(int)
        for a, b in zip(te[:-1], te[1:]):
            m = np.zeros(T, bool)
            m[a:b] = True
            regions[f"t in [{t[a]:.1f}, {t[b - 1]:.1f}] s"] = m
        ratios = {k: float(np.sqrt(np.mean(rj[m] ** 2)) / rms) for k, m in regions.items() if m.any()}
        where = max(ratios, key=ratios.get)
        out[jn] = {"rms": rms, "fraction_of_torque_rms": rms / (float(np.sqrt(np.mean(tau[:, j] ** 2))) + 1e-12),
                   "where": where, "ratio": ratios[where], "regions": ratios}
    return out
