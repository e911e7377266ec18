"""``depth_to_cloud`` node: depth Image + CameraInfo (+ confidence) -> PointCloud2.

Works for any depth camera that follows REP-118 (32FC1 metres or 16UC1 millimetres), not only
the iPhone. The three streams are matched by header stamp with
:class:`~wheelgrid_mapping.depth.StampSync` (message_filters is not in the ROS wheels); a depth
image whose camera info (or confidence) never arrives is dropped, never projected with guessed
intrinsics, and that is said once, naming the silent topic. Defaults are the bridge's topics,
so ``depth_to_cloud`` also serves apps that publish only images (Record3D-ROS2, ARKit-to-ROS2
bridges).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from wheelgrid_common.params import check_no_undeclared, field
from wheelgrid_mapping.depth import (
    StampSync,
    camera_info_doubts,
    camera_info_intrinsics,
    check_min_confidence,
    confidence_loss,
    depth_image_to_metres,
    depth_to_points,
    image_array,
)


@dataclass
class DepthToCloudConfig:
    depth_topic: str = field("iphone/depth/image", "depth Image (32FC1 m or 16UC1 mm)")
    info_topic: str = field("iphone/depth/camera_info", "CameraInfo of the depth image")
    confidence_topic: str = field(
        "iphone/confidence/image", "confidence Image (mono8/8UC1); empty = do not use one"
    )
    points_topic: str = field("iphone/points", "PointCloud2 output, in the depth image's frame")
    min_confidence: int = field(
        1,
        "pixels with confidence below this become NaN (ARKit: 0 low, 1 medium, 2 high)",
        bounds=(0, 2),
    )
    organized: bool = field(True, "organised cloud (H x W, NaN kept) or dense (valid only)")
    mm_scale: float = field(
        0.001, "metres per unit of 16UC1 depth (> 0)", "m", bounds=(0.0, math.inf)
    )
    sync_tolerance_s: float = field(
        0.001, "largest stamp difference still 'the same frame'", "s", bounds=(0.0, math.inf)
    )
    queue_size: int = field(
        10, "messages kept per stream while waiting for a match", bounds=(1, math.inf)
    )


def check_config(cfg: DepthToCloudConfig) -> None:
    """``ValueError`` for settings the node cannot run with: a queue of 0 or a NaN tolerance
    matched nothing, and a min_confidence outside ARKit's 0..2 dropped every pixel or none,
    all without a word."""
    check_min_confidence(cfg.min_confidence)
    if not (math.isfinite(cfg.mm_scale) and cfg.mm_scale > 0):
        raise ValueError(f"mm_scale must be a finite length > 0 m, not {cfg.mm_scale}")
    if not (math.isfinite(cfg.sync_tolerance_s) and cfg.sync_tolerance_s >= 0):
        raise ValueError(
            f"sync_tolerance_s must be a finite time >= 0 s, not {cfg.sync_tolerance_s}"
        )
    if cfg.queue_size < 1:
        raise ValueError(f"queue_size must be >= 1, not {cfg.queue_size}")


def _check_topics(node: Any, cfg: DepthToCloudConfig) -> None:
    """A bad topic name as one ``ValueError``, not rclpy's traceback from create_*."""
    from wheelgrid_common.ros_env import check_topic_params

    names = ("depth_topic", "info_topic", "confidence_topic", "points_topic")
    topics = {what: getattr(cfg, what) for what in names}
    check_topic_params(node, topics, optional=("confidence_topic",))  # "": no confidence


def _stamp_s(msg: Any) -> float:
    return float(msg.header.stamp.sec) + 1e-9 * float(msg.header.stamp.nanosec)


