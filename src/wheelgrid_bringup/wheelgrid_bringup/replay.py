"""Bag replay into the running graph (``ros2 bag play`` is not in the pip wheels).

Publishes the bag's CDR bytes as they are (no re-serialisation, but each checked to
deserialise: a damaged one is counted and said, not sent), paced by the recorded log times
divided by ``rate``. Unless topics are named, only the sensors' data goes out
(:func:`is_sensor_input`). Publishers are reliable so a reliable or a best-effort (sensor-data)
subscriber both match. With ``clock_hz``, the bag's time also goes out on ``/clock``, as
``ros2 bag play --clock`` sends it: nodes under ``use_sim_time`` then stamp what they make
on the sensor's clock, and a stack that looks transforms up at a cloud's stamp finds them.
"""

from __future__ import annotations

import importlib
import math
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from wheelgrid_common.bagio import BagError, BagReader, damage_hint

REPLAY_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# /tf_static as tf2's static broadcaster offers it: a latched reader (tf2's static listener,
# RViz) asks for transient local, which REPLAY_QOS cannot give, and got nothing (a review).
# Every message kept: each is one broadcaster's set of static transforms.
STATIC_TF_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# Only the newest time matters; reliable matches rclpy's best-effort /clock reader and a
# reliable one alike.
CLOCK_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


# Topics a chain in a namespace still shares with the rest of the system: the bag's time.
# The transform tree is the chain's own, as the mapper's `tf` is (Nav2's multi-robot
# convention): a bag's /tf and /tf_static go out under the namespace too.
GLOBAL_TOPICS = ("/clock",)


def replayed_name(topic: str, namespace: str) -> str:
    """The name a bag's ``topic`` goes out on for a chain in ``namespace`` (absolute, e.g.
    ``/chair1``; ``""`` for the root): ``/iphone/points`` -> ``/chair1/iphone/points``. The
    nodes name their topics relative to their namespace, so a bag replayed under its recorded
    names would reach none of them."""
    if not namespace.strip("/") or topic in GLOBAL_TOPICS:
        return topic
    return namespace.rstrip("/") + "/" + topic.lstrip("/")


def play_remaps(bag: Path, namespace: str) -> list[str]:
    """``ros2 bag play`` arguments that replay ``bag`` as :class:`BagPlayer` does for a chain
    in ``namespace`` (``["--remap", "/a:=/ns/a", ...]``, or ``[]`` when nothing moves):
    ``ros2 bag play`` has no namespace of its own, and its ``__ns`` leaves absolute names."""
    with BagReader(Path(bag)) as reader:
        names = sorted({t.name for t in reader.topics()})
    moved = ((name, replayed_name(name, namespace)) for name in names)
    rules = [f"{old}:={new}" for old, new in moved if old != new]
    return ["--remap", *rules] if rules else []


# What a replay sends unless its topics are named: sensor data. A bag recorded on a chair
# (`ros2 bag record -a`) holds /cmd_vel, /goal_pose, /initialpose and the chain's own
# outputs; replayed whole into a live chain, a recording's /cmd_vel drove the chair 3 m (a
# review). A joystick is a command, not a sensor.
SENSOR_TYPES = ("nav_msgs/msg/Odometry",)
COMMAND_SENSOR_TYPES = ("sensor_msgs/msg/Joy",)
# The replayed topics a replay waits for a reader of before it starts (the mapper's clouds
# and pose prior: the first frame defines the map frame); the rest go out when they come (a
# bag from import-stray also holds the depth images, which no node of the chain reads, and
# the demo failed waiting for a reader of them; a review).
AWAITED_TYPES = ("sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Odometry")


def is_sensor_input(topic: str, msgtype: str) -> bool:
    """Whether a bag's ``topic`` of ``msgtype`` is sensor data a replay sends by default: a
    sensor_msgs type (not a joystick), odometry or static transforms, and not one of the
    chain's own outputs: ``wheelgrid/NAME`` (its odometry is the planner's start pose; a chain
    recorded in a namespace called wheelgrid keeps its ``/wheelgrid/iphone/points``) and
    ``tf``, where the recorded mapper's map -> sensor transforms would go out beside the live
    mapper's (a review)."""
    parts = [p for p in topic.split("/") if p]
    if (len(parts) >= 2 and parts[-2] == "wheelgrid") or msgtype in COMMAND_SENSOR_TYPES:
        return False
    if msgtype == "tf2_msgs/msg/TFMessage":
        return bool(parts) and parts[-1] == "tf_static"
    return msgtype.startswith("sensor_msgs/msg/") or msgtype in SENSOR_TYPES


def sensor_topics(bag: Path) -> list[str]:
    """The topics of ``bag`` a replay sends by default (:func:`is_sensor_input`), for ``ros2
    bag play --topics``, which otherwise plays them all, commands included."""
    with BagReader(Path(bag)) as reader:
        return sorted({t.name for t in reader.topics() if is_sensor_input(t.name, t.msgtype)})


