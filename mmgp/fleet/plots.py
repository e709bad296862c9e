"""Trend plots: each effect's parameters over log time, one PNG per robot, effect and joint."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from ..data.outputs import write_figure


def _file_name(robot, effect, joint, taken: set) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{robot}__{effect}__{joint or 'log'}")
    name, i = f"{stem}.png", 1
    while name in taken:
        i += 1
        name = f"{stem}_{i}.png"
    taken.add(name)
    return name


def _series(drift_report: dict) -> dict:
    return {(s["robot"], s["effect"], s["joint"] or "", s["param"]): s for s in drift_report.get("series", [])}


#: least padding either side of the first and last log time: a single log (or copies sharing one
#: time) gets a two-hour axis, not matplotlib's default span of years around one date
MIN_PAD = pd.Timedelta(hours=1)


def _date_axis(ax, t: pd.Series) -> None:
    """A readable date axis: dates where they change, times below, limits around the logs."""
    import matplotlib.dates as mdates

    locator = mdates.AutoDateLocator(minticks=3, maxticks=7)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    pad = max((t.max() - t.min()) * 0.05, MIN_PAD)
    ax.set_xlim(t.min() - pad, t.max() + pad)
    ax.set_xlabel("log time (UTC)", fontsize=7)


def _panel(ax, g: pd.DataFrame, param: str, entry: dict | None) -> None:
    t = g["log_time"].dt.tz_convert("UTC").dt.tz_localize(None)
    has = np.isfinite(g["lo"]) & np.isfinite(g["hi"])
    err = np.vstack([(g["value"] - g["lo"]).where(has, 0.0), (g["hi"] - g["value"]).where(has, 0.0)])
    ax.errorbar(t, g["value"], yerr=err, fmt="o", ms=3, lw=0.8, capsize=2, color="C0", label="value, -+2 std")
    drift = g["drift"].astype(bool)
    if drift.any():
        ax.plot(t[drift], g["value"][drift], "o", ms=6, mfc="none", color="C3", label="drift")
        ax.axvline(t[drift].iloc[0], color="C3", ls="--", lw=0.8)
    band = (entry or {}).get("baseline")
    if band is not None:
        ax.axhspan(band["lo"], band["hi"], color="0.85", zorder=0, label="baseline interval")
    unit = g["unit"].iloc[0] if "unit" in g else None
    ax.set_ylabel(param if unit is None or pd.isna(unit) else f"{param} [{unit or '-'}]", fontsize=8)
    ax.set_title(f"{param}: {entry['status']}" if entry else param, fontsize=9)
    _date_axis(ax, t)
    ax.tick_params(axis="both", labelsize=7)


def trend_figure(g: pd.DataFrame, title: str, series: dict):
    """One figure of one robot, effect and joint: a panel per parameter of ``g`` (table rows),
    with its drift.json entry from ``series`` (keyed by param)."""
    import matplotlib.pyplot as plt

    params = list(dict.fromkeys(g["param"]))
    ncol = min(3, len(params))
    nrow = math.ceil(len(params) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.0 * nrow), squeeze=False)
    for ax, param in zip(axes.flat, params):
        _panel(ax, g[g["param"] == param], param, series.get(param))
    for ax in axes.flat[len(params):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_trends(table: pd.DataFrame, drift_report: dict, out_dir) -> list[str]:
    """Write ``out_dir/<robot>__<effect>__<joint>.png`` (one panel per parameter: value and
    interval per log over log time on a date axis, the unit on the y axis, the series' status in
    the title, the baseline interval shaded, drifting logs circled in red, a dashed line at the
    first); returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = table[table["error"].isna() & table["effect"].notna()]
    rows = rows.assign(_j=rows["joint"].fillna("")).sort_values("log_time", kind="stable")
    entries = _series(drift_report)
    names: list[str] = []
    for (robot, effect, joint), g in rows.groupby(["robot", "effect", "_j"], sort=True):
        series = {p: entries.get((robot, effect, joint, p)) for p in g["param"].unique()}
        fig = trend_figure(g, f"{robot}: {effect}" + (f" on {joint}" if joint else ""), series)
        name = _file_name(robot, effect, joint, set(names))
        write_figure(out / name, fig, dpi=90)
        plt.close(fig)
        names.append(name)
    return names
