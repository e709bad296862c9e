"""What a diagnosis tells: findings (CONTRACT section 2/3), the held-out error per stage, where
the residual concentrates, a Markdown report and residual plots."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..data.outputs import jsonable
from .corrected import corrected_markdown, write_corrected
from .plausibility import MIN_TORQUE_SHARE
from .summary import COLUMNS, WHOLE_LOG, finding_line, gp_sentence, grouped, joint_rows, summary_markdown

STAGES = ("nominal", "with_physics", "with_physics_and_gp")


def effect_finding(effect, params: dict, std: dict, evidence: dict, ctx, main_joint: int) -> dict:
    """A found effect per CONTRACT section 2: effect, joint or link, params, evidence, explanation
    (``main_joint``: the joint whose held-out error it cuts most)."""
    j = main_joint
    red = 100 * evidence["cv_error_reduction"]
    tail = (f"adding it cuts the held-out error on {ctx.joint_names[j]} by {red:.0f}%"
            if red > 0 else "it is kept by the selection rule although its own held-out gain is small")
    return {"effect": effect.name, **effect.where(ctx), "params": effect.report_params(params, ctx), "evidence": evidence,
            "explanation": f"{effect.describe(params, std, ctx)} is missing from the model; {tail}."}


def stand_in_finding(f: dict, reid: dict) -> dict:
    """Finding ``f`` withheld as the rigid body's stand-in (``Diagnoser._body_stand_ins``), in
    words an engineer can act on; ``reid`` the body's re-identification evidence."""
    where = f.get("joint") or f.get("link")
    red = 100 * f["evidence"]["cv_error_reduction"]
    return {**f, "explanation": (
        f"{where}: {finding_line(f)}. It would cut the held-out error on {where} by {red:.0f}%, but "
        f"re-identifying the rigid body explains the same torque, so it is not reported: the two differ only in "
        f"how the torque varies over the robot's poses; a log that moves {where} over a wider range, or the other "
        f"joints through more poses, tells them apart."),
        "withheld_because": (
            f"a stand-in for the rigid body: not chosen once the body is re-identified; the body itself is not "
            f"significant (held-out gain {reid['held_out_gain']:.1%}, p {reid['p_value']:.2g} against "
            f"{reid['level']:.2g}), so neither is reported")}


def mode_switch_finding(ms, ctx, *, alpha: float, n_folds: int) -> dict:
    """The ``mode_switch`` finding of a :class:`mmgp.diagnosis.modes.ModeSwitch`."""
    eff, d, pm = ms.effect, ms.test["d"], ms.per_mode
    first, unit = next(iter(eff.units.items()))
    where = next(iter(eff.where(ctx).values()))
    modes = [f"{m[first]:.3g} {unit} ({100 * m['fraction']:.0f}%{' of the time' if k == 0 else ''})"
             for k, m in enumerate(pm)]
    return {
        "effect": "mode_switch", "joint": None,
        "params": {"n_modes": 2, "per_mode": pm, "switch_times_s": ms.switch_times_s[:100]},
        "evidence": {"held_out_gain_per_fold": d.tolist(), "p_value": ms.test["p"],
                     "criterion": f"{n_folds}-fold time-block CV of one vs two {eff.name} modes (HMM predictive "
                                  "from a filter memory earlier, held-out blocks), one-sided Wilcoxon signed-rank "
                                  f"test, family-wise level {alpha:g} over {ms.n_tested} candidates"},
        "explanation": (f"the dynamics switch between two modes ({len(ms.switch_times_s)} switch(es)): "
                        f"{eff.label} on {where} of {modes[0]} and {modes[1]}; two modes cut the held-out error in "
                        f"{int((d > 0).sum())} of {len(d)} time blocks.")}


