"""depth.py on hand-made data: back-projection geometry, invalid pixels, frame conventions."""

from __future__ import annotations

import numpy as np
import pytest

from wheelgrid_mapping.depth import (
    ARKIT_CAMERA_TO_OPTICAL,
    ARKIT_WORLD_TO_ROS,
    arkit_pose_to_ros,
    depth_to_points,
    pose_from_xyz_quat,
    transform_points,
)

K = np.array([[100.0, 0.0, 2.0], [0.0, 50.0, 1.0], [0.0, 0.0, 1.0]])


def test_back_projection_matches_pinhole_model() -> None:
    depth = np.full((3, 5), 2.0, dtype=np.float32)
    pts = depth_to_points(depth, K)
    assert pts.shape == (15, 3) and pts.dtype == np.float32
    # pixel (row 0, col 4): x = (4 - cx) / fx * z, y = (0 - cy) / fy * z
    np.testing.assert_allclose(pts[4], [(4 - 2) / 100 * 2, (0 - 1) / 50 * 2, 2.0], rtol=1e-6)
    # principal point lies on the optical axis
    np.testing.assert_allclose(pts[1 * 5 + 2], [0.0, 0.0, 2.0])
    # optical convention: right of centre is +x, below centre is +y
    assert pts[1 * 5 + 4, 0] > 0 and pts[2 * 5 + 2, 1] > 0


def test_invalid_and_low_confidence_pixels_are_nan_in_place() -> None:
    depth = np.array([[1.0, 0.0, np.nan], [-1.0, np.inf, 3.0]], dtype=np.float32)
    conf = np.array([[2, 2, 2], [2, 2, 0]], dtype=np.uint8)
    pts = depth_to_points(depth, K)
    valid = np.isfinite(pts).all(axis=1)
    assert valid.tolist() == [True, False, False, False, False, True]
    assert np.isnan(pts[~valid]).all()
    pts_c = depth_to_points(depth, K, conf, min_confidence=1)
    assert np.isfinite(pts_c).all(axis=1).tolist() == [True] + [False] * 5
    # min_confidence 0 ignores the map entirely
    assert np.isfinite(depth_to_points(depth, K, conf, 0)).all(axis=1).sum() == 2


def test_rejects_bad_inputs() -> None:
    with pytest.raises(ValueError, match="2-D"):
        depth_to_points(np.zeros((2, 2, 2)), K)
    with pytest.raises(ValueError, match="fx"):
        depth_to_points(np.ones((2, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="confidence shape"):
        depth_to_points(np.ones((2, 2)), K, np.ones((3, 3)), 1)


def test_arkit_world_to_ros_axes() -> None:
    R = ARKIT_WORLD_TO_ROS[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3))
    assert np.isclose(np.linalg.det(R), 1.0)
    up_ark, forward_ark, right_ark = np.eye(3)[1], -np.eye(3)[2], np.eye(3)[0]
    np.testing.assert_allclose(R @ up_ark, [0, 0, 1])  # ARKit +y up -> ROS +z
    np.testing.assert_allclose(R @ forward_ark, [1, 0, 0])  # initial forward -> ROS +x
    np.testing.assert_allclose(R @ right_ark, [0, -1, 0])  # right -> ROS -y (y is left)


def test_arkit_pose_to_ros_level_camera_looks_along_x() -> None:
    # A level phone at the session start: ARKit camera axes = ARKit world axes, 1.2 m up.
    T_ark_cam = np.eye(4)
    T_ark_cam[1, 3] = 1.2
    T_ark_opt = T_ark_cam @ ARKIT_CAMERA_TO_OPTICAL
    T = arkit_pose_to_ros(T_ark_opt)
    np.testing.assert_allclose(T[:3, 3], [0, 0, 1.2])
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-12)  # optical z = forward = ROS x
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # optical y = down
    np.testing.assert_allclose(T[:3, 0], [0, -1, 0], atol=1e-12)  # optical x = right
    # a point 2 m ahead of the camera lands 2 m along ROS x at camera height
    p = transform_points(T, np.array([[0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(p[0], [2.0, 0.0, 1.2], atol=1e-12)
    with pytest.raises(ValueError):
        arkit_pose_to_ros(np.eye(3))


def test_pose_from_xyz_quat() -> None:
    s = np.sqrt(0.5)
    T = pose_from_xyz_quat(1, 2, 3, 0, 0, s, s)  # 90 deg about z
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
