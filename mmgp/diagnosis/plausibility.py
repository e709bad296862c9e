"""Whether a diagnosis can be believed: checks of the inputs and of the answer.

Wrong inputs (another robot's model, angles in degrees, joints in another order, a log of noise)
still give numbers; without these checks they come out as confident findings (a torque-sensor
offset of -183 N*m, a payload of 590 kg). Each check here gives a warning in words; what fails
a check is withheld from ``findings`` (kept under ``withheld_findings`` with the reason), never
silently reported.

Input checks (the log against the model: positions inside the model's joint limits, angles
that are radians, logged velocities that are the time derivative of the logged positions) are
the log-level checks every command runs, ``mmgp.physics.plausibility.log_checks``; when one of
them fails, every finding is withheld. Answer checks (here): the model with the found physics
must predict each joint's torque better than the torque's mean (held-out normalised MSE < 1; a
nominal model worse than the mean on most joints is told), and each finding's magnitude must
be physically possible (a torque offset or friction level within the joint's rated torque, a
payload mass positive and below the robot's own mass). A finding whose torque is under ``MIN_TORQUE_SHARE`` of its joint torque's
spread is withheld as too small to name (no warning).
"""
from __future__ import annotations

import numpy as np

from ..physics.plausibility import nominal_fit_warning


#: Level of the test that a still joint's found physics predicts worse than the nominal model and
#: the mean (``fit_warnings``), over the still joints together (Bonferroni): the conventional 5%.
STILL_LEVEL = 0.05


def fit_warnings(fit: dict, names: list) -> tuple[list[str], set]:
    """Warnings from the held-out errors per stage, and the joints whose findings they withhold:
    each joint the found physics leaves worse than the torque's mean, every joint (and the
    whole-log findings) when that is most of them; each joint the found physics predicts worse
    than the nominal model is told. A nominal model worse than the mean on most
    joints is told, but withholds nothing by itself: a real arm's URDF can be that far off and
    the re-identified body right.
    A joint held still (``fit["still_joints"]``: its torque varies by its noise alone) is judged
    against the nominal model as well as the mean: there the mean is exact, and a model's error
    in the torque's level of a fraction of a percent is many times the noise's variance (a UR5
    holding 2.5 kg: the shoulder's 14.8 N*m static torque against 0.1 N*m of noise). And it is
    worse only where the time blocks say so (``fit["still_worse_p"]``, signed-rank, at the 5%
    level over the still joints): every model's held-out error there is the noise's, give or
    take the blocks' chance."""
    bad = set()
    nom = fit.get("nominal", {}).get("nmse", {})
    phys = fit.get("with_physics", {}).get("nmse", {})
    still = set(fit.get("still_joints", ()))
    worse_p = fit.get("still_worse_p", {})
    level = STILL_LEVEL / max(len(still), 1)
    out = nominal_fit_warning(names, [nom.get(j, 0.0) for j in names],
                              [phys.get(j) for j in names] if phys else None, "the model with the found physics",
                              still=still)
    for j in names:
        reference = max(1.0, nom.get(j, 0.0)) if j in still else 1.0
        if phys.get(j, 0.0) > reference and (j not in still or worse_p.get(j, 0.0) < level):
            out.append(f"{j}: even with the found physics the model predicts the torque worse than its mean "
                       f"(held-out nMSE {phys[j]:.3g}); findings on this joint are withheld")
            bad.add(j)
        elif phys.get(j, 0.0) > max(1.25 * nom.get(j, 0.0), nom.get(j, 0.0) + 0.01):
            # told, withholding nothing: the joint's own findings may still be right, but what was
            # found elsewhere (a re-identified body shared by every joint) does not carry to it
            out.append(f"{j}: the found physics predicts this joint's held-out torque worse than the nominal "
                       f"model (nMSE {phys[j]:.3g} vs {nom[j]:.3g}): what was found does not carry to it (a "
                       "re-identified body fitted to the other joints, or an effect outside the library)")
    if len(bad) > len(names) / 2:
        bad.update(names)
    return out, bad


