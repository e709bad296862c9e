"""Baselines for disturbance detection, printed beside mmgp in the benchmarks.

- ``threshold_gp_labels``: one GP on everything, a sample is disturbed when its leave-one-out
  residual exceeds 3 predictive standard deviations on any joint.
- ``trimmed_gp_labels``: a robust GP by iterative trimming (fit, drop > 3 sigma, refit on the
  rest, predict everything), the classic least-trimmed-squares recipe applied to a GP. No
  maintained library offers a cheap Student-t GP regression in our dependency set (GPyTorch's
  Student-t likelihood needs a variational GP), so trimming is the robust baseline.
"""
from __future__ import annotations

import numpy as np

from mmgp.gp.exact import ExactGP


def threshold_gp_labels(X: np.ndarray, Y: np.ndarray, *, k_sigma: float = 3.0, seed: int = 0) -> np.ndarray:
    """Disturbed flags (T,) bool from one GP's LOO residuals. X (T, d), Y (T, n)."""
    Y = np.asarray(Y).reshape(len(Y), -1)
    gp = ExactGP(seed=seed).fit(X, Y)
    mean, std = gp.loo_predictive()
    mean, std = mean.reshape(Y.shape), std.reshape(Y.shape)
    return (np.abs(Y - mean) > k_sigma * std).any(1)


def trimmed_gp_labels(X: np.ndarray, Y: np.ndarray, *, k_sigma: float = 3.0, n_iter: int = 3,
                      seed: int = 0) -> np.ndarray:
    """Disturbed flags (T,) bool from an iteratively trimmed GP. X (T, d), Y (T, n)."""
    Y = np.asarray(Y).reshape(len(Y), -1)
    keep = np.ones(len(Y), bool)
    flags = np.zeros(len(Y), bool)
    for _ in range(n_iter):
        gp = ExactGP(seed=seed).fit(X[keep], Y[keep])
        mean, std = gp.predict(X, include_noise=True)
        mean, std = mean.reshape(Y.shape), std.reshape(Y.shape)
        flags = (np.abs(Y - mean) > k_sigma * std).any(1)
        if flags.all() or np.array_equal(~flags, keep):
            break
        keep = ~flags
    return flags
