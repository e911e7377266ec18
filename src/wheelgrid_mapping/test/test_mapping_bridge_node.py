"""iphone_bridge and depth_to_cloud as real processes over DDS on loopback, fed over real TCP."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wheelgrid_common.pointcloud2 import read_fields
from wheelgrid_common.testing import (
    diagnostics_log,
    free_port,
    managed_process,
    python_module,
    rclpy_context,
    spin_until,
)

pytestmark = pytest.mark.ros

BRIDGE = "wheelgrid_mapping.iphone_bridge_node"


def wait_listening(port: int, proc: subprocess.Popen[Any], timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert proc.poll() is None, "bridge exited early"
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"bridge not listening on {port}")


class Counter:
    def __init__(self, node: Any, topics: dict[str, Any], qos: Any) -> None:
        self.msgs: dict[str, list[Any]] = {t: [] for t in topics}
        for topic, typ in topics.items():
            node.create_subscription(typ, topic, lambda m, t=topic: self.msgs[t].append(m), qos)

    def counts(self) -> dict[str, int]:
        return {t: len(v) for t, v in self.msgs.items()}


@contextlib.contextmanager
def bridge_and_listener(name: str, *params: str) -> Iterator[tuple[int, Any, Any, Any]]:
    """The bridge as a process on a free port with ``params`` (``key:=value``), and a node
    ``name`` with its executor in this process to listen to it: (port, process, node,
    executor). Every one of them is stopped at the end, whatever fails."""
    from rclpy.executors import SingleThreadedExecutor

    port = free_port()
    args = [arg for param in (f"port:={port}", *params) for arg in ("-p", param)]
    with (
        managed_process(python_module(BRIDGE, "--ros-args", *args)) as proc,
        rclpy_context() as ctx,
    ):
        import rclpy

        node = rclpy.create_node(name, context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        try:
            yield port, proc, node, ex
        finally:
            ex.shutdown()
            node.destroy_node()


def test_stream_stray_through_bridge_loses_no_frame(stray_capture: Path) -> None:
    """90 real frames (1.5 s) at 1x real time: sent == published == received on every topic."""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from wheelgrid_common.qos import SENSOR_QOS
    from wheelgrid_mapping.cli_stray import stream_export
    from wheelgrid_mapping.depth import arkit_pose_to_ros, depth_to_points
    from wheelgrid_mapping.stray import StrayExport

    exp = StrayExport(stray_capture)
    start, n = 300, 90
    with bridge_and_listener("bridge_test_sub") as (port, proc, node, ex):
        topics = {
            "/iphone/points": PointCloud2,
            "/iphone/odometry": Odometry,
            "/iphone/depth/image": Image,
            "/iphone/depth/camera_info": CameraInfo,
            "/iphone/confidence/image": Image,
        }
        counter = Counter(node, topics, SENSOR_QOS)
        status = diagnostics_log(node, "/iphone/bridge_status")
        wait_listening(port, proc)
        # the bridge's own writers have matched this node's readers (its status says so): a
        # best-effort frame sent before that is lost, whatever this node's graph shows
        assert spin_until(
            ex,
            lambda: bool(status) and all(int(status[-1].get(f"readers:{t}", 0)) for t in topics),
            20,
        )
        result: dict[str, Any] = {}

        def send() -> None:
            result["stats"] = stream_export(
                exp, "127.0.0.1", port, rate=1.0, indices=range(start, start + n)
            )

        th = threading.Thread(target=send)
        th.start()
        spin_until(ex, lambda: not th.is_alive() and min(counter.counts().values()) >= n, 30)
        th.join()
        sent = result["stats"].frames_sent
        spin_until(ex, lambda: status[-1].get("frames_published") == str(n), 5)
    assert sent == n
    assert status[-1]["frames_published"] == str(n) and status[-1]["messages_rejected"] == "0"
    assert counter.counts() == dict.fromkeys(topics, n), counter.counts()

    # content: odometry in ROS conventions, organised cloud matching the depth, capture spacing
    odom = counter.msgs["/iphone/odometry"][0]
    assert odom.header.frame_id == "odom"
    assert odom.child_frame_id == "iphone_depth_optical_frame"
    f0 = exp.frame(start)
    T = arkit_pose_to_ros(f0.pose)  # type: ignore[arg-type]
    p = odom.pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], T[:3, 3], atol=1e-9)
    from wheelgrid_common.fileio import quat_to_matrix

    o = odom.pose.pose.orientation
    np.testing.assert_allclose(quat_to_matrix(o.x, o.y, o.z, o.w), T[:3, :3], atol=1e-6)
    cloud = counter.msgs["/iphone/points"][0]
    assert (cloud.height, cloud.width, cloud.is_dense) == (192, 256, False)
    assert cloud.header.frame_id == "iphone_depth_optical_frame"
    got = read_fields(cloud)
    want = depth_to_points(f0.depth, f0.K, f0.confidence, min_confidence=1)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-5)

    def sec(m: Any) -> float:
        return m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec

    stamps = np.array([sec(m) for m in counter.msgs["/iphone/points"]])
    capture = np.array([exp.stamp(i) for i in range(start, start + n)])
    np.testing.assert_allclose(np.diff(stamps), np.diff(capture), atol=2e-6)
    assert [sec(m) for m in counter.msgs["/iphone/odometry"]] == list(stamps)


def test_bridge_refuses_network_bind_without_token() -> None:
    cmd = python_module(BRIDGE, "--ros-args", "-p", "bind_address:=0.0.0.0", "-p", "port:=0")
    with managed_process(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT) as proc:
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert b"without a token" in out


def _frame(stamp: float, w: int = 16, h: int = 12, q: tuple[float, ...] | None = None) -> bytes:
    from wheelgrid_mapping import bridge_protocol as bp

    K = np.array([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]])
    raw = bp.encode_frame(stamp, K, np.full((h, w), 1.5, np.float32), pose=np.eye(4))
    if q is None:
        return raw
    fields = list(bp.FRAME_HEADER.unpack_from(raw, bp.PREFIX.size))
    fields[11:15] = q
    head = bp.PREFIX.size + bp.FRAME_HEADER.size
    return raw[: bp.PREFIX.size] + bp.FRAME_HEADER.pack(*fields) + raw[head:]


def test_bridge_keeps_serving_after_warnings_and_frees_a_silent_slot() -> None:
    """The node's first warning (a wrong token, a zero quaternion) used to raise in rclpy's
    logger and kill the TCP thread: later clients timed out. And a phone that went silent
    mid-frame held the only slot until idle_timeout_s dropped it."""
    from wheelgrid_mapping import bridge_protocol as bp

    port = free_port()
    cmd = python_module(
        BRIDGE, "--ros-args", "-p", f"port:={port}", "-p", "token:=s3cret",
        "-p", "idle_timeout_s:=0.5",
    )  # fmt: skip
    with managed_process(cmd) as proc:
        wait_listening(port, proc)
        with pytest.raises(ConnectionError, match="wrong token"):
            bp.connect("127.0.0.1", port, token="guess", timeout=3)
        with bp.connect("127.0.0.1", port, token="s3cret", timeout=3) as sock:
            sock.sendall(_frame(1.0, q=(0.0, 0.0, 0.0, 0.0)) + _frame(1e300) + _frame(2.0))
            half = _frame(3.0)
            sock.sendall(half[: len(half) // 2])  # then silence: Wi-Fi lost
            t0 = time.monotonic()
            while True:  # busy while the silent one holds the slot, then accepted
                try:
                    bp.connect("127.0.0.1", port, token="s3cret", timeout=3).close()
                    break
                except ConnectionError:
                    assert time.monotonic() - t0 < 3.0, "the silent client kept the slot"
                    time.sleep(0.1)
        assert proc.poll() is None


@pytest.mark.parametrize(
    ("module", "param"),
    [
        (BRIDGE, "port:=70000"),
        (BRIDGE, "port:=abc"),
        (BRIDGE, "hello_timeout_s:=.nan"),
        (BRIDGE, "max_frame_bytes:=0"),
        (BRIDGE, "max_errors_in_row:=0"),
        (BRIDGE, "min_confidence:=3"),
        ("wheelgrid_mapping.depth_to_cloud_node", "min_confidence:=abc"),
        ("wheelgrid_mapping.depth_to_cloud_node", "min_confidence:=-1"),
        ("wheelgrid_mapping.depth_to_cloud_node", "queue_size:=0"),
        ("wheelgrid_mapping.depth_to_cloud_node", "points_topic:=1abc"),
    ],
)
def test_bad_parameters_are_one_fatal_line_and_exit_2(module: str, param: str) -> None:
    cmd = python_module(module, "--ros-args", "-p", param)
    if module == BRIDGE and not param.startswith("port"):
        cmd += ["-p", "port:=0"]  # should it start after all, never on a port in use
    with managed_process(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT) as proc:
        out, _ = proc.communicate(timeout=10)
    text = out.decode(errors="replace")
    assert proc.returncode == 2, text
    assert "Traceback" not in text
    fatal = [line for line in text.splitlines() if "FATAL" in line]
    assert len(fatal) == 1 and param.split(":=")[0] in fatal[0], text


def test_offset_stamps_are_per_client() -> None:
    """Two phones at once, stamp_mode offset: each keeps its own clock offset, so each
    stream's published spacing is its phone's (0.1 s), not the arrival spacing (0.2 s)."""
    from sensor_msgs.msg import CameraInfo

    from wheelgrid_common.qos import SENSOR_QOS
    from wheelgrid_mapping import bridge_protocol as bp

    with bridge_and_listener("bridge_offset_sub", "max_clients:=2") as (port, proc, node, ex):
        got: dict[int, list[float]] = {16: [], 8: []}  # by width: phone A, phone B
        node.create_subscription(
            CameraInfo,
            "/iphone/depth/camera_info",
            lambda m: got[m.width].append(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec),
            SENSOR_QOS,
        )
        status = diagnostics_log(node, "/iphone/bridge_status")
        wait_listening(port, proc)
        # the bridge's camera_info writer has matched this reader (best effort: sent before,
        # a frame is lost; this node's graph showing the writer is not that)
        assert spin_until(
            ex,
            lambda: bool(status) and int(status[-1].get("readers:/iphone/depth/camera_info", 0)),
            20,
        )
        with (
            bp.connect("127.0.0.1", port, name="A", timeout=3) as a,
            bp.connect("127.0.0.1", port, name="B", timeout=3) as b,
        ):
            for i in range(4):
                a.sendall(_frame(1000.0 + 0.1 * i))
                spin_until(ex, lambda: False, 0.1)
                b.sendall(_frame(5.0 + 0.1 * i, w=8, h=6))
                spin_until(ex, lambda: False, 0.1)
            spin_until(ex, lambda: len(got[16]) == 4 and len(got[8]) == 4, 5)
    for stamps in got.values():
        assert len(stamps) == 4, got
        np.testing.assert_allclose(np.diff(stamps), 0.1, atol=1e-4)


def test_depth_to_cloud_matches_streams_by_stamp() -> None:
    """16UC1 depth + CameraInfo + confidence arriving in any order -> one cloud per full set;
    a depth image whose camera info never comes produces nothing."""
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import PointCloud2

    from wheelgrid_common.qos import SENSOR_QOS
    from wheelgrid_mapping.bridge_protocol import DEPTH_U16_MM, Frame
    from wheelgrid_mapping.iphone_bridge_node import frame_messages

    rng = np.random.default_rng(1)
    h, w = 24, 32
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    frames = []
    for i in range(4):
        depth = rng.integers(300, 5000, (h, w)).astype(np.uint16)
        depth[0, :5] = 0
        conf = rng.integers(0, 3, (h, w)).astype(np.uint8)
        frames.append(Frame(100.0 + i / 30, i, K, depth, DEPTH_U16_MM, conf))
    cmd = python_module(
        "wheelgrid_mapping.depth_to_cloud_node", "--ros-args", "-p", "min_confidence:=2"
    )
    with managed_process(cmd), rclpy_context() as ctx:
        import rclpy

        node = rclpy.create_node("d2c_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        msgs = [{t: m for t, _, m in frame_messages(f, f.stamp)} for f in frames]
        pubs = {
            t: node.create_publisher(type(m), t, SENSOR_QOS)
            for t, m in msgs[0].items()
            if t.startswith("/iphone/depth") or t.startswith("/iphone/confidence")
        }
        clouds: list[Any] = []
        node.create_subscription(PointCloud2, "/iphone/points", clouds.append, SENSOR_QOS)
        assert spin_until(
            ex,
            lambda: (
                all(p.get_subscription_count() == 1 for p in pubs.values())
                and node.count_publishers("/iphone/points") == 1
            ),
            20,
        )
        # warm-up: best-effort samples sent before the node's readers matched ours are lost,
        # so repeat one complete set (its own stamp) until its cloud comes back
        warm = Frame(50.0, 99, K, frames[0].depth, DEPTH_U16_MM, frames[0].confidence)
        warm_msgs = {t: m for t, _, m in frame_messages(warm, warm.stamp)}

        def warm_up() -> bool:
            for t, p in pubs.items():
                p.publish(warm_msgs[t])
            spin_until(ex, lambda: bool(clouds), 0.3)
            return bool(clouds)

        assert spin_until(ex, warm_up, 20)
        clouds.clear()
        orders = [
            ["/iphone/depth/image", "/iphone/depth/camera_info", "/iphone/confidence/image"],
            ["/iphone/confidence/image", "/iphone/depth/camera_info", "/iphone/depth/image"],
            ["/iphone/depth/image"],  # its camera info is lost: must not become a cloud
            ["/iphone/depth/camera_info", "/iphone/confidence/image", "/iphone/depth/image"],
        ]
        for m, order in zip(msgs, orders, strict=True):
            for t in order:
                pubs[t].publish(m[t])
                ex.spin_once(timeout_sec=0.02)
        spin_until(ex, lambda: len(clouds) >= 3, 10)
        spin_until(ex, lambda: False, 0.5)  # would a 4th (wrong) cloud show up?
        node.destroy_node()
        ex.shutdown()
    assert len(clouds) == 3
    from wheelgrid_mapping.depth import depth_to_points

    for cloud, f in zip(clouds, [frames[0], frames[1], frames[3]], strict=True):
        assert (cloud.height, cloud.width) == (h, w)
        assert cloud.header.stamp.sec == int(f.stamp)
        want = depth_to_points(f.depth_m(), K, f.confidence, 2)
        got = read_fields(cloud)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
        np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-6)


def test_bridge_status_goes_out_under_use_sim_time_with_no_clock() -> None:
    """The status timer ran on ROS time: under ``use_sim_time`` (a Nav2 params file's ``/**``)
    with no ``/clock`` the bridge never said whether a phone was connected."""
    from diagnostic_msgs.msg import DiagnosticArray

    from wheelgrid_common.qos import RELIABLE_QOS

    with bridge_and_listener("wg_bridge_status_test", "use_sim_time:=true") as (
        port,
        proc,
        node,
        ex,
    ):
        got: list[Any] = []
        node.create_subscription(DiagnosticArray, "/iphone/bridge_status", got.append, RELIABLE_QOS)
        wait_listening(port, proc)
        assert spin_until(ex, lambda: got, timeout=15.0), "no bridge status"


def test_depth_to_cloud_says_why_no_cloud_comes_when_confidence_never_arrives() -> None:
    """A camera that publishes depth and camera info but no confidence image (a phone that
    sends none, an app without one) with the default confidence_topic: every depth image
    waited for a confidence image that never came and was dropped, and the node said nothing,
    while no cloud came out. It now says so once, naming the topic and the setting."""
    from rclpy.executors import SingleThreadedExecutor

    from wheelgrid_common.qos import SENSOR_QOS
    from wheelgrid_mapping.bridge_protocol import DEPTH_U16_MM, Frame
    from wheelgrid_mapping.iphone_bridge_node import TOPIC_DEPTH, TOPIC_INFO, frame_messages

    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    depth = np.full((24, 32), 1500, np.uint16)
    cmd = python_module("wheelgrid_mapping.depth_to_cloud_node")
    with (
        managed_process(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT) as proc,
        rclpy_context() as ctx,
    ):
        import rclpy

        node = rclpy.create_node("d2c_noconf_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        frames = [Frame(100.0 + i / 30, i, K, depth, DEPTH_U16_MM) for i in range(40)]
        msgs = [{t: m for t, _, m in frame_messages(f, f.stamp)} for f in frames]
        pubs = {
            t: node.create_publisher(type(msgs[0][t]), t, SENSOR_QOS)
            for t in (TOPIC_DEPTH, TOPIC_INFO)
        }
        assert spin_until(
            ex, lambda: all(p.get_subscription_count() == 1 for p in pubs.values()), 20
        )
        for m in msgs:
            for t, p in pubs.items():
                p.publish(m[t])
            ex.spin_once(timeout_sec=0.02)
        spin_until(ex, lambda: False, 1.0)
        node.destroy_node()
        ex.shutdown()
        proc.send_signal(2)
        out, _ = proc.communicate(timeout=10)
    text = out.decode(errors="replace")
    warnings = [line for line in text.splitlines() if "confidence_topic" in line]
    assert len(warnings) == 1, text
    assert "/iphone/confidence/image" in warnings[0]
