"""Building the passive feedforward compensator from a learned model.

:func:`compensator_from_model` needs only the small :class:`FeedforwardSource` protocol, so any
estimator that can give its nominal torque at rest works (the public ``MultimodalGP``, or a
closed-form stand-in in tests and benchmarks).

Choices:

* The mean is the rigid-body gravity of the model's ``robot`` (when it has one), re-identified with
  physical consistency from what the model learned, its static nominal torque at its support poses
  (:func:`model_prior`): first a payload on the body of the last joint, the body the EM's payload
  mean describes (:func:`mmgp.physics.payload.fit_point_mass`: mass >= 0, centre of mass within
  ``payload_com_radius`` of the joint's origin), then every body's mass and first moment
  (log-Cholesky, ridge towards the nominal URDF plus that payload). The EM's own per-mode payload
  mean is an unconstrained 10-parameter fit (it has come out with negative masses on real data) and
  is not used directly. A payload the data hold is kept by the re-identification, which also
  takes most of what the nominal bodies get wrong off the GP
  (benchmarks/README.md, "sixth session: tuning history").
* Support positions (several joints): half of them the model's own support poses, half random ones
  of those moved by N(0, (``tube`` * range)^2) per joint (5 % of the data's range). The model's
  torque is not a gradient field (its Jacobian has an antisymmetric part); fitted only along a
  trajectory, where nothing shows the inconsistency, the likelihood interpolates it and the
  potential tilts off the trajectory. With the tube and the noise variances started at 10 % of
  the targets' mean squares, it calls the non-conservative part noise, and the deviation stays
  small over the whole valid region (benchmarks/README.md, "sixth session: tuning history").
* The deviation ``nominal_torque - grad V_rb`` is learned by a curl-free GP with Wendland's compactly
  supported kernel (:class:`mmgp.compensator.kernels.WendlandProfile`, smoothness 3). Its support
  radii are fitted by the marginal likelihood, started at 3 standard deviations of the support
  positions per joint and capped at ``max_radius_fraction`` (1) times the support's range per
  joint: the valid region reaches at most one data range beyond the data. Then all radii are
  shrunk by one factor, if needed, until a support point has at most ``max_neighbours`` support
  points within its radius on average, which bounds the work of the C evaluation near the data
  ("auto": 700 / n, 100 for 7 joints; the work per neighbour grows with n; ``info["radius_scale"]``).
  The trade-off: short radii revert to the prior sooner (the kernel's curvature lengthscale is
  radius / 4.7-5.6), so a smaller budget or a lower cap costs accuracy off the data
  (benchmarks/README.md, "sixth session: tuning history").
"""
from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

import numpy as np

from ..gp.gradient_field import CurlFreeGP, RBFGP
from .field import Compensator
from .kernels import WendlandProfile
from .passivity import deviation_sampled_max, storage_sampled_min
from .prior import RigidBodyPrior, prior_from_robot


@runtime_checkable
class FeedforwardSource(Protocol):
    """What :func:`compensator_from_model` reads from a model.

    ``support_q_`` : (N, n) joint positions (rad) the model was trained on; the compensator's
        support points are drawn from them and its workspace box is their range.
    ``nominal_torque(q)`` : q (T, n) rad -> (T, n) N*m, the model's torque at rest
        (dq = ddq = 0) in its nominal mode, rigid-body part included when it has one.
    ``joint_names_`` : optional, n joint names (default ``q_0, q_1, ...``).
    ``robot_`` (the public estimator's fitted robot) or ``robot`` (a stand-in's): optional
        :class:`mmgp.physics.robot.RobotModel` (none: no rigid-body prior); see :func:`model_robot`.
    """

    support_q_: np.ndarray

    def nominal_torque(self, q: np.ndarray) -> np.ndarray: ...


