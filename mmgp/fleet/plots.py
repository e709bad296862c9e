"""Trend plots: each effect's parameters over log time, one PNG per robot, effect and joint."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd


def _file_name(robot, effect, joint, taken: set) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{robot}__{effect}__{joint or 'log'}")
    name, i = f"{stem}.png", 1
    while name in taken:
        i += 1
        name = f"{stem}_{i}.png"
    taken.add(name)
    return name


def _baselines(drift_report: dict) -> dict:
    return {(s["robot"], s["effect"], s["joint"] or "", s["param"]): s["baseline"]
            for s in drift_report.get("series", []) if "baseline" in s}


def _panel(ax, g: pd.DataFrame, param: str, band: dict | None) -> None:
    t = g["log_time"].dt.tz_localize(None)
    has = np.isfinite(g["lo"]) & np.isfinite(g["hi"])
    err = np.vstack([(g["value"] - g["lo"]).where(has, 0.0), (g["hi"] - g["value"]).where(has, 0.0)])
    ax.errorbar(t, g["value"], yerr=err, fmt="o", ms=3, lw=0.8, capsize=2, color="C0", label="value, -+2 std")
    drift = g["drift"].astype(bool)
    if drift.any():
        ax.plot(t[drift], g["value"][drift], "o", ms=6, mfc="none", color="C3", label="drift")
        ax.axvline(t[drift].iloc[0], color="C3", ls="--", lw=0.8)
    if band is not None:
        ax.axhspan(band["lo"], band["hi"], color="0.85", zorder=0, label="baseline interval")
    ax.set_title(param, fontsize=9)
    ax.tick_params(axis="x", labelrotation=30, labelsize=7)
    ax.tick_params(axis="y", labelsize=7)


def plot_trends(table: pd.DataFrame, drift_report: dict, out_dir) -> list[str]:
    """Write ``out_dir/<robot>__<effect>__<joint>.png`` (one panel per parameter: value and
    interval per log over log time, the baseline interval shaded, drifting logs circled in red,
    a dashed line at the first); returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = table[table["error"].isna() & table["effect"].notna()]
    rows = rows.assign(_j=rows["joint"].fillna("")).sort_values("log_time", kind="stable")
    bands = _baselines(drift_report)
    names: list[str] = []
    for (robot, effect, joint), g in rows.groupby(["robot", "effect", "_j"], sort=True):
        params = list(dict.fromkeys(g["param"]))
        ncol = min(3, len(params))
        nrow = math.ceil(len(params) / ncol)
        fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.8 * nrow), squeeze=False)
        for ax, param in zip(axes.flat, params):
            _panel(ax, g[g["param"] == param], param, bands.get((robot, effect, joint, param)))
        for ax in axes.flat[len(params):]:
            ax.set_visible(False)
        axes.flat[0].legend(fontsize=7)
        fig.suptitle(f"{robot}: {effect}" + (f" on {joint}" if joint else ""), fontsize=10)
        fig.tight_layout()
        name = _file_name(robot, effect, joint, set(names))
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        names.append(name)
    return names
