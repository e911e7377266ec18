"""What the bag replay (``wheelgrid launch --bag``) refuses before a node starts: the bytes it
publishes go to subscribers as they are, so a bag whose bytes are no ROS 2 message, or a
replay that would publish nothing, must be a clear error and not a silent replay."""

from pathlib import Path

import pytest

from wheelgrid_common.bagio import BagError
from wheelgrid_common.testing import ros1_cloud_bag

PKG = Path(__file__).resolve().parents[1]
SCAN = PKG.parents[1] / "bags" / "paper_room" / "scan"


def _ros1_bag(path: Path) -> Path:
    """The paper room's first clouds as a ROS 1 .bag (ROS 1 serialisation, Header.seq)."""
    return ros1_cloud_bag(SCAN, path, 2)


def test_a_ros1_bag_is_refused_by_the_replay_with_the_conversion_to_run(tmp_path: Path) -> None:
    """A ROS 1 .bag holds ROS 1 bytes (no CDR header, a Header.seq): published as they are,
    every ROS 2 subscriber failed to deserialise them (rclpy: 'Fast CDR exception') or read
    garbage, while the launch's status line counted them as replayed."""
    import rclpy

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.testing import rclpy_context

    bag = _ros1_bag(tmp_path / "scan.bag")
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_ros1_test", context=ctx)
        try:
            with pytest.raises(BagError, match="ROS 1 bag") as exc:
                BagPlayer(node, bag)
            assert "rosbags-convert" in str(exc.value)
        finally:
            node.destroy_node()


def test_a_replay_topic_the_bag_lacks_is_refused(tmp_path: Path) -> None:
    """``--topic /iphone/point`` (a typo) replayed nothing and the launch ran on, its status
    line saying 'replay 0/0', the mapper waiting for frames that never came."""
    import rclpy

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.testing import rclpy_context

    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_topic_test", context=ctx)
        try:
            with pytest.raises(BagError, match="/iphone/point'") as exc:
                BagPlayer(node, SCAN, ["/iphone/point", "/iphone/odometry"])
            assert "/iphone/points" in str(exc.value)  # the bag's topics are listed
            assert BagPlayer(node, SCAN, ["/iphone/odometry"]).total > 0
        finally:
            node.destroy_node()
