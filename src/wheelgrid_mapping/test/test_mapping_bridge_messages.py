"""frame_messages (what the bridge publishes and import-stray writes), without DDS."""

from __future__ import annotations

import numpy as np
import pytest

from wheelgrid_common.fileio import quat_to_matrix
from wheelgrid_common.pointcloud2 import read_fields
from wheelgrid_mapping.bridge_protocol import DEPTH_F32_M, POSE_ARKIT, Frame
from wheelgrid_mapping.depth import ARKIT_CAMERA_TO_OPTICAL, arkit_pose_to_ros
from wheelgrid_mapping.iphone_bridge_node import frame_messages, stamp_to_msg

K = np.array([[20.0, 0, 4], [0, 20.0, 3], [0, 0, 1]])


def _frame(**kw: object) -> Frame:
    depth = np.full((6, 8), 2.0, dtype=np.float32)
    depth[0, 0] = np.nan
    conf = np.full((6, 8), 2, dtype=np.uint8)
    conf[5, 7] = 0
    args: dict[str, object] = dict(
        stamp=12.5, seq=0, K=K, depth=depth, depth_encoding=DEPTH_F32_M, confidence=conf
    )
    args.update(kw)
    return Frame(**args)  # type: ignore[arg-type]


def test_all_topics_for_a_full_frame() -> None:
    # level phone 1.2 m up in ARKit camera axes, yawed 90 deg left (about ARKit +y)
    pose = np.eye(4)
    pose[:3, :3] = quat_to_matrix(0, np.sqrt(0.5), 0, np.sqrt(0.5))
    pose[1, 3] = 1.2
    msgs = {t: m for t, _, m in frame_messages(_frame(pose=pose, pose_axes=POSE_ARKIT), 100.25)}
    assert set(msgs) == {
        "/iphone/depth/image",
        "/iphone/depth/camera_info",
        "/iphone/confidence/image",
        "/iphone/points",
        "/iphone/odometry",
    }
    for m in msgs.values():
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (100, 250_000_000)
    img = msgs["/iphone/depth/image"]
    assert (img.encoding, img.height, img.width, img.step) == ("32FC1", 6, 8, 32)
    info = msgs["/iphone/depth/camera_info"]
    assert list(info.k) == [20.0, 0, 4, 0, 20.0, 3, 0, 0, 1] and info.p[0] == 20.0
    assert msgs["/iphone/confidence/image"].encoding == "mono8"
    cloud = msgs["/iphone/points"]
    pts = read_fields(cloud)
    assert (cloud.height, cloud.width) == (6, 8)
    assert np.isnan(pts[0]).all() and np.isnan(pts[-1]).all()  # no return; low confidence
    assert np.isfinite(pts).all(axis=1).sum() == 46
    odom = msgs["/iphone/odometry"]
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "iphone_depth_optical_frame")
    assert odom.pose.covariance[0] == -1 and odom.twist.covariance[0] == -1
    T = arkit_pose_to_ros(pose @ ARKIT_CAMERA_TO_OPTICAL)
    p, o = odom.pose.pose.position, odom.pose.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z], [0, 0, 1.2], atol=1e-12)
    R = quat_to_matrix(o.x, o.y, o.z, o.w)
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-9)
    # yawed 90 deg left: the optical axis (forward) points along ROS +y
    np.testing.assert_allclose(R[:, 2], [0, 1, 0], atol=1e-9)


def test_no_pose_no_odometry_dense_cloud() -> None:
    msgs = {t: m for t, _, m in frame_messages(_frame(confidence=None), 1.0, organized=False)}
    assert "/iphone/odometry" not in msgs and "/iphone/confidence/image" not in msgs
    cloud = msgs["/iphone/points"]
    assert cloud.height == 1 and cloud.width == 47 and cloud.is_dense


def test_stamp_to_msg_rounding() -> None:
    t = stamp_to_msg(258528.999999999999)
    assert t.nanosec < 1_000_000_000
    t2 = stamp_to_msg(3.0000000004)
    assert (t2.sec, t2.nanosec) == (3, 0)


@pytest.mark.parametrize("seconds", [3e9, 2.0**31, -0.5, float("nan"), float("inf")])
def test_stamp_to_msg_refuses_what_a_ros_time_cannot_hold(seconds: float) -> None:
    """rclpy takes ``Time(sec=3000000000)`` and the int32 on the wire wraps it to 1928, so a
    corrupt Stray timestamp went into `import-stray`'s bag silently: it is an error here."""
    with pytest.raises(ValueError, match="outside 0"):
        stamp_to_msg(seconds)
