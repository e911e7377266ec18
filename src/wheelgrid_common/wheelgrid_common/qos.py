"""The two QoS profiles the suite uses (ROS conventions, see REP-2003).

Sensor streams tolerate loss and must never back up: best effort, keep last 5, volatile.
Maps are state, not a stream: reliable, transient-local, keep last 1, so a subscriber that
starts late (RViz, Nav2, the planner) still gets the current map at once.
"""

from __future__ import annotations

from typing import Any

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

SENSOR_QOS: QoSProfile = qos_profile_sensor_data

MAP_QOS: QoSProfile = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

# MAP_QOS for a reader that must see every map in turn, not only the newest: the mapper's
# ~/reset is an empty map, and while the grid node was busy gridding a big map the next map
# replaced it in the one slot, and the cleared map's grid stayed published (a review).
MAP_QUEUE_QOS: QoSProfile = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

# Commands and state that must arrive but need no late-joiner replay.
RELIABLE_QOS: QoSProfile = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

# /tf as tf2_ros's TransformBroadcaster sends it (DynamicBroadcasterQoS): a tf2 listener
# subscribes with the same profile and keeps up to 100 transforms in flight, so a burst of
# poses after a pause is not cut to the last ten.
TF_QOS: QoSProfile = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def volatile_writers_expected() -> Any:
    """Subscription event callbacks for a transient-local reader beside a volatile one on the
    same topic (the e-stop's latched copy): a volatile writer cannot match it, by DDS's rules,
    and is served by the other reader, so rclpy's default "offering incompatible QoS" warning
    at each such writer is noise, not a fault."""
    from rclpy.event_handler import SubscriptionEventCallbacks

    return SubscriptionEventCallbacks(incompatible_qos=lambda _status: None)
