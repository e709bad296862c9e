"""The fleet table: one row per log, effect, joint (or link) and parameter component.

Columns: ``log`` (path), ``robot``, ``log_time`` (UTC), ``log_time_source`` (``start_time``,
the legacy ``log_time``, or ``mtime``: see :func:`mmgp.fleet.work.log_time`), ``effect``,
``joint``, ``param``, ``value``, ``lo``, ``hi``, ``unit`` (:func:`param_unit`), ``error``; the
drift stage adds ``drift``. Rules:

* ``joint`` is the finding's joint, or its ``link`` for link effects (``payload``,
  ``inertial_parameters``), or empty (None) for whole-log effects (``external_disturbance``,
  ``mode_switch``).
* Every number in ``params`` is a row; a vector becomes one row per component (``com[0]``), a
  nested mapping is joined with dots (``delta.mass``, ``per_mode[1].mass``). Strings (the
  payload's ``link``) are not parameters, nor are lists of event times (``spans_s``,
  ``switch_times_s``).
* ``lo``/``hi`` = value -+ 2 standard deviations, the standard deviation being the finding's
  ``evidence.params_std`` (block jackknife over the time folds); NaN where none is given.
* A log without findings has one row with an empty ``effect``; a log that failed has one row
  with its message in ``error``.
* With training, rows of effect ``training`` carry the trained model's per-joint ``noise_std``
  and ``signal_std`` per mode (``modes[k].noise_std``), and whole-log ``n_modes`` and
  ``disturbed_fraction``; these have no interval.
"""
from __future__ import annotations

import math
import re
from functools import lru_cache
from numbers import Real

import numpy as np
import pandas as pd

#: finding params that list events (times, spans) rather than estimate a magnitude
EVENT_PARAMS = ("spans_s", "switch_times_s")
#: params that name where the effect is, not how large it is
PLACE_PARAMS = ("link", "joint")
COLUMNS = ["log", "robot", "log_time", "log_time_source", "effect", "joint", "param", "value", "lo", "hi",
           "unit", "error"]
#: units of parameters no effect class declares (whole-log effects, training rows, per-body deltas);
#: "" is dimensionless. The training's noise and signal levels are of the torque residual.
OTHER_UNITS = {"fraction": "", "n_samples": "samples", "n_modes": "", "disturbed_fraction": "",
               "noise_std": "N*m", "signal_std": "N*m", "mass": "kg", "com": "m", "inertia": "kg*m^2"}
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: half-width of the interval in standard deviations
INTERVAL_SD = 2.0


@lru_cache(maxsize=None)
def _declared_units() -> tuple[dict, dict]:
    """(effect -> its parameters' units, parameter -> unit where every effect agrees), from the
    effect classes (the contract's effect table, section 3)."""
    from ..physics.effects import EFFECT_CLASSES

    by_effect = {name: dict(cls.units) for name, cls in EFFECT_CLASSES.items()}
    seen: dict[str, set] = {}
    for units in by_effect.values():
        for key, unit in units.items():
            seen.setdefault(key, set()).add(unit)
    return by_effect, {k: next(iter(v)) for k, v in seen.items() if len(v) == 1}


def param_unit(effect: str | None, param: str | None) -> str | None:
    """The unit of a table row's ``param`` (``tau_c``, ``com[1]``, ``per_mode[0].mass``,
    ``delta.link3.inertia[2]``): its last name looked up in the effect's own units, then in the
    units every effect agrees on, then :data:`OTHER_UNITS`; None when unknown (e.g. a mode
    switch's ``offset``, which is rad on an encoder and N*m on a torque sensor)."""
    names = _NAME.findall(param or "")
    if not names:
        return None
    by_effect, agreed = _declared_units()
    own = by_effect.get(effect or "", {})
    for table in (own, agreed, OTHER_UNITS):
        if names[-1] in table:
            return table[names[-1]]
    return None


def _number(x) -> bool:
    return isinstance(x, Real) and not isinstance(x, bool)


def _leaves(name: str, value, std):
    """(param, value, std) for every number under ``value``; ``std`` mirrors its shape or is None."""
    if _number(value):
        yield name, float(value), float(std) if _number(std) else math.nan
    elif isinstance(value, dict):
        for key, v in value.items():
            yield from _leaves(f"{name}.{key}", v, std.get(key) if isinstance(std, dict) else None)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            s = std[i] if isinstance(std, (list, tuple)) and i < len(std) else None
            yield from _leaves(f"{name}[{i}]", v, s)


def finding_rows(finding: dict) -> list[dict]:
    """Rows (``effect``, ``joint``, ``param``, ``value``, ``lo``, ``hi``) of one contract finding."""
    where = finding.get("joint")
    if where is None:
        where = finding.get("link", finding.get("params", {}).get("link"))
    stds = (finding.get("evidence") or {}).get("params_std") or {}
    rows = []
    for key, value in (finding.get("params") or {}).items():
        if key in EVENT_PARAMS or key in PLACE_PARAMS:
            continue
        for param, v, s in _leaves(key, value, stds.get(key)):
            half = INTERVAL_SD * s
            rows.append({"effect": finding["effect"], "joint": None if where is None else str(where),
                         "param": param, "value": v, "lo": v - half, "hi": v + half})
    return rows


def training_rows(report: dict) -> list[dict]:
    """Rows of effect ``training`` from a training report (``mmgp train``'s report.json)."""
    base = {"effect": "training", "lo": math.nan, "hi": math.nan}
    rows = [dict(base, joint=None, param="n_modes", value=float(report["n_modes"])),
            dict(base, joint=None, param="disturbed_fraction",
                 value=report["disturbance"]["n_disturbed"] / max(report["n_samples"], 1))]
    for mode in report["hyperparameters"]:
        for pj in mode["per_joint"]:
            for key in ("noise_std", "signal_std"):
                rows.append(dict(base, joint=str(pj["joint"]), param=f"modes[{mode['mode']}].{key}",
                                 value=float(pj[key])))
    return rows


def outcome_rows(outcome: dict) -> list[dict]:
    """Every row of one log's outcome (see :func:`mmgp.fleet.work.process_log`)."""
    head = {"log": outcome["log"], "robot": outcome.get("robot"), "log_time": outcome["log_time"],
            "log_time_source": outcome.get("log_time_source"), "error": outcome.get("error")}
    rows = []
    for finding in outcome.get("findings") or []:
        rows += finding_rows(finding)
    if outcome.get("training"):
        rows += training_rows(outcome["training"]["report"])
    if not rows:
        rows = [{"effect": None, "joint": None, "param": None, "value": math.nan, "lo": math.nan, "hi": math.nan}]
    return [dict(head, unit=param_unit(r["effect"], r["param"]), **r) for r in rows]


def fleet_table(outcomes: list[dict]) -> pd.DataFrame:
    """The fleet table of all outcomes, ordered by log time, log, effect, joint, parameter."""
    rows = [r for o in outcomes for r in outcome_rows(o)]
    df = pd.DataFrame(rows, columns=COLUMNS)
    df["log_time"] = pd.to_datetime(df["log_time"].astype(np.float64), unit="s", utc=True)
    for col in ("value", "lo", "hi"):
        df[col] = df[col].astype(np.float64)
    df = df.sort_values(["log_time", "log", "effect", "joint", "param"], na_position="first", kind="stable")
    return df.reset_index(drop=True)
