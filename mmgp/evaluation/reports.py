"""The ``report.html`` of each command that writes plots, built from its JSON and its PNGs.

Each function reads only what the command already wrote (the JSON dict and the PNG files in the
output folder) and writes ``report.html`` beside them, so the page shows the same figures.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .html import HtmlReport
from .metrics import COMPARE_LABELS, HELDOUT_LABELS, SOURCE_FIGURES

__all__ = ["write_training_report", "write_compare_report"]


def _robot_name(spec: dict | None) -> str | None:
    if not spec:
        return None
    return spec.get("robot") or spec.get("urdf")


def _training_key_figures(rep: dict) -> dict:
    dist = rep["disturbance"]
    return {
        "logs": [Path(str(p)).name for p in rep["logs"]],
        "samples": rep["n_samples"],
        "joints": rep["n_joints"],
        "robot": _robot_name(rep.get("robot")),
        "modes": rep["n_modes"],
        "disturbance mode": dist["enabled"],
        "samples flagged disturbed": dist["n_disturbed"],
        "EM sweeps": rep["n_sweeps"],
        "converged": rep["converged"],
        "training time [s]": rep["timings"]["total_s"],
    }


def _hyperparameter_rows(rep: dict) -> list[list]:
    return [[hp["mode"], j["joint"], j["signal_std"], j["noise_std"], hp["n_support"]]
            for hp in rep["hyperparameters"] for j in hp["per_joint"]]


def _evaluation_rows(fig: dict) -> list[list]:
    rows = []
    for key, label in (("unperturbed_correct", "unperturbed correct"), ("perturbed_missed", "perturbed missed"),
                       ("accuracy", "accuracy"), ("disturbed_precision", "disturbed precision"),
                       ("disturbed_recall", "disturbed recall"), ("disturbed_f1", "disturbed F1"),
                       ("mode_adjusted_rand_index", "mode adjusted Rand index")):
        if key in fig:
            rows.append([label, fig[key], SOURCE_FIGURES.get(key)])
    return rows


def write_training_report(out_dir: str | Path, report: dict, evaluation: dict | None = None,
                          *, title: str = "mmgp train") -> Path:
    """``out_dir/report.html`` of a training run: key figures of ``report`` (report.json), the
    classification figures of ``evaluation`` (evaluation.json, with the source's beside them) when
    given, the plots ``labels.png`` and ``likelihood_trace.png`` found in ``out_dir``, the mode
    selection and per-mode hyperparameters, and both JSON documents. Returns the path."""
    out = Path(out_dir)
    logs = ", ".join(Path(str(p)).name for p in report["logs"])
    page = HtmlReport(title, subtitle=f"{logs}: {report['n_samples']} samples")
    _warnings_section(page, report.get("warnings"))
    page.section("Key figures").key_figures(_training_key_figures(report))
    if evaluation is not None:
        page.section("Classification against ground truth",
                     f"{evaluation.get('n_judged')} samples judged, {evaluation.get('n_ambiguous_left_out', 0)} "
                     "left out as ambiguous; source: Haninger 2016, ch. 5.")
        page.table(["figure", "mmgp", "source (2016)"], _evaluation_rows(evaluation), kind="evaluation")
    page.section("Plots")
    for name, caption in (("labels.png", "Torque per joint coloured by mode; disturbed samples as red crosses"),
                          ("likelihood_trace.png", "Likelihood and fraction of labels changed per EM sweep")):
        if (out / name).is_file():
            page.figure(out / name, caption)
    sel = report.get("mode_selection")
    if sel:
        page.section("Number of modes", "Tried in increasing order: K is kept while it raises the BIC-style score "
                     "on the chain's log marginal likelihood and each of its modes holds for at least "
                     f"{sel.get('min_mode_s', 0)} s in one stretch (a payload lasts, a push does not).")
        runs = sel.get("longest_run_s", {})
        rows = [[int(k), v, runs.get(k, runs.get(str(k))), int(k) == sel["chosen"]] for k, v in sel["scores"].items()]
        page.table(["modes", "score", "longest stretch of each mode [s]", "chosen"], rows, kind="mode-selection")
    fits = (report.get("dissipation") or {}).get("fits") or []
    if fits:
        page.section("Friction dissipates", "Share of each fit's sliding samples where its friction pushes the joint "
                     "along (injects energy) by more than 2 standard deviations, and the probability that a "
                     "dissipative model's friction stays as deep in the wrong sign (Bonferroni over modes and "
                     "joints; below 0.05 the fit injects energy). Where the basis fit's two starts differ (resting "
                     "samples left out, or counted) the EM runs from each; a fit that injects energy is refitted from "
                     "labels swapped there; of the fits that dissipate the one with the highest evidence is kept.")
        chosen = report["dissipation"]["chosen"]
        page.table(["fit", "start", "worst share injecting", "p (depth test)", "log marginal likelihood", "dissipative",
                    "kept"],
                   [[i + 1, f.get("start", ""), f["worst"], f"{f.get('p_value', float('nan')):.2g}", f["log_marginal"],
                     f["physical"], i == chosen] for i, f in enumerate(fits)], kind="dissipation")
    _heldout_section(page, report.get("heldout"))
    page.section("Per-mode GPs").table(["mode", "joint", "signal std [N*m]", "noise std [N*m]", "support points"],
                                       _hyperparameter_rows(report), kind="hyperparameters")
    page.section("Summary").json(report, "report")
    if evaluation is not None:
        page.json(evaluation, "evaluation")
    return page.write(out / "report.html")


def _warnings_section(page: HtmlReport, warnings: list | None) -> None:
    """The log's warnings (``mmgp.physics.plausibility``), first on the page, as the diagnosis's."""
    if warnings:
        page.section("Warnings")
        page.table(["warning"], [[w] for w in warnings], kind="warnings")


def _heldout_section(page: HtmlReport, heldout: dict | None) -> None:
    """The held-out normalised MSE per joint of the model, the rigid body and the mean (report.json
    ``heldout``, :func:`mmgp.evaluation.heldout.heldout_score`)."""
    if not heldout:
        return
    page.section("Held-out score", f"Normalised MSE per joint over {heldout['n_folds']} time blocks (each block "
                 f"predicted from the others, {heldout['gap']} samples on each side kept out): 0 is perfect, 1 is "
                 f"predicting the torque's mean. Scored: {heldout['scored']} ({heldout['n_scored']} scored, "
                 f"{heldout['n_disturbed_left_out']} disturbed left out). The model's labels and hyperparameters "
                 "are the trained ones; each block's GP conditions on the other blocks only.")
    nmse = heldout["nmse"]
    rows = [[name] + [None if nmse[m] is None else nmse[m][j] for m in HELDOUT_LABELS]
            for j, name in enumerate(heldout["joint_names"])]
    page.table(["joint"] + [f"{label} nMSE" for label in HELDOUT_LABELS.values()], rows, kind="heldout")


def write_compare_report(out_dir: str | Path, result: dict) -> Path:
    """``out_dir/report.html`` of ``mmgp compare``: the held-out normalised MSE per joint and
    method (``result`` = compare.json), the plot ``compare.png`` in ``out_dir`` and the JSON."""

    out = Path(out_dir)
    methods = result["methods"]
    page = HtmlReport("mmgp compare", subtitle=f"{Path(str(result.get('log', ''))).name}: "
                                               f"{result['n_samples']} samples")
    _warnings_section(page, result.get("warnings"))
    page.section("Key figures").key_figures({
        "robot": result.get("robot"), "samples": result["n_samples"], "time-block folds": result["n_folds"],
        "gap [samples]": result["gap"], "gap [s]": result["gap_s"],
        "training samples per fold (at most)": result["max_train"],
        "time [s]": result["timings"]["total_s"]})
    page.section("Held-out normalised MSE", "Pooled out-of-fold predictions; 0 is perfect, 1 is as good as "
                                            "predicting the log's mean.")
    improves = result.get("gp_improves_rigid_body")
    rows = [[name] + [result["nmse"][m][j] for m in methods] + ([improves[j]] if improves else [])
            for j, name in enumerate(result["joint_names"])]
    rows.append(["mean"] + [float(np.mean(result["nmse"][m])) for m in methods] + ([None] if improves else []))
    page.table(["joint"] + [COMPARE_LABELS[m] for m in methods] + (["GP helps"] if improves else []), rows, kind="nmse")
    if (out / "compare.png").is_file():
        page.figure(out / "compare.png", "Held-out normalised MSE per joint (log scale)")
    page.section("Summary").json(result, "compare")
    return page.write(out / "report.html")