def _make_node() -> Any:
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from wheelgrid_common.params import declare_dataclass
    from wheelgrid_common.pointcloud2 import to_pointcloud2
    from wheelgrid_common.qos import SENSOR_QOS

    class DepthToCloudNode(Node):
        def __init__(self) -> None:
            super().__init__("depth_to_cloud")
            try:
                self.cfg = declare_dataclass(self, DepthToCloudConfig())
                check_no_undeclared(self)
                check_config(self.cfg)
                _check_topics(self, self.cfg)
            except ValueError as exc:  # as the other nodes: one FATAL line, exit 2
                self.get_logger().fatal(f"invalid parameters: {exc}")
                raise SystemExit(2) from exc
            if loss := confidence_loss(self.cfg.min_confidence):
                self.get_logger().warning(loss)  # the mapper refuses it; its clouds come here
            use_conf = bool(self.cfg.confidence_topic)
            streams = ["depth", "info"] + (["conf"] if use_conf else [])
            self.sync = StampSync(streams, self.cfg.sync_tolerance_s, self.cfg.queue_size)
            self.pub = self.create_publisher(PointCloud2, self.cfg.points_topic, SENSOR_QOS)
            self.create_subscription(
                Image, self.cfg.depth_topic, lambda m: self._add("depth", m), SENSOR_QOS
            )
            self.create_subscription(
                CameraInfo, self.cfg.info_topic, lambda m: self._add("info", m), SENSOR_QOS
            )
            if use_conf:
                self.create_subscription(
                    Image, self.cfg.confidence_topic, lambda m: self._add("conf", m), SENSOR_QOS
                )
            # stream -> its topic as resolved in this node's namespace, for what the node says
            self._topics = {
                stream: self.resolve_topic_name(topic)
                for stream, topic in (
                    ("depth", self.cfg.depth_topic),
                    ("info", self.cfg.info_topic),
                    ("conf", self.cfg.confidence_topic),
                )
                if topic
            }
            self.published = 0
            self._warned: set[str] = set()
            self._seen: set[str] = set()  # streams that have had a message
            self.get_logger().info(" + ".join(self._topics.values()) + f" -> {self.pub.topic_name}")

        def _warn_once(self, key: str, text: str) -> None:
            if key not in self._warned:
                self._warned.add(key)
                self.get_logger().warning(text)

        def _add(self, stream: str, msg: Any) -> None:
            self._seen.add(stream)
            dropped = self.sync.dropped_by_stream["depth"]
            group = self.sync.add(stream, _stamp_s(msg), msg)
            if self.sync.dropped_by_stream["depth"] > dropped:
                self._say_why_depth_is_dropped()
            if group is not None:
                try:
                    self._publish(group["depth"], group["info"], group.get("conf"))
                except ValueError as exc:  # malformed input: log once per cause, keep running
                    self._warn_once(str(exc).split(":")[0], f"frame dropped: {exc}")

        def _say_why_depth_is_dropped(self) -> None:
            """Once per cause: a depth image left without its camera info or confidence of
            the same stamp is dropped, never projected with guesses, and a camera that
            publishes no confidence image (with the default confidence_topic) had every frame
            dropped while the node said nothing."""
            silent = [self._topics[s] for s in self.sync.streams if s not in self._seen]
            if silent:
                hint = (
                    " (a camera without confidence images needs -p confidence_topic:=\"''\" "
                    "in a shell, or confidence_topic: '' in a params file)"
                    if self._topics.get("conf") in silent
                    else ""
                )
                self._warn_once(
                    f"silent:{silent}",
                    f"depth images dropped: nothing has arrived on {', '.join(silent)}, "
                    f"which each depth image waits for{hint}",
                )
            else:
                self._warn_once(
                    "unmatched",
                    "depth images dropped: no camera info / confidence image within "
                    f"sync_tolerance_s ({self.cfg.sync_tolerance_s} s) of their stamps",
                )

        def _publish(self, depth_msg: Any, info: Any, conf_msg: Any) -> None:
            depth = depth_image_to_metres(
                depth_msg.encoding,
                depth_msg.height,
                depth_msg.width,
                depth_msg.step,
                bool(depth_msg.is_bigendian),
                bytes(depth_msg.data),
                self.cfg.mm_scale,
            )
            K = camera_info_intrinsics(info, depth_msg.width, depth_msg.height)
            for cause, text in camera_info_doubts(info, depth_msg.header.frame_id):
                self._warn_once(cause, text)
            conf = None
            if conf_msg is not None:
                conf = image_array(
                    conf_msg.encoding,
                    conf_msg.height,
                    conf_msg.width,
                    conf_msg.step,
                    bool(conf_msg.is_bigendian),
                    bytes(conf_msg.data),
                )
            pts = depth_to_points(depth, K, conf, self.cfg.min_confidence)
            frame_id = depth_msg.header.frame_id
            if self.cfg.organized:
                cloud = to_pointcloud2(pts, frame_id, depth_msg.header.stamp, height=depth.shape[0])
            else:
                pts = pts[np.isfinite(pts).all(axis=1)]
                cloud = to_pointcloud2(pts, frame_id, depth_msg.header.stamp)
            self.pub.publish(cloud)
            self.published += 1

    return DepthToCloudNode()


def main() -> None:
    from wheelgrid_common.ros_env import spin_node

    # organised clouds exceed Fast DDS's default 512 KB SHM segment: spin_node's
    # configure_ros_env gives every wheelgrid process a 16 MB one
    sys.exit(spin_node(_make_node))


if __name__ == "__main__":
    main()
