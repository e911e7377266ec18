"""`wheelgrid map` on a bag with one bad message: that frame is skipped and counted, the run
goes on (it used to end with exit 2 after mapping, losing every frame before it, or with a
traceback), and the second process never prints a traceback when the mapper stops early."""

from __future__ import annotations

import json
import multiprocessing as mp
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wheelgrid_common.testing import edit_bag
from wheelgrid_mapping import cli_map

BUNDLED = Path(__file__).resolve().parents[3] / "bags" / "paper_room" / "scan"
POINTS = "/iphone/points"


def _copy_first(
    tmp_path: Path, name: str, frames: int, damage: dict[int, object], topic: str = POINTS
) -> Path:
    """The bundled bag's first ``frames`` clouds (and their odometry), the k-th message on
    ``topic`` replaced by ``damage[k]``: raw CDR bytes, or a function of the deserialised
    message."""
    if not (BUNDLED / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")

    def spoil(k: int, msg: Any) -> bytes | None:
        change = damage.get(k)
        if isinstance(change, bytes):
            return change
        if change is not None:
            change(msg)  # type: ignore[operator]
        return None

    return edit_bag(
        BUNDLED,
        tmp_path / name,
        until=lambda t, k: t == POINTS and k == frames,
        edits={topic: spoil},
    )


def test_a_message_that_does_not_deserialise_costs_its_frame_only(tmp_path: Path, capsys) -> None:
    bag = _copy_first(tmp_path, "garbage", 10, {5: b"\x00\x01\x00\x00garbage"})
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
    assert cli_map.main(argv) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    rep = json.loads((out / "report.json").read_text())
    assert rep["malformed_frames"] == {"undeserialisable": 1}
    assert rep["frames"]["read"] == 9  # the 4 clouds after the bad one were mapped too
    assert (out / "map.ply").stat().st_size > 0


def test_a_broken_confidence_field_is_a_malformed_frame_not_a_traceback(
    tmp_path: Path, capsys
) -> None:
    def bad_confidence(msg: object) -> None:
        from rosbags.typesys import Stores, get_typestore

        field = get_typestore(Stores.ROS2_JAZZY).types["sensor_msgs/msg/PointField"]
        msg.fields = [*msg.fields, field("confidence", 0, 42, 1)]  # type: ignore[attr-defined]

    bag = _copy_first(tmp_path, "conf", 3, dict.fromkeys(range(3), bad_confidence))
    assert cli_map.main([str(bag), "--out", str(tmp_path / "o"), "--no-loop-closure"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "no readable PointCloud2 frame (bad_datatype)" in err, err
    assert not (tmp_path / "o" / "map.ply").exists()


def test_a_damaged_odometry_message_costs_the_prior_near_it_only(tmp_path: Path, capsys) -> None:
    """It ended the run with exit 2 before the first frame; a NaN pose was already only
    dropped for its frame."""
    bag = _copy_first(tmp_path, "odom", 10, {3: b"\x00\x01\x00\x00bad"}, "/iphone/odometry")
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
    assert cli_map.main(argv) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert "1 message(s) on /iphone/odometry do not deserialise" in err, err
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"]["read"] == 10


def test_a_bag_whose_storage_holds_none_of_its_listed_messages(tmp_path: Path, capsys) -> None:
    """A recording cut off keeps a metadata.yaml that lists messages its database never got:
    the run said 'all 0 frames have no valid points (all NaN/out of range)'."""
    import sqlite3

    bag = _copy_first(tmp_path, "hollow", 4, {})
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM messages")
    assert cli_map.main([str(bag), "--out", str(tmp_path / "o"), "--no-loop-closure"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "all 0 frames" not in err, err
    assert "lists 4 message(s) on the topic but none could be read" in err, err
    assert "bag-recover" in err


def test_the_prior_hint_is_given_only_for_the_prior_topic(tmp_path: Path, capsys) -> None:
    """`--prior arkit` appended '(--prior arkit needs one nav_msgs/Odometry topic)' to every
    bag error, a bag that does not open included."""
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("{{{: [\n")
    assert cli_map.main([str(broken), "--out", str(tmp_path / "o"), "--prior", "arkit"]) == 2
    err = capsys.readouterr().err
    assert "cannot open bag" in err and "Odometry" not in err, err

    bag = _copy_first(tmp_path, "short", 1, {})
    argv = [str(bag), "--out", str(tmp_path / "o"), "--prior", "arkit", "--prior-topic", POINTS]
    assert cli_map.main(argv) == 2
    assert "needs one nav_msgs/Odometry topic" in capsys.readouterr().err


def test_the_second_process_ends_quietly_when_the_mapper_has_gone(capfd) -> None:
    """The mapper closing the pipe while a frame is in preparation (an input error, Ctrl-C)
    made the second process print two BrokenPipeError tracebacks. Run as the mapper runs it: a
    spawned process (whose stderr is this test's fd 2), never in this one, where ``_serve``
    would leave SIGINT ignored for the rest of the session."""
    from wheelgrid_mapping.prefetch import _serve
    from wheelgrid_mapping.preprocess import PreprocessConfig
    from wheelgrid_mapping.registration import RegistrationConfig

    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve, args=(child,), name="wheelgrid-prepare-test", daemon=True)
    proc.start()
    try:
        child.close()
        pts = np.random.default_rng(0).uniform(-2, 2, (500, 3)) + np.array([0.0, 0.0, 3.0])
        parent.send((pts, None, PreprocessConfig(), RegistrationConfig()))
        parent.close()  # the mapper has gone while the frame is in preparation
        proc.join(timeout=60)
        assert not proc.is_alive(), "the second process did not end when the pipe closed"
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=5)
    err = capfd.readouterr().err
    assert proc.exitcode == 0, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


def test_a_bad_message_after_the_last_frame_asked_for_is_not_counted(
    tmp_path: Path, capsys
) -> None:
    """`--max-frames 6` on a bag whose 7th cloud is damaged: the 7th was read (to find that the
    run was over) and counted as malformed, so report.json and the summary named a skipped
    frame the run never used, and with `--max-frames 1` a good first frame was refused as 'no
    readable PointCloud2 frame'."""
    bag = _copy_first(tmp_path, "tail", 7, {6: b"\x00\x01\x00\x00garbage"})
    out = tmp_path / "map"
    argv = [
        str(bag),
        "--out",
        str(out),
        "--prior",
        "arkit",
        "--max-frames",
        "6",
        "--no-loop-closure",
    ]
    assert cli_map.main(argv) == 0
    captured = capsys.readouterr()
    assert "unreadable skipped" not in captured.out, captured.out
    rep = json.loads((out / "report.json").read_text())
    assert rep["malformed_frames"] == {} and rep["frames"]["read"] == 6
    argv = [str(bag), "--out", str(tmp_path / "one"), "--max-frames", "1", "--no-loop-closure"]
    cli_map.main(argv)
    assert "no readable PointCloud2 frame" not in capsys.readouterr().err


def test_a_metadata_yaml_that_lists_too_few_messages_loses_no_frame(tmp_path: Path, capsys) -> None:
    """metadata.yaml's message count (hand-edited, a tool that rewrote it) is what the bag's
    storage is indexed by, not what it holds: the run stopped after as many frames as it
    listed and dropped the rest of the recording without a word."""
    import re

    bag = _copy_first(tmp_path, "lies", 6, {})
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    listed = re.sub(r"message_count: 6\n(\s+topic_metadata:\n\s+name: /iphone/points)",
                    r"message_count: 2\n\1", text)  # fmt: skip
    assert listed != text
    meta.write_text(listed)
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
    assert cli_map.main(argv) == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"]["read"] == 6


@pytest.mark.parametrize("count", ["many", "null", "-5", "2.5"])
def test_a_metadata_count_that_is_not_a_count_is_bad_input(tmp_path: Path, capsys, count) -> None:
    """A message_count that is not a whole number >= 0 ended in a TypeError traceback (or,
    with --max-frames, a ValueError from islice) and exit 1."""
    import re

    bag = _copy_first(tmp_path, "count", 4, {})
    meta = bag / "metadata.yaml"
    meta.write_text(re.sub(r"message_count: 4\b", f"message_count: {count}", meta.read_text()))
    for extra in ([], ["--max-frames", "2"]):
        argv = [str(bag), "--out", str(tmp_path / "map"), *extra]
        assert cli_map.main(argv) == 2
        err = capsys.readouterr().err
        assert "not a whole number >= 0" in err and "Traceback" not in err, err
        assert not (tmp_path / "map").exists()


def test_a_metadata_yaml_that_lists_no_messages_loses_no_frame(tmp_path: Path, capsys) -> None:
    """A metadata.yaml that lists 0 messages on the topic (the only count it reads) was
    refused as an empty topic while its storage held every frame; with --max-frames it read
    none. The storage is asked, and all it holds is read."""
    import re

    bag = _copy_first(tmp_path, "zero", 4, {})
    meta = bag / "metadata.yaml"
    text = re.sub(r"message_count: 4\n(\s+topic_metadata:\n\s+name: /iphone/points)",
                  r"message_count: 0\n\1", meta.read_text())  # fmt: skip
    meta.write_text(text)
    for extra, frames in (([], 4), (["--max-frames", "3"], 3)):
        out = tmp_path / f"map{frames}"
        argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure", *extra]
        assert cli_map.main(argv) == 0, capsys.readouterr().err
        assert "lists no messages" in capsys.readouterr().err
        assert json.loads((out / "report.json").read_text())["frames"]["read"] == frames


def test_a_storage_file_listed_twice_is_bad_input(tmp_path: Path, capsys) -> None:
    """A metadata.yaml listing its .db3 twice had every frame read and mapped twice, each
    view agreeing with itself (the map 46 % larger, the report's counts doubled), exit 0."""
    import yaml

    bag = _copy_first(tmp_path, "twice", 4, {})
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    (name,) = info["relative_file_paths"]
    # the same name twice, and the same file under another spelling (read twice as well)
    for twice in ([name, name], [name, f"./{name}"], [name, str((bag / name).resolve())]):
        info["relative_file_paths"] = twice
        (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
        assert cli_map.main([str(bag), "--out", str(tmp_path / "map")]) == 2, twice
        err = capsys.readouterr().err
        assert "more than once" in err and "Traceback" not in err, err


def test_frames_the_bag_lists_but_does_not_hold_are_reported_lost(tmp_path: Path, capsys) -> None:
    """A bag whose storage lost some of the messages its index lists (an MCAP chunk zeroed
    on a damaged card reads as no messages at all, rows gone from a sqlite3 file) mapped the
    rest and said only 'N frames read': the frames missing from the map went without a word."""
    import sqlite3

    bag = _copy_first(tmp_path, "holes", 8, {})
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        (topic_id,) = con.execute("SELECT id FROM topics WHERE name = ?", (POINTS,)).fetchone()
        rows = [r for (r,) in con.execute(
            "SELECT id FROM messages WHERE topic_id = ? ORDER BY timestamp", (topic_id,))]  # fmt: skip
        con.executemany("DELETE FROM messages WHERE id = ?", [(r,) for r in rows[5:]])
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
    assert cli_map.main(argv) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "lists 8 message(s) on the topic but only 5 could be read" in err, err
    rep = json.loads((out / "report.json").read_text())
    # report.json says it too (only stderr did: the run read as complete from the report)
    assert rep["frames"]["read"] == 5
    assert rep["storage"] == {"listed": 8, "read": 5, "damage": None}


def test_storage_damaged_mid_bag_keeps_the_frames_before_it(tmp_path: Path, capsys) -> None:
    """An MCAP bag whose second chunk is damaged (a record length that runs past the chunk):
    the reader fails only when it gets there, and the run ended with exit 2 and threw away
    every frame mapped from the first chunk. They make the map now, and the run says where
    the bag broke."""
    import struct

    if not (BUNDLED / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")
    bag = edit_bag(
        BUNDLED, tmp_path / "chunks", until=lambda t, k: t == POINTS and k == 30, storage="mcap"
    )
    (mcap,) = bag.glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    pos, chunks = 8, []
    while data[pos] != 0x02:  # the records up to the footer; 0x06 is a chunk
        length = struct.unpack_from("<Q", data, pos + 1)[0]
        if data[pos] == 0x06:
            chunks.append(pos)
        pos += 9 + length
    assert len(chunks) >= 2, "the bag fits one chunk: nothing to damage after the first"
    body = chunks[1] + 9 + 8 + 8 + 8 + 4  # start, end, uncompressed size, crc
    assert struct.unpack_from("<I", data, body)[0] == 0, "the chunk is compressed"
    first = body + 4 + 8  # compression "" and the records' length: the first record
    struct.pack_into("<Q", data, first + 1, 2**40)
    mcap.write_bytes(bytes(data))

    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
    assert cli_map.main(argv) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "bag is corrupt" in err and "the map is made from the" in err, err
    rep = json.loads((out / "report.json").read_text())
    read = rep["frames"]["read"]
    assert 0 < read < 30
    storage = rep["storage"]
    assert storage["listed"] == 30 and storage["read"] == read
    assert "bag is corrupt" in storage["damage"]


def test_frames_empty_or_unreadable_are_said_as_both(tmp_path: Path, capsys) -> None:
    """Every frame unusable, half of them all NaN and half malformed: the run said "all 6
    frames have no valid points", 3 of which were unreadable."""

    def nan(msg: Any) -> None:
        msg.data = np.frombuffer(
            np.full(len(msg.data) // 4, np.nan, np.float32).tobytes(), np.uint8
        ).copy()

    def cut(msg: Any) -> None:
        msg.data = msg.data[: len(msg.data) // 2]

    bag = _copy_first(tmp_path, "mixed", 6, {k: (nan if k % 2 else cut) for k in range(6)})
    argv = [str(bag), "--out", str(tmp_path / "map"), "--no-loop-closure"]
    assert cli_map.main(argv) == 2
    err = capsys.readouterr().err
    assert "no usable frame: 3 without valid points" in err and "3 unreadable (" in err, err


def test_clouds_and_their_odometry_on_one_topic_map_with_the_prior(tmp_path: Path) -> None:
    """A merged bag with the clouds and the odometry on one topic: `--prior arkit` picked the
    topic for both, and the clouds were read as Odometry (a traceback, a review)."""
    from rosbags.rosbag2 import Writer

    from wheelgrid_common.bagio import POINTCLOUD2, BagReader, typestore

    if not (BUNDLED / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")
    with BagReader(BUNDLED) as r:
        msgs = []
        for topic, kind, t_ns, raw in r.raw([POINTS, "/iphone/odometry"]):
            msgs.append((kind, t_ns, raw))
            if topic == POINTS and sum(k == POINTCLOUD2 for k, _, _ in msgs) == 10:
                break
    bag = tmp_path / "merged"
    with Writer(bag, version=9) as w:
        conns = {
            kind: w.add_connection(POINTS, kind, typestore=typestore())
            for kind in ("nav_msgs/msg/Odometry", POINTCLOUD2)
        }
        for kind, t_ns, raw in msgs:
            w.write(conns[kind], t_ns, raw)
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
    assert cli_map.main(argv) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"]["read"] == 10 and rep["frames"]["used"] >= 9
    assert rep["prior"]["frames"] >= 9
