"""ARKit-like visual-inertial odometry: the true motion with a realistic, seeded drift.

A real iPhone capture comes with ARKit's pose for every depth frame, and scan registration on
a narrow-field depth camera (KISS-ICP on the bundled bag: lost within the first in-place turn)
needs it as a prior. ARKit's world is gravity aligned (the IMU keeps roll and pitch right), its
origin is where the session started, and it drifts in yaw and in scale by roughly a percent of
the distance travelled. This module reproduces exactly that, so a mapper that trusts the prior
blindly is caught out by the ground truth, and one that refines it with ICP can be measured.

Frames: ``odom`` is ARKit's world turned z-up (as the bridge publishes it): origin at the FIRST
camera position (not on the floor), x along the first viewing direction projected on the
floor, z up. Poses returned are ``odom_from_optical``.
"""

from __future__ import annotations

import math

import numpy as np

SCALE_SIGMA = 0.01  # std of the run's constant scale error (1 %)
YAW_RATE_SIGMA = math.radians(0.3)  # std of the yaw drift per metre travelled
YAW_STEP_SIGMA = math.radians(0.03)  # per-frame yaw jitter
POS_STEP_SIGMA = 0.001  # m, per-frame position jitter (random walk)


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def odom_from_room(first_pose: np.ndarray) -> np.ndarray:
    """4x4 ODOM <- ROOM for a session started at ``first_pose`` (room_from_optical)."""
    fwd = first_pose[:3, 2]
    yaw = math.atan2(fwd[1], fwd[0])
    room_from_odom = np.eye(4)
    room_from_odom[:3, :3] = _rz(yaw)
    room_from_odom[:3, 3] = first_pose[:3, 3]
    return np.linalg.inv(room_from_odom)


def arkit_like_odometry(poses_room: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(odom_from_optical (N,4,4) with drift, odom_from_room (4,4))`` for true room poses.

    Drift model: a constant scale error, a yaw drift proportional to the distance travelled
    plus per-frame jitter, and a small position random walk; roll and pitch stay exact.
    """
    poses = np.asarray(poses_room, dtype=np.float64)
    o_from_r = odom_from_room(poses[0])
    true = o_from_r @ poses
    rng = np.random.default_rng([seed, 0xA4])
    scale = 1.0 + rng.normal(0.0, SCALE_SIGMA)
    yaw_rate = rng.normal(0.0, YAW_RATE_SIGMA)
    out = np.empty_like(true)
    out[0] = true[0]
    yaw_err = 0.0
    pos = true[0, :3, 3].copy()
    for i in range(1, len(true)):
        step = true[i, :3, 3] - true[i - 1, :3, 3]
        dist = float(np.linalg.norm(step[:2]))
        yaw_err += yaw_rate * dist + rng.normal(0.0, YAW_STEP_SIGMA)
        rz = _rz(yaw_err)
        pos = pos + rz @ (scale * step) + rng.normal(0.0, POS_STEP_SIGMA, 3)
        out[i] = np.eye(4)
        out[i, :3, :3] = rz @ true[i, :3, :3]
        out[i, :3, 3] = pos
    return out, o_from_r
