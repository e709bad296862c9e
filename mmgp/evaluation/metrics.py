"""Classification and regression figures against ground truth."""
from __future__ import annotations

import numpy as np
import pandas as pd
from sklearn.metrics import adjusted_rand_score, precision_recall_fscore_support

# The source's figures (Haninger 2016, ch. 5; 1-DOF series-elastic actuator, 20 Hz):
# 192 of 235 unperturbed samples classified correctly, 14 of 92 perturbed samples missed.
SOURCE_FIGURES = {"unperturbed_correct": 192 / 235, "perturbed_missed": 14 / 92,
                  "unperturbed_n": 235, "perturbed_n": 92}

# The predictors `mmgp compare` scores, in table order, with the names tables and plots show.
COMPARE_LABELS = {"rigid_body": "rigid body only", "gp": "GP only", "rigid_body_gp": "rigid body + GP"}
# The predictors the held-out score of `mmgp train` compares (mmgp.evaluation.heldout), in table order.
HELDOUT_LABELS = {"model": "model", "rigid_body": "rigid body", "mean": "mean"}


def classification_figures(pred: pd.DataFrame, truth: pd.DataFrame) -> dict:
    """Figures of CONTRACT section 2 (``mmgp evaluate``).

    ``pred``: t, mode, disturbed (0/1); ``truth``: t, and ``disturbed`` (0/1/-1) and/or ``mode``,
    already aligned row by row with ``pred``. Ambiguous samples (disturbed == -1) are left out of
    every figure, including the mode index.
    """
    if len(pred) != len(truth):
        raise ValueError("predictions and truth must be aligned (same number of rows)")
    out: dict = {"n_samples": int(len(pred))}
    keep = np.ones(len(pred), bool)
    if "disturbed" in truth:
        d_true = truth["disturbed"].to_numpy().astype(int)
        keep = d_true != -1
        out["n_ambiguous_left_out"] = int((~keep).sum())
        out["n_judged"] = int(keep.sum())
        yt = d_true[keep]
        yp = pred["disturbed"].to_numpy().astype(int)[keep]
        out["accuracy"] = float((yt == yp).mean()) if len(yt) else float("nan")
        n_un, n_pert = int((yt == 0).sum()), int((yt == 1).sum())
        out["n_unperturbed"], out["n_perturbed"] = n_un, n_pert
        out["unperturbed_correct"] = float((yp[yt == 0] == 0).mean()) if n_un else float("nan")
        out["perturbed_missed"] = float((yp[yt == 1] == 0).mean()) if n_pert else float("nan")
        p, r, f, _ = precision_recall_fscore_support(yt, yp, average="binary", pos_label=1, zero_division=0)
        out["disturbed_precision"], out["disturbed_recall"], out["disturbed_f1"] = float(p), float(r), float(f)
    else:
        out["n_ambiguous_left_out"] = 0
        out["n_judged"] = int(len(pred))
    if "mode" in truth:
        out["mode_adjusted_rand_index"] = float(adjusted_rand_score(truth["mode"].to_numpy()[keep],
                                                                    pred["mode"].to_numpy()[keep]))
    return out


# FIGAROH's held-out figures (figaroh-examples, docs/development/log-cholesky-dataset-validation-2026-10-02.md,
# Pinocchio 3.7): aggregate torque RMS error on the validation rows (TIAGo mixes N and N*m), with
# their training / validation rows of each recording. None: the fit failed (TIAGo's SDP projection).
FIGAROH_FIGURES = {
    "tx40": {"nominal": 10.364936, "ols": 5.298469, "ols_sdp": 4.470204, "log_cholesky": 4.986377},
    "tiago": {"nominal": 3.865181, "ols": 1.518097, "ols_sdp": None, "log_cholesky": 1.410331},
}
FIGAROH_ROWS = {"tx40": ((0, 24750), (29250, 45000)), "tiago": ((921, 4149), (4736, 6791))}


def figaroh_samples(n: int, *, max_samples: int = 240, edge: int = 20) -> np.ndarray:
    """Indices of the samples FIGAROH scores in a processed partition of ``n`` samples: at most
    ``max_samples`` equally spaced (truncated to integers, repeats dropped), ``edge`` left out at
    each end."""
    if n < 2 * edge + 1:
        raise ValueError(f"a partition of {n} samples has none left between its {edge}-sample edges")
    return np.unique(np.linspace(edge, n - edge - 1, min(max_samples, n - 2 * edge)).astype(int))


def aggregate_rmse(tau: np.ndarray, tau_pred: np.ndarray) -> float:
    """FIGAROH's "held-out aggregate torque error": the root mean square of ``tau_pred - tau``
    (T, n) over every joint and sample together, in the torques' unit (N*m; N on a prismatic joint)."""
    tau, tau_pred = (np.asarray(x, dtype=np.float64) for x in (tau, tau_pred))
    if tau.shape != tau_pred.shape:
        raise ValueError(f"tau {tau.shape} and tau_pred {tau_pred.shape} must have the same shape")
    return float(np.sqrt(np.mean((tau_pred - tau) ** 2)))


def normalised_mse(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """Per-column MSE divided by the variance of the truth: (T, n) -> (n,). 1.0 = predicting the mean."""
    y_true = np.asarray(y_true, dtype=np.float64).reshape(len(y_true), -1)
    y_pred = np.asarray(y_pred, dtype=np.float64).reshape(len(y_pred), -1)
    var = y_true.var(0)
    return ((y_true - y_pred) ** 2).mean(0) / np.where(var > 0, var, 1.0)


def format_figures(fig: dict, *, with_source: bool = False) -> str:
    """Plain-text table of the figures, optionally beside the source's."""
    lines = [f"samples judged: {fig.get('n_judged')} (left out as ambiguous: {fig.get('n_ambiguous_left_out', 0)})"]
    if "unperturbed_correct" in fig:
        if with_source:
            lines.append(f"{'figure':<24}{'mmgp':>16}{'source (2016)':>20}")
            lines.append(f"{'unperturbed correct':<24}{fig['unperturbed_correct']:>16.3f}"
                         f"{SOURCE_FIGURES['unperturbed_correct']:>13.3f} (192/235)")
            lines.append(f"{'perturbed missed':<24}{fig['perturbed_missed']:>16.3f}"
                         f"{SOURCE_FIGURES['perturbed_missed']:>13.3f} (14/92)")
        else:
            lines.append(f"unperturbed correct: {fig['unperturbed_correct']:.3f} of {fig['n_unperturbed']}")
            lines.append(f"perturbed missed:    {fig['perturbed_missed']:.3f} of {fig['n_perturbed']}")
        lines.append(f"accuracy {fig['accuracy']:.3f}; disturbed precision {fig['disturbed_precision']:.3f}, "
                     f"recall {fig['disturbed_recall']:.3f}, F1 {fig['disturbed_f1']:.3f}")
    if "mode_adjusted_rand_index" in fig:
        lines.append(f"mode adjusted Rand index: {fig['mode_adjusted_rand_index']:.3f}")
    return "\n".join(lines)
