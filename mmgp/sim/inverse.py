"""MuJoCo inverse dynamics of a logged trajectory, with dry friction as a friction law.

``mj_inverse`` returns ``qfrc_inverse = M(q) qacc + qfrc_bias - qfrc_passive - qfrc_constraint``
(``M`` with joint and tendon armature; ``qfrc_passive`` holds joint and tendon damping and
springs). MuJoCo treats ``frictionloss`` as a soft constraint: its force in ``qfrc_constraint``
comes from the constraint solver for the given ``qacc``, anywhere within the friction band, not
``frictionloss * sign(dq)``. :func:`inverse_dynamics` therefore switches friction loss off
(``mjDSBL_FRICTIONLOSS``; the models mmgp writes have no other constraints) and adds the law
the diagnosis fits: ``frictionloss * sign(dq)`` per joint and ``J^T frictionloss * sign(J dq)``
per tendon. Units: rad, rad/s, rad/s^2, N*m; shapes (T, n).
"""
from __future__ import annotations

import mujoco
import numpy as np


def inverse_dynamics(model, q, dq, ddq) -> np.ndarray:
    """(T, n) joint torque (N*m) that moves ``model`` (a ``mujoco.MjModel`` whose qpos and qvel
    are the n hinge/slide joints, e.g. ``corrected.xml``) along ``q``, ``dq``, ``ddq`` (T, n):
    rigid body, armature, damping, springs and dry friction as ``frictionloss * sign(velocity)``."""
    q, dq, ddq = (np.atleast_2d(np.asarray(x, dtype=np.float64)) for x in (q, dq, ddq))
    if not (model.nq == model.nv == q.shape[1]) or q.shape != dq.shape or q.shape != ddq.shape:
        raise ValueError(f"q, dq, ddq must be (T, {model.nv}) with one angle per joint (model nq={model.nq}, "
                         f"nv={model.nv}); got {q.shape}, {dq.shape}, {ddq.shape}")
    saved = model.opt.disableflags
    model.opt.disableflags = saved | mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS
    try:
        data = mujoco.MjData(model)
        out = np.empty_like(q)
        for t in range(q.shape[0]):
            data.qpos[:], data.qvel[:], data.qacc[:] = q[t], dq[t], ddq[t]
            mujoco.mj_inverse(model, data)
            J = tendon_jacobian(model, data)
            out[t] = (data.qfrc_inverse + model.dof_frictionloss * np.sign(dq[t])
                      + J.T @ (model.tendon_frictionloss * np.sign(J @ dq[t])))
    finally:
        model.opt.disableflags = saved
    return out


def tendon_jacobian(model, data) -> np.ndarray:
    """(ntendon, nv) tendon moment arms dL/dq after a position pass; MuJoCo >= 4 keeps them
    sparse (row structure in the model), older versions dense."""
    if not model.ntendon:
        return np.zeros((0, model.nv))
    if not hasattr(model, "ten_J_rownnz"):
        return np.asarray(data.ten_J).reshape(model.ntendon, model.nv)
    J = np.zeros((model.ntendon, model.nv))
    mujoco.mju_sparse2dense(J, data.ten_J, model.ten_J_rownnz, model.ten_J_rowadr, model.ten_J_colind)
    return J


def explained_share(tau, tau_nominal, tau_model) -> np.ndarray:
    """(n,) share of the nominal model's residual power that a model explains, per joint:
    ``1 - sum (tau - tau_model)^2 / sum (tau - tau_nominal)^2`` over the samples (T, n)
    (1: all of it, 0: nothing, negative: worse than the nominal model)."""
    tau, nom, mod = (np.asarray(x, dtype=np.float64) for x in (tau, tau_nominal, tau_model))
    return 1.0 - ((tau - mod) ** 2).sum(axis=0) / np.maximum(((tau - nom) ** 2).sum(axis=0), 1e-300)
