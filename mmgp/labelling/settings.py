"""The EM's settings, declared once (:class:`EMSettings`).

:class:`~mmgp.labelling.sem.MultimodalSEM` reads them; :class:`mmgp.MultimodalGP` exposes those a user
sets under the same names, with these defaults, and builds one :class:`EMSettings` from its own
values (:meth:`EMSettings.of`); the diagnosis's learner overrides the sizes it needs. The GP part
goes on to :class:`~mmgp.labelling.mstep.FitterSettings` (:meth:`EMSettings.fitter`).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields

from .mstep import FitterSettings

__all__ = ["EMSettings", "ESTEPS", "UNCONVERGED", "em_setting_names"]

ESTEPS = ("mpm", "ffbs", "gibbs")
UNCONVERGED = ("best", "average")


@dataclass(frozen=True)
class EMSettings:
    """Settings of the EM over modes and the disturbance mode (times in s).

    disturbance : include the disturbance mode.
    estep : "mpm" (deterministic: the seed plays no part), "ffbs" or "gibbs" (stochastic: the
        labels depend on the seed; see benchmarks/bench_labels.py).
    stay_prob : fixed p(k_t = k_{t-1}); None learns it (Beta prior, mean 0.95).
    max_sweeps, min_sweeps, tol_changed, patience, average_last : when the sweeps stop and how many
        are averaged after convergence (:class:`.convergence.ConvergenceMonitor`).
    unconverged : the labels where the sweeps stop unconverged: "best", the sweep's of the highest
        log marginal (a chain that cycles); "average", the last sweeps' (a budget).
    max_support : at most this many undisturbed samples condition each mode's GP during the sweeps
        (evenly spaced; the others are predicted out of sample): each sweep costs
        O(max_support^2 * T) per joint.
    final_support : the returned GPs (used by predict/export) condition on up to this many of
        their mode's undisturbed samples (evenly spaced); None: every one.
    gp_method, n_inducing : the returned GPs' kind (:func:`mmgp.gp.sparse.make_gp`: "auto",
        "exact", "sgpr", "subset") and SGPR inducing inputs.
    fit_points, fit_iter : hyperparameter fitting subset size and L-BFGS iterations.
    exclusion_s, block_s : leave-window-out radius of the E-step likelihood and the block length
        of the hyperparameter objective (need times in ``fit``).
    mode_smoothing_s : running-median length of the residuals clustered into initial modes.
    min_mode_s : a mode lasts at least this long: in the final labels a shorter stretch of one
        mode takes a neighbouring stretch's mode (:func:`.estep.merge_short_runs`; needs times;
        K > 1): at poses where a payload barely loads the joints, a second or so of one mode looks
        like the other. :func:`.sem.select_n_modes` also requires every mode to last this long.
    abandon_short_modes : (K > 1, with times) stop the sweeps early, unconverged, once one mode
        has held nowhere for ``min_mode_s`` in one stretch (each sweep's most probable labels) for
        ``patience`` sweeps after ``min_sweeps``: such a mode is what :func:`.sem.select_n_modes`
        (which sets this) rejects.
    calibrate : scale each mode's predictive variance per joint by its undisturbed mean z^2.
    shared_basis : with a ``basis`` in ``fit``, one coefficient vector for all joints (a payload)
        instead of one per joint.
    push_s, gap_s, push_prior_n : prior push duration and time between pushes, and how many
        observed pushes that prior is worth.
    push_floor_z : a push is at least this many predictive standard deviations (Sigma_d floor).
    min_push_s : a push lasts at least this long: flagged stretches of the final labels shorter
        than this are set undisturbed (needs times; only the final labels: the short first flags
        of light pushes must stay out of the GP's training samples).
    push_scan_s, push_scan_z : a push is a sustained offset: in the final labels, undisturbed
        samples whose residual (standardised, averaged over ``push_scan_s`` of undisturbed
        samples) stands more than ``push_scan_z`` robust standard deviations of that average off
        on some joint are flagged too (:mod:`.scan`; needs times; 0 s: off). Light pushes 1-3
        predictive standard deviations off for 0.2-2 s, which no single sample shows.
    start_trim : fractions of the samples kept by the successive refits of the start.
    start_z : robust z-score over which a sample starts disturbed.
    abstain : flag nothing when the disturbance states do not pay their BIC price.
    gp_kwargs : passed to ExactGP (e.g. ard, objective, device).
    """

    disturbance: bool = True
    estep: str = "mpm"
    stay_prob: float | None = None
    max_sweeps: int = 40
    min_sweeps: int = 6
    tol_changed: float = 0.05
    patience: int = 3
    average_last: int = 5
    unconverged: str = "best"
    max_support: int = 500
    final_support: int | None = None
    gp_method: str = "auto"
    n_inducing: int = 2000
    fit_points: int = 2000
    fit_iter: int = 50
    exclusion_s: float = 1.0
    block_s: float = 2.0
    mode_smoothing_s: float = 4.0
    min_mode_s: float = 4.0
    abandon_short_modes: bool = False
    calibrate: bool = True
    shared_basis: bool = False
    push_s: float = 1.0
    gap_s: float = 5.0
    push_prior_n: float = 3.0
    push_floor_z: float = 5.0
    min_push_s: float = 0.15
    push_scan_s: float = 0.2
    push_scan_z: float = 6.0
    start_trim: tuple = (0.8, 0.6)
    start_z: float = 3.0
    abstain: bool = True
    gp_kwargs: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.estep not in ESTEPS or self.unconverged not in UNCONVERGED:
            raise ValueError(f"expected estep one of {ESTEPS} and unconverged one of {UNCONVERGED}; "
                             f"got {self.estep!r}, {self.unconverged!r}")

    @classmethod
    def of(cls, source, **given) -> "EMSettings":
        """The settings that ``source`` (an object, e.g. a :class:`mmgp.MultimodalGP`) holds under
        these names, the others at their defaults, then ``given``."""
        names = {f.name for f in fields(cls)} - set(given)
        return cls(**{k: getattr(source, k) for k in names if hasattr(source, k)}, **given)

    def replace(self, **changes) -> "EMSettings":
        """A copy with ``changes`` (unknown names raise TypeError)."""
        return dataclasses.replace(self, **changes)

    @property
    def fitter(self) -> FitterSettings:
        """What one mode's model is fitted with (the GP part of these settings)."""
        return FitterSettings.of(self)


def em_setting_names() -> tuple[str, ...]:
    """The names of :class:`EMSettings`' fields."""
    return tuple(f.name for f in fields(EMSettings))
