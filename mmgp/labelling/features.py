"""GP inputs and targets from checked logs: [q, dq, ddq, sliding sign of dq], the rigid-body part
(residual or feature) and the rigid-body regressor basis of each mode's mean."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..data.channels import dead_banded
from ..data.differentiation import SavitzkyGolay, complete_derivatives, downsample
from ..data.logs import RobotLog, read_log
from ..errors import InputError
from ..progress import report
from ..physics.context import rest_weight, resting


def load_logs(sources: Sequence[str | Path | RobotLog], *, robot=None, diff_window_s: float | None = None,
              rate_hz: float | None = None) -> list[RobotLog]:
    """Read (paths) and check each log, complete its derivatives (Savitzky-Golay, window
    ``diff_window_s`` or per joint by cross-validation) and downsample it to ``rate_hz``."""
    logs = []
    n_ref = None
    for i, src in enumerate(sources):
        report(f"reading and differentiating log {i + 1} of {len(sources)}")
        if isinstance(src, RobotLog):
            log = src
            if robot is not None:
                robot.check_log(log.n_joints, log.joint_names, file=log.path)
        else:
            log = read_log(src, n_joints=robot.n_joints if robot is not None else None,
                           joint_names=robot.joint_names if robot is not None else None)
        if n_ref is None:
            n_ref = log.n_joints
        elif log.n_joints != n_ref:
            raise InputError(f"log has {log.n_joints} joints but the first log has {n_ref}", file=log.path,
                             column="q_0")
        log = complete_derivatives(log, SavitzkyGolay(window_s=diff_window_s, cv=True))
        logs.append(log)
    return thin_logs(logs, rate_hz)[0]


def thin_logs(logs: list[RobotLog], rate_hz: float | None) -> tuple[list[RobotLog], dict | None]:
    """``logs`` downsampled to about ``rate_hz`` (:func:`mmgp.data.differentiation.downsample`,
    after differentiating), and what that did: ``{"rate_hz", "n_read", "n_used"}`` (samples read,
    samples kept; equal when every log's rate is at or below ``rate_hz``); None without a rate."""
    if rate_hz is None:
        return logs, None
    thinned = [downsample(log, rate_hz) for log in logs]
    return thinned, {"rate_hz": float(rate_hz), "n_read": int(sum(lg.n_samples for lg in logs)),
                     "n_used": int(sum(lg.n_samples for lg in thinned))}


@dataclass(frozen=True)
class MeanBasis:
    """The linear part of each mode's mean, under its GP: ``body`` "rbd" (every link's inertial
    parameters: the rigid-body regressor) or "payload" (the distal body's ten, one coefficient
    vector shared by the joints), with ``friction`` the per-joint dry-friction columns after them
    (Coulomb and load-dependent: :func:`friction_columns`). Its ``name`` ("payload+friction") is
    what a saved model records."""

    body: str
    friction: bool = False

    BODIES = ("rbd", "payload")

    def __post_init__(self):
        if self.body not in self.BODIES:
            raise ValueError(f"mean basis body must be one of {self.BODIES}, got {self.body!r}")

    @classmethod
    def parse(cls, name: str | None) -> "MeanBasis | None":
        """The basis a saved ``name`` records ("rbd", "payload", either + "+friction"); None: none.
        Raises ValueError on any other name."""
        if name is None:
            return None
        body, plus, extra = str(name).partition("+")
        if plus and extra != "friction":
            raise ValueError(f"unknown mean basis {name!r}")
        return cls(body, friction=bool(plus))

    @property
    def name(self) -> str:
        return self.body + ("+friction" if self.friction else "")

    @property
    def shared(self) -> bool:
        """One coefficient vector for every joint (a payload is one body)."""
        return self.body == "payload"

    def n_dry(self, n: int) -> int:
        """How many of the last columns are dry friction, for ``n`` joints."""
        return 2 * n if self.friction else 0

    def columns(self, robot, q, dq, ddq, tau_rbd, dry_sign) -> np.ndarray:
        """(T, n, p) the basis at states q, dq, ddq (T, n): the body's regressor columns, then
        with ``friction`` the Coulomb and load-dependent columns of ``dry_sign`` (T, n), the
        direction dry friction acts in, and the rigid body's torque ``tau_rbd`` (its load)."""
        Y = robot.regressor(q, dq, ddq)
        basis = Y if self.body == "rbd" else Y[..., -10:]
        return np.concatenate([basis, self.dry_columns(dry_sign, tau_rbd)], axis=2) if self.friction else basis

    @staticmethod
    def dry_columns(dry_sign: np.ndarray, tau_rbd: np.ndarray) -> np.ndarray:
        """(T, n, 2n) the dry-friction columns: Coulomb (``dry_sign`` (T, n)) and load-dependent
        (``dry_sign`` times the rigid body's torque's magnitude), one per joint."""
        return np.concatenate([friction_columns(dry_sign), friction_columns(dry_sign * np.abs(tau_rbd))], axis=2)


@dataclass
class Features:
    """GP inputs and targets built from logs. X (T, d), Y (T, n), tau_rbd (T, n) or None."""

    X: np.ndarray
    Y: np.ndarray
    tau_rbd: np.ndarray | None
    starts: list[int]
    t: np.ndarray | None = None
    basis: np.ndarray | None = None   # (T, n, p) rigid-body regressor, when the mean uses it
    muted: np.ndarray | None = None   # (n,) bool: dead-banded torque channels (no vote on pushes)
    has_sign: bool = False            # X's columns 3n..4n hold the smooth velocity sign

    def rest_band(self, mean_basis: MeanBasis | None, friction_scale: np.ndarray):
        """The EM's :class:`~mmgp.labelling.mstep.RestBand` for these features: the rest weights of
        the velocities (X's columns n..2n) at the smooth-sign scale ``friction_scale`` (n,) rad/s,
        the smooth-sign input columns (after q, dq, ddq) and the basis ``mean_basis`` on both
        sliding branches; None without the smooth-sign input."""
        from .mstep import RestBand

        n = self.Y.shape[1]
        if self.X.shape[1] < 4 * n:
            return None
        branches, dry_cols = None, []
        n_dry = mean_basis.n_dry(n) if mean_basis is not None else 0
        if n_dry:
            # the basis with its dry-friction columns (the last) on each sliding branch
            p = self.basis.shape[2]
            branches = tuple(np.concatenate([self.basis[..., :-n_dry], mean_basis.dry_columns(
                np.full_like(self.tau_rbd, s), self.tau_rbd)], axis=2) for s in (1.0, -1.0))
            dry_cols = list(range(p - n_dry, p))
        return RestBand(rest_weight(self.X[:, n:2 * n], friction_scale), list(range(3 * n, 4 * n)), branches, dry_cols)


    def velocity_reversal(self, mean_basis: MeanBasis | None):
        """What changes sign when every joint velocity reverses (a
        :class:`~mmgp.labelling.dissipation.VelocityReversal`): dq (X's columns n..2n), its smooth
        sign (3n..4n, with the friction input) and the basis's dry-friction columns (the last
        ``mean_basis.n_dry``); the rigid-body terms are even in dq."""
        from .dissipation import VelocityReversal

        n = self.Y.shape[1]
        dq = list(range(n, 2 * n))
        sign = list(range(3 * n, 4 * n)) if self.has_sign else []
        return VelocityReversal(dq, dq + sign, mean_basis.n_dry(n) if mean_basis is not None else 0)


def rest_band_on(setting, rigid_basis: MeanBasis | None) -> bool:
    """Whether training uses the friction band at rest (MultimodalGP ``rest_band``): ``setting``
    True / False, or "auto": on where the mean has a rigid-body basis (``rigid_basis``, from
    :func:`resolve_mean_basis` without friction), whose load makes the friction columns. Without
    one the band is read off the GP alone, and its target at rest depends on where the EM stops
    (benchmarks/README.md, "The friction band at rest becomes the default")."""
    if isinstance(setting, str) and setting == "auto":
        return rigid_basis is not None
    return bool(setting)


def resolve_mean_basis(kind: str, robot, semiparametric: str, friction: bool = False) -> MeanBasis | None:
    """The mean basis a model uses (MultimodalGP ``mean_basis``: "auto", "payload", "rbd" or
    "none"): a :class:`MeanBasis` with ``friction`` (the per-joint dry-friction columns join it),
    or None."""
    rbd_ok = robot is not None and semiparametric == "residual"
    if kind == "auto":
        kind = "payload" if rbd_ok else "none"
    if kind in MeanBasis.BODIES and not rbd_ok:
        raise InputError(f"mean_basis '{kind}' needs a robot model and semiparametric 'residual'")
    if kind == "none":
        return None
    return MeanBasis(kind, friction=friction)


@dataclass(frozen=True, eq=False)
class StateFeatures:
    """How states become the GP's inputs and targets, the one recipe of ``train``, ``predict``,
    ``compare`` and the diagnosis's learner.

    Inputs [q, dq, ddq(, friction input)(, tau_rbd)]: the friction input at the smooth-sign scale
    ``friction_scale`` (n,) rad/s (None: none), faded at rest (:func:`sliding_sign`) when
    ``sign_fades`` (with the friction band at rest), else ``tanh(dq / v_s)`` (models before
    version 4, and the diagnosis's learner, which has no band); with ``robot`` (a RobotModel)
    ``semiparametric`` "residual" (targets tau - RNEA), "feature" (RNEA as inputs) or "none";
    ``mean_basis`` the columns of each mode's linear mean (None: none)."""

    semiparametric: str
    robot: object = None
    friction_scale: np.ndarray | None = None
    sign_fades: bool = True
    mean_basis: MeanBasis | None = None

    def __call__(self, q, dq, ddq, tau, starts=(0,), friction_sign=None, basis: bool = True) -> Features:
        """Features at states q, dq, ddq and torques tau (T, n); ``friction_sign`` (+1 or -1, or
        per sample (T, 1)) replaces the friction input (prediction on one sliding branch);
        ``basis`` False: without the mean's columns."""
        # Coulomb friction is a step in dq that an RBF kernel can only follow with a tiny velocity
        # lengthscale, which then also lets the GP memorise pushes; a smooth-sign input gives the
        # step to the GP directly, so lengthscales can stay long.
        scale = self.friction_scale
        parts = [q, dq, ddq]
        if scale is not None:
            if friction_sign is not None:
                parts.append(np.full_like(dq, friction_sign))
            else:
                parts.append(sliding_sign(dq, scale) if self.sign_fades else np.tanh(dq / scale))
        X = np.concatenate(parts, axis=1)
        tau_rbd = None
        if self.robot is not None and self.semiparametric != "none":
            tau_rbd = self.robot.rnea(q, dq, ddq)
            if self.semiparametric == "feature":
                X = np.concatenate([X, tau_rbd], axis=1)
        Y = tau - tau_rbd if (tau_rbd is not None and self.semiparametric == "residual") else tau
        mean_basis = self.mean_basis if basis else None
        columns, sign = None, None
        if mean_basis is not None and mean_basis.friction:
            if scale is None:
                raise ValueError("a '+friction' mean basis needs the friction input (friction_scale)")
            # Dry friction per joint, last: Coulomb (smooth sign) and load-dependent (sign x |tau_rbd|,
            # gear friction growing with the load), as physics in the mean, so a sliding branch seen
            # once is still predicted and the band at rest grows with the load (MultimodalGP
            # rest_band). No viscous column: fitted, it extrapolated far beyond the true damping at
            # speed.
            sign = dry_friction_sign(dq, scale) if friction_sign is None else np.full_like(dq, friction_sign)
        if mean_basis is not None:
            columns = mean_basis.columns(self.robot, q, dq, ddq, tau_rbd, sign)
        return Features(X, Y, tau_rbd, list(starts), basis=columns, has_sign=scale is not None)

    def of_logs(self, logs: Sequence[RobotLog]) -> Features:
        """Features of checked logs (joined in time order), with their times, log starts and
        dead-banded torque channels (:func:`mmgp.data.channels.dead_banded`)."""
        q, dq, ddq, tau = (np.concatenate([getattr(lg, a) for lg in logs]) for a in ("q", "dq", "ddq", "tau"))
        starts = list(np.cumsum([0] + [lg.n_samples for lg in logs[:-1]]))
        f = self(q, dq, ddq, tau, starts)
        f.t = np.concatenate([lg.t for lg in logs])
        f.muted = dead_banded(tau)
        return f


def sliding_sign(dq: np.ndarray, friction_scale: np.ndarray) -> np.ndarray:
    """(T, n) the GP's friction input: the smooth sign ``tanh(dq / v_s)`` times one minus the rest
    weight (:func:`~mmgp.physics.context.rest_weight`), 0 where the joint rests, the smooth sign
    where it slides. Dry friction has a direction only while the joint slides: at rest the
    velocity's sign is the noise's, and a stuck joint holds any torque in its band. Read there,
    a hold at one edge of the band with the noise's sign teaches the GP an odd function of that
    noise, which then predicts friction pushing the joint along on the next slide from the same
    pose (energy injected: validation val03's start of a slide after a hold)."""
    return np.tanh(dq / friction_scale) * (1.0 - rest_weight(dq, friction_scale))


def dry_friction_sign(dq: np.ndarray, friction_scale: np.ndarray) -> np.ndarray:
    """(T, n) the direction dry friction acts in, per joint: the velocity's sign where the joint
    slides (rest weight at most 1/2, :func:`~mmgp.physics.context.rest_weight`), the smooth sign
    ``tanh(dq / v_s)`` where it may be stuck. Coulomb friction is a step: a joint creeping at
    half the smooth-sign scale already slides against its whole friction, and a column that gave
    it half would leave the other half to whatever else the mean can bend (a payload's gravity
    column). Where it may be stuck the band at rest (:class:`~mmgp.labelling.mstep.RestBand`) reads
    the torque instead."""
    sliding = ~resting(rest_weight(dq, friction_scale))
    return np.where(sliding, np.sign(dq), np.tanh(dq / friction_scale))


def friction_columns(v: np.ndarray) -> np.ndarray:
    """(T, n, n) regressor columns of a per-joint term: column j holds v[:, j] in joint j's row."""
    T, n = v.shape
    out = np.zeros((T, n, n))
    out[:, np.arange(n), np.arange(n)] = v
    return out


def input_names(n: int, with_rbd: bool, with_friction: bool) -> list[str]:
    """Names of the GP input columns, in order."""
    names = [f"q_{j}" for j in range(n)] + [f"dq_{j}" for j in range(n)] + [f"ddq_{j}" for j in range(n)]
    if with_friction:
        names += [f"tanh(dq_{j}/v_s)" for j in range(n)]
    if with_rbd:
        names += [f"tau_rbd_{j}" for j in range(n)]
    return names