#: Largest plausible encoder offset, rad (11.5 degrees). A robot that runs with its joint zero that
#: far off would be seen to (calibrated arms are within a fraction of a degree). A centre-of-mass
#: error of the distal link (which the payload rule keeps out of the re-identified body) can look
#: like one.
MAX_ENCODER_OFFSET = 0.2


def _effort(model, k: int) -> float:
    e = float(model.effortLimit[k]) if len(model.effortLimit) > k else 0.0
    return e if np.isfinite(e) and e > 0 else np.inf


def implausible(finding: dict, model, names: list) -> str | None:
    """Why a finding is physically impossible or implausible (None when it is not)."""
    p, j = finding.get("params", {}), finding.get("joint")
    k = names.index(j) if j in names else None
    if finding["effect"] == "payload":
        total = float(sum(model.inertias[i].mass for i in range(1, model.njoints)))
        m = float(p.get("mass", 0.0))
        if not 0 < m <= total:
            return f"a payload of {m:.3g} kg on {finding.get('link')} (the robot itself weighs {total:.3g} kg)"
    if k is None:
        return None
    if finding["effect"] == "encoder_offset" and abs(float(p.get("offset", 0.0))) > MAX_ENCODER_OFFSET:
        return (f"an encoder offset of {float(p['offset']):.3g} rad on {j}: a joint zero that far off would put "
                f"every pose the robot reports visibly wrong (more than {MAX_ENCODER_OFFSET:g} rad); a mass or "
                "centre-of-mass error of the links it moves can look like one")
    limit = _effort(model, k)
    for key in ("offset", "tau_c"):
        v = p.get(key)
        if finding["effect"] != "encoder_offset" and v is not None and abs(float(v)) > limit:
            return f"{finding['effect']} of {float(v):.3g} N*m on {j}, beyond its rated torque {limit:.3g} N*m"
    return None


#: Smallest torque a finding may have, as a share of its joint torque's spread (the RMS of its
#: fitted torque over the torque's standard deviation, ``fitting.torque_share``). Below it an
#: effect is within what a joint-torque sensor's calibration vouches for (commonly about a percent
#: of its range), and a held-out gain that small is the simulator's or the URDF's fine print (an
#: "armature" on a shoulder, a fraction of a percent of its torque's spread), while the smallest
#: real effects measured lie above a percent.
MIN_TORQUE_SHARE = 0.005


def immaterial(finding: dict) -> str | None:
    """Why a finding is too small to report (None when it is not)."""
    share = finding.get("evidence", {}).get("torque_share")
    if share is None or share >= MIN_TORQUE_SHARE:
        return None
    where = finding.get("joint") or finding.get("link")
    return (f"{finding['effect']} on {where}: its torque is {100 * share:.2g}% of the joint torque's spread, "
            f"below {100 * MIN_TORQUE_SHARE:g}%")


def check(findings: list, fit: dict, names: list, model, log_checks: tuple = ((), ())):
    """(kept findings, withheld findings each with its ``withheld_because``, warnings);
    ``log_checks`` the (suspect, informing) warnings of the log
    (``mmgp.physics.plausibility.log_checks``): a suspect one withholds every finding, an
    informing one (a dead-band torque channel: it concerns one joint) is only told."""
    suspect, notes = log_checks
    warnings = list(suspect)
    inputs_bad = bool(warnings)
    warnings += notes
    fw, bad = fit_warnings(fit, names)
    warnings += fw
    kept, withheld = [], []
    for f in findings:
        why = "the inputs failed the checks above" if inputs_bad else None
        if why is None and (f.get("joint") in bad or (bad >= set(names))):
            why = "the model stays worse than the torque's mean"
        why = why or implausible(f, model, names)
        small = None if why else immaterial(f)
        if why is None and small is None:
            kept.append(f)
        elif small is not None:
            # not a warning: nothing is wrong, the effect is too small to name
            withheld.append({**f, "withheld_because": small})
        else:
            withheld.append({**f, "withheld_because": why})
            if not inputs_bad and why not in warnings and not why.startswith("the model"):
                warnings.append(f"implausible result withheld: {why}")
    return kept, withheld, warnings
