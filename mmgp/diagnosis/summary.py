"""What an engineer reads first in a diagnosis: per joint, the held-out error of the nominal model
and of the model with the found physics, and what was found there, one line per finding with
its numbers, units and interval (``report.md`` and ``report.html`` open with it).

Joints are named as the URDF names them; findings on a link (a payload) or on the whole log (pushes,
mode switches, the re-identified body) are listed under the table.
"""
from __future__ import annotations

import numpy as np

from ..physics.effects import EFFECT_CLASSES

#: findings on the whole log, told by their explanation
WHOLE_LOG = ("external_disturbance", "mode_switch")
#: (stage, label) of the summary's error columns
COLUMNS = (("nominal", "nominal"), ("with_physics", "with the found physics"))


def _number(v) -> str:
    return f"{v:.3g}"


def _value(v, interval, unit: str) -> str | None:
    """A parameter's value with its unit and interval in words (None when not a number)."""
    tail = f" {unit}" if unit else ""
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        ci = (f" ({_number(interval[0])} to {_number(interval[1])})"
              if isinstance(interval, (list, tuple)) and len(interval) == 2 and None not in interval else "")
        return f"{_number(v)}{tail}{ci}"
    if isinstance(v, (list, tuple)) and v and all(isinstance(x, (int, float)) for x in v):
        return "[" + ", ".join(_number(x) for x in v) + "]" + tail
    if isinstance(v, str):
        return v
    return None


def finding_line(f: dict) -> str:
    """One finding in one line: its effect's name in words and each numeric parameter with its
    unit and interval, e.g. "Coulomb friction: tau_c 1.9 N*m (1.7 to 2.1)"."""
    cls = EFFECT_CLASSES.get(f["effect"])
    label = getattr(cls, "label", None) or f["effect"].replace("_", " ")
    units = getattr(cls, "units", {}) or {}
    ci = (f.get("evidence") or {}).get("params_interval") or {}
    parts = []
    for key, v in (f.get("params") or {}).items():
        if key == "link":
            continue
        text = _value(v, ci.get(key) if isinstance(ci, dict) else None, units.get(key, ""))
        if text is not None:
            parts.append(f"{key} {text}")
        elif isinstance(v, dict):
            parts.append(f"{key}: {len(v)} values (findings.json)")
    mode = f" in mode {f['mode']}" if f.get("mode") is not None else ""
    where = f" on {f['link']}" if f.get("link") else ""
    return f"{label}{where}{mode}" + (": " + ", ".join(parts) if parts else "")


def _affected(f: dict, joint_names: list) -> list[str]:
    """The joints a finding is listed under: its joint, and a coupled joint where it names one."""
    out = [f["joint"]] if f.get("joint") in joint_names else []
    other = (f.get("params") or {}).get("coupled_joint")
    return out + ([other] if other in joint_names and other not in out else [])


def joint_rows(findings: list, fit: dict, joint_names: list, withheld: list = ()) -> list[dict]:
    """Per joint: ``joint``, the held-out nMSE per stage of :data:`COLUMNS` (None where absent)
    and ``found`` (its findings' lines, then its ``withheld`` findings' marked "withheld": the
    engineer who reads the table alone still sees what was left out there)."""
    rows = []
    for j in joint_names:
        row = {"joint": j, **{s: fit.get(s, {}).get("nmse", {}).get(j) for s, _ in COLUMNS}}
        row["found"] = [finding_line(f) for f in findings if j in _affected(f, joint_names)]
        row["found"] += [f"withheld: {finding_line(f)}" for f in withheld if j in _affected(f, joint_names)]
        rows.append(row)
    return rows


def elsewhere(findings: list, joint_names: list) -> list[str]:
    """Lines of the findings that are on no joint: links, the whole model, the whole log."""
    return [f["explanation"] if f["effect"] in WHOLE_LOG else finding_line(f)
            for f in findings if not _affected(f, joint_names)]


def grouped(findings: list, joint_names: list) -> list[tuple[str, list[dict]]]:
    """(heading, findings) per joint with findings, in the URDF's order, then "elsewhere"."""
    out = [(j, [f for f in findings if j in _affected(f, joint_names)]) for j in joint_names]
    rest = [f for f in findings if not _affected(f, joint_names)]
    return [(j, fs) for j, fs in out if fs] + ([("elsewhere (links, the whole model, the whole log)", rest)]
                                               if rest else [])


def gp_worse_joints(fit: dict, joint_names: list) -> list[tuple[str, float, float]]:
    """(joint, with_physics_and_gp nMSE, with_physics nMSE) where the GP on the physics' residual
    predicts the held-out torque worse than the physics alone (by more than 10% and 0.001)."""
    gp = fit.get("with_physics_and_gp", {}).get("nmse", {})
    ph = fit.get("with_physics", {}).get("nmse", {})
    return [(j, gp[j], ph[j]) for j in joint_names
            if j in gp and j in ph and np.isfinite(gp[j]) and gp[j] > max(1.1 * ph[j], ph[j] + 1e-3)]


def gp_sentence(fit: dict, joint_names: list) -> str | None:
    """The sentence the report carries where the GP stage is worse than the physics alone."""
    worse = gp_worse_joints(fit, joint_names)
    if not worse:
        return None
    which = ", ".join(f"{j} ({_number(a)} vs {_number(b)})" for j, a, b in worse)
    return (f"On {which} the GP fitted on what the found physics leaves predicts the held-out torque worse "
            "than the physics alone: what is left there is noise or pushes the GP over-fits, so use the model "
            "with the found physics for those joints.")


def summary_markdown(findings: list, fit: dict, joint_names: list, withheld: list = ()) -> list[str]:
    """The report's opening section, as Markdown lines (``withheld``: :func:`joint_rows`)."""
    lines = ["## Summary", "", "Held-out normalised MSE per joint (time-block cross-validation; 0 is perfect, "
             "1 is the torque's own mean), nominal -> with the found physics, and what was found on each joint:",
             "", "| joint | " + " -> ".join(label for _, label in COLUMNS) + " | found |", "|---|---|---|"]
    for r in joint_rows(findings, fit, joint_names, withheld):
        err = " -> ".join("-" if r[s] is None else _number(r[s]) for s, _ in COLUMNS)
        lines.append(f"| {r['joint']} | {err} | {'; '.join(r['found']) or 'nothing'} |")
    other = elsewhere(findings, joint_names)
    if other:
        lines += ["", "Elsewhere:", ""] + [f"- {line}" for line in other]
    sentence = gp_sentence(fit, joint_names)
    return lines + ([""] + [sentence] if sentence else []) + [""]
