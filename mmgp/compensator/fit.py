"""Building the passive feedforward compensator from a learned model.

:func:`compensator_from_model` needs only the small :class:`FeedforwardSource` protocol, so any
estimator that can give its nominal torque at rest works (the saved ``TrainedModel`` of
:mod:`mmgp.models.trained`, the public ``MultimodalGP``, or a closed-form stand-in in tests).
"""
from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

import numpy as np

from ..gp.gradient_field import CurlFreeGP, RBFGP
from .field import Compensator
from .passivity import storage_sampled_min


@runtime_checkable
class FeedforwardSource(Protocol):
    """What :func:`compensator_from_model` reads from a model.

    ``support_q_`` : (N, n) joint positions (rad) the model was trained on; the compensator's
        support points are drawn from them and its workspace box is their range.
    ``nominal_torque(q)`` : q (T, n) rad -> (T, n) N*m, the model's torque at rest
        (dq = ddq = 0) in its nominal mode, rigid-body part included when it has one.
    ``joint_names_`` : optional, n joint names (default ``q_0, q_1, ...``).
    """

    support_q_: np.ndarray

    def nominal_torque(self, q: np.ndarray) -> np.ndarray: ...


def compensator_from_model(model: FeedforwardSource, *, max_support: int = 1000, seed: int = 0,
                           max_hyper_points: int | None = None, max_iter: int = 75) -> Compensator:
    """Build the passive feedforward ``tau_ff(q) = grad V(q)`` from a learned model.

    ``model``: see :class:`FeedforwardSource`. Support points are a random subset of the distinct
    ``support_q_`` rows of size ``max_support`` (the final solve has ``max_support * n`` unknowns,
    O((N n)^3) time; 1000 points x 7 joints is a 7000 system, a few seconds). Targets are the
    model's own ``nominal_torque`` at those points, so the compensator approximates the model, not
    the raw data. One joint -> ``"erf-1dof"`` (:class:`~mmgp.gp.gradient_field.RBFGP`); several ->
    ``"curl-free-rbf"`` (:class:`~mmgp.gp.gradient_field.CurlFreeGP`). Hyperparameters are fitted
    on ``max_hyper_points`` support points (default 500 for one joint, 150 for several: each
    likelihood evaluation factors a (150 n) x (150 n) matrix; 75 L-BFGS iterations take about a
    minute for 7 joints on one core). ``info`` records the hyperparameters, training error per
    joint, timings and where the sampled storage minimum lies.
    """
    t0 = time.perf_counter()
    Q = _support_positions(model, max_support, np.random.default_rng(seed))
    Y = np.asarray(model.nominal_torque(Q), dtype=np.float64).reshape(Q.shape)
    n = Q.shape[1]
    names = list(getattr(model, "joint_names_", None) or [f"q_{i}" for i in range(n)])
    if n == 1:
        gp = RBFGP(max_hyper_points, max_iter, seed=seed).fit(Q, Y)
    else:
        gp = CurlFreeGP(max_hyper_points, max_iter, seed=seed).fit(Q, Y)
    comp = Compensator("erf-1dof" if n == 1 else "curl-free-rbf", Q, gp.alpha_, gp.lengthscales_, gp.signal_var_,
                       joint_names=names, bounds=np.stack([Q.min(0), Q.max(0)]))
    fit = comp.torque(Q)
    info = {"lengthscales": gp.lengthscales_.tolist(), "signal_var": gp.signal_var_,
            "noise_var": gp.noise_var_.tolist(), "nll_per_datum": gp.nll_, "jitter": gp.jitter_,
            "hyper_time_s": gp.hyper_time_s_, "solve_time_s": gp.solve_time_s_,
            "train_rmse_per_joint": np.sqrt(np.mean((fit - Y) ** 2, axis=0)).tolist(),
            "train_nmse_per_joint": (np.mean((fit - Y) ** 2, axis=0) / np.maximum(np.var(Y, axis=0), 1e-300)).tolist()}
    s_min, q_min = storage_sampled_min(comp, seed=seed)
    comp.storage_sampled_min = s_min
    info["storage_sampled_argmin"] = np.asarray(q_min).tolist()
    info["build_time_s"] = time.perf_counter() - t0
    comp.info = info
    return comp


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

