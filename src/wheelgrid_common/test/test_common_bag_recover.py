"""``wheelgrid bag-recover``: a recording cut off mid-write (an MCAP file without its footer, a
folder without metadata.yaml) gives back every message written before the cut, byte for byte,
and nothing after it."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common import bag_recover
from wheelgrid_common.bagio import POINTCLOUD2, BagError, BagReader, BagWriter
from wheelgrid_common.pointcloud2 import to_pointcloud2

N = 60


def _recording(tmp_path: Path, storage: str = "mcap") -> tuple[Path, list[tuple[str, int, bytes]]]:
    """An MCAP bag of N clouds (~100 kB each, so it spans several of rosbags' 1 MB chunks) and
    N strings, and its messages as a reader returns them."""
    from std_msgs.msg import String

    rng = np.random.default_rng(3)
    bag = tmp_path / "rec"
    with BagWriter(bag, storage) as w:
        for i in range(N):
            w.write("/p", POINTCLOUD2, 1_000 + 100 * i, to_pointcloud2(rng.random((8000, 3)), "c"))
            w.write("/s", "std_msgs/msg/String", 1_050 + 100 * i, String(data=f"m{i}"))
    with BagReader(bag) as r:
        msgs = [(t, ns, raw) for t, _, ns, raw in r.raw(["/p", "/s"])]
    return bag, msgs


def _read(bag: Path) -> list[tuple[str, int, bytes]]:
    with BagReader(bag) as r:
        return [(t, ns, raw) for t, _, ns, raw in r.raw(["/p", "/s"])]


def test_a_cut_recording_gives_back_every_message_before_the_cut(tmp_path, capsys) -> None:
    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(0.6 * len(data))])  # the recorder died here
    # with a metadata.yaml (copied from elsewhere, or a split bag's) the hint comes from the file
    # itself not ending with the MCAP magic, not from the reader's error text
    with pytest.raises(BagError, match=r"cannot open bag.*bag-recover"):
        BagReader(bag).__enter__()
    (bag / "metadata.yaml").unlink()  # rosbag2 writes it only when it closes
    with pytest.raises(BagError, match="bag-recover"):  # the reader says what to do
        BagReader(bag).__enter__()

    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    line = capsys.readouterr().out
    got = _read(tmp_path / "back")
    # a prefix of the recording, byte for byte: every message complete before the cut, those
    # inside the (uncompressed) chunk the cut went through too (its whole chunk was dropped:
    # 65 of 120 here, now 72; a cut in a recording's first chunk gave back nothing)
    assert 0.55 * len(msgs) < len(got) <= 0.6 * len(msgs)
    assert sorted(got) == sorted(msgs[: len(got)])
    assert f"bag-recover: {len(got)} messages" in line and "the cut went through" in line
    assert mcap.read_bytes() == data[: int(0.6 * len(data))]  # the original is only read

    # cut inside the first chunk, its first messages complete: they come back
    first = tmp_path / "first"
    first.mkdir()
    (first / mcap.name).write_bytes(data[:300_000])
    assert bag_recover.main([str(first), "--out", str(tmp_path / "b1")]) == 0
    early = _read(tmp_path / "b1")
    assert len(early) >= 1 and sorted(early) == sorted(msgs[: len(early)]), len(early)
    capsys.readouterr()

    # the same into sqlite3, and a complete bag loses nothing
    assert bag_recover.main([str(mcap), "--out", str(tmp_path / "b2"), "--storage", "sqlite3"]) == 0
    assert _read(tmp_path / "b2") == got
    full, msgs = _recording(tmp_path / "full")
    res = bag_recover.recover(full, tmp_path / "b3", progress=False)
    assert res.already_complete == 1 and res.bytes_lost == 0
    assert _read(tmp_path / "b3") == msgs


def test_what_cannot_be_recovered_is_refused_clearly(tmp_path, capsys) -> None:
    bag, _ = _recording(tmp_path)
    assert bag_recover.main([str(bag), "--out", str(bag)]) == 2  # never over a bag
    assert "already exists" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a bag at all" * 10)
    assert bag_recover.main([str(junk), "--out", str(tmp_path / "o")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    mcap = next(bag.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[:20])  # inside the header record
    assert bag_recover.main([str(cut), "--out", str(tmp_path / "o")]) == 2
    assert "nothing to recover" in capsys.readouterr().err
    head = 17 + int.from_bytes(mcap.read_bytes()[9:17], "little")
    cut.write_bytes(mcap.read_bytes()[:head])  # the header, then nothing
    assert bag_recover.main([str(cut), "--out", str(tmp_path / "o")]) == 2
    assert "no complete message" in capsys.readouterr().err
    (tmp_path / "none").mkdir()
    assert bag_recover.main([str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "no .mcap or .db3 file" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_sqlite3_recording_without_its_metadata_is_given_back_whole(tmp_path, capsys) -> None:
    """A killed sqlite3 recorder leaves every committed message and no metadata.yaml.

    Nothing then lists how many messages were recorded: what the recorder still held in its
    cache when it was killed never reached the file, and no count can show it. The line says
    that much, not "nothing was cut off" (which it said)."""
    bag, msgs = _recording(tmp_path, "sqlite3")
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="bag-recover"):
        BagReader(bag).__enter__()
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    line = capsys.readouterr().out
    assert "nothing was cut off" not in line
    assert "every message committed to rec.db3 copied" in line, line
    assert "not written out when it stopped cannot be counted" in line, line
    assert _read(tmp_path / "back") == msgs
    # with its metadata.yaml the count is checked, and a whole bag loses nothing
    bag2, msgs2 = _recording(tmp_path / "whole", "sqlite3")
    assert bag_recover.main([str(bag2), "--out", str(tmp_path / "back2")]) == 0
    assert "nothing was cut off" in capsys.readouterr().out
    assert _read(tmp_path / "back2") == msgs2


def test_messages_committed_only_to_a_sqlite3_write_ahead_log_are_given_back(
    tmp_path, capsys
) -> None:
    """``ros2 bag record --storage-preset-profile resilient`` writes in WAL mode: killed, its
    last committed messages lie in NAME.db3-wal, which rosbags' reader does not look at, and
    half of them were left out with "every message committed copied" (a review). The file
    itself is not changed by the recovery."""
    import os
    import sqlite3
    import subprocess
    import sys

    bag, msgs = _recording(tmp_path, "sqlite3")
    (bag / "metadata.yaml").unlink()
    db = bag / "rec.db3"
    rows = (
        sqlite3.connect(db).execute("select id, topic_id, timestamp, data from messages").fetchall()
    )
    half = len(rows) // 2
    sqlite3.connect(db).execute(
        "delete from messages where id > ?", (rows[half - 1][0],)
    ).connection.commit()
    # a recorder that commits the rest in WAL mode and is killed before any checkpoint
    script = (
        "import sqlite3, sys, os, pickle\n"
        "rows = pickle.loads(sys.stdin.buffer.read())\n"
        f"d = sqlite3.connect({str(db)!r}, isolation_level=None)\n"
        "d.execute('PRAGMA journal_mode=WAL'); d.execute('PRAGMA wal_autocheckpoint=0')\n"
        "d.execute('begin')\n"
        "[d.execute('insert into messages values (?,?,?,?)', r) for r in rows]\n"
        "d.execute('commit'); sys.stdout.flush(); os._exit(0)\n"
    )
    import pickle

    subprocess.run([sys.executable, "-c", script], input=pickle.dumps(rows[half:]), check=True)
    wal = bag / "rec.db3-wal"
    assert wal.stat().st_size > 0
    before = {f.name: f.read_bytes() for f in bag.iterdir()}
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    assert _read(tmp_path / "back") == msgs
    assert {f.name: f.read_bytes() for f in bag.iterdir()} == before  # untouched
    import tempfile

    def copies() -> set[str]:
        return {n for n in os.listdir(tempfile.gettempdir()) if "wheelgrid_bag_recover_" in n}

    left = copies()
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "again")]) == 0
    assert copies() <= left  # the checkpointed copy goes with its reader
    # a copy that cannot be made (the temp folder full) is said as such, and leaves nothing
    real_copy = bag_recover._copy_prefix

    def full(src, dst, n):
        real_copy(src, dst, min(n, 10))
        raise OSError(28, "No space left on device")

    bag_recover._copy_prefix = full
    try:
        assert bag_recover.main([str(bag), "--out", str(tmp_path / "full")]) == 2
    finally:
        bag_recover._copy_prefix = real_copy
    err = capsys.readouterr().err
    assert "cannot make the copy it is read from" in err and "No space left" in err, err
    assert "damaged" not in err and copies() <= left


def test_messages_the_recording_lists_but_that_are_not_recovered_are_counted_lost(
    tmp_path, capsys
) -> None:
    """A file whose footer is intact but whose middle is damaged (zeroed by a bad sector, a
    sync cut short) is not "nothing was cut off": its own summary, or the folder's
    metadata.yaml, lists more messages than were copied, and the line says how many."""
    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    n = len(data)
    data[n // 3 : 2 * n // 3] = bytes(2 * n // 3 - n // 3)
    mcap.write_bytes(bytes(data))
    for src, out in ((mcap, "a"), (bag, "b")):  # the MCAP summary; metadata.yaml as well
        assert bag_recover.main([str(src), "--out", str(tmp_path / out)]) == 0
        line = capsys.readouterr().out
        got = len(_read(tmp_path / out))
        assert got < len(msgs)
        assert "nothing was cut off" not in line
        assert f"{len(msgs) - got} of the {len(msgs)} messages" in line, line

    # a sqlite3 bag whose metadata.yaml lists rows it no longer has
    import sqlite3

    bag, msgs = _recording(tmp_path / "sq", "sqlite3")
    db = next(bag.glob("*.db3"))
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM messages WHERE id % 3 = 0")
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "c")]) == 0
    line = capsys.readouterr().out
    got = len(_read(tmp_path / "c"))
    assert got < len(msgs) and "nothing was cut off" not in line
    assert f"{len(msgs) - got} of the {len(msgs)} messages" in line, line


def test_zeros_after_the_cut_are_space_never_written_not_data(tmp_path, capsys) -> None:
    """A power cut after the file system grew the file, before the data landed, leaves zeros
    after the cut. Walked as data they completed the chunk the cut went through (its length
    now inside the file), a message was copied with its cut-off end as zeros, and the zeros
    were reported as "kB written are lost" (a review). The zeros are left out of the walk:
    the same messages as the plain cut, byte for byte, and the zeros said as never written."""
    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    (bag / "metadata.yaml").unlink()
    plain = tmp_path / "plain"
    shutil.copytree(bag, plain)
    (plain / mcap.name).write_bytes(data[: int(0.6 * len(data))])
    ok = bag_recover.recover(plain, tmp_path / "back_plain", progress=False)
    mcap.write_bytes(data[: int(0.6 * len(data))] + bytes(500_000))
    capsys.readouterr()
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    line = capsys.readouterr().out
    got = _read(tmp_path / "back")
    assert got == _read(tmp_path / "back_plain") and set(got) <= set(msgs)
    assert f"its {ok.bytes_lost / 1e3:.0f} kB written are lost" in line, line
    assert "then 500 kB of zeros, space the file was given but never written" in line, line


def test_the_chunks_after_a_damaged_one_are_given_back(tmp_path, capsys) -> None:
    """A complete MCAP file whose middle was zeroed still has its summary, which says where
    every chunk starts: the walk from the header stops at the damage, but the chunks after it
    are intact and are copied too (they were lost with the damaged one)."""
    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    n = len(data)
    data[n // 3 : n // 2] = bytes(n // 2 - n // 3)
    mcap.write_bytes(bytes(data))
    assert bag_recover.main([str(mcap), "--out", str(tmp_path / "back")]) == 0
    line = capsys.readouterr().out
    got = _read(tmp_path / "back")
    assert set(msgs[-10:]) <= set(got)  # the last chunk, byte for byte
    assert set(msgs[:10]) <= set(got)  # and the first
    assert f"{len(msgs) - len(got)} of the {len(msgs)} messages" in line, line
    assert "the cut went through" not in line  # nothing was cut off: it was damaged


def test_a_reader_that_fails_on_damage_inside_an_mcap_names_the_recovery(tmp_path, capsys) -> None:
    """A damaged summary (the file still ends with the MCAP magic): the reader refused the bag
    with no word of ``bag-recover``, which copies every message of it."""
    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    data[-300:-100] = bytes(200)
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError) as err:
        BagReader(bag).__enter__()
    text = str(err.value)
    assert "cannot open bag" in text and "\n" not in text, text
    assert f"`wheelgrid bag-recover {bag} --out NEW_BAG` copies the messages of its intact" in text
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    assert sorted(_read(tmp_path / "back")) == sorted(msgs)


def test_an_interrupted_recovery_leaves_no_bag_that_looks_complete(
    tmp_path, capsys, monkeypatch
) -> None:
    """Ctrl-C during the copy: the writer was closed as it was, and --out opened as a complete
    bag of fewer messages, with nothing to say so (and a rerun was refused: --out exists). The
    part written is removed. (The interrupt is raised from the progress bar, where a Ctrl-C
    during a long copy lands as often as anywhere.)"""
    bag, _ = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: int(0.6 * mcap.stat().st_size)])
    (bag / "metadata.yaml").unlink()
    calls = {"n": 0}

    def update(self, n: int = 1, **kw: object) -> None:
        calls["n"] += 1
        if calls["n"] == 10:
            raise KeyboardInterrupt

    monkeypatch.setattr(bag_recover.Progress, "update", update)
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 130
    assert "interrupted; the part of" in capsys.readouterr().err
    assert calls["n"] == 10 and not (tmp_path / "back").exists()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_message_type_this_distribution_does_not_know_is_copied_with_its_definition(
    tmp_path, capsys, storage
) -> None:
    """A vendor's message type beside the clouds: the copy passed rosbags' writer an empty type
    hash, which it refuses, and every such recording ended "damaged before the cut" with two
    messages copied. Its definition and hash now travel from the file, and a reader that checks
    the one against the other opens the copy."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(
        get_types_from_msg("std_msgs/Header header\nfloat32 level\n", "acme_msgs/msg/Battery")
    )
    battery = store.types["acme_msgs/msg/Battery"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    bag = tmp_path / "rec"
    w = Writer(bag, version=9, storage_plugin=plugin)
    w.open()
    conn = w.add_connection("/acme/battery", "acme_msgs/msg/Battery", typestore=store)
    for i in range(5):
        msg = battery(
            header=store.types["std_msgs/msg/Header"](
                stamp=store.types["builtin_interfaces/msg/Time"](sec=i, nanosec=0), frame_id="base"
            ),
            level=0.5 + i,
        )
        w.write(conn, 1_000 + i, store.serialize_cdr(msg, "acme_msgs/msg/Battery"))
    w.close()
    if storage == "sqlite3":
        (bag / "metadata.yaml").unlink()  # the definitions are in the database
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0, capsys.readouterr()
    with AnyReader([tmp_path / "back"]) as r:
        (c,) = r.connections
        levels = [r.deserialize(raw, c.msgtype).level for c, _, raw in r.messages()]
    assert c.msgtype == "acme_msgs/msg/Battery" and levels == [0.5, 1.5, 2.5, 3.5, 4.5]
    assert c.digest == store.hash_rihs01("acme_msgs/msg/Battery")


def _compress_chunks(data: bytes, codec: str) -> bytes:
    """``data`` (an MCAP file) with every chunk's records compressed by ``codec``, as libmcap
    writes them by default (zstd); the file is cut afterwards, so its summary, whose offsets
    this moves, is never read."""
    import struct

    if codec == "zstd":
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        pack = zstd.compress
    else:
        import lz4.frame

        pack = lz4.frame.compress
    out, pos = bytearray(data[:8]), 8
    while pos + 9 <= len(data):
        op, length = data[pos], struct.unpack("<Q", data[pos + 1 : pos + 9])[0]
        body = data[pos + 9 : pos + 9 + length]
        if op == 0x06:  # chunk: start, end, uncompressed size, crc, compression, records
            (name_len,) = struct.unpack("<I", body[28:32])
            assert name_len == 0
            records = body[32 + 8 :]
            packed = pack(records)
            name = codec.encode()
            body = (
                body[:28]
                + struct.pack("<I", len(name))
                + name
                + struct.pack("<Q", len(packed))
                + packed
            )
        out += bytes([op]) + struct.pack("<Q", len(body)) + body
        pos += 9 + length
    return bytes(out + data[pos:])


@pytest.mark.parametrize("codec", ["zstd", "lz4"])
def test_the_messages_inside_a_cut_compressed_chunk_come_back(tmp_path, codec, capsys) -> None:
    """A cut in a compressed MCAP chunk (libmcap's default is zstd) lost the whole chunk, and
    a cut in the first chunk every message. A streaming decompressor reads the compressed
    chunk's beginning, and its complete messages come back."""
    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = _compress_chunks(mcap.read_bytes(), codec)
    assert data.count(codec.encode()) >= 5  # every chunk (random floats: they hardly shrink)
    for share in (0.15, 0.6):
        cut = tmp_path / f"cut{share}"
        cut.mkdir()
        (cut / mcap.name).write_bytes(data[: int(share * len(data))])
        res = bag_recover.recover(cut, tmp_path / f"back{share}", progress=False)
        got = _read(tmp_path / f"back{share}")
        assert sorted(got) == sorted(msgs[: len(got)]), share  # a prefix, byte for byte
        # the messages before the cut, less at most a cloud and a string being written
        assert len(got) >= share * len(msgs) * 0.93 - 2, (share, len(got))
        assert 0 < res.bytes_lost < 0.05 * len(data), res.bytes_lost
    # a records length that lies (larger than the file; 2^64 - 1 overflowed the read itself)
    # is read as far as the file goes: the same messages, not a failed recovery
    import struct

    cut = tmp_path / "cut0.6" / mcap.name
    start = bag_recover.mcap_extent(cut).data_end
    (name_len,) = struct.unpack("<I", cut.read_bytes()[start + 37 : start + 41])
    at = start + 41 + name_len
    lying = tmp_path / "lying"
    lying.mkdir()
    raw = cut.read_bytes()
    (lying / mcap.name).write_bytes(raw[:at] + struct.pack("<Q", 2**64 - 1) + raw[at + 8 :])
    bag_recover.recover(lying, tmp_path / "back_lying", progress=False)
    assert _read(tmp_path / "back_lying") == _read(tmp_path / "back0.6")
    # a complete file has no chunk the cut went through
    assert bag_recover.cut_chunk_records(mcap, bag_recover.mcap_extent(mcap)) == (b"", 0)


def _with_checksums(data: bytes) -> bytes:
    """``data`` (an MCAP file of uncompressed chunks, as rosbags writes them) with each chunk's
    CRC-32 of its records set, as libmcap (``ros2 bag record``) writes it."""
    import struct
    from binascii import crc32

    out, pos = bytearray(data), 8
    while pos + 9 <= len(out):
        op, length = out[pos], struct.unpack("<Q", out[pos + 1 : pos + 9])[0]
        if op in (0x0F, 0x02):
            break
        if op == 0x06:
            records = bytes(out[pos + 9 + 40 : pos + 9 + length])
            out[pos + 9 + 24 : pos + 9 + 28] = struct.pack("<I", crc32(records))
        pos += 9 + length
    return bytes(out)


def test_a_damaged_chunk_before_the_cut_costs_its_messages_only(tmp_path, capsys) -> None:
    """A cut file whose second chunk was damaged too (its checksum fails): rosbags' scan of
    the complete records failed on it, and the recovery ended "damaged before the cut" with
    nothing copied (a review). Each chunk is read on its own now: the damaged one is skipped
    and said, the chunks before and after it and the messages of the cut chunk come back."""
    import struct

    bag, msgs = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(_compress_chunks(_with_checksums(mcap.read_bytes()), "zstd"))
    chunks, pos = [], 8
    while data[pos] not in (0x0F, 0x02):
        length = struct.unpack("<Q", data[pos + 1 : pos + 9])[0]
        if data[pos] == 0x06:
            chunks.append((pos, pos + 9 + length))
        pos += 9 + length
    assert len(chunks) >= 5
    data = data[: (chunks[-2][0] + chunks[-2][1]) // 2]  # cut inside the last chunk but one
    whole = tmp_path / "whole"
    whole.mkdir()
    (whole / mcap.name).write_bytes(bytes(data))
    assert bag_recover.main([str(whole), "--out", str(tmp_path / "back_whole")]) == 0
    before = _read(tmp_path / "back_whole")  # what the cut alone leaves
    a, b = chunks[1]
    data[a + 200 : a + 2200] = bytes(2000)
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / mcap.name).write_bytes(bytes(data))
    capsys.readouterr()
    assert bag_recover.main([str(damaged), "--out", str(tmp_path / "back")]) == 0
    line = capsys.readouterr().out
    got = _read(tmp_path / "back")
    lost = [m for m in before if m not in got]
    assert got == [m for m in before if m not in lost]  # the rest byte for byte, in order
    assert 10 < len(lost) < 30 and set(msgs[:10]) <= set(got)  # one chunk's, not the first's
    assert f"1 damaged chunk(s) before the cut ({(b - a) / 1e3:.0f} kB) skipped" in line, line
    assert "the cut went through a record" in line  # and the cut chunk's messages came back
    assert set(before[-3:]) <= set(got)


def test_a_message_on_a_channel_nothing_defines_ends_the_salvage_counted_lost(tmp_path) -> None:
    """A reader skips a message whose channel nothing defines without a word: inside the chunk
    a cut went through (damage, never a recorder's doing) it reported no bytes lost. The
    salvage ends there, and it and what follows count as lost."""
    import struct

    bag, _ = _recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()[: int(0.6 * len(mcap.read_bytes()))]
    clean = tmp_path / "clean"
    clean.mkdir()
    (clean / mcap.name).write_bytes(data)
    ok = bag_recover.recover(clean, tmp_path / "back_clean", progress=False)

    start = bag_recover.mcap_extent(clean / mcap.name).data_end
    (name_len,) = struct.unpack("<I", data[start + 37 : start + 41])
    assert name_len == 0  # rosbags writes its chunks uncompressed
    pos = start + 41 + 8  # the chunk's records
    messages = []  # where each complete message record inside the cut chunk begins
    while pos + 9 <= len(data):
        op, length = data[pos], struct.unpack("<Q", data[pos + 1 : pos + 9])[0]
        if pos + 9 + length > len(data):
            break
        if op == 0x05:
            messages.append(pos)
        pos += 9 + length
    assert len(messages) > 3
    pos = messages[2]  # the third is put on channel 999
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / mcap.name).write_bytes(data[: pos + 9] + struct.pack("<H", 999) + data[pos + 11 :])
    res = bag_recover.recover(damaged, tmp_path / "back", progress=False)
    got, before = _read(tmp_path / "back"), _read(tmp_path / "back_clean")
    # the two messages before it come back, nothing from it on; its bytes on count lost
    assert len(got) == res.messages == ok.messages - len(messages) + 2
    assert got == before[: len(got)]
    assert res.bytes_lost >= len(data) - pos > ok.bytes_lost


