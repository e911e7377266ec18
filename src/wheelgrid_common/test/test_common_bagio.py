"""Bags: written from rclpy messages, read back in both storages; unusable bags named clearly."""

import numpy as np
import pytest

from wheelgrid_common.bagio import POINTCLOUD2, BagError, BagReader, BagWriter
from wheelgrid_common.pointcloud2 import read_xyz, to_pointcloud2


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_write_read_round_trip_is_reproducible(tmp_path, storage):
    from std_msgs.msg import String

    pts = np.arange(12.0).reshape(4, 3)
    for name in ("a", "b"):
        with BagWriter(tmp_path / name, storage) as w:
            w.write("/p", POINTCLOUD2, 10, to_pointcloud2(pts, "cam"))
            w.write("/s", "std_msgs/msg/String", 20, String(data="hi"))
    raws = []
    for name in ("a", "b"):
        with BagReader(tmp_path / name) as r:
            raws.append([raw for *_, raw in r.raw(["/p", "/s"])])
    assert raws[0] == raws[1]  # no uninitialised padding bytes leak into the bag
    with BagReader(tmp_path / "a") as r:
        assert r.pick_topic(None) == "/p"
        msgs = list(r.messages(["/p", "/s"]))
    assert [m[0] for m in msgs] == ["/p", "/s"]
    np.testing.assert_allclose(read_xyz(msgs[0][2]), pts)


def test_a_bag_without_the_type_asked_for_lists_what_it_holds(tmp_path):
    """It said "0 sensor_msgs/msg/PointCloud2 topics (none)": the user who recorded a depth
    image topic was not told what the bag does hold."""
    from std_msgs.msg import String

    with BagWriter(tmp_path / "b") as w:
        w.write("/camera/depth_text", "std_msgs/msg/String", 10, String(data="hi"))
    with BagReader(tmp_path / "b") as r, pytest.raises(BagError) as err:
        r.pick_topic(None)
    assert "no sensor_msgs/msg/PointCloud2 topic" in str(err.value)
    assert "/camera/depth_text (std_msgs/msg/String)" in str(err.value)


def test_unusable_bags_raise_bag_error(tmp_path):
    with pytest.raises(BagError, match="no such bag"):
        BagReader(tmp_path / "missing").__enter__()
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match=r"metadata\.yaml"):
        BagReader(tmp_path / "empty").__enter__()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    with pytest.raises(BagError, match="cannot open"):
        BagReader(bad).__enter__()


def test_a_metadata_yaml_that_does_not_parse_is_one_line(tmp_path):
    """The YAML parser's own message spans five lines with a caret; the CLIs promise one."""
    (tmp_path / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: [5\n  : x: {\n"
    )
    with pytest.raises(BagError, match="cannot open") as info:
        BagReader(tmp_path).__enter__()
    text = str(info.value)
    assert "\n" not in text and "line 2" in text, text


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_edit_bag_copies_keeps_stops_and_edits(tmp_path, storage):
    """The test helper that every bag-bending test goes through: untouched messages copied
    byte for byte, ``keep`` and ``until`` counted per topic, an edit decoded and re-encoded,
    raw bytes written as given."""
    from std_msgs.msg import String

    from wheelgrid_common.testing import edit_bag

    src = tmp_path / "src"
    with BagWriter(src, storage) as w:
        for i in range(6):
            w.write("/a", "std_msgs/msg/String", 10 * i, String(data=f"a{i}"))
            w.write("/b", "std_msgs/msg/String", 10 * i + 5, String(data=f"b{i}"))

    def shout(k, msg):
        msg.data = msg.data.upper()

    out = edit_bag(
        src,
        tmp_path / "out",
        keep=lambda t, k: not (t == "/b" and k == 1),
        until=lambda t, k: t == "/a" and k == 4,
        edits={"/b": lambda k, m: b"\x00\x01\x00\x00bad" if k == 3 else shout(k, m)},
        storage=storage,
    )
    with BagReader(src) as r:
        before = {(t, ns): raw for t, _, ns, raw in r.raw(["/a", "/b"])}
    with BagReader(out) as r:
        after = list(r.raw(["/a", "/b"]))
    assert [(t, ns) for t, _, ns, _ in after] == [
        ("/a", 0), ("/b", 5), ("/a", 10), ("/a", 20), ("/b", 25), ("/a", 30), ("/b", 35)
    ]  # fmt: skip
    assert all(raw == before[(t, ns)] for t, _, ns, raw in after if t == "/a")
    with BagReader(out) as r:
        msgs = list(r.messages(["/b"], damaged_as_none=True))
    assert [m.data if m is not None else None for _, _, m in msgs] == ["B0", "B2", None]


@pytest.mark.parametrize("first", ["odometry", "cloud"])
def test_a_topic_that_carries_two_message_types_is_read_as_the_type_picked(tmp_path, first):
    """A merged or ROS 1 bag may hold two types on one topic. The last connection's type named
    the topic: the bag then had "no PointCloud2 topic", or the other type's messages were read
    as clouds (a traceback in ``wheelgrid map``). The cloud topic is found, and only its clouds
    are read."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import Writer

    from wheelgrid_common.bagio import typestore

    store = typestore()
    bag = tmp_path / "mixed"
    cloud = to_pointcloud2(np.random.default_rng(0).random((50, 3)), "cam")
    with Writer(bag, version=9) as w:
        kinds = ["odometry", "cloud"] if first == "odometry" else ["cloud", "odometry"]
        conns = {
            k: w.add_connection(
                "/iphone/points",
                "nav_msgs/msg/Odometry" if k == "odometry" else POINTCLOUD2,
                typestore=store,
            )
            for k in kinds
        }
        w.write(conns["odometry"], 1, serialize_message(Odometry()))
        for i in range(3):
            w.write(conns["cloud"], 10 + i, serialize_message(cloud))
    with BagReader(bag) as r:
        assert r.pick_topic(None) == "/iphone/points"
        # the same topic picked as the pose prior's too: each read keeps its own type
        assert r.pick_topic(None, "nav_msgs/msg/Odometry") == "/iphone/points"
        assert r.count(["/iphone/points"], POINTCLOUD2) == 3
        got = [read_xyz(m) for _, _, m in r.messages(["/iphone/points"], msgtype=POINTCLOUD2)]
        assert len(got) == 3 and all(g.shape == (50, 3) for g in got)
        odom = list(r.messages(["/iphone/points"], msgtype="nav_msgs/msg/Odometry"))
        assert len(odom) == 1 and hasattr(odom[0][2], "pose")
        assert r.count(["/iphone/points"]) == 4  # no type named: every message of the topic
    with BagReader(bag) as r:  # named with --topic: the same
        assert r.pick_topic("/iphone/points") == "/iphone/points"
        with pytest.raises(BagError, match=r"carries .*Odometry.*PointCloud2, not .*Imu"):
            r.pick_topic("/iphone/points", "sensor_msgs/msg/Imu")
