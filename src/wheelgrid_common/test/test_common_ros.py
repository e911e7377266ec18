"""The ROS plumbing every node relies on, over real DDS on loopback."""

import os

import numpy as np
import pytest

from wheelgrid_common.pointcloud2 import read_xyz, to_pointcloud2
from wheelgrid_common.qos import MAP_QOS
from wheelgrid_common.testing import rclpy_context, spin_until

pytestmark = pytest.mark.ros


def test_environment_keeps_dds_on_this_machine():
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert os.environ.get("ROS_DOMAIN_ID")


def test_map_qos_delivers_to_a_late_subscriber():
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    pts = np.arange(30, dtype=np.float64).reshape(10, 3)
    with rclpy_context() as ctx:
        pub_node = Node("wg_test_pub", context=ctx)
        sub_node = Node("wg_test_sub", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(pub_node)
        ex.add_node(sub_node)
        pub = pub_node.create_publisher(PointCloud2, "/wg_test/map_cloud", MAP_QOS)
        pub.publish(to_pointcloud2(pts, "map"))
        got = []
        sub_node.create_subscription(PointCloud2, "/wg_test/map_cloud", got.append, MAP_QOS)
        assert spin_until(ex, lambda: bool(got), timeout=10.0)
        np.testing.assert_allclose(read_xyz(got[0]), pts)
        ex.shutdown()
        pub_node.destroy_node()
        sub_node.destroy_node()