def mode_effect_findings(ms, ctx) -> list[dict]:
    """One finding of the switching effect per mode whose magnitude (its first parameter, e.g.
    the payload's mass) is above zero with 97.5% confidence (CONTRACT section 3: a payload per
    mode when it switches); a mode without one (the payload off) gives none."""
    eff = ms.effect
    first, unit = next(iter(eff.units.items()))
    out = []
    for k, pm in enumerate(ms.per_mode):
        ci = pm.get("interval") or {}
        if not (pm.get("present") and ci.get(first)):
            continue
        params = {key: v for key, v in pm.items() if key not in ("fraction", "interval", "present")}
        lo, hi = ci[first]
        out.append({"effect": eff.name, **eff.where(ctx), "mode": k, "params": params,
                    "evidence": {"mode": k, "fraction_of_time": pm["fraction"], "params_interval": ci,
                                 "interval_method": "block bootstrap of the mode's fit over the mode test's time "
                                                    "blocks, percentile"},
                    "explanation": f"in mode {k} ({100 * pm['fraction']:.0f}% of the time): "
                                   f"{next(iter(eff.where(ctx).values()))} carries {eff.label} of "
                                   f"{pm[first]:.3g} {unit} ({lo:.3g} to {hi:.3g})."})
    return out


def disturbance_finding(disturbed: np.ndarray, spans: list, evidence: dict) -> dict:
    """The ``external_disturbance`` finding: ``disturbed`` (T,) bool, ``spans`` in s."""
    return {"effect": "external_disturbance", "joint": None,
            "params": {"n_samples": int(disturbed.sum()), "fraction": float(disturbed.mean()), "spans_s": spans[:50]},
            "evidence": evidence,
            "explanation": f"{len(spans)} span(s) of unmodelled external force ({int(disturbed.sum())} "
                           f"samples, {100 * disturbed.mean():.1f}% of the log) were found and left out "
                           "of the effect fitting."}