def test_the_rows_after_a_damaged_page_of_a_sqlite3_recording_are_given_back(
    tmp_path, capsys, stray_capture: Path
) -> None:
    """200 kB zeroed in the middle of a sqlite3 recording (twenty frames of the real capture,
    as import-stray writes them): the copy, one query, ended at the first damaged row (40 of
    100 messages kept where 97 read one by one) with exit 2, and never said how many of the
    listed messages were missing (a review). Rows are read one by one now: every row that
    reads and decodes is given back, the damaged ones are counted."""
    from wheelgrid_mapping.cli_stray import import_main

    bag = tmp_path / "rec"
    assert (
        import_main([str(stray_capture), "--out", str(bag), "--frames", "20", "--start", "300"])
        == 0
    )
    db = next(bag.glob("*.db3"))
    with db.open("r+b") as f:  # inside image rows' overflow pages, not the tables' own
        f.seek(6_000_000)
        f.write(bytes(200_000))
    capsys.readouterr()
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    out = capsys.readouterr().out
    with BagReader(tmp_path / "back") as r:
        kept = sum(t.count for t in r.topics())
    assert kept == 97, out
    assert "3 of the 100 messages the recording lists" in out, out
    assert "3 damaged row(s) skipped, the rows after them copied" in out, out


@pytest.mark.parametrize("where", ["middle", "end"])
def test_a_damaged_page_of_the_messages_table_costs_its_rows_only(tmp_path, capsys, where) -> None:
    """A leaf page of the messages table zeroed (not an image's overflow page): rosbags counts
    the messages per topic in one query over the whole table, which failed on it, and 2000
    messages gave back none, "damaged before the cut" (a review). The topics are read on their
    own and the rows one by one now: only the page's rows are lost, and counted. The table's
    last page hides its largest id too; the ids are probed past the last one read."""
    from std_msgs.msg import String

    bag = tmp_path / "rec"
    n = 2000
    with BagWriter(bag, "sqlite3") as w:
        for i in range(n):
            w.write("/s", "std_msgs/msg/String", 1_000 + i, String(data=f"row-{i:05d}-" + "x" * 40))
    with BagReader(bag) as r:
        msgs = [(t, ns, raw) for t, _, ns, raw in r.raw(["/s"])]
    db = next(bag.glob("*.db3"))
    data = bytearray(db.read_bytes())
    at = data.find(f"row-{1000 if where == 'middle' else n - 1:05d}-".encode())
    page = at // 4096 * 4096
    assert data[page] == 0x0D  # a leaf page of a table
    on_page = {i for i in range(n) if f"row-{i:05d}-".encode() in data[page : page + 4096]}
    assert 10 < len(on_page) < 100
    data[page : page + 4096] = bytes(4096)
    db.write_bytes(bytes(data))
    capsys.readouterr()
    assert bag_recover.main([str(bag), "--out", str(tmp_path / "back")]) == 0
    out = capsys.readouterr().out
    with BagReader(tmp_path / "back") as r:
        got = [(t, ns, raw) for t, _, ns, raw in r.raw(["/s"])]
    assert got == [m for i, m in enumerate(msgs) if i not in on_page]  # byte for byte, in order
    assert f"{len(on_page)} of the {n} messages the recording lists" in out, out
    if where == "middle":  # rows before later ones that read are rows: counted as damaged
        assert f"{len(on_page)} damaged row(s) skipped, the rows after them copied" in out, out


def test_a_sqlite3_file_without_its_topics_table_is_one_line_naming_it(tmp_path, capsys) -> None:
    """Where the topics themselves cannot be read no message can be placed on a topic: one
    line says so (it said "damaged before the cut", as if the file had been cut), exit 2, and
    no bag is left half written."""
    import sqlite3

    db = tmp_path / "rec" / "rec_0.db3"
    db.parent.mkdir()
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER, "
                "timestamp INTEGER, data BLOB)")  # fmt: skip
    con.execute("INSERT INTO messages VALUES (1, 1, 1000, x'00010000')")
    con.commit()
    con.close()
    assert bag_recover.main([str(db.parent), "--out", str(tmp_path / "back")]) == 2
    err = capsys.readouterr().err
    assert f"{db}: its tables of topics cannot be read, so none of its messages can" in err, err
    assert "\n" not in err.strip() and "before the cut" not in err
    assert not (tmp_path / "back").exists()
