"""Plots of training results (matplotlib, Agg backend: no display needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.outputs import write_figure


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_labels(path: str | Path, t: np.ndarray, tau: np.ndarray, mode: np.ndarray, p_disturbed: np.ndarray,
                joint_names: list[str], max_joints: int = 7) -> None:
    """Torque against time per joint, coloured by mode; disturbed samples marked in red.

    t (T,), tau (T, n), mode (T,), p_disturbed (T,)."""
    plt = _plt()
    n = min(tau.shape[1], max_joints)
    fig, axes = plt.subplots(n + 1, 1, figsize=(11, 2.0 * (n + 1)), sharex=True, squeeze=False)
    axes = axes[:, 0]
    cmap = plt.get_cmap("tab10")
    dist = p_disturbed > 0.5
    for j in range(n):
        ax = axes[j]
        for k in np.unique(mode):
            sel = (mode == k) & ~dist
            ax.scatter(t[sel], tau[sel, j], s=4, color=cmap(int(k) % 10), label=f"mode {k}")
        ax.scatter(t[dist], tau[dist, j], s=10, marker="x", color="red", label="disturbed")
        ax.set_ylabel(f"{joint_names[j]}\n[N*m]", fontsize=8)
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[n].plot(t, p_disturbed, color="red", lw=1)
    axes[n].set_ylabel("p(disturbed)")
    axes[n].set_ylim(-0.05, 1.05)
    axes[n].set_xlabel("t [s]")
    fig.tight_layout()
    write_figure(path, fig, dpi=90)
    plt.close(fig)


def plot_trace(path: str | Path, trace: list[dict]) -> None:
    """Log joint and log marginal likelihood per sweep, and the fraction of labels changed."""
    plt = _plt()
    sweeps = [r["sweep"] for r in trace]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    a1.plot(sweeps, [r["log_joint"] for r in trace], "o-", ms=3, label="log p(Y, labels)")
    a1.plot(sweeps, [r["log_marginal"] for r in trace], "s-", ms=3, label="log p(Y)")
    a1.legend(fontsize=8)
    a1.set_ylabel("log likelihood")
    a2.plot(sweeps, [r["changed"] for r in trace], "o-", ms=3, color="gray")
    a2.set_ylabel("labels changed")
    a2.set_xlabel("sweep")
    fig.tight_layout()
    write_figure(path, fig, dpi=90)
    plt.close(fig)