@dataclass
class DiagnosisResult:
    """Findings (CONTRACT section 2), held-out fit per stage, residual locations.

    ``findings``: list of dicts with ``effect``, ``joint`` or ``link``, ``params``, ``evidence``,
    ``explanation``; ``fit``: {stage: {"nmse": {joint: value}, "mean_nmse": value}, "folds",
    "samples_used", "samples_excluded_as_disturbed", "still_joints", "still_worse_p" (with still
    joints: {joint: p} that the found physics predicts it worse than the nominal model and the
    mean)}; ``location``: per joint, where the nominal
    residual concentrates; ``labels``: per analysed sample {"t", "mode" (int), "disturbed"
    (0/1)} when modes or pushes were found; ``plot_data``: arrays for the residual plots;
    ``urdf``: the nominal URDF the diagnosis used (None: a robot given without one);
    ``corrected``: what :meth:`write` wrote of the corrected model (``corrected.write_corrected``).
    """

    findings: list
    fit: dict
    location: dict
    joint_names: list
    info: dict = field(default_factory=dict)
    plot_data: dict | None = field(default=None, repr=False)
    labels: dict | None = field(default=None, repr=False)
    warnings: list = field(default_factory=list)
    withheld: list = field(default_factory=list)
    urdf: str | None = None
    corrected: dict | None = None

    def to_dict(self) -> dict:
        out = {"findings": self.findings, "warnings": self.warnings, "withheld_findings": self.withheld,
               "fit": self.fit, "location": self.location, "info": self.info}
        return out if self.corrected is None else {**out, "corrected_model": self.corrected}

    def to_json(self, indent: int = 2) -> str:
        return json.dumps(jsonable(self.to_dict()), indent=indent)

    def report_markdown(self) -> str:
        effects = [f for f in self.findings if f["effect"] not in WHOLE_LOG]
        lines = ["# Sim-vs-real diagnosis", ""] + summary_markdown(self.findings, self.fit, self.joint_names, self.withheld)
        if self.warnings:
            lines += ["## Warnings", ""] + [f"- **{w}**" for w in self.warnings] + [""]
        if self.withheld:
            lines += ["## Withheld findings", ""]
            lines += [f"- {f['explanation']} ({f['withheld_because']})" for f in self.withheld] + [""]
        if not effects and self.warnings:
            lines.append("No finding is reported: the warnings above say what limits the numbers.")
        elif not effects:
            lines.append("Nothing is missing: no candidate effect improves the held-out (time-block "
                         "cross-validated) error significantly over the nominal model.")
            lines += [""] * bool(self.findings) + [f"- {f['explanation']}" for f in self.findings]
        else:
            lines += ["## Findings by joint"]
            for head, fs in grouped(self.findings, self.joint_names):
                lines += ["", f"### {head}", ""] + [f"- {f['explanation']}" for f in fs]
        lines += ["", "## Held-out normalised MSE per joint (time-block cross-validation)", "",
                  "| joint | " + " | ".join(STAGES) + " |", "|---|" + "---|" * len(STAGES)]
        for jn in self.joint_names:
            row = [f"{self.fit[s]['nmse'].get(jn, float('nan')):.4g}" if s in self.fit else "-" for s in STAGES]
            lines.append(f"| {jn} | " + " | ".join(row) + " |")
        lines += ["", "## Where the nominal residual concentrates", ""]
        for jn, loc in self.location.items():
            lines.append(f"- {jn}: residual RMS {loc['rms']:.3g} N*m ({100 * loc['fraction_of_torque_rms']:.1f}% "
                         f"of the torque RMS); largest in {loc['where']} ({loc['ratio']:.2f}x the overall RMS)")
        lines += ["", "## Method", "",
                  f"Candidates: {self.info.get('n_candidates')} effects. Forward selection on {self.info.get('n_folds')} "
                  "time blocks: an effect is added while its paired held-out gain is significant (one-sided "
                  "Wilcoxon signed-rank test over the blocks, Bonferroni over the candidates of each step; an "
                  "effect on one joint's torque is tested on that joint and on all joints, the smaller p doubled); "
                  f"a finding whose torque is under {100 * MIN_TORQUE_SHARE:g}% of its joint torque's spread is "
                  "withheld as too small; "
                  "parameters by non-negative least squares on all undisturbed samples, standard deviations by "
                  "block jackknife over the folds. Coulomb friction uses tanh(dq/v_s), v_s = "
                  f"{self.info.get('sign_noise_factor')} x velocity noise: "
                  + ", ".join(f"{v:.3g}" for v in self.info.get("v_s", [])) + " rad/s.", ""]
        lines += corrected_markdown(self.corrected)
        if self.info.get("plots"):
            lines += ["## Plots", ""] + [f"![{p}]({p})" for p in self.info["plots"]]
        return "\n".join(lines) + "\n"

    def write(self, out_dir) -> Path:
        """Write ``findings.json``, ``report.md``, residual plots (with plot data), (when modes
        or pushes were found) ``labels.parquet`` (t, mode, disturbed per analysed sample) and the
        corrected model, ``corrected.urdf`` and ``corrected.xml`` (CONTRACT 1.2; none without a
        URDF, and the report says so). All of them or none: they are written beside ``out_dir``
        and moved into it at the end (:func:`mmgp.data.outputs.atomic_output_files`; other files
        in ``out_dir`` stay, those of the same names are replaced)."""
        from ..data.outputs import atomic_output_files, atomic_write_text, write_table

        out = Path(out_dir)
        with atomic_output_files(out) as tmp:
            # what was written of the corrected model stays with the result (the CLI prints its report)
            v_s = self.info.get("v_s")
            self.corrected = write_corrected(self.findings, self.urdf, self.joint_names, tmp,
                                             None if v_s is None else dict(zip(self.joint_names, v_s)))
            doc = self
            if self.plot_data is not None:
                doc = dataclasses.replace(doc, info={**self.info, "plots": plot_residuals(self.plot_data, tmp)})
            atomic_write_text(tmp / "findings.json", doc.to_json())
            if self.labels is not None:
                import pandas as pd

                write_table(tmp / "labels.parquet", pd.DataFrame(self.labels))
            atomic_write_text(tmp / "report.md", doc.report_markdown())
            doc.report_html(tmp)
        return out

    def report_html(self, out: Path) -> Path:
        """``out/report.html``: warnings, findings with their intervals, the held-out error per
        stage and joint, the plots (PNGs already in ``out``) and the JSON, on one page."""
        from ..evaluation.html import HtmlReport

        page = HtmlReport("mmgp diagnose", subtitle=f"{self.info.get('n_samples')} samples analysed")
        sentence = gp_sentence(self.fit, self.joint_names)
        page.section("Summary", "Held-out normalised MSE per joint (0 is perfect, 1 is the torque's own mean) and "
                                "what was found on each joint." + (" " + sentence if sentence else ""))
        page.table(["joint"] + [label for _, label in COLUMNS] + ["found"],
                   [[r["joint"]] + [r[s] for s, _ in COLUMNS] + ["; ".join(r["found"]) or "nothing"]
                    for r in joint_rows(self.findings, self.fit, self.joint_names, self.withheld)], kind="summary")
        if self.warnings:
            page.section("Warnings", "What limits the numbers below:")
            page.table(["warning"], [[w] for w in self.warnings], kind="warnings")
            if self.withheld:
                page.table(["withheld finding", "because"],
                           [[f["explanation"], f["withheld_because"]] for f in self.withheld], kind="withheld")
        page.section("Findings", None if self.findings else "Nothing is missing from the nominal model.")
        rows = [[head, finding_line(f), f["explanation"]] for head, fs in grouped(self.findings, self.joint_names)
                for f in fs]
        page.table(["where", "found (interval)", "explanation"], rows, kind="findings")
        stages = [s for s in STAGES if s in self.fit]
        page.section("Held-out normalised MSE per joint", "Time-block cross-validation; 0 is perfect, 1 is as good "
                                                          "as the torque's mean.")
        page.table(["joint"] + stages, [[j] + [self.fit[s]["nmse"].get(j) for s in stages] for j in self.joint_names],
                   kind="nmse")
        self._html_corrected(page)
        plots = self.info.get("plots") or []
        if plots:
            page.section("Residuals", "Per joint: residual against velocity, position and torque before and "
                                      "after the found effects; the fitted friction law in red over what the "
                                      "rest of the model leaves.")
            for name in plots:
                page.figure(out / name)
        page.section("findings.json").json(self.to_dict(), "findings")
        return page.write(out / "report.html")

    def _html_corrected(self, page) -> None:
        """The corrected model's part of report.html (see ``corrected_markdown``)."""
        c = self.corrected
        if c is None:
            return
        if not c.get("written"):
            page.section("Corrected model", f"Not written: {c.get('why')}.")
            return
        page.section("Corrected model", "corrected.urdf (Pinocchio) and corrected.xml (MuJoCo) in this folder; "
                                        "load them with: " + " / ".join(c["load"][1:]))
        rows = [["written", w] for w in c["carries"]] + [["not expressed in MJCF", w] for w in c["not_expressed"]]
        page.table(["", "what"], rows, kind="corrected")


