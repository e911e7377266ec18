"""Bag replay into the running graph (``ros2 bag play`` is not in the pip wheels).

Publishes the bag's CDR bytes as they are (no re-serialisation), paced by the recorded log
times divided by ``rate``. Publishers are reliable so a reliable or a best-effort (sensor-data)
subscriber both match.
"""

from __future__ import annotations

import importlib
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from wheelgrid_common.bagio import BagError, BagReader

REPLAY_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def message_class(msgtype: str) -> Any:
    """'sensor_msgs/msg/PointCloud2' -> the rclpy class (ImportError if not installed)."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


class BagPlayer:
    """Replays selected topics of a bag from a background thread."""

    def __init__(
        self, node: Any, bag: Path, topics: Iterable[str] | None = None, rate: float = 1.0
    ) -> None:
        if rate <= 0:
            raise ValueError("rate must be > 0")
        self.node = node
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
            wanted = set(topics) if topics else {t.name for t in infos}
            absent = sorted(wanted - {t.name for t in infos})
            if absent:
                # a misspelt --topic replayed nothing of it, without a word
                listing = ", ".join(f"{t.name} ({t.msgtype})" for t in infos) or "none"
                raise BagError(
                    f"{self.bag}: no topic {', '.join(map(repr, absent))} to replay; "
                    f"topics: {listing}"
                )
            self.topics = [t for t in infos if t.name in wanted]
            self.total = sum(t.count for t in self.topics)
        self._pubs = {
            t.name: node.create_publisher(message_class(t.msgtype), t.name, REPLAY_QOS)
            for t in self.topics
        }
        self._thread = threading.Thread(target=self._run, name="bag-replay", daemon=True)

    def unsubscribed(self) -> list[str]:
        """Replayed topics nobody subscribes to yet (a frame sent now would be lost)."""
        return [t for t, pub in self._pubs.items() if pub.get_subscription_count() == 0]

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
                        t0_bag = t_ns
                    due = t0_wall + (t_ns - t0_bag) / 1e9 / self.rate
                    if self._stop.wait(max(0.0, due - time.monotonic())):
                        return
                    self._pubs[topic].publish(raw)
                    self.published += 1
        except Exception as exc:  # reported by the launcher's status line, never swallowed
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.done.set()
