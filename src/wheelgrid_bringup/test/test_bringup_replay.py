"""What the bag replay (``wheelgrid launch --bag``) refuses before a node starts: the bytes it
publishes go to subscribers as they are, so a bag whose bytes are no ROS 2 message, or a
replay that would publish nothing, must be a clear error and not a silent replay."""

from pathlib import Path

import pytest

from wheelgrid_common.bagio import BagError, BagReader

PKG = Path(__file__).resolve().parents[1]
SCAN = PKG.parents[1] / "bags" / "paper_room" / "scan"


def _ros1_bag(path: Path) -> Path:
    """The paper room's first clouds as a ROS 1 .bag (ROS 1 serialisation, Header.seq)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    PC2 = ts.types["sensor_msgs/msg/PointCloud2"]
    PF = ts.types["sensor_msgs/msg/PointField"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    with BagReader(SCAN) as src, Writer(path) as w:
        conn = w.add_connection("/iphone/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for n, (_, t_ns, m) in enumerate(src.messages(["/iphone/points"])):
            if n >= 2:
                break
            fields = [PF(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                      for f in m.fields]  # fmt: skip
            stamp = Time(sec=m.header.stamp.sec, nanosec=m.header.stamp.nanosec)
            msg = PC2(header=Header(seq=n, stamp=stamp, frame_id=m.header.frame_id),
                      height=m.height, width=m.width, fields=fields,
                      is_bigendian=m.is_bigendian, point_step=m.point_step,
                      row_step=m.row_step, data=m.data, is_dense=m.is_dense)  # fmt: skip
            w.write(conn, t_ns, ts.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))
    return path


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
