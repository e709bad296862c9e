"""The fleet's ``report.html``: run figures, drift flags, every log, the trend plots embedded."""
from __future__ import annotations

from pathlib import Path

from ..evaluation.html import HtmlReport

_FLAGGED = ("drift", "appeared")


def _key_figures(summary: dict, drift: dict) -> dict:
    return {"logs": summary["n_logs"], "failed": summary["n_failed"], "engine": summary["engine"],
            "workers": summary["workers"], "wall time [s]": summary["seconds"],
            "of which starting Ray [s]": summary.get("ray_start_seconds"),
            "baseline logs per robot": drift["baseline_size"], "drifting series": drift["n_drifting"],
            "appeared series": drift["n_appeared"]}


def _drift_rows(drift: dict) -> list[list]:
    rows = []
    for s in drift["series"]:
        if s["status"] not in _FLAGGED:
            continue
        base = s.get("baseline") or {}
        rows.append([s["status"], s["robot"], s["effect"], s["joint"], s["param"], s.get("first_log"),
                     s.get("first_value"), base.get("lo"), base.get("hi"), len(s.get("flagged_logs", []))])
    return rows


def write_fleet_report(out_dir: str | Path, summary: dict, drift: dict) -> Path:
    """``out_dir/report.html``: the key figures of ``summary`` (fleet.json) and ``drift``
    (drift.json), the drifting and appeared series, one row per log, the trend plots listed in
    ``summary["trends"]`` (files in ``out_dir/trends``) and both JSON documents. Returns the path."""
    out = Path(out_dir)
    page = HtmlReport("mmgp fleet", subtitle=f"{summary['n_logs']} log(s), {summary['n_failed']} failed")
    page.section("Key figures").key_figures(_key_figures(summary, drift))
    page.section("Drift flags", drift["rule"] + ".")
    rows = _drift_rows(drift)
    if rows:
        page.table(["status", "robot", "effect", "joint", "param", "first log", "first value", "baseline lo",
                    "baseline hi", "logs flagged"], rows, kind="drift")
    else:
        page.paragraph("No parameter left its baseline interval and none appeared.")
    page.section("Logs").table(
        ["log", "robot", "log time", "time source", "findings", "error", "seconds"],
        [[s["log"], s["robot"], s["log_time"], s["log_time_source"], s["n_findings"], s["error"], s["seconds"]]
         for s in summary["logs"]], kind="logs")
    trends = summary.get("trends") or []
    if trends:
        page.section("Trends", "Each effect's parameters over log time: value and interval per log, the "
                               "baseline interval shaded, drifting logs circled in red.")
        for name in trends:
            page.figure(out / "trends" / name, name)
    page.section("Summary").json(summary, "fleet").json(drift, "drift")
    return page.write(out / "report.html")
