"""Inertial-parameter helpers: Pinocchio's 10-parameter order, frame changes, point masses.

A body's dynamic parameters are ``[m, m*c_x, m*c_y, m*c_z, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]`` (kg,
kg*m, kg*m^2; Pinocchio's ``toDynamicParameters`` order), expressed in a frame with the inertia
taken about that frame's origin. Joint torques are linear in them (``tau = Y @ pi``, with Y the
joint torque regressor), which is what makes payloads and rigid-body errors identifiable by
least squares.
"""
from __future__ import annotations

import numpy as np


def vech(S: np.ndarray) -> np.ndarray:
    """Symmetric 3x3 -> Pinocchio order [xx, xy, yy, xz, yz, zz]."""
    return np.array([S[0, 0], S[0, 1], S[1, 1], S[0, 2], S[1, 2], S[2, 2]])


def unvech(v: np.ndarray) -> np.ndarray:
    """Pinocchio order [xx, xy, yy, xz, yz, zz] -> symmetric 3x3."""
    xx, xy, yy, xz, yz, zz = v
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def transport(pi: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Dynamic parameters expressed in frame B -> the same body expressed in frame A.

    ``R``, ``p``: rotation and origin of B in A (x_A = R x_B + p). Linear in ``pi``: the inertia
    about A's origin is R I_B R^T + (2 p.h) 1 - h p^T - p h^T + m (|p|^2 1 - p p^T), h = R h_B.
    """
    m, hB, IB = pi[0], pi[1:4], unvech(pi[4:10])
    h = R @ hB
    IA = R @ IB @ R.T + (2.0 * p @ h) * np.eye(3) - np.outer(h, p) - np.outer(p, h) \
        + m * ((p @ p) * np.eye(3) - np.outer(p, p))
    return np.concatenate([[m], h + m * p, vech(IA)])


def transport_matrix(placement) -> np.ndarray:
    """10x10 matrix A with pi_parent_joint = A @ pi_link for a link frame at ``placement``
    (a ``pinocchio.SE3``: the link frame in its parent joint's frame)."""
    R, p = np.asarray(placement.rotation), np.asarray(placement.translation)
    return np.stack([transport(e, R, p) for e in np.eye(10)], axis=1)


def point_mass_inertia(com: np.ndarray) -> np.ndarray:
    """(6,) inertia per unit mass of a point at ``com`` (3,) m about the frame origin, Pinocchio
    order: vech(|c|^2 1 - c c^T), kg*m^2 per kg."""
    c = np.asarray(com, dtype=np.float64)
    return vech((c @ c) * np.eye(3) - np.outer(c, c))


def point_mass_parameters(mass: float, com: np.ndarray) -> np.ndarray:
    """Dynamic parameters (10,) of a point mass ``mass`` (kg) at ``com`` (3,), m, in its frame."""
    c = np.asarray(com, dtype=np.float64)
    return np.concatenate([[mass], mass * c, mass * point_mass_inertia(c)])


def point_mass_jacobian(mass: float, com: np.ndarray) -> np.ndarray:
    """d point_mass_parameters / d(mass, c_x, c_y, c_z), shape (10, 4)."""
    c = np.asarray(com, dtype=np.float64)
    J = np.zeros((10, 4))
    J[:, 0] = point_mass_parameters(1.0, c)
    J[1:4, 1:4] = mass * np.eye(3)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        dS = 2.0 * c[k] * np.eye(3) - np.outer(e, c) - np.outer(c, e)
        J[4:, 1 + k] = mass * vech(dS)
    return J
