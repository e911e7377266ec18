"""``iphone_bridge`` node: depth frames from a phone over TCP -> ROS topics.

The network side (listening, tokens, limits, decoding) is the ROS-free
:class:`~wheelgrid_mapping.bridge_protocol.BridgeServer`; this module only turns each decoded
:class:`~wheelgrid_mapping.bridge_protocol.Frame` into messages. :func:`frame_messages` is also
what ``wheelgrid import-stray`` writes into bags, so a live stream and an imported capture look
the same to the mapper.

Published (sensor-data QoS): /iphone/depth/image, /iphone/depth/camera_info,
/iphone/confidence/image, /iphone/points (organised unless ``organized`` is false),
/iphone/odometry (ARKit pose in ROS conventions: ``odom`` z-up <- optical camera). Also
/iphone/bridge_status (DiagnosticArray, 1 Hz, reliable): frames received / published /
rejected, clients, so a user can see that a phone is connected and streaming, and
``readers:TOPIC``, the subscriptions each frame topic's writer has matched (what a test or a
launcher waits for before a phone streams: a frame sent before is lost).
"""

from __future__ import annotations

import array
import math
import os
import sys
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from wheelgrid_common.params import check_no_undeclared, field
from wheelgrid_mapping.bridge_protocol import (
    DEPTH_U16_MM,
    MAX_FRAME_BYTES,
    MAX_FRAME_LIMIT,
    MAX_STAMP_S,
    MIN_FRAME_LIMIT,
    BridgeServer,
    Frame,
)
from wheelgrid_mapping.depth import (
    arkit_pose_to_ros,
    check_min_confidence,
    confidence_loss,
    depth_to_points,
)

# The topics as a bag records them (`wheelgrid import-stray`) and in the root namespace; the
# node publishes them relative to its own (`--ros-args -r __ns:=/chair1` -> /chair1/iphone/...).
TOPIC_DEPTH = "/iphone/depth/image"
TOPIC_INFO = "/iphone/depth/camera_info"
TOPIC_CONF = "/iphone/confidence/image"
TOPIC_POINTS = "/iphone/points"
TOPIC_ODOM = "/iphone/odometry"
TOPIC_STATUS = "/iphone/bridge_status"
CAMERA_FRAME = "iphone_depth_optical_frame"
ODOM_FRAME = "odom"
DEFAULT_PORT = 8765
TOKEN_ENV = "WHEELGRID_BRIDGE_TOKEN"


@dataclass
class BridgeConfig:
    bind_address: str = field(
        "127.0.0.1", "address to listen on; anything but loopback requires a token"
    )
    port: int = field(DEFAULT_PORT, "TCP port to listen on (0 = any free port)", bounds=(0, 65535))
    token: str = field("", f"shared secret the phone must send in HELLO (or env {TOKEN_ENV})")
    max_clients: int = field(
        1,
        "phones streaming at once; later ones are refused as busy. Every phone's frames go out "
        "on the same topics and frames: more than one is for handing over from one phone to "
        "the next, not for two mapping at once (the mapper takes them for one camera jumping)",
        bounds=(1, math.inf),
    )
    max_frame_bytes: int = field(
        MAX_FRAME_BYTES,
        "largest message accepted",
        "bytes",
        bounds=(MIN_FRAME_LIMIT, MAX_FRAME_LIMIT),
    )
    hello_timeout_s: float = field(
        5.0, "a client that sends no HELLO in this time is dropped", "s", bounds=(0.0, math.inf)
    )
    idle_timeout_s: float = field(
        5.0,
        "a client that has said HELLO and then makes no progress for this long (no whole "
        "message, nor 64 KiB of one) is dropped, freeing its slot (a phone that lost Wi-Fi "
        "sends no FIN); a stream of 10+ Hz is never that idle",
        "s",
        bounds=(0.0, math.inf),
    )
    max_errors_in_row: int = field(
        20, "bad messages in a row before a client is disconnected", bounds=(1, math.inf)
    )
    min_confidence: int = field(
        1,
        "ARKit confidence (0 low, 1 medium, 2 high) a pixel needs to become a point; low "
        "confidence pixels are mostly flying pixels at edges. Dropped pixels are NaN (unknown)",
        bounds=(0, 2),
    )
    organized: bool = field(True, "publish /iphone/points organised (H x W, NaN kept) or dense")
    stamp_mode: str = field(
        "offset",
        "offset: phone clock shifted onto ROS time at each connection's first frame (keeps "
        "the phone's exact frame spacing); phone: phone clock as is; receive: ROS time on "
        "arrival",
    )
    camera_frame: str = field(CAMERA_FRAME, "frame_id of images, camera info and points")
    odom_frame: str = field(ODOM_FRAME, "header.frame_id of /iphone/odometry (ARKit world z-up)")