def compensator_from_model(model: FeedforwardSource, *, max_support: int = 1000, seed: int = 0,
                           max_hyper_points: int | None = None, max_iter: int = 75, kernel: str = "wendland",
                           prior: str = "auto", payload_com_radius: float = 0.5,
                           max_radius_fraction: float = 1.0, max_neighbours: int | str | None = "auto",
                           tube: float = 0.05) -> Compensator:
    """Build the passive feedforward ``tau_ff(q) = grad (V_rb + V_dev)(q)`` from a learned model.

    ``model``: see :class:`FeedforwardSource`. Support points are a random subset of the distinct
    ``support_q_`` rows of size ``max_support`` (the final solve has ``max_support * n`` unknowns,
    O((N n)^3) time; 1000 points x 7 joints is a 7000 system, a few seconds). Targets are the
    model's own ``nominal_torque`` at those points, so the compensator approximates the model, not
    the raw data. ``prior``: with a model that has a ``robot``, "auto" (the rigid-body prior with a
    payload, every body re-identified where the data ask for it, :func:`model_prior`), "payload" (nominal bodies plus the
    payload only) or "none" (zero mean, as without a robot).
    ``kernel``: "wendland" (kind ``curl-free-wendland``, a valid region, module docstring) or "rbf"
    (the Gaussian kinds of format version 1: ``erf-1dof`` for one joint, ``curl-free-rbf``).
    Hyperparameters are fitted on ``max_hyper_points`` support points (default 150 for the curl-free
    GP, 500 for one joint's RBF). ``info`` records the hyperparameters, the identified payload,
    training error per joint, timings and where the sampled storage minimum lies.
    """
    if kernel not in ("wendland", "rbf") or prior not in ("auto", "payload", "none"):
        raise ValueError("kernel must be 'wendland' or 'rbf', prior 'auto', 'payload' or 'none'")
    t0 = time.perf_counter()
    Q = _support_positions(model, max_support, np.random.default_rng(seed), tube if kernel == "wendland" else 0.0)
    Y = np.asarray(model.nominal_torque(Q), dtype=np.float64).reshape(Q.shape)
    n = Q.shape[1]
    names = list(getattr(model, "joint_names_", None) or [f"q_{i}" for i in range(n)])
    robot = model_robot(model) if prior != "none" else None
    reidentify = "auto" if prior == "auto" else False
    rb = model_prior(model, robot, payload_com_radius, reidentify=reidentify) if robot is not None else None
    Y_dev = Y - rb.torque(Q) if rb is not None else Y
    if kernel == "wendland":
        span = np.maximum(Q.max(0) - Q.min(0), 1e-3)
        budget = max(1, round(700 / n)) if max_neighbours == "auto" else max_neighbours
        gp = CurlFreeGP(max_hyper_points, max_iter, seed=seed, profile=WendlandProfile(n), lengthscale_init=3.0,
                        max_lengthscale=max_radius_fraction * span, max_neighbours=budget,
                        noise_init=0.1).fit(Q, Y_dev)
        kind = "curl-free-wendland"
    elif n == 1:
        gp, kind = RBFGP(max_hyper_points, max_iter, seed=seed).fit(Q, Y_dev), "erf-1dof"
    else:
        gp, kind = CurlFreeGP(max_hyper_points, max_iter, seed=seed).fit(Q, Y_dev), "curl-free-rbf"
    comp = Compensator(kind, Q, gp.alpha_, gp.lengthscales_, gp.signal_var_, joint_names=names,
                       bounds=np.stack([Q.min(0), Q.max(0)]), prior=rb)
    fit = comp.torque(Q)
    info = {"lengthscales": gp.lengthscales_.tolist(), "signal_var": gp.signal_var_,
            "radius_scale": getattr(gp, "radius_scale_", None),
            "noise_var": gp.noise_var_.tolist(), "nll_per_datum": gp.nll_, "jitter": gp.jitter_,
            "hyper_time_s": gp.hyper_time_s_, "solve_time_s": gp.solve_time_s_,
            "prior": None if rb is None else dict(rb.identification, nominal_robot=getattr(robot, "name", None)),
            "train_rmse_per_joint": np.sqrt(np.mean((fit - Y) ** 2, axis=0)).tolist(),
            "train_nmse_per_joint": (np.mean((fit - Y) ** 2, axis=0) / np.maximum(np.var(Y, axis=0), 1e-300)).tolist(),
            "deviation_rms_per_joint": np.sqrt(np.mean(Y_dev ** 2, axis=0)).tolist()}
    s_min, q_min = storage_sampled_min(comp, seed=seed)
    comp.storage_sampled_min = s_min
    comp.deviation_sampled_max = deviation_sampled_max(comp, seed=seed)
    info["storage_sampled_argmin"] = np.asarray(q_min).tolist()
    info["build_time_s"] = time.perf_counter() - t0
    comp.info = info
    return comp