def not_replayed_note(player: BagPlayer) -> str:
    """The line that names the bag's topics a replay leaves out."""
    return (
        f"not replayed: {', '.join(player.left_out)} (not sensor data: commands, goals and "
        "the chain's own outputs would reach the running chain; `wheelgrid launch --topic` "
        "names the topics to replay)"
    )


def message_class(msgtype: str) -> Any:
    """'sensor_msgs/msg/PointCloud2' -> the rclpy class (ImportError if not installed)."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


class BagPlayer:
    """Replays selected topics of a bag from a background thread."""

    def __init__(
        self,
        node: Any,
        bag: Path,
        topics: Iterable[str] | None = None,
        rate: float = 1.0,
        clock_hz: float = 0.0,
        clock_readers: int = 0,
        namespace: str = "",
    ) -> None:
        """``namespace`` (absolute, e.g. ``/chair1``) puts the bag's topics under it, for a
        chain started there: ``/iphone/points`` goes out on ``/chair1/iphone/points``."""
        if not (math.isfinite(rate) and rate > 0):  # NaN made every due time NaN: a spin
            raise ValueError(f"rate must be a number > 0, not {rate}")
        if not clock_hz >= 0:
            raise ValueError("clock_hz must be >= 0 (0: no /clock)")
        self.node = node
        self.clock_readers = clock_readers
        self.bag = Path(bag)
        self.rate = rate
        self.published = 0
        self.total = 0
        self.error: str | None = None
        self.done = threading.Event()
        self._stop = threading.Event()
        with BagReader(self.bag) as reader:
            if not reader.reader.is2:
                # Its bytes are ROS 1 serialisation (no CDR header, Header.seq): published as
                # they are, every ROS 2 subscriber failed to read them, or misread them.
                raise BagError(
                    f"{self.bag}: a ROS 1 bag, whose messages ROS 2 nodes cannot read as they "
                    f"are: convert it first (`rosbags-convert --src {self.bag} --dst NEW_BAG`) "
                    "and replay NEW_BAG; `wheelgrid map` reads it as it is"
                )
            infos = reader.topics()
            sensors = {t.name for t in infos if is_sensor_input(t.name, t.msgtype)}
            wanted = set(topics) if topics else sensors
            # said by the launcher and the demo: a topic not sent is no silent loss
            self.left_out = sorted({t.name for t in infos} - wanted)
            if not wanted:
                raise BagError(
                    f"{self.bag}: no sensor data to replay (topics: "
                    f"{', '.join(f'{t.name} ({t.msgtype})' for t in infos) or 'none'}); name "
                    "the topics to replay with `wheelgrid launch --bag ... --topic`"
                )
            if clock_hz > 0 and any(n in GLOBAL_TOPICS for n in wanted):
                # two clocks on /clock: the replay's and the recording's, 40 of 191 going back
                raise BagError(
                    f"{self.bag}: --clock publishes the bag's time on /clock; replaying its "
                    "recorded /clock too would send two clocks: leave --topic /clock out"
                )
            absent = sorted(wanted - {t.name for t in infos})
            if absent:
                # a misspelt --topic replayed nothing of it, without a word
                listing = ", ".join(f"{t.name} ({t.msgtype})" for t in infos) or "none"
                raise BagError(
                    f"{self.bag}: no topic {', '.join(map(repr, absent))} to replay; "
                    f"topics: {listing}"
                )
            self.topics = [t for t in infos if t.name in wanted]
            names = [t.name for t in self.topics]
            if twice := sorted({n for n in names if names.count(n) > 1}):
                # one publisher a topic: the other type's messages went out as this one's
                types = ", ".join(t.msgtype for t in self.topics if t.name == twice[0])
                raise BagError(
                    f"{self.bag}: topic {twice[0]} carries more than one message type "
                    f"({types}), which ROS 2 cannot publish on one topic; replay the other "
                    "topics with `wheelgrid launch --bag ... --topic`"
                )
            self.total = sum(t.count for t in self.topics)
        classes = {}
        for t in self.topics:
            try:
                classes[t.name] = message_class(t.msgtype)
            except (ImportError, AttributeError, ValueError):
                # a robot's bag often carries a vendor's types: a traceback named no topic
                raise BagError(
                    f"{self.bag}: {t.name} holds {t.msgtype}, a message type this ROS "
                    "installation does not have; replay the other topics with "
                    "`wheelgrid launch --bag ... --topic`"
                ) from None
        self._classes = classes
        self._awaited = {t.name for t in self.topics if t.msgtype in AWAITED_TYPES}
        self.damaged = 0  # messages that do not deserialise: not sent
        self._pubs = {}
        for t in self.topics:
            try:
                self._pubs[t.name] = node.create_publisher(
                    classes[t.name],
                    replayed_name(t.name, namespace),
                    STATIC_TF_QOS if t.name.rstrip("/").endswith("tf_static") else REPLAY_QOS,
                )
            except Exception as exc:  # rclpy's InvalidTopicNameException: a traceback
                for pub in self._pubs.values():
                    node.destroy_publisher(pub)
                raise BagError(
                    f"{self.bag}: topic {t.name} cannot be published in ROS 2 ({exc}); replay "
                    "the other topics with `wheelgrid launch --bag ... --topic`"
                ) from None
        self._clock_period = 1.0 / clock_hz if clock_hz > 0 else 0.0
        self._clock_next = -math.inf  # monotonic time of the next /clock
        self._clock_pub = None
        if clock_hz > 0:
            from rosgraph_msgs.msg import Clock

            self._clock_msg = Clock()
            self._clock_pub = node.create_publisher(Clock, "/clock", CLOCK_QOS)
        self._thread = threading.Thread(target=self._run, name="bag-replay", daemon=True)

    def unsubscribed(self) -> list[str]:
        """The chain's input topics nobody subscribes to yet (a frame sent now would be lost), and
        ``/clock`` while fewer than ``clock_readers`` nodes follow it (a node that matched it
        late stamped its first map or grid with time 0)."""
        # only the chain's inputs are waited for (AWAITED_TYPES): a latched /tf_static
        # reaches a later reader anyway, and no node of the chain reads a depth image
        topics = [
            p.topic_name
            for name, p in self._pubs.items()
            if name in self._awaited and p.get_subscription_count() == 0
        ]
        clock = self._clock_pub
        if clock is not None and clock.get_subscription_count() < self.clock_readers:
            topics.append("/clock")
        return topics

    def start(self, delay: float = 0.0) -> None:
        self._delay = delay
        self._thread.start()

    def stop(self) -> None:
        """Safe before ``start``: the launch opens the bag first and may stop the chain (a
        node that died while starting) before the replay began."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        try:
            if self._stop.wait(getattr(self, "_delay", 0.0)):
                return
            with BagReader(self.bag) as reader:
                t0_bag: int | None = None
                t0_wall = time.monotonic()
                for topic, _msgtype, t_ns, raw in reader.raw(self._pubs):
                    if t0_bag is None:
                        t0_bag, t0_wall = t_ns, time.monotonic()
                    due = t0_wall + (t_ns - t0_bag) / 1e9 / self.rate
                    if self._wait_until(due, t0_wall, t0_bag):
                        return
                    try:
                        # what every subscriber does with it: a message cut short went out
                        # as it was, subscribers dropped it with an rmw error, and the
                        # replay read as complete, exit 0 (a review)
                        deserialize_message(raw, self._classes[topic])
                    except Exception:
                        self.damaged += 1
                        continue
                    self._pubs[topic].publish(raw)
                    self.published += 1
                if self._clock_pub is not None and t0_bag is not None:
                    self._publish_clock(t_ns)  # the clock ends on the last message's time
                if self.damaged:
                    raise BagError(
                        f"{self.bag}: {self.damaged} message(s) do not deserialise (damaged?) "
                        f"and were not replayed; the other {self.published} were"
                    )
                if self.published < self.total:
                    # the MCAP reader ends quietly at a damaged chunk: 5 of 12 went out, and
                    # the replay read as complete
                    hint = damage_hint(self.bag)
                    raise BagError(
                        f"{self.bag}: its metadata lists {self.total} message(s) but only "
                        f"{self.published} could be read (damaged storage?)"
                        + (f"; {hint}" if hint else "")
                    )
        except Exception as exc:  # reported by the launcher, never swallowed
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.done.set()

    def _wait_until(self, due: float, t0_wall: float, t0_bag: int) -> bool:
        """Sleep until the monotonic time ``due``, sending the bag's time on ``/clock`` every
        clock period meanwhile; True when stopped. The clock reads ``t0_bag`` plus the wall
        time since ``t0_wall`` times ``rate``, never past the message about to go out: a node
        never sees the clock ahead of a message still on its way."""
        while True:
            now = time.monotonic()
            if self._clock_pub is not None and now >= self._clock_next:
                self._publish_clock(t0_bag + int((min(now, due) - t0_wall) * self.rate * 1e9))
                self._clock_next = now + self._clock_period
            left = due - now
            if left <= 0:
                return self._stop.is_set()
            if self._clock_pub is not None:
                left = min(left, self._clock_next - now)
            # in slices: a wait past ~9.2e9 s (0.2 s between messages at --rate 1e-11) raised
            # OverflowError and ended the replay
            if self._stop.wait(min(left, 60.0)):
                return True

    def _publish_clock(self, bag_ns: int) -> None:
        assert self._clock_pub is not None
        self._clock_msg.clock.sec, self._clock_msg.clock.nanosec = divmod(bag_ns, 1_000_000_000)
        self._clock_pub.publish(self._clock_msg)