def check_config(cfg: BridgeConfig) -> None:
    """``ValueError`` for the node's own settings; the network ones are
    :class:`~wheelgrid_mapping.bridge_protocol.BridgeServer`'s to check."""
    if cfg.stamp_mode not in ("offset", "phone", "receive"):
        raise ValueError(f"stamp_mode must be offset, phone or receive, not {cfg.stamp_mode!r}")
    check_min_confidence(cfg.min_confidence)


def stamp_to_msg(seconds: float) -> Any:
    """``ValueError`` for a stamp a ROS Time cannot hold: rclpy takes ``sec=3000000000`` and the
    serialised int32 wraps it to 1928, without a word."""
    from builtin_interfaces.msg import Time

    if not 0 <= seconds < MAX_STAMP_S:
        raise ValueError(f"stamp {seconds} s outside 0 .. 2^31 s (a ROS Time's int32 seconds)")
    sec = int(np.floor(seconds))
    nsec = round((seconds - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return Time(sec=sec, nanosec=nsec)


def _image(stamp: Any, frame_id: str, arr: np.ndarray, encoding: str) -> Any:
    from sensor_msgs.msg import Image

    a = np.ascontiguousarray(arr)
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(a.shape[0]), int(a.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = sys.byteorder == "big"
    msg.step = int(a.shape[1] * a.dtype.itemsize)
    msg.data = array.array("B", a.tobytes())
    return msg


def camera_info(stamp: Any, frame_id: str, K: np.ndarray, width: int, height: int) -> Any:
    from sensor_msgs.msg import CameraInfo

    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(width), int(height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5  # ARKit depth is already undistorted
    msg.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def odometry(stamp: Any, T_odom_optical: np.ndarray, odom_frame: str, child_frame: str) -> Any:
    """nav_msgs/Odometry of the ARKit pose. ARKit gives no covariance and no twist: both
    covariances carry -1 in element 0 ("unknown", the sensor_msgs convention), never a false
    certainty of zero."""
    from nav_msgs.msg import Odometry

    from wheelgrid_common.fileio import matrix_to_quat

    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = odom_frame
    msg.child_frame_id = child_frame
    x, y, z = (float(v) for v in T_odom_optical[:3, 3])
    qx, qy, qz, qw = matrix_to_quat(T_odom_optical[:3, :3])
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = x, y, z
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = qx, qy, qz, qw
    cov = [0.0] * 36
    cov[0] = -1.0
    msg.pose.covariance = cov
    msg.twist.covariance = cov
    return msg


def frame_messages(
    frame: Frame,
    stamp_s: float,
    *,
    min_confidence: int = 1,
    organized: bool = True,
    camera_frame: str = CAMERA_FRAME,
    odom_frame: str = ODOM_FRAME,
) -> list[tuple[str, str, Any]]:
    """All messages one frame becomes: ``[(topic, rosbag2 msgtype, rclpy message), ...]``."""
    from wheelgrid_common.pointcloud2 import to_pointcloud2

    stamp = stamp_to_msg(stamp_s)
    out: list[tuple[str, str, Any]] = []
    enc = "16UC1" if frame.depth_encoding == DEPTH_U16_MM else "32FC1"
    out.append(
        (TOPIC_DEPTH, "sensor_msgs/msg/Image", _image(stamp, camera_frame, frame.depth, enc))
    )
    out.append(
        (
            TOPIC_INFO,
            "sensor_msgs/msg/CameraInfo",
            camera_info(stamp, camera_frame, frame.K, frame.width, frame.height),
        )
    )
    if frame.confidence is not None:
        out.append(
            (
                TOPIC_CONF,
                "sensor_msgs/msg/Image",
                _image(stamp, camera_frame, frame.confidence, "mono8"),
            )
        )
    pts = depth_to_points(frame.depth_m(), frame.K, frame.confidence, min_confidence)
    if organized:
        cloud = to_pointcloud2(pts, camera_frame, stamp, height=frame.height)
    else:
        cloud = to_pointcloud2(pts[np.isfinite(pts).all(axis=1)], camera_frame, stamp)
    out.append((TOPIC_POINTS, "sensor_msgs/msg/PointCloud2", cloud))
    T = frame.pose_optical()
    if T is not None:
        out.append(
            (
                TOPIC_ODOM,
                "nav_msgs/msg/Odometry",
                odometry(stamp, arkit_pose_to_ros(T), odom_frame, camera_frame),
            )
        )
    return out


def _make_node(cfg_override: BridgeConfig | None = None) -> Any:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from wheelgrid_common.params import declare_dataclass
    from wheelgrid_common.qos import RELIABLE_QOS, SENSOR_QOS
    from wheelgrid_common.ros_env import exit_logger, steady_timer

    class IPhoneBridgeNode(Node):
        def __init__(self) -> None:
            super().__init__("iphone_bridge")
            log = self.get_logger()
            try:
                self.cfg = declare_dataclass(self, cfg_override or BridgeConfig())
                check_no_undeclared(self)
                check_config(self.cfg)
                token = self.cfg.token or os.environ.get(TOKEN_ENV, "")
                server = BridgeServer(
                    self._on_frame,
                    self._log,
                    bind_address=self.cfg.bind_address,
                    port=self.cfg.port,
                    token=token,
                    max_clients=self.cfg.max_clients,
                    max_frame_bytes=self.cfg.max_frame_bytes,
                    hello_timeout_s=self.cfg.hello_timeout_s,
                    idle_timeout_s=self.cfg.idle_timeout_s,
                    max_errors_in_row=self.cfg.max_errors_in_row,
                    on_disconnect=self._on_disconnect,
                )
            except (ValueError, OverflowError) as exc:  # as the other nodes: one FATAL, exit 2
                log.fatal(f"invalid parameters: {exc}")
                raise SystemExit(2) from exc
            if loss := confidence_loss(self.cfg.min_confidence):
                log.warning(loss)  # the mapper refuses it; its clouds come from here
            if self.cfg.max_clients > 1:
                # two phones at once went out as one camera: the mapper failed 80 of 95
                # frames, relocalising, and the bridge said nothing (a review)
                log.warning(
                    f"max_clients {self.cfg.max_clients}: every phone's frames go out on the "
                    "same topics and frames, as one camera; for a hand-over from one phone to "
                    "the next, not two phones mapping at once"
                )
            kinds = (
                (TOPIC_DEPTH, Image),
                (TOPIC_INFO, CameraInfo),
                (TOPIC_CONF, Image),
                (TOPIC_POINTS, PointCloud2),
                (TOPIC_ODOM, Odometry),
            )
            self._pubs = {
                topic: self.create_publisher(kind, topic.lstrip("/"), SENSOR_QOS)
                for topic, kind in kinds
            }
            self._status_pub = self.create_publisher(
                DiagnosticArray, TOPIC_STATUS.lstrip("/"), RELIABLE_QOS
            )
            self._lock = threading.Lock()
            self._offsets: dict[int, float] = {}  # client -> ROS time - phone time
            self.frames_published = 0
            self.frames_without_pose = 0
            try:
                server.start()
            except (OSError, OverflowError) as exc:  # port taken, address not ours: exit 2
                log.fatal(f"cannot start: {exc}")
                raise SystemExit(2) from exc
            self.server = server
            log.info(
                f"listening on {self.cfg.bind_address}:{self.server.port} "
                f"(token {'required' if token else 'not required: loopback only'})"
            )
            self._diag = (DiagnosticArray, DiagnosticStatus, KeyValue)
            steady_timer(self, 1.0, self._publish_status)

        def _log(self, level: str, text: str) -> None:
            # One call per severity: rclpy raises when one call site logs at two severities,
            # and a single shared call killed the server thread on its first warning.
            log = self.get_logger()
            if level == "info":
                log.info(text)
            elif level == "error":
                log.error(text)
            else:
                log.warning(text)

        def _stamp(self, frame: Frame, client: int) -> float:
            now = self.get_clock().now().nanoseconds * 1e-9
            if self.cfg.stamp_mode == "receive":
                return now
            if self.cfg.stamp_mode == "phone":
                return frame.stamp
            if client not in self._offsets:  # new connection: new phone clock
                self._offsets[client] = now - frame.stamp
            stamp = frame.stamp + self._offsets[client]
            if not 0 <= stamp < MAX_STAMP_S:  # the phone clock jumped by decades
                raise ValueError(
                    f"stamp {frame.stamp} s shifted to {stamp:.3f} s is outside what a ROS "
                    "Time holds"
                )
            return stamp

        def _on_disconnect(self, client: int) -> None:
            self._offsets.pop(client, None)

        def _on_frame(self, frame: Frame, client: int) -> None:
            msgs = frame_messages(
                frame,
                self._stamp(frame, client),
                min_confidence=self.cfg.min_confidence,
                organized=self.cfg.organized,
                camera_frame=self.cfg.camera_frame,
                odom_frame=self.cfg.odom_frame,
            )
            with self._lock:
                for topic, _, msg in msgs:
                    self._pubs[topic].publish(msg)
                self.frames_published += 1
                if frame.pose_optical() is None:
                    self.frames_without_pose += 1

        def _publish_status(self) -> None:
            DiagnosticArray, DiagnosticStatus, KeyValue = self._diag
            s = self.server
            values = {
                "port": s.port,
                "clients": s.clients,
                "frames_received": s.frames_received,
                "frames_published": self.frames_published,
                "frames_without_pose": self.frames_without_pose,
                "messages_rejected": s.messages_rejected,
                "rejected_by_reason": ", ".join(
                    # a copy: the server thread may add a reason meanwhile
                    f"{r} {n}"
                    for r, n in sorted(dict(s.rejected_by_reason).items())
                ),
                "clients_refused": s.clients_refused,
                "clients_timed_out": s.clients_timed_out,
                # the readers each frame topic's writer has matched: best-effort and volatile,
                # a frame published before the mapper's reader is matched here is lost, and a
                # reader seen in another node's graph may not be matched here yet
                **{
                    f"readers:{pub.topic_name}": pub.get_subscription_count()
                    for pub in self._pubs.values()
                },
            }
            st = DiagnosticStatus(
                level=DiagnosticStatus.OK if s.clients else DiagnosticStatus.WARN,
                name="iphone_bridge",
                message="streaming" if s.clients else "waiting for a phone",
                hardware_id=f"{self.cfg.bind_address}:{s.port}",
                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
            )
            arr = DiagnosticArray(status=[st])
            arr.header.stamp = self.get_clock().now().to_msg()
            self._status_pub.publish(arr)

        def close(self) -> None:
            if not hasattr(self, "server"):
                return
            self.server.stop()
            exit_logger(self).info(
                f"stopped: {self.server.frames_received} frames received, "
                f"{self.frames_published} published, {self.server.messages_rejected} rejected"
            )

    return IPhoneBridgeNode()


def main() -> None:
    from wheelgrid_common.ros_env import spin_node

    # spin_node's configure_ros_env gives it the large shared-memory profile
    # (wheelgrid_common/fastdds_loopback.xml): an organised cloud exceeds Fast DDS's default
    # 512 KB segment, and best-effort UDP fragments lose up to half of them
    sys.exit(spin_node(_make_node))


if __name__ == "__main__":
    main()
