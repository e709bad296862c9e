"""MuJoCo inverse dynamics of a logged trajectory, with dry friction as a friction law.

``mj_inverse`` returns ``qfrc_inverse = M(q) qacc + qfrc_bias - qfrc_passive - qfrc_constraint``
(``M`` with joint and tendon armature; ``qfrc_passive`` holds joint and tendon damping and
springs). MuJoCo treats ``frictionloss`` as a soft constraint: its force in ``qfrc_constraint``
comes from the constraint solver for the given ``qacc``, anywhere within the friction band, not
``frictionloss * sign(dq)``. :func:`inverse_dynamics` therefore switches friction loss off
(``mjDSBL_FRICTIONLOSS``; the models mmgp writes have no other constraints) and adds the law
the diagnosis fits: ``frictionloss * tanh(dq / v_s)`` per joint and ``J^T frictionloss * tanh(J dq
/ v_w)`` per tendon, ``v_w = sqrt(sum_i (J_i v_s_i)^2)`` (:func:`~mmgp.physics.context.combined_velocity_scale`, as the coupled transmission of ``mmgp.physics.effects``). ``v_s`` (rad/s,
per joint) is the velocity scale the diagnosis fitted with, which ``corrected.xml`` carries as the
custom numeric :data:`FRICTION_VELOCITY`; a model without it gets ``sign``. The two differ where
a joint stands still: there static friction takes any value in its band, and the smooth law
predicts its middle, zero, where ``sign`` of a velocity at noise level (a filtered standstill
reads 1e-15 rad/s) adds the whole level with a coin-flip sign. Units: rad, rad/s, rad/s^2, N*m;
shapes (T, n).
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..physics.context import combined_velocity_scale
from ..physics.mjcf import FRICTION_VELOCITY


def inverse_dynamics(model, q, dq, ddq, v_s=None) -> np.ndarray:
    """(T, n) joint torque (N*m) that moves ``model`` (a ``mujoco.MjModel`` whose qpos and qvel
    are the n hinge/slide joints, e.g. ``corrected.xml``) along ``q``, ``dq``, ``ddq`` (T, n):
    rigid body, armature, damping, springs and dry friction as ``frictionloss * tanh(dq / v_s)``.
    ``v_s`` (n,) rad/s: default the model's :data:`FRICTION_VELOCITY` numeric, else 0 (``sign``)."""
    q, dq, ddq = (np.atleast_2d(np.asarray(x, dtype=np.float64)) for x in (q, dq, ddq))
    if not (model.nq == model.nv == q.shape[1]) or q.shape != dq.shape or q.shape != ddq.shape:
        raise ValueError(f"q, dq, ddq must be (T, {model.nv}) with one angle per joint (model nq={model.nq}, "
                         f"nv={model.nv}); got {q.shape}, {dq.shape}, {ddq.shape}")
    v_s = friction_velocity(model) if v_s is None else np.broadcast_to(np.asarray(v_s, dtype=np.float64), (model.nv,))
    saved = model.opt.disableflags
    model.opt.disableflags = saved | mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS
    try:
        data = mujoco.MjData(model)
        out = np.empty_like(q)
        for t in range(q.shape[0]):
            data.qpos[:], data.qvel[:], data.qacc[:] = q[t], dq[t], ddq[t]
            mujoco.mj_inverse(model, data)
            J = tendon_jacobian(model, data)
            v_w = combined_velocity_scale(J, v_s)
            out[t] = (data.qfrc_inverse + model.dof_frictionloss * smooth_sign(dq[t], v_s)
                      + J.T @ (model.tendon_frictionloss * smooth_sign(J @ dq[t], v_w)))
    finally:
        model.opt.disableflags = saved
    return out


def friction_velocity(model) -> np.ndarray:
    """(nv,) the dry friction's velocity scale v_s (rad/s) ``model`` carries (:data:`FRICTION_VELOCITY`),
    zeros (``sign``) when it carries none."""
    for i in range(model.nnumeric):
        if mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_NUMERIC, i) == FRICTION_VELOCITY:
            adr, size = model.numeric_adr[i], model.numeric_size[i]
            if size != model.nv:
                raise ValueError(f"numeric {FRICTION_VELOCITY!r} has {size} values for {model.nv} joints")
            return np.array(model.numeric_data[adr:adr + size], dtype=np.float64)
    return np.zeros(model.nv)


def smooth_sign(v: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """tanh(v / scale), elementwise; sign(v) where scale is 0."""
    scale = np.asarray(scale, dtype=np.float64)
    return np.where(scale > 0, np.tanh(v / np.where(scale > 0, scale, 1.0)), np.sign(v))


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
