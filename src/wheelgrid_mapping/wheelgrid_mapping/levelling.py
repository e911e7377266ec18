"""The levelled map frame (ROS-free).

Convention (REP-103/105, the same as docs/CONVENTIONS.md):

* z up, gravity-aligned; z = 0 on the floor plane;
* origin directly below the FIRST sensor pose (the sensor's optical centre projected vertically
  onto the floor);
* x axis = the first viewing direction projected onto the floor (optical convention: the camera
  +z axis; ROS body convention: the sensor +x axis); y = z cross x (left of the first view).

Registration runs in the "odom" frame of the first sensor pose (identity at frame 0). This
module finds ``T_map_odom`` either from the floor plane (automatic: the lowest large plane whose
normal lies within ``max_tilt_deg`` of the direction the convention calls "down") or from an
explicit mount transform ``T_base_sensor`` (base: z up, z = 0 on the floor).

Why automatic from the floor: a hand-held or chair-mounted phone is pitched and rolled
arbitrarily; the floor is the one surface every indoor scan sees and the grid stage needs
exactly z = 0 on it to apply its height thresholds.
"""

from __future__ import annotations

import math

import numpy as np

# Direction of gravity ("down") in the sensor frame when the sensor is upright and level.
DOWN_HINT = {"optical": np.array([0.0, 1.0, 0.0]), "body": np.array([0.0, 0.0, -1.0])}
VIEW_AXIS = {"optical": np.array([0.0, 0.0, 1.0]), "body": np.array([1.0, 0.0, 0.0])}


def convention_for_frame(frame_id: str, setting: str = "auto") -> str:
    """``optical`` or ``body``: an explicit setting wins; ``auto`` follows REP-103 naming."""
    if setting in ("optical", "body"):
        return setting
    if setting != "auto":
        raise ValueError(f"sensor_convention must be auto, optical or body, not {setting!r}")
    return (
        "optical"
        if frame_id.endswith("optical_frame") or frame_id.endswith("optical")
        else ("body")
    )


class FloorNotFoundError(RuntimeError):
    """No plane in the cloud qualifies as the floor."""


def find_floor(
    points: np.ndarray,
    down: np.ndarray,
    sensor_origin: np.ndarray | None = None,
    max_tilt_deg: float = 40.0,
    distance: float = 0.03,
    min_fraction: float = 0.03,
    min_points: int = 200,
    max_planes: int = 8,
    seed: int = 0,
) -> tuple[np.ndarray, float]:
    """Floor plane ``(n, d)`` with ``n . p + d = 0``, ``n`` pointing UP (against ``down``).

    RANSAC (Open3D ``segment_plane``) peels up to ``max_planes`` planes; candidates need a normal
    within ``max_tilt_deg`` of vertical, at least ``min_fraction`` of the points, and must lie
    below the sensor. The LOWEST candidate wins (a table top is also horizontal and can be big,
    but it is never below the floor). The normal is then refined by least squares on the inliers.
    """
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.shape[0] < min_points:
        raise FloorNotFoundError(f"only {pts.shape[0]} points, need {min_points} to find the floor")
    down = np.asarray(down, dtype=np.float64)
    down = down / np.linalg.norm(down)
    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=float)
    o3d.utility.random.seed(seed)
    remaining = pts
    best: tuple[float, np.ndarray, float] | None = None
    need = max(min_points, int(min_fraction * pts.shape[0]))
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    for _ in range(max_planes):
        if remaining.shape[0] < need:
            break
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(remaining))
        model, inliers = cloud.segment_plane(distance, 3, 200)
        inl = np.asarray(inliers)
        if inl.size < need:
            break
        n = np.asarray(model[:3], dtype=float)
        d = float(model[3])
        norm = np.linalg.norm(n)
        n, d = n / norm, d / norm
        if n @ down > 0:  # make n point up
            n, d = -n, -d
        plane_pts = remaining[inl]
        if -(n @ down) >= cos_tilt:
            # Height of the sensor above this plane; the floor is below the sensor.
            below = float(n @ origin + d)
            if below > 0.1:
                n, d = _refine_plane(plane_pts, n)
                below = float(n @ origin + d)
                if best is None or below > best[0]:
                    best = (below, n, d)
        remaining = np.delete(remaining, inl, axis=0)
    if best is None:
        raise FloorNotFoundError(
            f"no plane within {max_tilt_deg:.0f} deg of level below the sensor "
            f"({pts.shape[0]} points); check sensor_convention or give mount_xyz_rpy"
        )
    return best[1], best[2]


def _refine_plane(pts: np.ndarray, n_up: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through RANSAC inliers, normal kept pointing up."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[2]
    if n @ n_up < 0:
        n = -n
    return n, float(-n @ c)


def map_from_floor(
    normal_up: np.ndarray, d: float, convention: str, first_pose: np.ndarray | None = None
) -> np.ndarray:
    """``T_map_odom`` from the floor plane (in odom) and the first sensor pose (odom)."""
    T0 = np.eye(4) if first_pose is None else np.asarray(first_pose, dtype=float)
    z = np.asarray(normal_up, dtype=float)
    z = z / np.linalg.norm(z)
    view = T0[:3, :3] @ VIEW_AXIS[convention]
    x = view - (view @ z) * z
    if np.linalg.norm(x) < 1e-6:  # looking straight down/up: use the sensor's "up" instead
        x = T0[:3, :3] @ -DOWN_HINT[convention]
        x = x - (x @ z) * z
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: map axes expressed in odom
    p0 = T0[:3, 3]
    height = float(z @ p0 + d)  # sensor height above the floor
    foot = p0 - height * z  # the point on the floor below the first sensor pose
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ foot
    return T


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (REP-103 fixed-axis roll-pitch-yaw)."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def map_from_mount(xyz_rpy: list[float] | tuple[float, ...], convention: str) -> np.ndarray:
    """``T_map_odom`` from an explicit mount ``T_base_sensor`` = [x, y, z, roll, pitch, yaw].

    The base frame is levelled with z = 0 on the floor, so the mount's z is the sensor height.
    The result still follows the convention (origin below the first pose, x = first view).
    """
    if len(xyz_rpy) != 6:
        raise ValueError("mount_xyz_rpy needs 6 numbers: x y z roll pitch yaw (m, rad)")
    T_base_sensor = np.eye(4)
    T_base_sensor[:3, :3] = rpy_matrix(*xyz_rpy[3:])
    T_base_sensor[:3, 3] = xyz_rpy[:3]
    # In odom (= first sensor frame) the floor is the base's z = 0 plane.
    R_sb = T_base_sensor[:3, :3].T
    n_up = R_sb @ np.array([0.0, 0.0, 1.0])
    base_origin_in_sensor = -R_sb @ T_base_sensor[:3, 3]
    d = float(-n_up @ base_origin_in_sensor)
    return map_from_floor(n_up, d, convention)


def tilt_deg(T_map_odom: np.ndarray, down_in_odom: np.ndarray) -> float:
    """Angle between the map's -z and a known gravity direction in odom (for tests/benches)."""
    g = T_map_odom[:3, :3] @ (np.asarray(down_in_odom) / np.linalg.norm(down_in_odom))
    return math.degrees(math.acos(float(np.clip(-g[2], -1.0, 1.0))))