def model_robot(model):
    """The model's rigid-body model: ``robot_`` (``MultimodalGP``, fitted) or else ``robot`` (a
    stand-in's), when it is a RobotModel (has ``regressor``); otherwise None (a setting such
    as a robot's name is not a model)."""
    robot = getattr(model, "robot_", None)
    if robot is None:
        robot = getattr(model, "robot", None)
    return robot if hasattr(robot, "regressor") and hasattr(robot, "pin_model") else None


def model_prior(model: FeedforwardSource, robot, com_radius: float = 0.5, reidentify: bool | str = "auto",
                ridge: float = 1e-2) -> RigidBodyPrior:
    """The rigid-body prior of ``robot`` identified, with physical consistency, from ``model``.

    Data: ``tau = model.nominal_torque(q)`` at the distinct ``support_q_`` rows, and the robot's
    static regressor ``Y(q)`` (gravity is ``Y pi``). First a payload on the last joint's body: the
    consistent point mass (:func:`~mmgp.physics.payload.fit_point_mass`, mass >= 0, com within
    ``com_radius`` of the joint) that best explains ``tau - Y pi_nominal``. Then, with
    ``reidentify``, every body's parameters by :func:`~mmgp.physics.consistent.fit_consistent_parameters`
    (log-Cholesky: every body stays physical) with a ridge towards the nominal-plus-payload values
    for what gravity cannot tell apart. The prior keeps each body's mass and centre of mass; the
    file records the payload, the re-identified and nominal masses and the fit residuals.
    ``reidentify="auto"`` re-identifies only where the data ask for it (:func:`_reidentify_pays`):
    where the URDF is right, re-identifying every body from the model's torque moves bodies the
    data barely constrain and costs accuracy at poses far from the data
    (benchmarks/README.md, "sixth session: tuning history").
    """
    from ..physics.consistent import fit_consistent_parameters
    from ..physics.payload import fit_point_mass
    from ..physics.inertial import point_mass_parameters

    Q = np.unique(np.asarray(model.support_q_, dtype=np.float64), axis=0)
    tau = np.asarray(model.nominal_torque(Q), dtype=np.float64).reshape(Q.shape)
    Y = robot.regressor(Q)
    nominal = robot.dynamic_parameters()
    fit = fit_point_mass(Y[..., -10:-6].reshape(-1, 4), (tau - Y @ nominal).reshape(-1), com_radius=com_radius)
    pi = nominal.copy()
    pi[-10:] += point_mass_parameters(fit.mass, fit.com)
    info = {"payload": {"body_of_joint": robot.joint_names[-1], "link": robot.body_names[-1], "mass": fit.mass,
                        "com": fit.com.tolist(), "com_radius": com_radius, "active_constraints": fit.active,
                        "unconstrained_first_moments": fit.unconstrained.tolist(), "residual_rms": fit.residual_rms},
            "n_poses": int(Q.shape[0]), "nominal_masses": nominal[0::10].tolist(),
            "how": ("consistent point mass on the last body fitted to nominal_torque - URDF gravity at the support "
                    "poses" + ("; then every body re-identified (log-Cholesky, ridge towards it)" if reidentify else ""))}
    if reidentify == "auto":
        reidentify, info["reidentify_decision"] = _reidentify_pays(Y, tau, pi, ridge)
    if reidentify:
        pi, rid = fit_consistent_parameters(Y.reshape(-1, nominal.size), tau.reshape(-1), pi, ridge=ridge)
        info["reidentified"] = dict(rid, masses=pi[0::10].tolist(), ridge=ridge)
    masses = pi[0::10]
    coms = np.stack([pi[10 * i + 1:10 * i + 4] / max(masses[i], 1e-300) for i in range(masses.size)])
    return prior_from_robot(robot, bodies=(masses, coms), identification=info)


