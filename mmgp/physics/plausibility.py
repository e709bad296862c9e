"""Whether a log can be believed: the checks of a log's arrays, alone and against the robot model.

Wrong inputs (another robot's model, angles in degrees, joints in another order, a log of noise)
still give numbers; ``mmgp train``, ``mmgp diagnose`` and ``mmgp compare`` all call
:func:`log_checks` once on the logs they checked and read, and report its warnings in the same
words (report.json ``warnings``, the diagnosis's ``warnings``, compare.json ``warnings``), so
every command warns the same way. The checks only warn: labels and figures are unchanged (the
diagnosis withholds its findings when a check of the first kind fails,
``mmgp.diagnosis.plausibility``).

Checks that make the log's numbers suspect: positions inside the model's joint limits (another
robot, joints in another order, or units), positions that span more than two turns (degrees:
the log must hold radians; no model needed), logged velocities that are the time derivative of
the logged positions (columns swapped, mixed units, a log of noise). Checks that only inform:
a torque channel that reads one exact value on most samples (``mmgp.data.channels``), and logged
velocities that lagged their positions and were replaced by the positions' derivatives
(``mmgp.data.differentiation.undelay_velocities``).

Checks of the held-out fit (:func:`fit_warnings`: each command passes its own held-out
normalised MSE per joint, where 1 is the torque's own mean; they come after the log's checks):
a nominal model worse than the mean on most joints (another robot's model, or a URDF far from the
robot: said apart by whether the command's learnt model predicts those joints; joints held
still, whose torque varies by its noise alone, are not judged against the mean), and a joint
whose torque not even the learnt model predicts better than its mean (a log of noise, a wrong
column, or a joint too still for its torque to rise above the sensor's noise).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.channels import dead_band_warnings
from ..data.differentiation import position_difference
from ..data.filtering import lowpass_for
from ..data.statistics import difference_noise_sd
from .context import pin_model

#: angles beyond the model's limits by more than this (rad) count as violations
LIMIT_MARGIN = 0.05
#: share of the samples beyond the limits that makes a warning
LIMIT_FRACTION = 0.01
#: a joint whose positions span more than this (rad, two turns) is read as logged in degrees
MAX_SPAN_RAD = 4 * np.pi
#: logged dq against the derivative of the logged q: lowest correlation, largest scale mismatch
MIN_DQ_CORRELATION = 0.7
MAX_DQ_SCALE_RATIO = 1.5
#: the position's motion (variance in its band, less the noise's) must exceed this many times the
#: noise's variance there for a joint's velocity to be judged
MOTION_NOISE_RATIO = 10.0


def _limited_joints(model) -> list[tuple[int, float, float]]:
    """(joint index, lower, upper) of the revolute/prismatic joints with finite limits."""
    out = []
    for k, j in enumerate(range(1, model.njoints)):
        if model.nqs[j] != 1:
            continue
        i = model.idx_qs[j]
        lo, hi = float(model.lowerPositionLimit[i]), float(model.upperPositionLimit[i])
        if np.isfinite(lo) and np.isfinite(hi) and hi > lo and hi - lo < 1e3:
            out.append((k, lo, hi))
    return out


def limit_warnings(q: np.ndarray, model, names: list) -> list[str]:
    """Warnings for positions ``q`` (T, n) rad outside the limits of pinocchio ``model``."""
    out = []
    for k, lo, hi in _limited_joints(model):
        beyond = (q[:, k] < lo - LIMIT_MARGIN) | (q[:, k] > hi + LIMIT_MARGIN)
        if beyond.mean() > LIMIT_FRACTION:
            out.append(f"{names[k]}: the logged position leaves the model's joint limits [{lo:.3g}, {hi:.3g}] rad "
                       f"on {100 * beyond.mean():.0f}% of the samples (range {q[:, k].min():.3g} to "
                       f"{q[:, k].max():.3g}): wrong robot model, joint order or units")
    return out


def degree_warnings(q: np.ndarray, names: list) -> list[str]:
    """One warning naming the joints of ``q`` (T, n) whose positions span more than
    :data:`MAX_SPAN_RAD` (two turns): a range only degrees explain. Needs no robot model."""
    span = np.ptp(q, axis=0)
    deg = [names[k] for k in range(q.shape[1]) if span[k] > MAX_SPAN_RAD]
    if not deg:
        return []
    return [f"{', '.join(deg)}: the positions span more than two turns ({span.max():.3g}); angles in "
            "degrees? (the log must hold radians)"]


def _band_statistics(t: np.ndarray, a: np.ndarray, b: np.ndarray, na: np.ndarray, nb: np.ndarray):
    """(covariance, signal variance of a, of b, noise variance of b, of a), (n,) each, of ``a`` and
    ``b`` (T, n) low-passed alike to the band where ``b`` moves (``lowpass_for``), their white
    noises of variances ``na``, ``nb`` (n,) taken out at the filter's noise gain."""
    lp, _ = lowpass_for(t, b)
    a, b = lp(a - a.mean(0)), lp(b - b.mean(0))
    impulse = np.zeros((len(t), 1))
    impulse[len(t) // 2] = 1.0
    gain = float(np.sum(lp(impulse) ** 2))  # variance of filtered unit white noise
    a, b = a - a.mean(0), b - b.mean(0)
    return (np.mean(a * b, axis=0), np.mean(a * a, axis=0) - gain * na, np.mean(b * b, axis=0) - gain * nb,
            gain * nb, gain * na)


def velocity_warnings(t: np.ndarray, q: np.ndarray, dq: np.ndarray, names: list) -> list[str]:
    """Warnings where logged velocities ``dq`` (T, n) are not the time derivative of ``q``: the
    central difference of q over about 20 ms, correlated with dq and compared in scale.

    Both are compared in the band where the position moves (a zero-phase low-pass, the same for
    both) with their white noise taken out (each noise from its signal's second differences: dq's
    robustly, q's as an RMS, an encoder being quantised): an arm holding a pose has a logged
    velocity that is noise, whose correlation with the position's steps says nothing. A joint
    whose position moves no more than :data:`MOTION_NOISE_RATIO` times its noise variance in that
    band is not judged (nothing to compare); where its motion stays under the velocity's own noise
    there, only a velocity larger than the position allows is told (it could not show the
    motion); above both, a velocity that shows none of it is (scale ratio near 0)."""
    dt = float(np.median(np.diff(t)))
    fd, h = position_difference(t, q)
    if len(t) <= 2 * h + 10:
        return []
    v = dq[h:-h]
    nq = difference_noise_sd(q, robust=False) ** 2
    cov, sa, sb, nb, na = _band_statistics(t[h:-h], v, fd, difference_noise_sd(dq) ** 2, 2 * nq / (2 * h * dt) ** 2)
    out = []
    for k in range(q.shape[1]):
        if not sb[k] > MOTION_NOISE_RATIO * nb[k]:
            continue
        corr = float(cov[k] / np.sqrt(sa[k] * sb[k])) if sa[k] > 0 else 0.0
        ratio = float(np.sqrt(max(sa[k], 0.0) / sb[k]))
        # under the velocity's own noise a motion need not show: only a velocity larger than the
        # position allows (units) is then told
        shows = sb[k] > na[k]
        if ratio >= MAX_DQ_SCALE_RATIO or shows and (corr < MIN_DQ_CORRELATION or ratio <= 1 / MAX_DQ_SCALE_RATIO):
            out.append(f"{names[k]}: the logged velocity is not the time derivative of the logged position "
                       f"(correlation {corr:.2f}, scale ratio {ratio:.2f}, of the motion above the sensors' noise): "
                       "columns swapped, mixed units or a corrupt log")
    return out


def log_checks(logs, names: list, robot=None) -> tuple[list[str], list[str]]:
    """(warnings that make the numbers of ``logs`` suspect, warnings that only inform).

    ``logs``: a :class:`mmgp.RobotLog` or a list of them (one robot's recordings, checked and
    read); ``names`` (n,) the joint names; ``robot``: a RobotModel (or pinocchio model) of the
    log's joints, or None (then the limits are not checked). Velocities are checked where they
    were logged (not estimated), per log."""
    logs = list(logs) if isinstance(logs, (list, tuple)) else [logs]
    q = np.concatenate([lg.q for lg in logs])
    suspect = limit_warnings(q, pin_model(robot), names) if robot is not None else []
    suspect += degree_warnings(q, names)
    for lg in logs:
        if lg.dq is not None and not getattr(lg, "dq_estimated", False):
            where = f"{Path(str(lg.path)).name}: " if len(logs) > 1 else ""
            suspect += [where + w for w in velocity_warnings(lg.t, lg.q, lg.dq, names)]
    return suspect, dead_band_warnings(np.concatenate([lg.tau for lg in logs]), names) + delay_notes(logs)


def delay_notes(logs: list) -> list[str]:
    """One note per log whose logged velocities lagged their positions and were replaced
    (``mmgp.data.differentiation.undelay_velocities``: ``metadata["velocity_delay_s"]``)."""
    out = []
    for lg in logs:
        late = lg.metadata.get("velocity_delay_s") or {}
        if late:
            where = f"{Path(str(lg.path)).name}: " if len(logs) > 1 else ""
            ms = [1e3 * s for s in late.values()]
            out.append(f"{where}the logged velocity of {len(late)} joint(s) ({', '.join(late)}) lags the derivative "
                       f"of the logged position by {min(ms):.0f}-{max(ms):.0f} ms (a filtered velocity estimate): "
                       "their velocities and accelerations were taken from the positions instead")
    return out


def log_warnings(logs, names: list, robot=None) -> list[str]:
    """All the warnings of :func:`log_checks`, in its order."""
    suspect, notes = log_checks(logs, names, robot)
    return suspect + notes


def nominal_fit_warning(names: list, nominal, learnt=None, learnt_label: str = "the learnt model",
                        still=()) -> list[str]:
    """One warning when the nominal model predicts the held-out torque worse than its mean
    (normalised MSE ``nominal`` (n,) > 1) on most of the judged joints, else none. ``learnt`` (n,):
    the command's own model's figure; where it predicts every such joint (< 1) the URDF is far
    from the robot rather than another robot's model, and the warning says so. ``still``: names
    of joints held still (their torque varies by its noise alone), not judged: there the torque's
    mean is exact and any model's error in the torque's level, however small, is "worse" (a
    held pose)."""
    judged = [k for k, j in enumerate(names) if j not in set(still)]
    worse = [k for k in judged if nominal[k] is not None and nominal[k] > 1.0]
    if len(worse) <= len(judged) / 2:
        return []
    head = (f"the nominal model predicts the torque worse than its mean on {len(worse)} of {len(names)} joints "
            f"(held-out nMSE up to {max(nominal[k] for k in worse):.3g})")
    if learnt is not None and all(learnt[k] is not None and learnt[k] < 1.0 for k in worse):
        return [f"{head}, and {learnt_label} predicts them (nMSE up to {max(learnt[k] for k in worse):.3g}): the "
                "URDF is far from this robot (its inertial parameters, friction or a payload), or it is another "
                "robot's model"]
    return [f"{head}: a wrong robot model, joint order or units, or a URDF far from the robot"]


def unpredictable_joints(learnt, nominal=None) -> list[int]:
    """Joints whose torque no model predicts: held-out normalised MSE ``learnt`` (n,) above 1
    (worse than the torque's own mean) and ``nominal`` (n,) too, where given. A learnt model
    worse than a nominal one that predicts is short of samples, not the log wrong."""
    return [k for k, v in enumerate(learnt) if v is not None and v > 1.0
            and (nominal is None or nominal[k] is None or nominal[k] > 1.0)]


def unpredictable_warning(name: str, nmse: float, learnt_label: str = "the learnt model",
                          nominal: float | None = None) -> str:
    """The warning for a joint whose torque neither ``learnt_label`` (held-out normalised MSE
    ``nmse``) nor the nominal model (``nominal``, if any) predicts better than its mean."""
    who = (f"neither the nominal model (nMSE {nominal:.3g}) nor {learnt_label} (nMSE {nmse:.3g}) predicts"
           if nominal is not None else f"{learnt_label} (nMSE {nmse:.3g}) does not predict")
    return (f"{name}: {who} the held-out torque better than its mean: the torque there is not a function of the "
            "logged state (a log of noise, a wrong column, or a joint too still for its torque to rise above the "
            "sensor's noise)")


def fit_warnings(names: list, nominal=None, learnt=None, learnt_label: str = "the learnt model") -> list[str]:
    """The held-out fit's warnings of a command (module docstring): ``nominal`` (n,) and
    ``learnt`` (n,) held-out normalised MSE per joint of the nominal rigid body and of the
    command's model (either None when absent)."""
    out = nominal_fit_warning(names, nominal, learnt, learnt_label) if nominal is not None else []
    if learnt is not None:
        out += [unpredictable_warning(names[k], learnt[k], learnt_label, None if nominal is None else nominal[k])
                for k in unpredictable_joints(learnt, nominal)]
    return out
