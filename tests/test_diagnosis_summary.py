"""The report an engineer reads first (mmgp.diagnosis.summary): per joint the held-out error
nominal -> with the found physics and the findings in one line each, with numbers, units and
intervals; findings grouped by joint; a sentence where the GP stage is worse than the physics.
Expected lines are written out by hand from the numbers put in."""
from __future__ import annotations

import re

from mmgp.diagnosis.result import DiagnosisResult

NAMES = ["j1", "j2", "j3"]


def _result() -> DiagnosisResult:
    coulomb = {"effect": "coulomb_friction", "joint": "j1", "params": {"tau_c": 1.9},
               "evidence": {"params_interval": {"tau_c": [1.7, 2.1]}},
               "explanation": "j1: Coulomb friction of 1.9 N*m is missing from the model."}
    viscous = {"effect": "viscous_friction", "joint": "j1", "params": {"b": 0.25},
               "evidence": {"params_interval": {"b": [0.2, 0.3]}}, "explanation": "j1: viscous friction."}
    spring = {"effect": "joint_spring", "joint": "j3", "params": {"k": 12.0, "q0": -0.1},
              "evidence": {"params_interval": {"k": [11.0, 13.5], "q0": None}}, "explanation": "j3: a spring."}
    payload = {"effect": "payload", "link": "tool", "joint": None, "params": {"link": "tool", "mass": 0.5,
                                                                             "com": [0.0, 0.01, 0.1]},
               "evidence": {"params_interval": {"mass": [0.45, 0.55]}}, "explanation": "link tool: a payload."}
    push = {"effect": "external_disturbance", "joint": None, "params": {"n_samples": 40, "fraction": 0.04},
            "evidence": {}, "explanation": "2 span(s) of unmodelled external force (40 samples, 4.0% of the log)."}
    fit = {"nominal": {"nmse": {"j1": 0.5, "j2": 0.02, "j3": 0.3}},
           "with_physics": {"nmse": {"j1": 0.01, "j2": 0.02, "j3": 0.0019}},
           "with_physics_and_gp": {"nmse": {"j1": 0.009, "j2": 0.02, "j3": 1.809}}}
    return DiagnosisResult(findings=[coulomb, viscous, spring, payload, push], fit=fit, location={},
                           joint_names=NAMES)


def test_the_summary_opens_the_report_with_numbers_units_and_intervals():
    md = _result().report_markdown()
    assert md.index("## Summary") < md.index("## Findings by joint") < md.index("## Held-out normalised MSE")
    rows = [ln for ln in md.splitlines() if ln.startswith("| j") and "->" in ln and "|---" not in ln][1:]
    assert rows[0] == ("| j1 | 0.5 -> 0.01 | Coulomb friction: tau_c 1.9 N*m (1.7 to 2.1); "
                       "viscous friction: b 0.25 N*m*s/rad (0.2 to 0.3) |")
    assert rows[1] == "| j2 | 0.02 -> 0.02 | nothing |"
    assert rows[2] == "| j3 | 0.3 -> 0.0019 | a joint spring: k 12 N*m/rad (11 to 13.5), q0 -0.1 rad |"
    assert "- a payload on tool: mass 0.5 kg (0.45 to 0.55), com [0, 0.01, 0.1] m" in md
    assert "- 2 span(s) of unmodelled external force (40 samples, 4.0% of the log)." in md
    # the GP stage worse than the physics alone on j3 (1.809 vs 0.0019), not on j1 (0.009 vs 0.01)
    gp = [ln for ln in md.splitlines() if "the GP fitted on what the found physics leaves" in ln]
    assert len(gp) == 1 and gp[0].startswith("On j3 (1.81 vs 0.0019) ")


def test_a_withheld_finding_is_marked_on_its_joints_row():
    import dataclasses

    offset = {"effect": "torque_offset", "joint": "j2", "params": {"offset": -3.5},
              "evidence": {"params_interval": {"offset": [-4.0, -3.1]}}, "explanation": "j2: an offset.",
              "withheld_because": "a stand-in for the rigid body"}
    md = dataclasses.replace(_result(), withheld=[offset]).report_markdown()
    row = next(ln for ln in md.splitlines() if ln.startswith("| j2 |"))
    assert row == "| j2 | 0.02 -> 0.02 | withheld: a torque-sensor offset: offset -3.5 N*m (-4 to -3.1) |"
    assert "- j2: an offset. (a stand-in for the rigid body)" in md


def test_findings_are_grouped_by_joint_in_the_urdf_order():
    md = _result().report_markdown()
    body = md[md.index("## Findings by joint"):md.index("## Held-out normalised MSE")]
    heads = re.findall(r"^### (.+)$", body, flags=re.M)
    assert heads == ["j1", "j3", "elsewhere (links, the whole model, the whole log)"]
    j1 = body[body.index("### j1"):body.index("### j3")]
    assert "Coulomb friction of 1.9" in j1 and "viscous friction" in j1 and "spring" not in j1


def test_the_html_summary_and_findings_tables(tmp_path):
    from html.parser import HTMLParser

    class Tables(HTMLParser):
        def __init__(self):
            super().__init__()
            self.tables, self._cell = {}, None

        def handle_starttag(self, tag, attrs):
            if tag == "table":
                self.kind = dict(attrs).get("class")
                self.tables[self.kind] = []
            elif tag == "tr":
                self.tables[self.kind].append([])
            elif tag in ("td", "th"):
                self._cell = ""

        def handle_data(self, data):
            if self._cell is not None:
                self._cell += data

        def handle_endtag(self, tag):
            if tag in ("td", "th"):
                self.tables[self.kind][-1].append(self._cell.strip())
                self._cell = None

    path = _result().report_html(tmp_path)
    parser = Tables()
    parser.feed(path.read_text())
    summary = parser.tables["summary"]
    assert summary[0] == ["joint", "nominal", "with the found physics", "found"]
    assert summary[3][0] == "j3" and summary[3][3] == "a joint spring: k 12 N*m/rad (11 to 13.5), q0 -0.1 rad"
    found = parser.tables["findings"]
    assert [r[0] for r in found[1:]] == ["j1", "j1", "j3"] + ["elsewhere (links, the whole model, the whole log)"] * 2
    assert found[1][1] == "Coulomb friction: tau_c 1.9 N*m (1.7 to 2.1)"
