"""The ray caster against distances worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wheelgrid_sim import (
    Box,
    DepthCamera,
    Scene,
    camera_pose,
    depth_to_points,
    make_trajectory,
    paper_scene,
    raycast,
)
from wheelgrid_sim.camera import cull_boxes
from wheelgrid_sim.scene import shell_boxes


def empty_room(w: float = 6.0, h: float = 6.0, ceiling: float = 2.7) -> Scene:
    room = (0.0, 0.0, w, h)
    return Scene(room=room, boxes=shell_boxes(room, ceiling), name="empty", ceiling=ceiling)


def analytic_depth_in_empty_room(
    cam: DepthCamera, T: np.ndarray, w: float, h: float, ceiling: float
) -> np.ndarray:
    """First hit inside a convex box room = the smallest positive plane-crossing parameter."""
    d = cam.rays() @ T[:3, :3].T  # z-depth parametrisation: t = depth
    o = T[:3, 3]
    ts = []
    for axis, planes in ((0, (0.0, w)), (1, (0.0, h)), (2, (0.0, ceiling))):
        for p in planes:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (p - o[axis]) / d[:, axis]
            ts.append(np.where(t > 0, t, np.inf))
    return np.min(ts, axis=0).reshape(cam.rows, cam.cols)


def test_every_pixel_matches_plane_intersections_in_an_empty_room() -> None:
    scene = empty_room()
    cam = DepthCamera(max_range=50.0)
    T = camera_pose(2.0, 2.5, 1.1, yaw=math.radians(30), pitch=math.radians(20), roll=0.05)
    got = cam.render(scene, T, noise=False).astype(np.float64)
    want = analytic_depth_in_empty_room(cam, T, 6.0, 6.0, 2.7)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)  # float32 output


def test_facing_a_wall_gives_constant_z_depth() -> None:
    scene = empty_room()
    cam = DepthCamera()
    T = camera_pose(2.0, 3.0, 1.35, yaw=0.0, pitch=0.0)
    depth = cam.render(scene, T, noise=False)
    # Rows near the optical centre see the east wall (x = 6), 4 m ahead, at every column.
    mid = depth[cam.rows // 2 - 10 : cam.rows // 2 + 10]
    np.testing.assert_allclose(mid, 4.0, atol=1e-6)


def test_floor_distance_at_known_pitch() -> None:
    scene = empty_room(20.0, 20.0)
    # Odd sizes put a pixel exactly on the optical axis.
    cam = DepthCamera(width=255, height=191)
    for pitch_deg, height in ((30.0, 1.0), (45.0, 1.2), (20.0, 0.9)):
        T = camera_pose(5.0, 5.0, height, yaw=1.0, pitch=math.radians(pitch_deg))
        depth = cam.render(scene, T, noise=False)
        centre = float(depth[cam.rows // 2, cam.cols // 2])
        assert centre == pytest.approx(height / math.sin(math.radians(pitch_deg)), abs=1e-6)


def test_box_in_front_occludes_the_wall_and_camera_inside_a_box_sees_out() -> None:
    scene = empty_room()
    scene.boxes.append(Box("cube", "table", (3.0, 2.5, 0.5), (3.5, 3.5, 1.5)))
    cam = DepthCamera()
    T = camera_pose(2.0, 3.0, 1.0, yaw=0.0, pitch=0.0)
    depth = cam.render(scene, T, noise=False)
    assert depth[cam.rows // 2, cam.cols // 2] == pytest.approx(1.0, abs=1e-6)
    # A box around the camera is ignored rather than giving depth 0.
    scene.boxes.append(Box("around", "pillar", (1.5, 2.5, 0.5), (2.5, 3.5, 1.5)))
    depth2 = cam.render(scene, T, noise=False)
    np.testing.assert_array_equal(depth, depth2)


def test_raycast_misses_are_inf_and_handles_axis_aligned_rays() -> None:
    lo = np.array([[1.0, -1.0, -1.0]])
    hi = np.array([[2.0, 1.0, 1.0]])
    dirs = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    t = raycast(np.zeros(3), dirs, lo, hi)
    assert t[0] == pytest.approx(1.0)
    assert np.isinf(t[1]) and np.isinf(t[2])
    assert t[3] == pytest.approx(1.0)  # enters through the corner edge x = 1, y = 1


def test_out_of_range_is_nan() -> None:
    scene = empty_room(9.0, 9.0)
    cam = DepthCamera(max_range=5.0)
    T = camera_pose(1.0, 4.5, 1.35, yaw=0.0, pitch=0.0)  # east wall 8 m away
    depth = cam.render(scene, T, noise=False)
    assert np.isnan(depth[cam.rows // 2]).all()
    near = DepthCamera(min_range=0.2)
    T2 = camera_pose(8.9, 4.5, 1.35, yaw=0.0, pitch=0.0)  # east wall 0.1 m away
    assert np.isnan(near.render(scene, T2, noise=False)[near.rows // 2]).all()


def test_intrinsics_and_stride_geometry() -> None:
    full = DepthCamera()
    k = full.intrinsics()
    assert 2 * math.degrees(math.atan(128 / k[0, 0])) == pytest.approx(64.0)
    assert (k[0, 2], k[1, 2]) == (127.5, 95.5)
    s3 = DepthCamera(stride=3)
    assert (s3.rows, s3.cols) == (64, 86)
    # Output pixel (r, c) of the strided image looks along sensor pixel (3r, 3c).
    np.testing.assert_allclose(
        s3.rays().reshape(64, 86, 3)[5, 7], full.rays().reshape(192, 256, 3)[15, 21]
    )


def test_depth_to_points_keeps_nan_and_reprojects() -> None:
    cam = DepthCamera(stride=8)
    k = cam.intrinsics()
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (cam.rows, cam.cols)).astype(np.float32)
    depth[3, 4] = np.nan
    pts = depth_to_points(depth, k)
    assert pts.shape == (cam.rows * cam.cols, 3)
    assert np.isnan(pts[3 * cam.cols + 4]).all()
    ok = np.isfinite(pts).all(axis=1)
    uv = (pts[ok] @ k.T)[:, :2] / pts[ok][:, 2:3]
    v, u = np.mgrid[0 : cam.rows, 0 : cam.cols]
    np.testing.assert_allclose(uv, np.stack([u.ravel(), v.ravel()], 1)[ok], atol=1e-9)
    np.testing.assert_allclose(pts[ok][:, 2], depth.ravel()[ok], atol=0)


def test_frustum_culling_never_changes_an_in_range_depth() -> None:
    scene = paper_scene()
    cam = DepthCamera(stride=2)
    lo, hi = scene.box_arrays()
    _, poses = make_trajectory(scene, 25, 5.0, 1)
    culled_any = False
    for T in poses:
        culled_any |= len(cull_boxes(cam, T, lo, hi)) < len(lo)
        got = cam.render(scene, T, noise=False)
        full = raycast(T[:3, 3], cam.rays() @ T[:3, :3].T, lo, hi).reshape(got.shape)
        full = np.where((full >= cam.min_range) & (full <= cam.max_range), full, np.nan)
        np.testing.assert_array_equal(got, full.astype(np.float32))
    assert culled_any
