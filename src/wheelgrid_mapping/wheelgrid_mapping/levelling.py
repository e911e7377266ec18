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

from wheelgrid_common.frames import convention_for_frame as convention_for_frame
from wheelgrid_common.geometry import fit_plane

# Direction of gravity ("down") in the sensor frame when the sensor is upright and level.
DOWN_HINT = {"optical": np.array([0.0, 1.0, 0.0]), "body": np.array([0.0, 0.0, -1.0])}
VIEW_AXIS = {"optical": np.array([0.0, 0.0, 1.0]), "body": np.array([1.0, 0.0, 0.0])}


class FloorNotFoundError(RuntimeError):
    """No plane in the cloud qualifies as the floor."""


def find_floor(
    points: np.ndarray,
    down: np.ndarray,
    sensor_origin: np.ndarray | None = None,
    max_tilt_deg: float = 45.0,
    distance: float = 0.03,
    min_fraction: float = 0.03,
    min_points: int = 200,
    max_planes: int = 8,
    seed: int = 0,
    vertical: bool = False,
) -> tuple[np.ndarray, float]:
    """Floor plane ``(n, d)`` with ``n . p + d = 0``, ``n`` pointing UP (against ``down``).

    RANSAC (Open3D ``segment_plane``) peels up to ``max_planes`` planes; candidates need a normal
    within ``max_tilt_deg`` of vertical, at least ``min_fraction`` of the points, and must lie
    below the sensor. The LOWEST candidate wins (a table top is also horizontal and can be big,
    but it is never below the floor). The normal is then refined by least squares on the inliers.

    ``vertical``: ``down`` is gravity itself (a gravity-aligned pose prior's), so the plane keeps
    it as its normal and only the height is fitted: the median, along it, of the points within
    ``distance`` of the candidate's. Why: the first frames may see only a patch of floor, and a
    plane fitted to a patch tilts with its noise; on the real capture it leaned 3.3 deg, which
    put z = 0 17 cm off the floor below the first pose, 3 m from the patch.
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
        norm = float(np.linalg.norm(n))
        n, d = n / norm, d / norm
        if n @ down > 0:  # make n point up
            n, d = -n, -d
        plane_pts = remaining[inl]
        if -(n @ down) >= cos_tilt:
            # Height of the sensor above this plane; the floor is below the sensor.
            below = float(n @ origin + d)
            if below > 0.1:
                if vertical:
                    n, d = height_along(remaining, plane_pts, -down, distance)
                else:
                    n, d = fit_plane(plane_pts, n)
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


def height_along(
    pts: np.ndarray, plane_pts: np.ndarray, up: np.ndarray, distance: float
) -> tuple[np.ndarray, float]:
    """The level plane (normal ``up``) through a candidate's points: the median height of its
    inliers, then of every point within ``distance`` of that height (a slab that leans with the
    noise holds only a strip of a level floor)."""
    h = float(np.median(plane_pts @ up))
    heights = pts @ up
    near = heights[np.abs(heights - h) < distance]
    if near.size:
        h = float(np.median(near))
    return up.copy(), -h


def lean_within(n: np.ndarray, up: np.ndarray, max_deg: float) -> np.ndarray:
    """``n`` (unit) turned toward ``up`` (unit) in their common plane until it is at most
    ``max_deg`` from it; ``n`` itself if it already is."""
    cos = float(np.clip(n @ up, -1.0, 1.0))
    angle = math.acos(cos)
    limit = math.radians(max_deg)
    if angle <= limit:
        return n
    side = n - cos * up  # the way n leans, orthogonal to up
    side /= np.linalg.norm(side)
    return math.cos(limit) * up + math.sin(limit) * side


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
    if not np.isfinite(np.asarray(xyz_rpy, dtype=np.float64)).all():
        # a NaN mount made every pose NaN: 0 map points, and the run still exited 0
        raise ValueError(f"mount_xyz_rpy must be 6 finite numbers, not {list(xyz_rpy)}")
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
    """Angle between the map's -z and a known gravity direction in odom (the pose prior's
    gravity against the map frame: the report's ``prior_gravity_deg``)."""
    g = T_map_odom[:3, :3] @ (np.asarray(down_in_odom) / np.linalg.norm(down_in_odom))
    return math.degrees(math.acos(float(np.clip(-g[2], -1.0, 1.0))))


