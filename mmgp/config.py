"""Settings for training, built once from YAML plus command-line flags and passed down."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import yaml

from .errors import InputError


@dataclass
class TrainConfig:
    """Everything ``mmgp train`` can be told. Defaults are meant to work on a log nobody tuned for.

    modes: number of dynamic modes, or "auto" (chosen among 1..3 by a BIC-style score).
    disturbance: include the disturbance mode.
    estep: "ffbs" (joint label sampling; default, see benchmarks/bench_estep.py) or "gibbs".
    stay_prob: fixed p(mode_t = mode_{t-1}); null learns it.
    rate_hz: downsample to about this rate after differentiating (null keeps the log's rate).
    diff_window_s: Savitzky-Golay window in seconds (null: per joint, by leave-one-out
        cross-validation of the smoother, between max(5 samples, 0.05 s) and 0.5 s).
    semiparametric: with a robot model, "residual" (GP learns tau - tau_rbd; default),
        "feature" (tau_rbd is an extra GP input) or "none".
    exclusion_s: samples within this many seconds of a sample are left out of its likelihood
        (leave-window-out; 0 = plain leave-one-out).
    friction_feature: add tanh(dq / v_s) per joint to the GP inputs (Coulomb friction's step).
    mean_basis: with a robot and "residual", each mode's mean is linear in rigid-body
        regressors, fitted robustly per mode, and the GP learns the rest, so a mode extrapolates
        like physics to states its data never visited. "payload" (what "auto" picks with a
        robot): the distal body's 10 inertial parameters, one vector shared by all joints, i.e.
        a payload at the tool; "rbd": every body's parameters, separately per joint (more
        flexible; it also absorbed smooth pushes in once-visited states: Panda seed 2 F1 0.82 vs
        0.95); "none". Without a robot "auto" is "none".
    max_support / fit_points / fit_iter / max_sweeps / min_sweeps / average_last: see MultimodalSEM.
    objective: "loo" (full LOO log predictive) or "marginal".
    ard: per-input lengthscales.
    device: torch device ("cpu", "cuda", "auto").
    seed: random seed of the stochastic EM.
    """

    modes: int | str = 1
    disturbance: bool = True
    estep: str = "ffbs"
    stay_prob: float | None = None
    rate_hz: float | None = None
    diff_window_s: float | None = None
    semiparametric: str = "residual"
    exclusion_s: float = 1.0
    friction_feature: bool = True
    mean_basis: str = "auto"
    max_support: int = 500
    final_support: int = 2000
    fit_points: int = 500
    fit_iter: int = 50
    max_sweeps: int = 40
    min_sweeps: int = 6
    average_last: int = 5
    objective: str = "loo"
    ard: bool = True
    device: str = "cpu"
    seed: int = 0

    def validate(self, source: str = "settings") -> "TrainConfig":
        def bad(key, msg):
            raise InputError(f"setting '{key}': {msg}", file=source if source != "settings" else None)

        if not (self.modes == "auto" or (isinstance(self.modes, int) and self.modes >= 1)):
            bad("modes", f"expected a positive integer or 'auto', got {self.modes!r}")
        if self.estep not in ("ffbs", "gibbs"):
            bad("estep", f"expected 'ffbs' or 'gibbs', got {self.estep!r}")
        if self.mean_basis not in ("auto", "rbd", "payload", "none"):
            bad("mean_basis", f"expected 'auto', 'rbd', 'payload' or 'none', got {self.mean_basis!r}")
        if self.semiparametric not in ("residual", "feature", "none"):
            bad("semiparametric", f"expected 'residual', 'feature' or 'none', got {self.semiparametric!r}")
        if self.objective not in ("loo", "marginal"):
            bad("objective", f"expected 'loo' or 'marginal', got {self.objective!r}")
        if self.stay_prob is not None and not 0.0 < self.stay_prob < 1.0:
            bad("stay_prob", "expected a probability strictly between 0 and 1")
        if self.rate_hz is not None and self.rate_hz <= 0:
            bad("rate_hz", "expected a positive rate in Hz")
        for key in ("max_support", "final_support", "fit_points", "fit_iter", "max_sweeps", "min_sweeps", "average_last"):
            if int(getattr(self, key)) < 1:
                bad(key, "expected a positive integer")
        return self

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def load_config(path: str | Path | None = None, **overrides) -> TrainConfig:
    """TrainConfig from a YAML file (optional) with non-None ``overrides`` applied on top."""
    values: dict = {}
    source = "settings"
    if path is not None:
        path = Path(path)
        source = str(path)
        if not path.is_file():
            raise InputError("config file does not exist", file=path)
        try:
            loaded = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(f"not valid YAML ({exc})", file=path) from None
        if not isinstance(loaded, dict):
            raise InputError("expected a mapping of setting: value", file=path)
        known = {f.name for f in dataclasses.fields(TrainConfig)}
        unknown = sorted(set(loaded) - known)
        if unknown:
            raise InputError(f"unknown setting(s) {unknown}; known: {sorted(known)}", file=path)
        values.update(loaded)
    values.update({k: v for k, v in overrides.items() if v is not None})
    if isinstance(values.get("modes"), str) and values["modes"] != "auto":
        try:
            values["modes"] = int(values["modes"])
        except ValueError:
            raise InputError(f"setting 'modes': expected a positive integer or 'auto', got {values['modes']!r}") from None
    return TrainConfig(**values).validate(source)
