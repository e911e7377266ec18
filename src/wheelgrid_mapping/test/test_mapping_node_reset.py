"""The mapper node's outputs stay consistent with its input as a stream changes: ~/reset clears
the latched map cloud too (/wheelgrid/map_cloud is transient-local, and a subscriber that
started after a reset, a restarted grid node or RViz, got the cleared map, in a map frame the
frames after the reset no longer share), and each pose on /wheelgrid/odometry names the frame
of the cloud it is the pose of, where the input's frame_id changes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from wheelgrid_common.testing import (
    bag_cloud_odometry,
    call_service,
    managed_process,
    python_module,
    rclpy_context,
    spin_until,
)

pytestmark = pytest.mark.ros

BAG = Path(__file__).resolve().parents[3] / "bags" / "paper_room" / "scan"


def _bag_pairs(n: int) -> list:
    return bag_cloud_odometry(BAG, n)


def test_reset_replaces_the_latched_map_cloud(tmp_path: Path) -> None:
    if not BAG.exists():
        pytest.skip("bags/paper_room: not present")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from wheelgrid_common.qos import MAP_QOS, SENSOR_QOS

    args = python_module(
        "wheelgrid_mapping.mapper_node",
        "--ros-args",
        "-p", "topic:=/reset_test/points",
        "-p", "pose_prior_topic:=/reset_test/odometry",
        "-p", f"output_dir:={tmp_path}",
        "-p", "publish_period:=0.5",
        "-p", "save_on_exit:=false",
    )  # fmt: skip
    pairs = _bag_pairs(6)
    with managed_process(args, env=dict(os.environ)), rclpy_context() as ctx:
        node = rclpy.create_node("reset_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        try:
            pub = node.create_publisher(PointCloud2, "/reset_test/points", SENSOR_QOS)
            odom_pub = node.create_publisher(
                pairs[0][1].__class__, "/reset_test/odometry", SENSOR_QOS
            )
            maps: list = []
            node.create_subscription(PointCloud2, "/wheelgrid/map_cloud", maps.append, MAP_QOS)
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 20.0), "node not up"
            assert spin_until(ex, lambda: odom_pub.get_subscription_count() > 0, 20.0)
            spin_until(ex, lambda: False, 1.0)
            for cloud, odom in pairs:
                pub.publish(cloud)
                odom_pub.publish(odom)
                spin_until(ex, lambda: False, 0.4)
            assert spin_until(ex, lambda: any(m.width > 0 for m in maps), 60.0), "no map"

            reset = node.create_client(Trigger, "/mapper/reset")
            assert reset.wait_for_service(timeout_sec=10.0)
            done = call_service(ex, reset, Trigger.Request)
            assert done is not None and done.success, done
            assert spin_until(ex, lambda: maps[-1].width == 0, 10.0), "no empty map after reset"

            late: list = []  # a subscriber that starts after the reset
            node.create_subscription(PointCloud2, "/wheelgrid/map_cloud", late.append, MAP_QOS)
            assert spin_until(ex, lambda: bool(late), 10.0), "nothing latched"
            assert late[-1].width * late[-1].height == 0, "the cleared map is still latched"
            assert late[-1].header.frame_id == "map"
        finally:
            ex.shutdown()
            node.destroy_node()


def _sec(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def test_each_pose_names_the_frame_of_its_own_cloud(tmp_path: Path) -> None:
    """Frames are filtered one ahead: where frames queue, the pose of the last cloud before a
    frame_id change was published when the next cloud was taken, under that next cloud's
    frame_id (a map -> sensor transform of one frame labelled as another)."""
    if not BAG.exists():
        pytest.skip("bags/paper_room: not present")
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import PointCloud2

    from wheelgrid_common.qos import SENSOR_QOS

    args = python_module(
        "wheelgrid_mapping.mapper_node",
        "--ros-args",
        "-p", "topic:=/frames_test/points",
        "-p", "pose_prior_topic:=/frames_test/odometry",
        "-p", f"output_dir:={tmp_path}",
        "-p", "max_queue:=100",
        "-p", "save_on_exit:=false",
    )  # fmt: skip
    pairs = _bag_pairs(8)
    renamed = "iphone_depth_optical_frame_2"  # the same camera, its driver restarted
    for cloud, odom in pairs[4:]:
        cloud.header.frame_id = renamed
        odom.child_frame_id = renamed
    sent = {_sec(c.header.stamp): c.header.frame_id for c, _ in pairs}
    with managed_process(args, env=dict(os.environ)), rclpy_context() as ctx:
        node = rclpy.create_node("frames_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        try:
            pub = node.create_publisher(PointCloud2, "/frames_test/points", SENSOR_QOS)
            odom_pub = node.create_publisher(Odometry, "/frames_test/odometry", SENSOR_QOS)
            poses: list = []
            node.create_subscription(Odometry, "/wheelgrid/odometry", poses.append, SENSOR_QOS)
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 20.0), "node not up"
            assert spin_until(ex, lambda: odom_pub.get_subscription_count() > 0, 20.0)
            spin_until(ex, lambda: False, 1.0)
            for cloud, odom in pairs:  # faster than they are mapped: frames wait in the queue
                odom_pub.publish(odom)
                pub.publish(cloud)
                spin_until(ex, lambda: False, 0.05)

            def both_frames() -> bool:
                return {p.child_frame_id for p in poses} >= {pairs[0][0].header.frame_id, renamed}

            assert spin_until(ex, both_frames, 30.0), [p.child_frame_id for p in poses]
            spin_until(ex, lambda: False, 2.0)
            for p in poses:
                stamp = min(sent, key=lambda s: abs(s - _sec(p.header.stamp)))
                assert abs(stamp - _sec(p.header.stamp)) < 1e-6
                assert p.child_frame_id == sent[stamp], (stamp, p.child_frame_id, sent[stamp])
        finally:
            ex.shutdown()
            node.destroy_node()
