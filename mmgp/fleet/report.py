"""The fleet's ``report.html``: run figures, drift flags, every series' status, every log with
where its time came from, each log's findings, the trend plots embedded."""
from __future__ import annotations

from pathlib import Path

from ..evaluation.html import HtmlReport

_FLAGGED = ("drift", "appeared")
#: what each status means, said on the page (a status that was not compared must say so)
_STATUS_WORDS = {"steady": "every later log inside the baseline interval",
                 "drift": "a later log entirely outside the baseline interval",
                 "appeared": "found in no baseline log, found later",
                 "no baseline": "the robot has fewer logs than the baseline needs: nothing compared",
                 "not compared": "no log after the baseline found it: nothing compared"}


def _key_figures(summary: dict, drift: dict) -> dict:
    return {"logs": summary["n_logs"], "failed": summary["n_failed"],
            "logs timed by file mtime": sum(s["log_time_source"] == "mtime" for s in summary["logs"]),
            "engine": summary["engine"], "workers": summary["workers"], "wall time [s]": summary["seconds"],
            "of which starting Ray [s]": summary.get("ray_start_seconds"),
            "baseline logs per robot": drift["baseline_size"], "drifting series": drift["n_drifting"],
            "appeared series": drift["n_appeared"], "steady series": drift.get("n_steady"),
            "series without baseline": drift.get("n_no_baseline"),
            "series not compared": drift.get("n_not_compared")}


def _drift_rows(drift: dict) -> list[list]:
    rows = []
    for s in drift["series"]:
        if s["status"] not in _FLAGGED:
            continue
        base = s.get("baseline") or {}
        rows.append([s["status"], s["robot"], s["effect"], s["joint"], s["param"], s.get("first_log"),
                     s.get("first_value"), base.get("lo"), base.get("hi"), len(s.get("flagged_logs", []))])
    return rows


def _time_note(logs: list[dict]) -> str:
    """The log-time rule, and which logs fell back to their file's modification time."""
    text = ("A log's time is its metadata 'start_time' (ISO 8601 with offset; the legacy key 'log_time' is "
            "read too); without either, the file's modification time (source 'mtime'), which copying a file "
            "changes.")
    fell_back = [s["log"] for s in logs if s["log_time_source"] == "mtime"]
    if fell_back:
        text += (f" {len(fell_back)} of {len(logs)} log(s) have no time in their metadata and are placed by "
                 "mtime: " + ", ".join(fell_back[:10]) + (" ..." if len(fell_back) > 10 else "") + ".")
    return text


def _series_section(page: HtmlReport, drift: dict) -> None:
    words = "; ".join(f"{k}: {v}" for k, v in _STATUS_WORDS.items())
    page.section("Series", f"Every (robot, effect, joint, parameter) and its status ({words}).")
    without = drift.get("robots_without_baseline") or []
    if without:
        page.paragraph(f"No baseline for {', '.join(map(str, without))}: fewer than {drift['baseline_size']} "
                       "log(s) ran, so none of their series was judged (--baseline sets the number).")
    page.table(["status", "robot", "effect", "joint", "param", "reason"],
               [[s["status"], s["robot"], s["effect"], s["joint"], s["param"], s.get("reason")]
                for s in drift["series"]], kind="series")


def _findings_section(page: HtmlReport, summary: dict, findings: dict) -> None:
    page.section("Findings per log", "What the diagnosis found in each log, in log-time order (the "
                                     "explanation gives each value with its unit).")
    rows = []
    for s in sorted(summary["logs"], key=lambda s: (s["log_time"] or "", s["log"])):
        found = findings.get(s["log"])
        if s["error"] is not None:
            rows.append([s["log"], s["log_time"], "(failed)", None, s["error"]])
        elif not found:
            rows.append([s["log"], s["log_time"], "(none)", None, "no effect found"])
        for f in found or []:
            where = f.get("joint") if f.get("joint") is not None else f.get("link", (f.get("params") or {}).get("link"))
            rows.append([s["log"], s["log_time"], f["effect"], where, f.get("explanation")])
    page.table(["log", "log time", "effect", "where", "explanation"], rows, kind="findings")


def write_fleet_report(out_dir: str | Path, summary: dict, drift: dict, findings: dict | None = None) -> Path:
    """``out_dir/report.html``: the key figures of ``summary`` (fleet.json) and ``drift``
    (drift.json), the drifting and appeared series, every series' status, one row per log with
    its time source, each log's ``findings`` (log -> contract findings), the trend plots listed in
    ``summary["trends"]`` (files in ``out_dir/trends``) and both JSON documents. Returns the path."""
    out = Path(out_dir)
    page = HtmlReport("mmgp fleet", subtitle=f"{summary['n_logs']} log(s), {summary['n_failed']} failed")
    page.section("Key figures").key_figures(_key_figures(summary, drift))
    page.section("Drift flags", drift["rule"] + ".")
    rows = _drift_rows(drift)
    if rows:
        page.table(["status", "robot", "effect", "joint", "param", "first log", "first value", "baseline lo",
                    "baseline hi", "logs flagged"], rows, kind="drift")
    elif drift.get("n_steady"):
        page.paragraph("No parameter left its baseline interval and none appeared.")
    else:
        page.paragraph("Nothing was compared: no series has a baseline and a later log (see Series).")
    _series_section(page, drift)
    page.section("Logs", _time_note(summary["logs"])).table(
        ["log", "robot", "log time", "time source", "findings", "error", "seconds"],
        [[s["log"], s["robot"], s["log_time"], s["log_time_source"], s["n_findings"], s["error"], s["seconds"]]
         for s in summary["logs"]], kind="logs")
    _findings_section(page, summary, findings or {})
    trends = summary.get("trends") or []
    if trends:
        page.section("Trends", "Each effect's parameters over log time (UTC), with their units: value and "
                               "interval per log, the series' status in each panel's title, the baseline "
                               "interval shaded, drifting logs circled in red.")
        for name in trends:
            page.figure(out / "trends" / name, name)
    page.section("Summary").json(summary, "fleet").json(drift, "drift")
    return page.write(out / "report.html")
