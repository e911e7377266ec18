"""Reading and writing bags with ``rosbags`` (there is no rosbag2 in the ROS wheels).

Reads rosbag2 folders (sqlite3 or mcap) and ROS 1 ``.bag`` files through one API; every way a
bag can be unusable becomes a :class:`BagError` with a sentence a user can act on. Writes
rosbag2 (sqlite3 or mcap) from rclpy messages: rclpy's CDR bytes are what rosbag2 stores.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .params import read_yaml

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


class BagError(Exception):
    """A bag that cannot be used; the message says why and what to do."""


def typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def recover_hint(path: Path) -> str:
    """What to do with a recording that was cut off (``wheelgrid bag-recover``)."""
    return (
        f"a recording that was cut off? `wheelgrid bag-recover {path} --out NEW_BAG` copies "
        "its complete messages into a bag that opens"
    )


def damage_hint(path: Path) -> str:
    """What to do with an MCAP recording a reader fails on: cut off (:func:`recover_hint`), or
    damaged inside, where ``wheelgrid bag-recover`` still copies the chunks that are intact (a
    zeroed first chunk lost a map every frame of the second; nothing said the tool would help).
    '' for other storage."""
    if cut_off_mcap(path):
        return recover_hint(path)
    if not _mcap_files(path):
        return ""
    return (
        f"`wheelgrid bag-recover {path} --out NEW_BAG` copies the messages of its intact "
        "chunks into a bag that opens"
    )


MCAP_MAGIC = b"\x89MCAP0\r\n"


def cut_off_mcap(path: Path) -> bool:
    """Whether a bag folder (or file) holds an MCAP file that does not end with the MCAP magic.

    A complete MCAP file ends with its footer and the magic; one a killed recorder left does
    not. Judged from the file itself, not from a reader's error text, which a release may reword.
    """
    for f in _mcap_files(path):
        try:
            size = f.stat().st_size
            with f.open("rb") as fh:
                fh.seek(max(size - len(MCAP_MAGIC), 0))
                if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                    return True
        except OSError:
            continue
    return False


def _mcap_files(path: Path) -> list[Path]:
    """The MCAP files of a bag folder, or the file itself where it is one."""
    files = [path] if path.is_file() else sorted(path.glob("*.mcap")) if path.is_dir() else []
    return [f for f in files if f.suffix == ".mcap"]


def _check_path(path: Path) -> None:
    if not path.exists():
        raise BagError(f"{path}: no such bag (expected a rosbag2 folder or a ROS 1 .bag file)")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        if any(path.glob("*.mcap")) or any(path.glob("*.db3")):
            raise BagError(f"{path}: bag files but no metadata.yaml: {recover_hint(path)}")
        raise BagError(f"{path}: folder has no metadata.yaml, so it is not a rosbag2 bag")
    if path.is_file() and path.suffix != ".bag":
        raise BagError(f"{path}: not a bag (a rosbag2 folder or a ROS 1 .bag file)")


def _check_metadata(path: Path) -> None:
    """``BagError`` for a metadata.yaml whose file list or message counts cannot be true: a
    count that is not a whole number >= 0 ended ``wheelgrid map`` in a TypeError traceback
    (or, with ``--max-frames``, a ValueError), and a storage file listed twice was read twice,
    every frame mapped twice, exit 0."""
    if not path.is_dir():
        return
    try:
        info = (read_yaml(path / "metadata.yaml") or {}).get("rosbag2_bagfile_information")
    except (OSError, ValueError, AttributeError):
        return  # rosbags says what is wrong with it, in its own words
    if not isinstance(info, dict):
        return
    files = info.get("relative_file_paths") or []
    if isinstance(files, list):
        # the same file under two spellings (x.mcap, ./x.mcap, its absolute path) is read
        # twice as surely as one name listed twice
        where = [os.path.realpath(path / str(f)) for f in files]
        twice = sorted({str(f) for f, w in zip(files, where, strict=True) if where.count(w) > 1})
        if twice:
            raise BagError(
                f"{path}: metadata.yaml lists {', '.join(twice)} more than once; each "
                "storage file is read once (fix relative_file_paths)"
            )
    for entry in info.get("topics_with_message_count") or []:
        if not isinstance(entry, dict) or "message_count" not in entry:
            continue
        count = entry["message_count"]
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            topic = (entry.get("topic_metadata") or {}).get("name", "?")
            raise BagError(
                f"{path}: metadata.yaml gives topic {topic} a message_count of {count!r}, not "
                "a whole number >= 0"
            )


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int


class BagReader:
    """Context manager over ``rosbags.highlevel.AnyReader`` with clear errors."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader: Any = None

    def __enter__(self) -> BagReader:
        from rosbags.highlevel import AnyReader

        _check_path(self.path)
        _check_metadata(self.path)
        try:
            reader = AnyReader([self.path], default_typestore=typestore())
            reader.open()
            self._reader = reader  # only an opened reader is ever closed in __exit__
        except Exception as exc:  # rosbags raises several unrelated types for corrupt bags
            # One line: a YAML parser's message spans several, with carets under the error.
            detail = " ".join(str(exc).split())
            text = f"{self.path}: cannot open bag ({type(exc).__name__}: {detail})"
            hint = damage_hint(self.path)
            raise BagError(text + (f"; {hint}" if hint else "")) from exc
        return self

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            finally:
                self._reader = None

    @property
    def reader(self) -> Any:
        if self._reader is None:
            raise RuntimeError("BagReader used outside its with-block")
        return self._reader

    def topics(self) -> list[TopicInfo]:
        """One entry per topic and message type (a topic may carry two: merged bags, ROS 1)."""
        out: dict[tuple[str, str], TopicInfo] = {}
        for c in self.reader.connections:
            prev = out.get((c.topic, c.msgtype))
            count = (prev.count if prev else 0) + c.msgcount
            out[c.topic, c.msgtype] = TopicInfo(c.topic, c.msgtype, count)
        return sorted(out.values(), key=lambda t: (t.name, t.msgtype))

    def pick_topic(
        self, topic: str | None, msgtype: str = POINTCLOUD2, flag: str = "--topic"
    ) -> str:
        """The requested topic, or the only topic of ``msgtype``; BagError listing them if not,
        naming the option (``flag``) that chooses one."""
        infos = self.topics()
        if topic is not None:
            match = [t for t in infos if t.name == topic]
            if not match:
                listing = ", ".join(f"{t.name} ({t.msgtype})" for t in infos) or "none"
                raise BagError(f"{self.path}: no topic {topic!r}; topics: {listing}")
            if all(t.msgtype != msgtype for t in match):
                carried = ", ".join(t.msgtype for t in match)
                raise BagError(f"{self.path}: topic {topic!r} carries {carried}, not {msgtype}")
            return topic
        cands = [t for t in infos if t.msgtype == msgtype]
        if len(cands) == 1:
            return cands[0].name
        if not cands:  # say what the bag holds instead: a user who recorded the wrong topic
            others = ", ".join(f"{t.name} ({t.msgtype})" for t in infos) or "none"
            raise BagError(f"{self.path}: no {msgtype} topic; the bag's topics: {others}")
        listing = ", ".join(f"{t.name} ({t.count} msgs)" for t in cands)
        raise BagError(
            f"{self.path}: {len(cands)} {msgtype} topics ({listing}); choose one with {flag}"
        )

    def _connections(self, topics: Iterable[str], msgtype: str | None) -> list[Any]:
        """The connections of ``topics``, only those of ``msgtype`` where it is given: a ROS 1
        or merged bag may hold two types on one topic, and the other type's messages were
        read as this one's (a traceback in ``wheelgrid map``)."""
        wanted = set(topics)
        return [
            c for c in self.reader.connections if c.topic in wanted and msgtype in (None, c.msgtype)
        ]

    def count(self, topics: Iterable[str], msgtype: str | None = None) -> int:
        return sum(c.msgcount for c in self._connections(topics, msgtype))

    def raw(
        self, topics: Iterable[str], msgtype: str | None = None
    ) -> Iterator[tuple[str, str, int, bytes]]:
        """(topic, msgtype, log time ns, CDR bytes) in log-time order; of ``msgtype`` only,
        where it is given."""
        conns = self._connections(topics, msgtype)
        try:
            for conn, t_ns, raw in self.reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, int(t_ns), bytes(raw)
        except Exception as exc:
            hint = damage_hint(self.path)
            raise BagError(
                f"{self.path}: bag is corrupt ({type(exc).__name__}: {exc})"
                + (f"; {hint}" if hint else "")
            ) from exc

    def messages(
        self, topics: Iterable[str], *, damaged_as_none: bool = False, msgtype: str | None = None
    ) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time ns, deserialised rosbags message) in log-time order.

        A message that does not deserialise is a ``BagError``, or with ``damaged_as_none`` its
        place in the order with ``None`` for the message: one damaged message in a long bag
        then costs the reader that message only (``wheelgrid map`` counts it and maps on)."""
        for topic, kind, t_ns, raw in self.raw(topics, msgtype):
            try:
                msg = self.reader.deserialize(raw, kind)
            except Exception as exc:  # rosbags raises several types for a damaged message
                if damaged_as_none:
                    yield topic, t_ns, None
                    continue
                raise BagError(
                    f"{self.path}: message on {topic} at {t_ns} ns does not deserialise as "
                    f"{kind} ({type(exc).__name__}: {exc})"
                ) from exc
            yield topic, t_ns, msg


class BagWriter:
    """Write rclpy messages (or raw CDR bytes) into a new rosbag2 bag."""

    def __init__(self, path: str | Path, storage: str = "sqlite3") -> None:
        from rosbags.rosbag2 import StoragePlugin

        if storage not in ("sqlite3", "mcap"):
            raise ValueError(f"storage must be sqlite3 or mcap, not {storage!r}")
        self.path = Path(path)
        self.storage = storage
        self._plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer: Any = None
        self._conns: dict[str, Any] = {}
        self._store = typestore()

    def __enter__(self) -> BagWriter:
        from rosbags.rosbag2 import Writer

        if self.path.exists():
            raise BagError(f"{self.path}: already exists; rosbag2 will not overwrite a bag")
        self._writer = Writer(self.path, version=9, storage_plugin=self._plugin)
        self._writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        if isinstance(msg, bytes | bytearray | memoryview):
            data = bytes(msg)
        else:
            from rclpy.serialization import serialize_message

            data = serialize_message(msg)
        # rclpy leaves the alignment padding after strings uninitialised; a rosbags round trip
        # zeroes it, so the same messages always give the same bag bytes (reproducible bags).
        data = bytes(self._store.serialize_cdr(self._store.deserialize_cdr(data, msgtype), msgtype))
        self._writer.write(self._conns[topic], int(stamp_ns), data)
