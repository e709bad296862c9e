"""Drift (wear) flags: a parameter whose interval leaves the range it had in a robot's first logs.

Rule. Per robot, the *baseline* is its first ``k`` logs in log-time order (logs that failed do
not count). For each (effect, joint, parameter) found in at least one baseline log, the baseline
interval is the envelope of the baseline logs' intervals, [min lo, max hi] (the pooled range the
parameter took across those logs, each log's own uncertainty included). A later log *drifts*
when its interval [lo, hi] lies entirely outside the baseline interval (lo > baseline hi, or
hi < baseline lo). The first such log is named. A parameter found in no baseline log but in a
later one is listed as *appeared* (an effect that was not there, or too small to be found).
Rows without an interval (training rows, parameters without a standard deviation) are not judged.

Only a comparison earns ``steady`` or ``drift``. A robot with fewer than ``k`` logs that ran has
no baseline yet: its series are ``no baseline`` (all its logs are baseline logs, nothing comes
after them). A series with a complete baseline but no later log that found the parameter is
``not compared``. Both say why in ``reason``.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

KEYS = ["robot", "effect", "joint", "param"]
RULE = ("baseline = each robot's first {k} logs by log time; baseline interval = [min lo, max hi] over "
        "the baseline logs where the parameter was found (lo/hi = value -+ 2 std); a later log drifts "
        "when its [lo, hi] lies entirely outside the baseline interval; a robot with fewer than {k} logs "
        "has no baseline and none of its series is judged")
#: every status a series can have; only the first two are the result of a comparison
STATUSES = ("steady", "drift", "appeared", "no baseline", "not compared")


def _iso(ts) -> str | None:
    return None if pd.isna(ts) else pd.Timestamp(ts).isoformat()


def baseline_logs(table: pd.DataFrame, k: int) -> dict[str, list[str]]:
    """Per robot, its first ``k`` logs that ran without error (log-time order, then path)."""
    ok = table[table["error"].isna()].drop_duplicates("log").sort_values(["log_time", "log"], kind="stable")
    return {str(robot): list(g["log"].iloc[:k]) for robot, g in ok.groupby("robot", sort=True)}


def _band(rows: pd.DataFrame) -> dict:
    """The baseline interval of one series: its baseline logs and [min lo, max hi]."""
    return {"logs": list(rows["log"]), "lo": float(rows["lo"].min()), "hi": float(rows["hi"].max())}


def _unjudged(g: pd.DataFrame, robot: str, n_ok: int, k: int) -> dict:
    """The entry of a series whose robot has no complete baseline."""
    key = {c: (None if pd.isna(v) else v) for c, v in zip(KEYS, g.iloc[0][KEYS])}
    return dict(key, status="no baseline", n_logs=int(g["log"].nunique()),
                reason=f"robot {robot} has {n_ok} log(s) that ran; the baseline needs {k}, and a later log "
                       "to compare with it")


def _judge(g: pd.DataFrame, base: list[str], n_ok: int) -> tuple[dict, pd.Index]:
    """One series (rows of one robot, effect, joint, param in time order) of a robot with
    ``n_ok`` logs that ran: its drift.json entry and the index of its drifting rows."""
    key = {k: (None if pd.isna(v) else v) for k, v in zip(KEYS, g.iloc[0][KEYS])}
    in_base = g["log"].isin(base)
    later = g[~in_base]
    if later.empty:  # the baseline logs alone: nothing to compare them with
        why = (f"all {n_ok} logs of the robot are baseline logs: none comes after them" if n_ok <= len(base)
               else "no log after the baseline found this parameter")
        return dict(key, status="not compared", reason=why, baseline=_band(g[in_base])), g.index[:0]
    if not in_base.any():
        first = later.iloc[0]
        return dict(key, status="appeared", first_log=first["log"], first_log_time=_iso(first["log_time"]),
                    first_value=float(first["value"])), g.index[:0]
    band = _band(g[in_base])
    lo, hi = band["lo"], band["hi"]
    out = (later["lo"] > hi) | (later["hi"] < lo)
    flagged = later[out]
    entry = dict(key, status="drift" if len(flagged) else "steady", baseline=band, n_later_logs=int(len(later)),
                 flagged_logs=list(flagged["log"]))
    if len(flagged):
        first = flagged.iloc[0]
        entry.update(first_log=first["log"], first_log_time=_iso(first["log_time"]),
                     first_value=float(first["value"]), first_interval=[float(first["lo"]), float(first["hi"])],
                     direction="up" if first["lo"] > hi else "down")
    return entry, flagged.index


def flag_drift(table: pd.DataFrame, baseline: int = 5) -> tuple[pd.DataFrame, dict]:
    """Add the ``drift`` column (bool) to a copy of the fleet table and build ``drift.json``.

    ``baseline``: number of first logs per robot that define the baseline (>= 1). Returns
    ``(table, report)``; ``report["series"]`` has one entry per series with ``status`` ``steady``,
    ``drift`` (naming ``first_log``), ``appeared``, or, where nothing was compared, ``no baseline``
    or ``not compared`` (with the ``reason``)."""
    if baseline < 1:
        raise ValueError(f"baseline must be at least 1 log, got {baseline}")
    out = table.copy()
    out["drift"] = False
    judged = out[out["error"].isna() & out["effect"].notna() & np.isfinite(out["lo"]) & np.isfinite(out["hi"])]
    bases = baseline_logs(out, baseline)
    n_ok = {str(r): int(g["log"].nunique()) for r, g in out[out["error"].isna()].groupby("robot")}
    series = []
    ordered = judged.assign(_j=judged["joint"].fillna("")).sort_values(["log_time", "log"], kind="stable")
    for _, g in ordered.groupby(["robot", "effect", "_j", "param"], sort=True):
        robot = str(g["robot"].iloc[0])
        base = bases.get(robot, [])
        if len(base) < baseline:
            series.append(_unjudged(g.drop(columns="_j"), robot, len(base), baseline))
            continue
        entry, drifting = _judge(g.drop(columns="_j"), base, n_ok.get(robot, 0))
        out.loc[drifting, "drift"] = True
        series.append(entry)
    count = {s: sum(e["status"] == s for e in series) for s in STATUSES}
    report = {"rule": RULE.format(k=baseline), "baseline_size": baseline, "baseline_logs": bases,
              "robots_without_baseline": sorted(r for r, logs in bases.items() if len(logs) < baseline),
              "n_drifting": count["drift"], "n_appeared": count["appeared"], "n_steady": count["steady"],
              "n_no_baseline": count["no baseline"], "n_not_compared": count["not compared"], "series": series}
    return out, report
