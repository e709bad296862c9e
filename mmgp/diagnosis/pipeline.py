"""Sim-vs-real diagnosis: which physical effects is the nominal model missing, where, how large.

:class:`Diagnoser` is assembled from swappable parts, in PySINDy's shape: the candidate
``effects`` (``mmgp.physics.effects``: each one class with its columns, constraints and words),
the ``selector`` that chooses among them (``ForwardCVSelector``), and the ``differentiator``
that estimates velocities and accelerations a log lacks (the cross-validated Savitzky-Golay
windows ``mmgp train`` uses). The steps (``mmgp.diagnosis.stages``):

1. *Locate*: residual ``r = tau - tau_rbd(q, dq, ddq)`` per joint; where it concentrates (near
   zero velocity, high load, position/acceleration ranges, time spans). Residual and every
   regressor column are low-passed alike (parallel filtering). A joint's equation is left out
   where its velocity stays within noise of zero (``valid_mask``): stuck, static friction is
   set-valued, and fitting it would feed look-alike effects. A joint only passing through zero
   velocity (a reversal, shorter than a tenth of the filter's cutoff period) is not stuck.
2. *Separate* pushes before naming anything: a robust (Huber then Tukey IRLS) fit of the whole
   library gives sample weights with pushes at zero; effects are selected on those weights; the
   residual of the *selected* model is scanned for pushes, away from every passage through zero
   velocity, where the friction law's transition is least certain (chi-square scan at a family-wise
   level over the log's independent samples; excursions shorter than the filter's resolution
   are not events). The multimodal learner (``MultimodalSEM``, disturbance mode on, GP inputs
   ``[q, dq, ddq, tanh(dq/v_s)]``, on <= ``em_points`` samples of ``tau - tau_rbd`` evenly spaced
   in time, leave-window-out likelihoods) then gates the scan (``separate="auto"``): a scanned
   span is kept when the learner also flags some of it, or when the scan's statistic peaks at
   >= ``em_gate_peak`` times its threshold. Where a payload mode switch is found, the pushes are
   scanned again on the two-mode residual and gated by a two-mode learner. Why: the learner
   alone (``separate="em"``) flags pushes on logs without any, so it cannot lead, and a union
   of both inherits that; the scan alone keeps false pushes the gate removes; the strong-span
   exemption keeps a long push whose part the learner's GP absorbed (measured on
   ``benchmarks/bench_diagnose.py``: benchmarks/README.md, "sixth session: tuning history").
3. *Name*: forward selection on time-block cross-validation (``n_folds`` blocks laid over the
   samples that carry an equation, ``selection.carried_folds``): an effect is
   added only while the best candidate's paired held-out gain is significant (one-sided
   Wilcoxon signed-rank test over the blocks; an effect on one joint's torque is tested on that
   joint and on the joint-weighted sum, the smaller p doubled, the weighted total not raised:
   ``selection.gain_p``) at family-wise level ``alpha`` (Bonferroni over the
   candidates tried at that step); physical constraints must hold; nested effects (load
   dependence in Coulomb friction) are only tried as extensions. No magnitude threshold.
   Where the rigid body is not re-identified, a static effect (a spring, an offset) that is not
   chosen once the body is in the model cannot be told from the body's gravity error: withheld,
   not reported (``Diagnoser._body_stand_ins``).
4. *Model*: refit the nominal model plus the chosen effects (non-negative least squares), then a
   GP (``mmgp.gp.exact.ExactGP``) on what is left; held-out normalised MSE per joint at three
   stages. Mode switches: one vs two payload modes per link (sticky two-state switching
   regression, HMM predictive from samples a filter memory earlier, on held-out blocks).
5. *Tell*: findings per CONTRACT section 2/3 (a finding whose torque stays under half a percent of
   its joint torque's spread is withheld as too small to name: ``plausibility.MIN_TORQUE_SHARE``),
   a Markdown report and residual plots; the corrected model (``corrected.urdf``, ``corrected.xml``:
   the nominal model with what MuJoCo can express of the findings, ``mmgp.diagnosis.corrected``).

Units: N*m, rad, s throughout; shapes (T, n) for T samples of n joints.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from sklearn.base import BaseEstimator, clone

from ..errors import InputError
from ..progress import report
from ..threads import limit_threads
from . import stages as st
from . import coupling
from .fitting import effect_findings, fit_physics
from .modes import near_switches
from .reidentify import consistent_refit, model_torque, reidentify
from .result import DiagnosisResult, disturbance_finding, mode_effect_findings, mode_switch_finding, stand_in_finding
from .selection import FoldGrams, ForwardCVSelector, extend_nested, prune
from .separation import SEPARATION_METHODS, runs, spans_of

_SELECTION = ForwardCVSelector()   # the selection's settings are declared there; the Diagnoser's defaults are its


#: the stages of a diagnosis, in order, as its progress reports name them (``work="diagnosis"``,
#: ``done`` = the stage's index, ``total`` = their number); a stage a log does not need is skipped
STAGES = ("reading the log", "estimating derivatives, building the effect library",
          "multimodal learner (pushes)", "fitting the effects, re-identifying the rigid body", "separating pushes",
          "selecting effects", "selecting effects again, with the rigid body (its stand-ins)", "mode switch",
          "selecting effects again, with the modes",
          "held-out errors per stage", "GP on what the physics leaves")


def _stage(name: str) -> None:
    report(f"diagnosis: {name}", work="diagnosis", done=STAGES.index(name), total=len(STAGES))


class _Laps:
    """Seconds between successive marks, by name."""

    def __init__(self):
        self.t0 = self.last = time.perf_counter()
        self.laps: dict = {}

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self.last
        self.last = now

    def total(self) -> dict:
        return {**self.laps, "total_s": time.perf_counter() - self.t0}


class Diagnoser(BaseEstimator):
    """Name the physics a nominal rigid-body model misses in a log, and how large it is.

    Parts (swappable):

    effects: candidate effects, as names (CONTRACT section 3) or ``mmgp.physics.effects.Effect``
        subclasses; None = every registered effect.
    selector: chooses effects from held-out errors; None = ``ForwardCVSelector(alpha=alpha,
        max_steps=max_steps)``. A given selector is cloned and used with its own settings.
    differentiator: estimates dq/ddq a log lacks, ``differentiator(t, x, deriv)``; None =
        ``SavitzkyGolay(cv=True)`` (per-joint windows by leave-one-out cross-validation, as
        ``mmgp train`` and ``mmgp predict`` use).

    Settings:

    n_folds: time blocks of the cross-validation (selection, uncertainty and the stage figures).
    alpha: family-wise significance level of the selection and of the mode-switch test.
    max_steps: at most this many effects (None: no limit).
    payload_links: "auto" (the most distal links, where the trajectory can see a mass: CONTRACT
        section 3 names a mass elsewhere an inertial-parameter difference) or 0-based link indices.
    reid_min_gain: the rigid body is re-identified (effect ``inertial_parameters``) when its base
        parameters cut the whole library's held-out error significantly and by at least this
        fraction.
    separate: how pushes are found: "auto" (robust scan gated by the learner), "scan" (the scan
        alone), "em" (the learner's flags alone) or "none".
    push_alpha: family-wise false-alarm level of the push scan over the log's independent samples.
    em_modes, em_points: dynamic modes of the learner (the re-scan after a mode switch uses at
        least 2) and the most samples it sees (evenly thinned in time).
    em_gate_peak: scanned spans peaking at this many times the scan threshold are kept without
        the learner's confirmation.
    rest_factor: a joint's equation is left out where |dq| < rest_factor * v_s for at least a
        tenth of the filter's cutoff period (the velocity stays within noise of zero; widened by
        the filter's memory): at rest friction takes any value in [-tau_c, tau_c] (stiction),
        which no function of the state can fit.
    sign_noise_factor: v_s = this times the velocity noise (smooth sign of Coulomb friction).
    lowpass: low-pass residual and regressor columns alike (parallel filtering) at a cutoff set
        by the trajectory's bandwidth, so noise in estimated accelerations does not bias the fit.
    max_samples: longer logs are thinned evenly to this many samples (runtime bound).
    modes: test for an effect that switches between two values (``mode_switch``); mode_folds,
        mode_max_samples: time blocks and (thinned) samples of that test.
    gp: fit the third stage (a GP on what the physics leaves). gp_points: training points per
        fold; gp_hyper_points, gp_iter: subset size and L-BFGS iterations of its one
        hyperparameter optimisation.
    plots: ``report`` writes residual plots (PNG).
    seed: random seed (learner, GP subsets).

    ``fit(log, robot)`` learns ``findings_`` (contract findings), ``fit_stages_`` (held-out
    normalised MSE per joint at the stages "nominal", "with_physics", "with_physics_and_gp"),
    ``location_``, ``labels_`` (per analysed sample t, mode, disturbed; None without modes or
    pushes), ``info_`` and ``result_`` (a :class:`DiagnosisResult`); ``report(dir)`` writes
    findings.json, report.md, plots, labels.parquet and the corrected model (corrected.urdf,
    corrected.xml: ``mmgp.diagnosis.corrected``).
    """

    def __init__(self, effects=None, selector=None, differentiator=None, *, n_folds: int = 20,
                 alpha: float = _SELECTION.alpha, max_steps: int | None = _SELECTION.max_steps, payload_links="auto", reid_min_gain: float = 0.05,
                 separate: str = "auto",
                 push_alpha: float = 0.001, em_modes: int = 1, em_points: int = 500, em_gate_peak: float = 5.0,
                 rest_factor: float = 1.0, sign_noise_factor: float = 3.0, lowpass: bool = True,
                 max_samples: int = 6000, modes: bool = True, mode_folds: int = 10, mode_max_samples: int = 1000,
                 gp: bool = True, gp_points: int = 600, gp_hyper_points: int = 300, gp_iter: int = 25,
                 plots: bool = True, seed: int = 0):
        self.effects = effects
        self.selector = selector
        self.differentiator = differentiator
        self.n_folds = n_folds
        self.alpha = alpha
        self.max_steps = max_steps
        self.payload_links = payload_links
        self.reid_min_gain = reid_min_gain
        self.separate = separate
        self.push_alpha = push_alpha
        self.em_modes = em_modes
        self.em_points = em_points
        self.em_gate_peak = em_gate_peak
        self.rest_factor = rest_factor
        self.sign_noise_factor = sign_noise_factor
        self.lowpass = lowpass
        self.max_samples = max_samples
        self.modes = modes
        self.mode_folds = mode_folds
        self.mode_max_samples = mode_max_samples
        self.gp = gp
        self.gp_points = gp_points
        self.gp_hyper_points = gp_hyper_points
        self.gp_iter = gp_iter
        self.plots = plots
        self.seed = seed

    # ---- parts ----------------------------------------------------------------------------
    def _selector(self):
        return ForwardCVSelector(alpha=self.alpha, max_steps=self.max_steps) if self.selector is None \
            else clone(self.selector)

    def _differentiator(self):
        from ..data.differentiation import SavitzkyGolay

        return SavitzkyGolay(cv=True) if self.differentiator is None else self.differentiator

    def _check(self) -> None:
        from ..physics.effects import effect_classes

        if self.separate not in SEPARATION_METHODS:
            raise InputError(f"setting 'separate': expected one of {sorted(SEPARATION_METHODS)}, got {self.separate!r}")
        try:
            effect_classes(self.effects)
        except ValueError as exc:
            raise InputError(f"setting 'effects': {exc}") from None

    # ---- fitting --------------------------------------------------------------------------
    def fit(self, log, robot) -> "Diagnoser":
        """Diagnose ``log`` (a RobotLog, or a log file read against the robot's joints; dq/ddq
        estimated when absent) against ``robot`` (an mmgp RobotModel, or a pinocchio.Model with
        the log's joints). Returns self."""
        self._check()
        _stage("reading the log")
        log = _read(log, robot)
        # the linear algebra here is many small products; multi-threaded BLAS only adds contention
        # (mmgp.threads)
        with limit_threads(1, blas_only=True):
            res = self._diagnose(log, robot)
        res = _checked(res, log, robot)
        # the corrected model (report) is written from the nominal URDF; a bare pinocchio.Model has none
        urdf = getattr(robot, "urdf_path", None)
        res = dataclasses.replace(res, urdf=None if urdf is None else str(urdf))
        self.result_ = res
        self.findings_, self.fit_stages_, self.location_ = res.findings, res.fit, res.location
        self.labels_, self.info_ = res.labels, res.info
        return self

    def report(self, out_dir) -> Path:
        """Write findings.json, report.md, residual plots, (with modes or pushes)
        labels.parquet and the corrected model (corrected.urdf, corrected.xml; not without a
        URDF) into ``out_dir``; returns it."""
        from sklearn.utils.validation import check_is_fitted

        check_is_fitted(self, "result_")
        return self.result_.write(out_dir)

    def _settings(self, *names) -> dict:
        return {k: getattr(self, k) for k in names}

    def _problem(self, log, robot) -> tuple:
        """The prepared log (derivatives, thinning) and the diagnosis's Problem built on it with
        this estimator's settings (:func:`.stages.prepare_log`, :func:`.stages.build_problem`)."""
        log, n_full, smear_s = st.prepare_log(log, self._differentiator(), self.max_samples)
        prob = st.build_problem(log, robot, n_full, smear_s, effects=self.effects, payload_links=self.payload_links,
                                n_folds=self.n_folds, **self._settings("sign_noise_factor", "lowpass", "rest_factor"))
        return log, prob

    def _diagnose(self, log, robot) -> DiagnosisResult:
        laps = _Laps()
        _stage("estimating derivatives, building the effect library")
        log, prob = self._problem(log, robot)
        laps("context_s")
        push_kw = self._settings("push_alpha", "em_modes", "em_points", "em_gate_peak", "seed")
        # the learner's push flags are where the robust fit starts: with many long pushes a fit
        # that starts from least squares can settle where the pushes dragged it
        _stage("multimodal learner (pushes)")
        em = st.run_learner(prob, self.em_modes, max_points=self.em_points, seed=self.seed) \
            if self.separate != "none" else None
        init = None if em is None else 1.0 - em["p_disturbed"]
        prob, couplings, coupling_ev = self._couplings(prob, init)
        _stage("fitting the effects, re-identifying the rigid body")
        lib = st.fit_library(prob, prob.ctx, np.ones(len(prob.t), bool), relinearise=2, init=init)
        lib_rest = st.fit_library(st.without_body(prob), prob.ctx, np.ones(len(prob.t), bool), relinearise=2,
                                  init=init)
        start, reid = reidentify(prob, lib, lib_rest, alpha=self.alpha, min_gain=self.reid_min_gain)
        start = start + couplings
        laps("reidentify_s")
        _stage("separating pushes")
        pushes = st.separate_pushes(prob, lib, self._selector(), method=self.separate, start=start, em=em, **push_kw)
        use = ~pushes.disturbed
        if pushes.disturbed.any():
            lib = st.fit_library(prob, lib.ctx, use, init=None if em is None else 1.0 - em["p_disturbed"])
        laps("separate_s")
        _stage("selecting effects")
        phys, selector, dropped, rb_ev = self._select(prob, lib, use, start)
        held = self._held_com_context(prob, phys, lib.ctx, use)
        if held is not None:
            lib = st.fit_library(prob, held, use, relinearise=2, init=init)
            phys, selector, dropped, rb_ev = self._select(prob, lib, use, start)
        exclude, withheld = self._body_stand_ins(prob, lib, use, start, phys, reid)
        if exclude:
            phys, selector, dropped, rb_ev = self._select(prob, lib, use, start, exclude)
        laps("select_s")
        ms, pushes = self._mode_switch(prob, phys, pushes, laps)
        if ms is not None:
            # the modes explain their part: the other effects are chosen again on what they leave
            # (samples within a filter memory of a switch mix both modes: left out)
            near = near_switches(ms, prob.t, prob.f_c, margin_s=prob.smear_s)
            (prob, body), use = st.with_modes(prob, ms), ~pushes.disturbed & ~near
            _stage("selecting effects again, with the modes")
            phys, selector, dropped, rb_ev = self._select(prob, st.fit_library(prob, phys.ctx, use), use, start + body,
                                                          exclude)
            if pushes.disturbed.any():
                pushes = st.confirm_pushes(prob, phys, pushes, near, push_alpha=self.push_alpha)
                use = ~pushes.disturbed & ~near
            laps("reselect_s")
        denom = st.torque_variance(prob, use)  # (n,) what the held-out errors and the findings' sizes are relative to
        findings = effect_findings(phys, alpha=self.alpha, torque_sd=np.sqrt(denom))
        for f in findings:
            if f["effect"] == "inertial_parameters":
                f["evidence"].update(identifiability=rb_ev, reidentification=reid)
            if f["effect"] == "coupled_transmission":
                f["evidence"]["coupling_search"] = coupling_ev
        fit = self._stage_errors(prob, phys, use, denom, laps)
        if ms is not None:
            findings += mode_effect_findings(ms, phys.ctx)
            findings.append(mode_switch_finding(ms, phys.ctx, alpha=self.alpha, n_folds=self.mode_folds))
        if pushes.disturbed.any():
            findings.append(_disturbance(pushes, prob.t))
        info = {"velocity_delay_s": log.metadata.get("velocity_delay_s", {}),
                "reidentification": reid, "coupling_search": coupling_ev, "dropped": [{"effect": f"{e.name}@{e.where(phys.ctx)}", "p_value": p}
                                                      for e, p in dropped]}
        return dataclasses.replace(self._result(prob, phys, selector, pushes, ms, findings, fit, use, laps, info),
                                   withheld=withheld)

    @staticmethod
    def _held_com_context(prob, phys, ctx, use):
        """On a log whose every joint holds still (:func:`.stages.still_joints`: the torques are
        statics), a payload's centre of mass along gravity has no torque to show, whatever the
        log: the context (the library's ``ctx`` with those directions held on the line through the
        link origin) in which the effects are to be chosen again, where :func:`.fitting.unresolved_com`
        (given the payload's mass alone) leaves such a direction; else None. Left free, the
        first moment there takes whatever the few samples a push tilts say, and look-alikes (a
        spring, an encoder offset) then take its torque."""
        from .fitting import unresolved_com

        if len(st.still_joints(prob, use)) < prob.ctx.n:
            return None
        base, coef = ctx, phys.coefficients()
        for e in phys.chosen:
            held_already = e.index in ctx.payload_held
            if e.name == "payload" and not held_already and coef.get(e.atoms()[0], 0) > 0:
                dirs = [v for v, _ in unresolved_com(phys, e, given_others=False)]
                ctx = ctx.with_payload_held(e.index, np.array(dirs)) if dirs else ctx
        return None if ctx is base else ctx

    def _couplings(self, prob, init):
        """Coupled transmissions (``coupling``), searched first when the effects include them, on
        the valid equations weighted by ``init`` (T,) (the learner's undisturbed probability;
        None: 1). Returns (problem, couplings found, evidence)."""
        from ..physics.effects import effect_classes

        if not any(cls.own_family for cls in effect_classes(self.effects)) or prob.ctx.n < 2:
            return prob, [], []
        W = prob.M * (1.0 if init is None else np.asarray(init, dtype=np.float64)[:, None])
        prob, found, ev = coupling.find_couplings(prob, W, st.nominal_weights(prob), alpha=self.alpha, seed=self.seed)
        return coupling.motor_rest_masks(prob, found, rest_factor=self.rest_factor), found, ev

    def _body_stand_ins(self, prob, lib, use, start, phys, reid: dict) -> tuple[list, list]:
        """Which static effects stand in for the rigid body, and the findings of those ``phys``
        (chosen without the body) holds, withheld with the reason. Where the body is not
        re-identified, an effect whose torque at rest is a function of the positions
        (``Effect.static``: a spring, an offset) may be taking the body's gravity error: the
        effects are chosen once more with the body in the model, and a static effect that is then
        not chosen cannot be told from the body by this log: it is no candidate (the selection
        leaves it out) and, where it was chosen, its finding is withheld. Exempt: an effect whose
        columns lie in the span of the body's base columns (one of the body's own base parameters
        under a physical name, the same torque whichever names it). Effects of motion are kept:
        friction dissipates, which no rigid body does, and a geared joint's rotor inertia is
        expected beside the body (benchmarks/README, "a static effect that stands in for the body
        is withheld"). Returns (effects the selection leaves out, the withheld findings)."""
        from .reidentify import rigid_body

        rb = rigid_body(prob.library)
        if not rb or not reid or reid["re_identified"]:
            return [], []
        _stage("selecting effects again, with the rigid body (its stand-ins)")
        with_body = self._select(prob, lib, use, start + rb)[0]
        static = [e for e in st.candidates(prob, start) if e.static and e not in with_body.chosen]
        apart = _outside_body_span(prob, phys, static)
        static = [e for e, out in zip(static, apart) if out]
        stand_ins = [e for e in phys.chosen if e in static]
        reid["stand_ins"] = [f"{e.name}@{next(iter(e.where(phys.ctx).values()))}" for e in stand_ins]
        if not stand_ins:
            return [], []
        sd = np.sqrt(st.torque_variance(prob, use))
        return static, [stand_in_finding(f, reid)
                        for f in effect_findings(phys, alpha=self.alpha, torque_sd=sd, only=stand_ins)]

    def _select(self, prob, lib, use, start, exclude=()):
        """Forward selection from ``start`` on samples ``use`` among the candidates but
        ``exclude``, nested extensions (load dependence of a found Coulomb friction), backward
        pruning of effects whose own held-out gain is not significant, the refit; then once more
        with the load of load-dependent friction taken from the fitted model. The rigid body,
        when re-identified, is refitted physically consistent."""
        ctx, keys, A = lib.ctx, lib.keys, lib.A
        w = st.nominal_weights(prob, use)
        rounds = 2 if any(e.name == "load_dependent_friction" for e in prob.library) else 1
        for k in range(rounds):
            # robust weights of the whole library's fit: a push the separation missed does not
            # decide which effect wins
            grams = FoldGrams(A, prob.r, use, prob.folds, W=lib.weights)
            cands = [e for e in st.candidates(prob, start) if e not in exclude]
            selector = self._selector().fit(cands, keys, grams, w, ctx, start=start)
            chosen = extend_nested(selector.selected_, prob.library, keys, grams, w, ctx, self.alpha)
            chosen, dropped = prune(chosen, keys, grams, w, self.alpha)
            phys = fit_physics(prob, st.LibraryFit(ctx, keys, A, lib.coef, lib.weights), grams, chosen, w, use,
                               seed=self.seed)
            if k + 1 < rounds:
                ctx = phys.ctx.with_load(model_torque(prob, phys.ctx, chosen, phys.coefficients()))
                keys, A = prob.atoms(ctx)
        coef, rb_ev = consistent_refit(prob, phys, use)
        if coef:
            phys = phys.with_coefficients(coef)
        return phys, selector, dropped, rb_ev

    def _stage_errors(self, prob, phys, use, denom, laps) -> dict:
        _stage("held-out errors per stage")
        still = st.still_joints(prob, use)
        fit = st.stage_errors(prob, phys, use, denom, still=still)
        laps("fit_s")
        if self.gp:
            _stage("GP on what the physics leaves")
            fit["with_physics_and_gp"] = st.gp_stage_errors(prob, phys, use, denom, points=self.gp_points,
                                                             hyper_points=self.gp_hyper_points, n_iter=self.gp_iter,
                                                             seed=self.seed)
            laps("gp_s")
        return {**fit, "folds": self.n_folds, "samples_used": int(use.sum()),
                "samples_excluded_as_disturbed": int((~use).sum()), "still_joints": still}

    def _mode_switch(self, prob, phys, pushes, laps):
        """Does a switchable effect (a payload) that changes over time (two sticky states)
        predict the held-out residual better than one fixed value? If so, pushes are looked for
        again once the modes explain their part of the residual."""
        from .modes import find_mode_switch

        index = {a: i for i, a in enumerate(phys.keys)}
        cands = [(e, phys.A[:, :, [index[a] for a in e.atoms()]]) for e in prob.library if e.switchable]
        if not (self.modes and cands):
            return None, pushes
        _stage("mode switch")
        # the modes the multimodal learner (the inference `mmgp train` makes) sees in what the
        # physics leaves: where the switching fits start, and the gate of the push re-scan
        resid = st.raw_residual(prob, phys)
        em = st.run_learner(prob, max(2, self.em_modes), max_points=self.em_points, seed=self.seed,
                            previous=pushes.em, resid=resid)
        pushes = dataclasses.replace(pushes, em=em)
        e, coef, ctx = phys.residual(prob.r), phys.coefficients(), phys.ctx
        kw = dict(alpha=self.alpha, n_folds=self.mode_folds, max_samples=self.mode_max_samples)
        ms = find_mode_switch(cands, e, phys.w, prob.M, prob.t, prob.f_c, coef, ctx, init=em["mode"], **kw)
        if ms is not None and ms.effect.linearised:
            # the point mass's inertia is linearised at one centre of mass for both modes: at the
            # heavier mode's own (the lighter one's mass makes its part small), then refitted
            eff, C0 = ms.effect, dict(cands)[ms.effect]
            atoms = eff.atoms()
            ctx = eff.relinearise(dict(zip(atoms, ms.base + ms.theta[1])), ctx)
            C = prob.lowpass(np.stack(eff.columns(ctx), axis=2))
            e = e + (C0 - C) @ ms.base
            again = find_mode_switch([(eff, C)], e, phys.w, prob.M, prob.t, prob.f_c, coef, ctx, init=ms.labels, **kw)
            ms = again or ms
        if ms is not None and self.separate in ("auto", "scan"):
            pushes = st.rescan_pushes(prob, ms, phys, pushes, resid, method=self.separate,
                                      **self._settings("push_alpha", "em_modes", "em_points", "em_gate_peak", "seed"))
        laps("modes_s")
        return ms, pushes

    def _result(self, prob, phys, selector, pushes, ms, findings, fit, use, laps, extra: dict) -> DiagnosisResult:
        from .location import locate

        ctx, t = phys.ctx, prob.t
        loc = locate(prob.r[use], ctx.q[use], ctx.dq[use], ctx.ddq[use], prob.tau[use], ctx.tau_rbd[use], t[use],
                     ctx.v_s, ctx.joint_names)
        info = {"n_samples": len(t), "n_samples_in_log": prob.n_samples_in_log, "n_candidates": len(prob.library),
                "n_folds": self.n_folds, "lowpass_hz": prob.f_c, "sign_noise_factor": self.sign_noise_factor,
                "v_s": ctx.v_s.tolist(),
                "selection_path": [{"effects": [f"{e.name}@{e.where(ctx)}" for e in p.effects[-1:]], "cv": p.cv_mean}
                                   for p in selector.path_],
                "chosen_step": selector.chosen_step_,
                "separation": {k: v for k, v in pushes.info.items() if k != "spans"}, **extra,
                "timings": laps.total()}
        plot = None
        if self.plots:
            plot = {"q": ctx.q[use], "dq": ctx.dq[use], "tau": prob.tau[use], "r_before": prob.r[use],
                    "r_after": phys.residual(prob.r)[use], **dict(zip(("friction", "friction_law"), (f[use] for f in _friction_torque(phys)))),
                    "joint_names": ctx.joint_names}
        labels = None
        if pushes.disturbed.any() or ms is not None:
            labels = {"t": t.copy(), "mode": (ms.labels if ms is not None else np.zeros(len(t), int)).astype(int),
                      "disturbed": pushes.disturbed.astype(int)}
        return DiagnosisResult(findings=findings, fit=fit, location=loc, joint_names=ctx.joint_names, info=info,
                               plot_data=plot, labels=labels)


FRICTION = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
# linear dependence up to rounding: the columns are built from the same states by one filter
SPAN_RTOL = 1e-6


def _friction_torque(phys) -> tuple[np.ndarray, np.ndarray]:
    """(T, n) the fitted friction laws' torque, N*m: low-passed like the residual, and as the
    laws themselves (unfiltered, to draw against velocity)."""
    from ..physics.effects import build_atoms
    from .selection import atom_indices

    chosen = [e for e in phys.chosen if e.name in FRICTION]
    if not chosen:
        return np.zeros(phys.A.shape[:2]), np.zeros(phys.A.shape[:2])
    coef = phys.coefficients()
    S = atom_indices(chosen, {a: i for i, a in enumerate(phys.keys)})
    keys, A = build_atoms(chosen, phys.ctx)
    return (phys.A[:, :, S] @ np.array([coef[phys.keys[i]] for i in S]),
            A @ np.array([coef.get(k, 0.0) for k in keys]))


def _disturbance(pushes, t: np.ndarray) -> dict:
    evidence = {"method": pushes.info.get("method"), "threshold": pushes.info.get("threshold")}
    if pushes.em is not None:
        p = pushes.em["p_disturbed"]
        evidence["em_p_disturbed_max_per_span"] = [float(p[a:b].max()) for a, b in runs(pushes.disturbed)][:50]
    return disturbance_finding(pushes.disturbed, spans_of(pushes.disturbed, t), evidence)


def _outside_body_span(prob, phys, effects) -> list[bool]:
    """Per effect, whether its columns leave the span of the rigid body's base columns on the
    log's valid equations (a least-squares fit by them leaves more than ``SPAN_RTOL`` of some
    column's norm); inside it, the effect and the body are one parameter of the log's torque."""
    if not effects:
        return []
    index = {a: i for i, a in enumerate(phys.keys)}
    rb = [i for i, a in enumerate(phys.keys) if a[0] == "rb"]
    cols = [[index[a] for a in e.atoms()] for e in effects]
    valid = prob.M > 0
    B, E = phys.A[:, :, rb][valid], phys.A[:, :, sum(cols, [])][valid]
    left = np.linalg.norm(E - B @ np.linalg.lstsq(B, E, rcond=None)[0], axis=0)
    out = left > SPAN_RTOL * np.maximum(np.linalg.norm(E, axis=0), 1e-300)
    bounds = np.cumsum([0] + [len(c) for c in cols])
    return [bool(out[a:b].any()) for a, b in zip(bounds[:-1], bounds[1:])]


def _checked(res: DiagnosisResult, log, robot) -> DiagnosisResult:
    """``res`` with what fails the plausibility checks (the log's, ``mmgp.physics.plausibility``,
    and the answer's, ``plausibility.check``) withheld and the warnings in words."""
    from ..physics.context import pin_model
    from ..physics.plausibility import log_checks
    from .plausibility import check

    # the velocities the diagnosis replaced (``undelay_velocities``, in prepare_log) are told too
    delay = res.info.get("velocity_delay_s")
    log = log.replace(metadata={**log.metadata, "velocity_delay_s": delay}) if delay else log
    kept, withheld, warnings = check(res.findings, res.fit, res.joint_names, pin_model(robot),
                                     log_checks(log, res.joint_names, robot))
    return dataclasses.replace(res, findings=kept, withheld=res.withheld + withheld, warnings=warnings)


def _read(log, robot):
    """The RobotLog ``fit`` was given, or the log file read and checked against ``robot``."""
    from ..data.logs import RobotLog, read_log

    if isinstance(log, RobotLog):
        return log
    names = getattr(robot, "joint_names", None)
    return read_log(log, n_joints=len(names) if names else None, joint_names=names)