def _reidentify_pays(Y: np.ndarray, tau: np.ndarray, pi: np.ndarray, ridge: float,
                     material: float = 0.02, gain: float = 0.2) -> tuple[bool, dict]:
    """Whether re-identifying every body is worth it, on the static regressor ``Y`` (P, n, p) and the
    model's torque ``tau`` (P, n) at P poses, from the nominal-plus-payload parameters ``pi`` (p,).

    Yes when the payload-only prior leaves more than ``material`` of the torque's RMS unexplained
    and the re-identified parameters, fitted on one half of the poses (alternate poses), cut the
    other half's residual by at least ``gain`` (both ways round): a URDF that already explains the
    model is kept, so gravity's unidentifiable combinations cannot drift where no data constrain them.
    """
    from ..physics.consistent import fit_consistent_parameters

    rms = lambda r: float(np.sqrt(np.mean(r ** 2)))  # noqa: E731
    before = rms(tau - Y @ pi)
    scale = max(rms(tau), 1e-12)
    out = {"rule": f"payload-only residual > {material:.0%} of the torque RMS and a held-out (alternate "
                   f"poses) residual cut of >= {gain:.0%}", "payload_only_residual_rms": before,
           "torque_rms": scale}
    if before <= material * scale or Y.shape[0] < 4:
        return False, out
    halves = (np.arange(Y.shape[0]) % 2 == 0, np.arange(Y.shape[0]) % 2 == 1)
    held = []
    for fit_on, test_on in (halves, halves[::-1]):
        p_half, _ = fit_consistent_parameters(Y[fit_on].reshape(-1, pi.size), tau[fit_on].reshape(-1), pi, ridge=ridge)
        held.append((rms(tau[test_on] - Y[test_on] @ p_half), rms(tau[test_on] - Y[test_on] @ pi)))
    after, base = (float(np.sqrt(np.mean(np.square([h[i] for h in held])))) for i in (0, 1))
    out.update(heldout_residual_rms_reidentified=after, heldout_residual_rms_payload_only=base)
    return bool(after <= (1.0 - gain) * base), out


def _support_positions(model: FeedforwardSource, max_support: int, rng: np.random.Generator,
                       tube: float = 0.0) -> np.ndarray:
    """Support positions (N, n): distinct rows of ``model.support_q_``, a random ``max_support`` of
    them if more. With ``tube`` > 0 and several joints, at most half of them are rows and as many
    again are random rows moved by N(0, (tube * range)^2) per joint (the range of ``support_q_``)."""
    Q = np.asarray(model.support_q_, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[0] < 2:
        raise ValueError("model.support_q_ must be (N, n) with N >= 2")
    # Exact duplicates make the kernel matrix singular and carry no information.
    Q = np.unique(Q, axis=0)
    jitter = tube > 0 and Q.shape[1] > 1
    n_on = min(Q.shape[0], max_support // 2 if jitter else max_support)
    on = Q[np.sort(rng.choice(Q.shape[0], n_on, replace=False))]
    if not jitter:
        return on
    n_off = min(max_support - n_on, n_on)
    off = Q[rng.integers(Q.shape[0], size=n_off)] + rng.normal(size=(n_off, Q.shape[1])) * tube * (Q.max(0) - Q.min(0))
    return np.concatenate([on, off])