def plot_residuals(d: dict, out: Path) -> list[str]:
    """Per joint, residual before/after the found effects against dq, q and tau; PNG names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..data.outputs import write_figure

    names = []
    T = d["q"].shape[0]
    idx = np.linspace(0, T - 1, min(T, 3000)).astype(int)
    for j, jn in enumerate(d["joint_names"]):
        fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharey="row")
        fr = d.get("friction")
        for row, (res, lab) in enumerate(((d["r_before"], "nominal"), (d["r_after"], "with physics"))):
            for col, (x, xl) in enumerate(((d["dq"], "dq [rad/s]"), (d["q"], "q [rad]"), (d["tau"], "tau [N*m]"))):
                ax = axes[row, col]
                ax.plot(x[idx, j], res[idx, j], ".", ms=1.5, alpha=0.5, rasterized=True)
                ax.axhline(0, color="k", lw=0.5)
                if row == 1 and col == 0 and fr is not None and np.any(fr[:, j]):
                    # what friction must explain (the rest of the model removed) and the law fitted to it
                    ax.plot(x[idx, j], res[idx, j] + fr[idx, j], ".", ms=1.0, color="0.6", alpha=0.4,
                            rasterized=True)
                    order = idx[np.argsort(x[idx, j])]
                    ax.plot(x[order, j], d["friction_law"][order, j], "-", color="tab:red", lw=1.2,
                            label="fitted friction")
                    ax.legend(loc="upper left", fontsize=7)
                ax.set_xlabel(xl)
                if col == 0:
                    ax.set_ylabel(f"residual, {lab} [N*m]")
        fig.suptitle(f"{jn}: residual before / after the found effects")
        fig.tight_layout()
        name = f"residual_{j}_{jn}.png".replace("/", "_")
        write_figure(out / name, fig, dpi=80)
        plt.close(fig)
        names.append(name)
    return names
