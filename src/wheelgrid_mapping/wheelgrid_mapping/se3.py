"""Rigid-motion helpers shared by registration and loop closure (ROS-free, numpy only).

Small-motion corrections are handled as 6-vectors ``[t, omega]`` (translation, rotation
vector) so that they can be projected onto the directions a scene observes and scaled
(:func:`.registration.constrain_to_observable`, :func:`.loop_closure.observable_part`).
"""

from __future__ import annotations

import math

import numpy as np


def exp_se3(x: np.ndarray) -> np.ndarray:
    """``[t, omega]`` -> 4x4 (Rodrigues for the rotation; the translation is taken as is)."""
    T = np.eye(4)
    w = np.asarray(x[3:], dtype=np.float64)
    th = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        T[:3, :3] = np.eye(3) + K
    else:
        K = K / th
        T[:3, :3] = np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K
    T[:3, 3] = x[:3]
    return T


def log_se3(T: np.ndarray) -> np.ndarray:
    """4x4 -> ``[t, omega]`` (rotation vector), the inverse of :func:`exp_se3`."""
    R = T[:3, :3]
    th = math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    w = v * (0.5 if th < 1e-9 else th / (2 * math.sin(th)))
    return np.concatenate([T[:3, 3], w])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix (or the rotation of a 4x4) in degrees."""
    return math.degrees(math.acos(float(np.clip((np.trace(R[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def transform(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to ``(N, 3)`` points."""
    return points @ T[:3, :3].T + T[:3, 3]


# Farther than any place on Earth lies from a map-wide origin (m; UTM northings reach 1e7):
# a pose prior's translation of 1e300 is finite, and folded into registration's prior offset
# it failed every frame after it for good (a review: one flipped exponent bit in a phone's
# frame). 1e5 refused a bag's odometry in map-wide coordinates (a review).
MAX_TRANSLATION_M = 1e7


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """Whether ``T`` is a finite 4x4 rigid transform (rotation to within ``tol``) whose
    translation lies within :data:`MAX_TRANSLATION_M`."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        return False
    if float(np.abs(M[:3, 3]).max()) > MAX_TRANSLATION_M:
        return False
    R = M[:3, :3]
    return (
        bool(np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=tol))
        and bool(np.allclose(R.T @ R, np.eye(3), atol=tol))
        and float(np.linalg.det(R)) > 0.0
    )