def level_vertical(
    points: np.ndarray, up: np.ndarray, voxel: float = 0.05
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertical as the map's level surfaces give it, about ``up`` (known to within about
    15 deg): the mean normal of the surfaces that face up or down (floor, seats, table tops and
    ceiling share it), in cones of 15, 10 and 5 deg about the previous estimate. Returns the
    ``voxel`` centroids, which of them are level, and the vertical (unit, on ``up``'s side).

    Each surface votes by its area, not by how well a plane fits it: a 3 cm RANSAC slab through
    a narrow strip of floor tilts with the strip (7 deg beside a large low table, a review),
    where the strip's and the table top's normals both point straight up."""
    import open3d as o3d

    from .preprocess import voxel_downsample

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = voxel_downsample(pts[np.isfinite(pts).all(axis=1)], voxel)
    if pts.shape[0] < 200:
        raise FloorNotFoundError(f"only {pts.shape[0]} map cells, need 200 to check the floor")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    normals = np.asarray(cloud.normals)
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    level = np.zeros(pts.shape[0], dtype=bool)
    for cone in (15.0, 10.0, 5.0):
        c = normals @ u
        level = np.abs(c) > math.cos(math.radians(cone))
        if level.sum() < 200:
            raise FloorNotFoundError(f"only {int(level.sum())} map cells face up or down")
        u = (normals[level] * np.sign(c[level])[:, None]).sum(axis=0)
        u /= np.linalg.norm(u)
    return pts, level, u


def floor_of_map(
    points: np.ndarray,
    up: np.ndarray,
    sensor_origin: np.ndarray,
    voxel: float = 0.05,
    min_fraction: float = 0.03,
    band: float = 0.05,
    gate: float = 0.03,
    max_lean_deg: float | None = None,
    vote: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, float]:
    """Floor plane ``(n, d)`` (``n`` up) of a whole map whose vertical ``up`` is known to within
    a few degrees: for checking a floor that :func:`find_floor` found on the first frames.

    Not :func:`find_floor`'s RANSAC: on a whole online map the floor is a population a few
    centimetres thick (drift between the frames that saw it); a 3 cm slab catches a strip of
    it, and which strip, tilted by up to 8 deg, changed with the RANSAC seed on the real
    capture. Here every surface that faces up or down votes instead:

    1. the vertical is the mean normal of the map's level surfaces (:func:`level_vertical`);
    2. the floor is the DEEPEST peak (2 cm bins) of those surfaces below the sensor that holds
       ``min_fraction`` of them: the same "lowest large level surface" as the first search;
    3. the plane is fitted by least squares to the level points within ``band`` of that peak,
       then twice to those within ``gate`` of the fit (feet and skirting drop out).

    Deterministic, and ~0.2 s on a 450 k-point map (the normals are found on ``voxel``
    centroids, so dense and sparse parts vote alike).

    ``max_lean_deg``: ``up`` is gravity itself (a gravity-aligned pose prior's), and the
    plane's normal may lean at most this much from it; the height is then the median of the
    fitted floor points along the normal kept.

    ``vote``: :func:`level_vertical` of these points about ``up`` with this ``voxel``, where the
    caller has it already (it is the costly part).
    """
    pts, level, u = level_vertical(points, up, voxel) if vote is None else vote
    origin = np.asarray(sensor_origin, dtype=np.float64)
    flat = pts[level]
    depth = (origin - flat) @ u
    below = depth[depth > 0.1]
    need = max(200.0, min_fraction * flat.shape[0])
    if below.size < need:
        raise FloorNotFoundError("too little of the map faces up below the sensor")
    edges = np.arange(0.1, below.max() + 0.04, 0.02)
    hist, edges = np.histogram(below, edges)
    smooth = np.convolve(hist, np.ones(3), "same")
    peaks = [
        i
        for i in range(smooth.size)
        if smooth[i] >= need
        and smooth[i] >= smooth[max(i - 1, 0)]
        and smooth[i] >= smooth[min(i + 1, smooth.size - 1)]
    ]
    if not peaks:
        raise FloorNotFoundError(
            f"no level surface below the sensor holds {100 * min_fraction:.0f} % of the level map"
        )
    floor_depth = 0.5 * (edges[peaks[-1]] + edges[peaks[-1] + 1])
    sel = np.abs(depth - floor_depth) < band
    n, d = u, float(-u @ origin + floor_depth)
    for _ in range(3):
        if sel.sum() < 3:
            raise FloorNotFoundError("the floor peak holds too few points to fit a plane")
        n, d = fit_plane(flat[sel], u)
        sel = np.abs(flat @ n + d) < gate
    if max_lean_deg is not None:
        g = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        kept = lean_within(n, g, max_lean_deg)
        if kept is not n and sel.any():
            n, d = kept, -float(np.median(flat[sel] @ kept))
    return n, d
