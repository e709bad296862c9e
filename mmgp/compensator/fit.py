"""Building the passive feedforward compensator from a learned model.

:func:`compensator_from_model` needs only the small :class:`FeedforwardSource` protocol, so any
estimator that can give its nominal torque at rest works (the saved ``TrainedModel`` of
:mod:`mmgp.models.trained`, the public ``MultimodalGP``, or a closed-form stand-in in tests).

Choices (issue 12):

* The mean is the rigid-body gravity of the model's ``robot`` (when it has one) with a payload on
  the body of the last joint, the body the EM's payload mean describes. The payload is fitted here,
  with physical consistency, from what the model learned: the model's static nominal torque at its
  support poses minus the nominal URDF gravity, by :func:`mmgp.physics.consistent.fit_point_mass`
  (mass >= 0, centre of mass within ``payload_com_radius`` of the joint's origin). The EM's own
  per-mode payload mean is an unconstrained 10-parameter fit (it has come out with negative
  masses on real data) and is not used directly.
* The deviation ``nominal_torque - grad V_rb`` is learned by a curl-free GP with Wendland's compactly
  supported kernel (:class:`mmgp.compensator.kernels.WendlandProfile`, smoothness 3). Its support
  radii are fitted by the marginal likelihood, started at 3 standard deviations of the support
  positions per joint and capped at ``max_radius_fraction`` of the support's range per joint (the
  valid region must not reach much beyond the data, and a short radius keeps the C evaluation
  sparse).
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
    ``robot`` : optional :class:`mmgp.physics.robot.RobotModel` (None: no rigid-body prior).
    """

    support_q_: np.ndarray

    def nominal_torque(self, q: np.ndarray) -> np.ndarray: ...


def compensator_from_model(model: FeedforwardSource, *, max_support: int = 1000, seed: int = 0,
                           max_hyper_points: int | None = None, max_iter: int = 75, kernel: str = "wendland",
                           prior: str = "auto", payload_com_radius: float = 0.5,
                           max_radius_fraction: float = 0.5) -> Compensator:
    """Build the passive feedforward ``tau_ff(q) = grad (V_rb + V_dev)(q)`` from a learned model.

    ``model``: see :class:`FeedforwardSource`. Support points are a random subset of the distinct
    ``support_q_`` rows of size ``max_support`` (the final solve has ``max_support * n`` unknowns,
    O((N n)^3) time; 1000 points x 7 joints is a 7000 system, a few seconds). Targets are the
    model's own ``nominal_torque`` at those points, so the compensator approximates the model, not
    the raw data. ``prior``: "auto" (the rigid-body prior when the model has a ``robot``) or "none".
    ``kernel``: "wendland" (kind ``curl-free-wendland``, a valid region, module docstring) or "rbf"
    (the Gaussian kinds of format version 1: ``erf-1dof`` for one joint, ``curl-free-rbf``).
    Hyperparameters are fitted on ``max_hyper_points`` support points (default 150 for the curl-free
    GP, 500 for one joint's RBF). ``info`` records the hyperparameters, the identified payload,
    training error per joint, timings and where the sampled storage minimum lies.
    """
    if kernel not in ("wendland", "rbf") or prior not in ("auto", "none"):
        raise ValueError("kernel must be 'wendland' or 'rbf', prior 'auto' or 'none'")
    t0 = time.perf_counter()
    Q = _support_positions(model, max_support, np.random.default_rng(seed))
    Y = np.asarray(model.nominal_torque(Q), dtype=np.float64).reshape(Q.shape)
    n = Q.shape[1]
    names = list(getattr(model, "joint_names_", None) or [f"q_{i}" for i in range(n)])
    robot = getattr(model, "robot", None) if prior == "auto" else None
    rb = model_prior(model, robot, payload_com_radius) if robot is not None else None
    Y_dev = Y - rb.torque(Q) if rb is not None else Y
    if kernel == "wendland":
        span = np.maximum(Q.max(0) - Q.min(0), 1e-3)
        gp = CurlFreeGP(max_hyper_points, max_iter, seed=seed, profile=WendlandProfile(n),
                        lengthscale_init=3.0, max_lengthscale=max_radius_fraction * span).fit(Q, Y_dev)
        kind = "curl-free-wendland"
    elif n == 1:
        gp, kind = RBFGP(max_hyper_points, max_iter, seed=seed).fit(Q, Y_dev), "erf-1dof"
    else:
        gp, kind = CurlFreeGP(max_hyper_points, max_iter, seed=seed).fit(Q, Y_dev), "curl-free-rbf"
    comp = Compensator(kind, Q, gp.alpha_, gp.lengthscales_, gp.signal_var_, joint_names=names,
                       bounds=np.stack([Q.min(0), Q.max(0)]), prior=rb)
    fit = comp.torque(Q)
    info = {"lengthscales": gp.lengthscales_.tolist(), "signal_var": gp.signal_var_,
            "noise_var": gp.noise_var_.tolist(), "nll_per_datum": gp.nll_, "jitter": gp.jitter_,
            "hyper_time_s": gp.hyper_time_s_, "solve_time_s": gp.solve_time_s_,
            "prior": None if rb is None else {"payload": rb.payload, "nominal_robot": getattr(robot, "name", None)},
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


def model_prior(model: FeedforwardSource, robot, com_radius: float = 0.5) -> RigidBodyPrior:
    """The rigid-body prior of ``robot`` plus a payload identified from ``model`` (module docstring).

    The payload is the consistent point mass on the last joint's body that best explains
    ``model.nominal_torque(q) - robot.gravity(q)`` over the distinct ``support_q_`` rows, using the
    first four (mass, first moment) columns of that body's static regressor."""
    from ..physics.consistent import fit_point_mass

    Q = np.unique(np.asarray(model.support_q_, dtype=np.float64), axis=0)
    resid = np.asarray(model.nominal_torque(Q), dtype=np.float64).reshape(Q.shape) - robot.gravity(Q)
    A = robot.regressor(Q)[..., -10:-6]
    fit = fit_point_mass(A.reshape(-1, 4), resid.reshape(-1), com_radius=com_radius)
    info = {"body_of_joint": robot.joint_names[-1], "link": robot.body_names[-1], "mass": fit.mass,
            "com": fit.com.tolist(), "com_radius": com_radius, "active_constraints": fit.active,
            "unconstrained_first_moments": fit.unconstrained.tolist(),
            "residual_rms": fit.residual_rms, "n_poses": int(Q.shape[0]),
            "how": "consistent point mass fitted to nominal_torque - URDF gravity at the support poses"}
    return prior_from_robot(robot, payload=(fit.mass, fit.com), payload_info=info)


def _support_positions(model: FeedforwardSource, max_support: int, rng: np.random.Generator) -> np.ndarray:
    """Distinct rows of ``model.support_q_`` (N, n), a random ``max_support`` of them if more."""
    Q = np.asarray(model.support_q_, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[0] < 2:
        raise ValueError("model.support_q_ must be (N, n) with N >= 2")
    # Exact duplicates make the kernel matrix singular and carry no information.
    Q = np.unique(Q, axis=0)
    if Q.shape[0] > max_support:
        Q = Q[np.sort(rng.choice(Q.shape[0], max_support, replace=False))]
    return Q
