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


def test_image_array_and_depth_encodings() -> None:
    from wheelgrid_mapping.depth import depth_image_to_metres, image_array

    mm = np.array([[0, 1500, 65535], [10, 20, 30]], dtype=np.uint16)
    padded = np.zeros((2, 4), dtype=np.uint16)
    padded[:, :3] = mm
    d = depth_image_to_metres("16UC1", 2, 3, 8, False, padded.tobytes())
    assert np.isnan(d[0, 0]) and d[0, 1] == pytest.approx(1.5) and d[1, 2] == pytest.approx(0.03)
    be = mm.astype(">u2").tobytes()
    np.testing.assert_array_equal(image_array("16UC1", 2, 3, 6, True, be), mm)
    f = np.array([[1.0, np.nan], [0.0, -2.0]], dtype=np.float32)
    d2 = depth_image_to_metres("32FC1", 2, 2, 8, False, f.tobytes())
    assert d2[0, 0] == 1.0 and np.isnan(d2[0, 1]) and np.isnan(d2[1, 0]) and np.isnan(d2[1, 1])
    far = np.array([[3e38, np.inf, 65.535, 70.0]], dtype=np.float32)  # beyond any return: NaN
    d3 = depth_image_to_metres("32FC1", 1, 4, 16, False, far.tobytes())
    assert np.isnan(d3[0, [0, 1, 3]]).all() and d3[0, 2] == np.float32(65.535)
    with pytest.raises(ValueError, match="needs step"):
        image_array("mono8", 2, 3, 3, False, b"12345")
    with pytest.raises(ValueError, match="not supported"):
        depth_image_to_metres("rgb8", 1, 1, 3, False, b"123")
    with pytest.raises(ValueError, match="step"):
        image_array("32FC1", 1, 2, 4, False, b"12345678")


def test_stamp_sync_matches_by_stamp_and_bounds_memory() -> None:
    from wheelgrid_mapping.depth import StampSync

    sync = StampSync(["depth", "info", "conf"], tolerance=0.001, queue=3)
    assert sync.add("depth", 1.0, "d1") is None
    assert sync.add("info", 1.0005, "i1") is None
    assert sync.add("depth", 2.0, "d2") is None
    assert sync.add("conf", 1.0, "c1") == {"depth": "d1", "info": "i1", "conf": "c1"}
    # info for 2.0 never arrives; the depth queue stays bounded
    for k in range(3, 10):
        sync.add("depth", float(k), f"d{k}")
    assert len(sync._items["depth"]) == 3 and sync.dropped >= 5
    assert sync.add("info", 9.0, "i9") is None
    assert sync.add("conf", 9.0, "c9") == {"depth": "d9", "info": "i9", "conf": "c9"}
    assert sync._items["depth"] == []  # d7, d8 were older than the completed set: abandoned


def test_camera_info_of_a_binned_cropped_or_other_resolution_image_is_refused() -> None:
    """depth_to_cloud projected any depth image whose CameraInfo had its size with that K,
    whatever binning and roi said (REP-104: K is for the calibration's full resolution) or
    where its principal point lay: a cloud squashed or shifted, never a word."""
    from sensor_msgs.msg import CameraInfo

    from wheelgrid_mapping.depth import camera_info_intrinsics

    def info(**kw: object) -> CameraInfo:
        msg = CameraInfo(width=256, height=192, k=[200.0, 0, 128, 0, 200.0, 96, 0, 0, 1])
        for key, value in kw.items():
            if key.startswith("roi_"):
                setattr(msg.roi, key[4:], value)
            else:
                setattr(msg, key, value)
        return msg

    np.testing.assert_allclose(camera_info_intrinsics(info(), 256, 192)[0, 2], 128)
    camera_info_intrinsics(info(binning_x=1, roi_width=256, roi_height=192), 256, 192)
    for bad, says in (
        (info(), "camera info is 256x192, depth 128x96"),
        (info(binning_x=2, binning_y=2), "binned or cropped"),
        (info(roi_x_offset=10, roi_width=100, roi_height=50), "binned or cropped"),
        (info(k=[1400.0, 0, 960, 0, 1400.0, 720, 0, 0, 1]), "not near the centre"),
        (info(k=[0.0, 0, 128, 0, 200.0, 96, 0, 0, 1]), r"fx, fy in \[1, 100000\] px"),
        # finite and positive was all: a cloud of inf, points 64 km away, or on one axis
        (info(k=[1e-40, 0, 128, 0, 1e-40, 96, 0, 0, 1]), r"fx, fy in \[1, 100000\] px"),
        (info(k=[1e-3, 0, 128, 0, 1e-3, 96, 0, 0, 1]), r"fx, fy in \[1, 100000\] px"),
        (info(k=[1e300, 0, 128, 0, 1e300, 96, 0, 0, 1]), r"fx, fy in \[1, 100000\] px"),
        (info(p=[1e-30, 0, 128, 0, 0, 1e-30, 96, 0, 0, 0, 1, 0]), r"fx, fy in \[1, 100000\]"),
    ):
        size = (128, 96) if "depth 128x96" in says else (256, 192)
        with pytest.raises(ValueError, match=says):
            camera_info_intrinsics(bad, *size)


def test_camera_info_projects_with_p_and_says_what_it_cannot_honour() -> None:
    """depth_to_cloud back-projected with K whatever else the CameraInfo said (a review): P,
    a rectified image's projection, which depth_image_proc uses (clouds of half the scale
    where P's focal length was half K's); K's last row (0 0 0 accepted); distortion; and the
    info's frame (another camera's). It takes P where set, refuses a K that is no camera
    matrix, and says once of distortion or a frame other than the depth image's."""
    from sensor_msgs.msg import CameraInfo

    from wheelgrid_mapping.depth import camera_info_doubts, camera_info_intrinsics

    k = [30.0, 0, 4, 0, 30.0, 3, 0, 0, 1]
    info = CameraInfo(width=8, height=6, k=k)  # P unset (zeros): K
    assert camera_info_intrinsics(info, 8, 6)[0, 0] == 30.0
    info.p = [15.0, 0, 4, 0, 0, 15.0, 3, 0, 0, 0, 1, 0]
    np.testing.assert_allclose(
        camera_info_intrinsics(info, 8, 6), [[15, 0, 4], [0, 15, 3], [0, 0, 1]]
    )
    with pytest.raises(ValueError, match="last row"):
        camera_info_intrinsics(
            CameraInfo(width=8, height=6, k=[30.0, 0, 4, 0, 30.0, 3, 0, 0, 0]), 8, 6
        )
    info.header.frame_id = "depth_optical"
    info.distortion_model, info.d = "plumb_bob", [0.0] * 5
    assert camera_info_doubts(info, "depth_optical") == []
    info.d = [-0.4, 0.2, 0.0, 0.0, 0.0]
    info.header.frame_id = "color_optical"
    causes = [cause for cause, _ in camera_info_doubts(info, "depth_optical")]
    assert causes == ["distortion", "info_frame"]
