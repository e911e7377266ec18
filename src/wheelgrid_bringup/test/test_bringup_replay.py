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


def test_the_replay_sends_the_bags_time_on_clock_never_ahead_of_its_messages() -> None:
    """``wheelgrid launch --bag --clock``: the bag's log time on ``/clock``, as ``ros2 bag
    play --clock`` sends it. Without it, nodes under ``use_sim_time`` had no time at all
    (their outputs stamped 0), and without ``use_sim_time`` they stamped the replay's wall
    clock, years after the clouds. The clock starts at the first message, runs at ``rate``
    times the wall clock, is not ahead of the messages still to come, and ends on the last
    message's time; an rclpy node under use_sim_time follows it."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.bagio import BagReader
    from wheelgrid_common.testing import rclpy_context, spin_until

    with BagReader(SCAN) as reader:
        times = [t for _topic, _type, t, _raw in reader.raw(["/iphone/odometry"])]
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_clock_test", context=ctx)
        sim = rclpy.create_node(
            "replay_clock_sim_time",
            context=ctx,
            parameter_overrides=[Parameter("use_sim_time", value=True)],
        )
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        ex.add_node(sim)
        got: list[tuple[str, int]] = []  # (what, bag ns) in the order received
        node.create_subscription(
            Clock,
            "/clock",
            lambda m: got.append(("clock", m.clock.sec * 10**9 + m.clock.nanosec)),
            10,
        )
        node.create_subscription(
            Odometry,
            "/iphone/odometry",
            lambda m: got.append(("odom", m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)),
            10,
        )
        rate, hz = 10.0, 50.0
        player = BagPlayer(node, SCAN, ["/iphone/odometry"], rate=rate, clock_hz=hz)
        try:
            assert spin_until(ex, lambda: not player.unsubscribed(), 10.0)
            player.start()
            assert spin_until(ex, lambda: sum(w == "odom" for w, _ in got) >= len(times), 30.0)
            assert player.done.wait(5.0) and player.error is None
            assert spin_until(ex, lambda: ("clock", times[-1]) in got, 5.0), got[-3:]
            clocks = [t for w, t in got if w == "clock"]
            assert clocks == sorted(clocks), "the clock went back"
            assert clocks[0] == times[0] and clocks[-1] == times[-1]
            wall = (times[-1] - times[0]) / 1e9 / rate
            assert len(clocks) >= 0.5 * wall * hz, (len(clocks), wall)
            odom_seen: list[int] = []
            for what, t in got:
                if what == "odom":
                    odom_seen.append(t)
                else:  # at most the next message's time; one message of slack, as the
                    # executor may take a clock before an odometry that came first
                    assert t <= times[min(len(odom_seen) + 1, len(times) - 1)], (t, odom_seen)
            assert sim.get_clock().now().nanoseconds >= times[len(times) // 2]
        finally:
            player.stop()
            ex.shutdown()
            node.destroy_node()
            sim.destroy_node()


def test_launch_clock_runs_every_node_on_the_bags_time_and_needs_a_bag(capsys) -> None:
    """``--clock`` without ``use_sim_time`` on the nodes would send a clock nobody follows;
    with ``--iphone`` there is no bag time to send, and a rate of 0 Hz sends none."""
    from wheelgrid_bringup.launcher import build_parser, main, node_overrides

    args = build_parser().parse_args(["--bag", str(SCAN), "--clock"])
    assert args.clock == 40.0
    for name in ("mapper", "grid", "planner", "drive", "iphone_bridge"):
        assert node_overrides(name, args)["use_sim_time"] is True
    plain = build_parser().parse_args(["--bag", str(SCAN)])
    assert "use_sim_time" not in node_overrides("grid", plain)
    assert main(["--iphone", "--clock"]) == 2
    assert "--clock needs --bag" in capsys.readouterr().err
    assert main(["--bag", str(SCAN), "--clock", "0"]) == 2
    assert "--clock must be > 0 Hz" in capsys.readouterr().err


@pytest.mark.ros
def test_a_replay_that_fails_mid_bag_is_said_and_ends_the_launch_with_exit_1(
    tmp_path: Path,
) -> None:
    """A bag that opens and lists but breaks part-way (an MCAP chunk zeroed): the replay died,
    its error showed only on the scrolling status line, and the launch ended with exit 0 on a
    map of half the bag."""
    import subprocess

    from wheelgrid_common.bagio import POINTCLOUD2, BagReader, BagWriter
    from wheelgrid_common.testing import chain_params, managed_process, wheelgrid_command

    bag = tmp_path / "broken"
    with BagReader(SCAN) as r, BagWriter(bag, "mcap") as w:
        for i, (topic, _type, t_ns, raw) in enumerate(r.raw(["/iphone/points"])):
            if i == 12:
                break
            w.write(topic, POINTCLOUD2, t_ns, raw)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    n = len(data)
    data[n // 3 : n // 2] = bytes(n // 2 - n // 3)
    mcap.write_bytes(bytes(data))
    with BagReader(bag) as r:  # it opens and counts its messages: the damage shows when read
        assert sum(t.count for t in r.topics()) == 12

    params = chain_params(tmp_path, tmp_path / "out")
    cmd = wheelgrid_command(
        "launch", "--bag", str(bag), "--rate", "4", "--no-drive", "--duration", "8",
        "--params", str(params), "--log-dir", str(tmp_path / "logs"),
    )  # fmt: skip
    with managed_process(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        out, err = proc.communicate(timeout=90)  # a launcher outside a group of its own was
    assert proc.returncode == 1, out + err  # not stopped on a timeout (killpg of its pid)
    said = [ln for ln in err.splitlines() if "the replay failed after" in ln]
    assert len(said) == 1 and " of 12 messages (" in said[0], out + err
    assert "Traceback" not in err


def test_a_bags_tf_static_reaches_a_latched_reader_that_comes_after_it(tmp_path: Path) -> None:
    """Every topic was replayed volatile: tf2's static listener (RViz, a Nav2 stack) asks for
    transient local and got no /tf_static at all, and the launch waited 30 s for a reader that
    could never match (a review). /tf_static goes out latched, as tf2's static broadcaster
    sends it, and is not waited for."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from wheelgrid_common.ros_env import tf2_problem

    if tf2_problem():
        pytest.skip(f"no /tf here: {tf2_problem()}")
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore
    from tf2_msgs.msg import TFMessage

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.testing import rclpy_context, spin_until

    ts = get_typestore(Stores.ROS2_JAZZY)
    types = ts.types
    msg = types["tf2_msgs/msg/TFMessage"](transforms=[types["geometry_msgs/msg/TransformStamped"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1700000000, nanosec=0),
            frame_id="base_link"),
        child_frame_id="camera",
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=0.1, y=0.0, z=1.0),
            rotation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))])  # fmt: skip
    bag = tmp_path / "tf"
    with Writer(bag, version=9) as w:
        conn = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        w.write(conn, 1_700_000_000_000_000_000, ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_tf_static_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        player = BagPlayer(node, bag, ["/tf_static"])
        try:
            assert player.unsubscribed() == []  # latched: nobody to wait for
            player.start()
            assert player.done.wait(10.0) and player.error is None
            got: list = []
            latched = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip
            node.create_subscription(TFMessage, "/tf_static", got.append, latched)
            assert spin_until(ex, lambda: bool(got), 10.0), "the static transform never came"
            assert got[0].transforms[0].child_frame_id == "camera"
        finally:
            player.stop()
            ex.shutdown()
            node.destroy_node()


def test_a_wait_beyond_what_a_timeout_holds_is_waited_in_slices() -> None:
    """At --rate 1e-11, 0.2 s between two messages is a 2e10 s wait: Event.wait raised
    OverflowError and the replay ended "ERROR" (a review). It waits in slices, and a stop
    still ends it at once."""
    import threading
    import time

    import rclpy

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.testing import rclpy_context

    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_slices_test", context=ctx)
        player = BagPlayer(node, SCAN, ["/iphone/odometry"], rate=1e-11)
        out: list = []
        waiter = threading.Thread(
            target=lambda: out.append(player._wait_until(time.monotonic() + 2e10, 0.0, 0))
        )
        waiter.start()
        time.sleep(0.3)
        player.stop()
        waiter.join(5.0)
        node.destroy_node()
    assert out == [True]  # stopped, not an OverflowError


def _chair_recording(path: Path, cut: set[int] | None = None) -> Path:
    """The paper room's first 8 clouds and their odometry, with what `ros2 bag record -a` on a
    chair also holds: /cmd_vel, /goal_pose, the chain's own /wheelgrid/odometry and /clock.
    Clouds numbered in ``cut`` are cut to half their bytes (a damaged message)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from wheelgrid_common.bagio import BagReader

    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    twist = t["geometry_msgs/msg/Twist"](
        linear=t["geometry_msgs/msg/Vector3"](x=0.3, y=0.0, z=0.0),
        angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    clock = t["rosgraph_msgs/msg/Clock"](clock=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0))
    extra = {
        "/wheelgrid/odometry": None,  # the odometry's own bytes
        "/cmd_vel": ts.serialize_cdr(twist, "geometry_msgs/msg/Twist"),
        "/clock": ts.serialize_cdr(clock, "rosgraph_msgs/msg/Clock"),
    }
    kinds = {
        "/iphone/points": "sensor_msgs/msg/PointCloud2",
        "/iphone/odometry": "nav_msgs/msg/Odometry",
        "/wheelgrid/odometry": "nav_msgs/msg/Odometry",
        "/cmd_vel": "geometry_msgs/msg/Twist",
        "/clock": "rosgraph_msgs/msg/Clock",
    }
    n = 0
    with BagReader(SCAN) as r, Writer(path, version=9) as w:  # raw bytes, damaged ones too
        conns = {name: w.add_connection(name, kind, typestore=ts) for name, kind in kinds.items()}
        for topic, _msgtype, t_ns, raw in r.raw(["/iphone/points", "/iphone/odometry"]):
            if topic == "/iphone/points":
                if n == 8:
                    break
                if n in (cut or set()):
                    raw = raw[: len(raw) // 2]
                n += 1
            w.write(conns[topic], t_ns, raw)
            if topic == "/iphone/odometry":
                for name, data in extra.items():
                    w.write(conns[name], t_ns, raw if data is None else data)
    return path


def test_a_replay_sends_sensor_data_only_unless_topics_are_named(tmp_path: Path) -> None:
    """`wheelgrid launch --bag` replayed every topic: a chair's recording's /cmd_vel drove a
    connected chair 3 m (a review), and its /wheelgrid/odometry would be the planner's start.
    Only sensor data goes out unless --topic names more, and what is left out is said. With
    --clock a named /clock is refused (two clocks, 40 of 191 going back)."""
    import rclpy

    from wheelgrid_bringup.replay import BagPlayer, is_sensor_input, not_replayed_note
    from wheelgrid_common.testing import rclpy_context

    bag = _chair_recording(tmp_path / "rec")
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_sensors_test", context=ctx)
        try:
            player = BagPlayer(node, bag)
            assert sorted(player._pubs) == ["/iphone/odometry", "/iphone/points"]
            assert player.left_out == ["/clock", "/cmd_vel", "/wheelgrid/odometry"]
            assert "not replayed: /clock, /cmd_vel, /wheelgrid/odometry" in not_replayed_note(
                player
            )
            assert sorted(BagPlayer(node, bag, ["/cmd_vel"])._pubs) == ["/cmd_vel"]  # named
            with pytest.raises(BagError, match="two clocks"):
                BagPlayer(node, bag, ["/iphone/points", "/clock"], clock_hz=40.0)
            # the chain's outputs by their last two names (a chain recorded in a namespace
            # called wheelgrid keeps its clouds); /tf holds the recorded mapper's transforms
            assert is_sensor_input("/wheelgrid/iphone/points", "sensor_msgs/msg/PointCloud2")
            assert not is_sensor_input("/chair1/wheelgrid/odometry", "nav_msgs/msg/Odometry")
            assert not is_sensor_input("/tf", "tf2_msgs/msg/TFMessage")
            assert is_sensor_input("/chair1/tf_static", "tf2_msgs/msg/TFMessage")
            assert not is_sensor_input("/joy", "sensor_msgs/msg/Joy")
        finally:
            node.destroy_node()


def test_a_damaged_message_is_not_replayed_and_is_said(tmp_path: Path) -> None:
    """Clouds cut to half their bytes went out as they were: every subscriber dropped them
    with an rmw error, and the replay read 'replay 59/59', exit 0 (a review). Each message is
    deserialised first; the damaged ones are counted, not sent, and the replay ends in an
    error that says how many, after sending the others."""
    import rclpy

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.testing import rclpy_context

    bag = _chair_recording(tmp_path / "cut", cut={2, 3})
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_damaged_test", context=ctx)
        player = BagPlayer(node, bag, ["/iphone/points"], rate=20.0)
        try:
            player.start()
            assert player.done.wait(30.0)
            assert player.damaged == 2 and player.published == 6, player.error
            assert "2 message(s) do not deserialise" in (player.error or "")
        finally:
            player.stop()
            node.destroy_node()


def test_a_topic_name_ros2_refuses_is_a_bag_error_naming_it(tmp_path: Path) -> None:
    """A bag topic rclpy will not publish on ('/cam/depth-points') ended the launch in a
    traceback, exit 1 (a review)."""
    import rclpy

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.bagio import BagReader, BagWriter
    from wheelgrid_common.testing import rclpy_context

    bag = tmp_path / "dash"
    with BagReader(SCAN) as r, BagWriter(bag) as w:
        for i, (_topic, msgtype, t_ns, raw) in enumerate(r.raw(["/iphone/points"])):
            if i == 2:
                break
            w.write("/cam/depth-points", msgtype, t_ns, raw)
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_name_test", context=ctx)
        try:
            with pytest.raises(BagError, match="topic /cam/depth-points cannot be published"):
                BagPlayer(node, bag)
        finally:
            node.destroy_node()
