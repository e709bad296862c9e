"""Issue 29 item 4: what each labelling rule that is a number earns on issue 29's held-out levers.

Each rule is switched off in turn (the defaults otherwise) and the held-out source-shaped levers
(``bench_labels.py --sets issue29``: 12 pushed, 4 push-free) are labelled once per setting, one
run each (the default E-step draws nothing, so one run is the answer). Printed per setting: the
pushed levers within both lines (unperturbed correct >= 0.95 and perturbed missed <= 0.05), the
worst unperturbed correct and perturbed missed, the most flagged on a push-free lever, the mean F1
over the pushed levers, and the change of each against the defaults from the same run. A rule
earns its place where switching it off loses on these figures.

Rules (``RULES``): ``push_floor_z`` (a push's spread at least 5 predictive sd; off: 0),
``min_push_s`` (flagged stretches under 0.15 s relabelled; off: 0), ``push_scan_s`` (the sustained
offset scan; off: 0, which also retires ``push_scan_z``), ``exclusion_s`` (leave-window-out; off:
plain leave-one-out), ``abstain`` (flag nothing unless the disturbance mode pays its BIC price;
off: false), ``rest_band`` (the stuck joint's band; off: false). ``push_s`` / ``gap_s`` are the
push prior's durations, not on/off rules: halved and doubled with ``--priors``. ``min_mode_s``
concerns several modes, which these one-mode levers do not have (not run here).

Usage: python benchmarks/bench_rules.py [--json FILE] [--priors] [--summarise-only]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

RULES = ("push_floor_z=0", "min_push_s=0", "push_scan_s=0", "exclusion_s=0", "abstain=false",
         "rest_band=false")
#: the push prior's durations, halved and doubled (``--priors``)
PRIORS = ("push_s=0.5", "push_s=2.0", "gap_s=2.5", "gap_s=10.0")


def lever_names() -> list[str]:
    from bench_labels import ISSUE29_SOURCE, ISSUE29_SOURCE_FREE

    return [f"source{s}" for s in ISSUE29_SOURCE] + [f"source-free{s}" for s in ISSUE29_SOURCE_FREE]


def summarise(lines: list[dict]) -> None:
    rows = defaultdict(dict)
    for ln in lines:
        rows[ln["method"]][ln["case"]] = ln
    # every setting on the same logs (a run stopped early has the last log for some only)
    common = set.intersection(*(set(per) for per in rows.values())) if rows else set()
    rows = {m: {c: r for c, r in per.items() if c in common} for m, per in rows.items()}
    print(f"{len(common)} levers scored by every setting")
    base = _figures(rows.get("mmgp", {}))
    print(f"{'setting':<26}{'within':>8}{'UC worst':>10}{'PM worst':>10}{'free max':>10}{'F1 mean':>9}"
          f"{'d within':>10}{'d UC':>8}{'d PM':>8}{'d free':>8}{'d F1':>8}")
    for method in ["mmgp"] + [f"mmgp[{r}]" for r in RULES + PRIORS]:
        if method not in rows:
            continue
        f = _figures(rows[method])
        d = [f[k] - base[k] for k in ("within", "uc", "pm", "free", "f1")] if base else [0] * 5
        print(f"{method:<26}{f['within']:>5}/{f['n']:<2}{f['uc']:>10.3f}{f['pm']:>10.3f}{f['free']:>10.3f}"
              f"{f['f1']:>9.3f}{d[0]:>+10d}{d[1]:>+8.3f}{d[2]:>+8.3f}{d[3]:>+8.3f}{d[4]:>+8.3f}")


def _figures(per_case: dict) -> dict:
    pushed = [r for c, r in per_case.items() if not c.startswith("source-free")]
    free = [r for c, r in per_case.items() if c.startswith("source-free")]
    if not pushed:
        return {}
    within = sum(1 for r in pushed if r["uc"] >= 0.95 and r["pm"] <= 0.05)
    return {"n": len(pushed), "within": within, "uc": min(r["uc"] for r in pushed),
            "pm": max(r["pm"] for r in pushed), "free": max((r["flagged"] for r in free), default=0.0),
            "f1": sum(r["f1"] for r in pushed) / len(pushed)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=Path("bench_rules.jsonl"))
    ap.add_argument("--priors", action="store_true", help="also the push prior's durations")
    ap.add_argument("--summarise-only", action="store_true")
    a = ap.parse_args(argv)
    if not a.summarise_only:
        methods = ",".join(["mmgp"] + [f"mmgp[{r}]" for r in RULES + (PRIORS if a.priors else ())])
        subprocess.run([sys.executable, str(HERE / "bench_labels.py"), "--sets", "issue29", "--only",
                        ",".join(lever_names()), "--methods", methods, "--seeds-1dof", "1", "--json", str(a.json)],
                       check=True, stdout=subprocess.DEVNULL)
    summarise([json.loads(ln) for ln in a.json.read_text().splitlines() if ln.strip()])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
