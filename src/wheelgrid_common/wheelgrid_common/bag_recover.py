"""``wheelgrid bag-recover``: the messages of a rosbag2 recording that was cut off.

A recorder killed mid-scan (a phone's battery, a chair's power switch, ``kill -9``) leaves an
MCAP file without its summary and footer, and a rosbag2 folder without ``metadata.yaml``: no
reader opens it, though every record written before the cut is intact (a sqlite3 recording
keeps every committed message; only its ``metadata.yaml`` is missing). This copies those
messages into a new, complete rosbag2 bag and says how much was lost; the original is only
read. Records are walked from the file's header by their length fields: the first record that
runs past the end of the file (or an opcode MCAP does not have) is where the cut was.

What was copied is then checked against what the recording itself lists (an MCAP file's
summary statistics, the folder's ``metadata.yaml``): a file whose footer is intact but whose
middle was damaged (zeroed by a bad sector, a copy cut short) has nothing cut off, yet the
messages of its damaged chunks are gone. Such a file is read chunk by chunk where its summary
puts them, so the chunks after the damage are copied too.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import shutil
import struct
import sys
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from .bagio import MCAP_MAGIC, BagError, typestore
from .fileio import out_folder
from .progress import Progress

_HEADER, _FOOTER, _STATISTICS, _DATA_END = 0x01, 0x02, 0x0B, 0x0F
_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x03, 0x04, 0x05, 0x06


@dataclass
class Extent:
    """Where an MCAP file's complete data records are."""

    data_start: int  # first byte after the header record
    data_end: int  # first byte after the last complete data record
    size: int  # the file's size, less the zeros that end it (``unwritten``)
    complete: bool  # a data-end record or footer was reached: nothing was cut off
    unwritten: int = 0  # zero bytes ending the file: space given it, never written


@dataclass
class Recovery:
    """What ``recover`` copied (one line of it is printed)."""

    files: list[str] = field(default_factory=list)
    messages: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    bytes_lost: int = 0  # the incomplete tail after the last complete record
    # zeros that end a cut file: space a file system gave it that was never written (a
    # power cut after the size grew, before the data landed), no recorded data lost
    bytes_unwritten: int = 0
    already_complete: int = 0  # files that had their footer (damage is counted in ``lost``)
    start_ns: int = 0
    end_ns: int = 0
    copied: dict[str, int] = field(default_factory=dict)  # messages copied, per file
    # what the recording's own summary or metadata.yaml lists, for the files that list any
    # (and listed files that are not there), and how many of those were not copied
    listed: int = 0
    lost: int = 0
    missing: list[str] = field(default_factory=list)  # files metadata.yaml lists, not there
    # sqlite3 files nothing lists a count for (no metadata.yaml): what their recorder had not
    # yet written out when it stopped cannot be counted, so "nothing was cut off" is not known
    unlisted: list[str] = field(default_factory=list)
    # sqlite3 rows that could not be read or do not decode (a damaged page): skipped, the rows
    # after them copied
    unreadable: int = 0
    # chunks of a cut MCAP file, before the cut, that do not decode (a checksum, a codec's
    # error): skipped, the records after them copied
    damaged_chunks: int = 0
    damaged_bytes: int = 0


def _record_heads(f: BinaryIO, pos: int, end: int) -> Iterator[tuple[int, int, int]]:
    """``(position, opcode, length)`` of each record from ``pos`` on, by their length fields,
    while a record's opcode and length lie before ``end``: the one walk of an MCAP file's
    records that its extent, its listed count and its parts take."""
    while pos + 9 <= end:
        f.seek(pos)
        rec = f.read(9)
        op, length = rec[0], struct.unpack("<Q", rec[1:])[0]
        yield pos, op, length
        pos += 9 + length


def mcap_extent(path: Path) -> Extent:
    """The complete records of ``path`` (an MCAP file, footer or not); BagError if it is not
    MCAP at all."""
    # A file ends with the MCAP magic or where the cut was; zeros after that were never
    # written. Walked as data, they completed the record the cut went through (its declared
    # length now inside the file) and a message was copied with its cut-off end as zeros.
    unwritten = trailing_zeros(path)
    with path.open("rb") as f:
        size = f.seek(0, 2) - unwritten
        f.seek(0)
        if f.read(8) != MCAP_MAGIC:
            raise BagError(f"{path}: not an MCAP file (its first bytes are not the MCAP magic)")
        head = f.read(9)
        if len(head) < 9 or head[0] != _HEADER:
            raise BagError(f"{path}: MCAP file without a header record: nothing to recover")
        pos = 17 + struct.unpack("<Q", head[1:])[0]
        if pos > size:
            raise BagError(f"{path}: cut off inside its header record: nothing to recover")
        start = end = pos
        for pos, op, length in _record_heads(f, start, size):
            if op in (_DATA_END, _FOOTER):
                return Extent(start, end, size, True, unwritten)
            nxt = pos + 9 + length
            if not 0x01 <= op <= 0x0F or nxt > size:
                break  # a record the cut went through (or garbage after it)
            end = nxt
        return Extent(start, end, size, False, unwritten)


def mcap_listed(path: Path) -> int | None:
    """The message count an MCAP file's own summary (its Statistics record) lists, or None
    where it has no footer, no summary or no statistics (a cut file): the count a recorder
    wrote when it closed the file, whatever happened to the records since."""
    with path.open("rb") as f:
        size = f.seek(0, 2)
        if size < 8 + 9 + 37:
            return None
        f.seek(size - 37)
        foot = f.read(37)
        if foot[-8:] != MCAP_MAGIC or foot[0] != _FOOTER:
            return None
        pos = struct.unpack("<Q", foot[9:17])[0]
        if not 8 <= pos <= size - 37:
            return None
        for _, op, length in _record_heads(f, pos, size - 37):
            if op == _STATISTICS and length >= 8:
                return int(struct.unpack("<Q", f.read(8))[0])
            if op == _FOOTER:
                break
    return None


def metadata_listed(folder: Path) -> dict[str, int] | None:
    """Messages per storage file name that ``folder``'s metadata.yaml lists, or None where
    there is none (a cut recording) or it lists no per-file counts."""
    import yaml

    try:
        info = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return {Path(e["path"]).name: int(e["message_count"]) for e in info["files"]}
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None


def _count_lost(src: Path, files: list[Path], res: Recovery) -> None:
    """Compare what was copied from each file with what the recording lists for it: the file's
    summary or metadata.yaml, whichever lists more (a loss either one saw is a loss); files
    metadata.yaml lists that are not in the folder lost all of theirs."""
    meta = metadata_listed(src if src.is_dir() else src.parent) or {}
    for path in files:
        own = mcap_listed(path) if path.suffix == ".mcap" else None
        counts = [n for n in (meta.get(path.name), own) if n is not None]
        if counts:
            res.listed += max(counts)
            res.lost += max(max(counts) - res.copied.get(str(path), 0), 0)
        elif path.suffix == ".db3":
            res.unlisted.append(path.name)
    if src.is_dir():
        for name, n in sorted(meta.items()):
            if not (src / name).exists():
                res.missing.append(name)
                res.listed += n
                res.lost += n


def _cut_reader(path: Path, extent: Extent) -> Any:
    """rosbags' MCAP reader over the complete records only (its own scan, no summary), not yet
    opened."""
    from rosbags.rosbag2.storage_mcap import McapReader

    class _CutReader(McapReader):  # type: ignore[misc]
        # the [start, end) of the parts read one by one, where a chunk inside the complete
        # records does not decode (None: read whole), and of those that do not decode
        segments: tuple[tuple[int, int], ...] | None = None
        damaged: tuple[tuple[int, int], ...] = ()

        def _open(self) -> None:
            self.data_start, self.data_end = extent.data_start, extent.data_end
            try:
                self.meta_scan()
                # (meta_scan counts the records it read; no counts is no messages)
                counts = dict(self.statistics.channel_message_counts if self.statistics else {})
            except Exception:  # a damaged chunk (a checksum, a codec's error) before the cut
                counts = self._scan_part_by_part()
            conns: list[Any] = self.connections  # type: ignore[has-type]  # (untyped base)
            self.connections = [c._replace(msgcount=counts.get(c.id, 0)) for c in conns]

        def _scan_part_by_part(self) -> dict[int, int]:
            """Each chunk, and each run of records between chunks, scanned on its own: one
            damaged chunk failed the whole scan, and every message before and after it was
            lost with it (a review)."""
            self.schemas.clear()
            self.channels.clear()
            self.connections.clear()  # type: ignore[has-type]
            read: list[tuple[int, int]] = []
            damaged: list[tuple[int, int]] = []
            counts: dict[int, int] = {}
            for part in _parts(path, extent):
                self.data_start, self.data_end = part
                try:
                    self.meta_scan()
                except Exception:  # this chunk's messages are lost, and counted
                    damaged.append(part)
                    continue
                read.append(part)
                stats = self.statistics.channel_message_counts if self.statistics else {}
                for cid, n in stats.items():
                    counts[cid] = counts.get(cid, 0) + n
            self.data_start, self.data_end = extent.data_start, extent.data_end
            self.segments, self.damaged = tuple(read), tuple(damaged)
            return counts

        def messages(self, connections: Any, start: Any = None, stop: Any = None) -> Any:
            # In file order: rosbags' unindexed path refuses messages out of stamp order, and a
            # recorder writes them in arrival order.
            if self.segments is None:
                return self.messages_scan(connections, start, stop)
            return self._messages_part_by_part(connections, start, stop)

        def _messages_part_by_part(self, connections: Any, start: Any, stop: Any) -> Any:
            for part in self.segments or []:
                self.data_start, self.data_end = part
                yield from self.messages_scan(connections, start, stop)

    return _CutReader(path)


def _parts(path: Path, extent: Extent) -> list[tuple[int, int]]:
    """The [start, end) of each chunk record of ``extent`` and of each run of other records
    between them, in file order."""
    parts: list[tuple[int, int]] = []
    with Path(path).open("rb") as f:
        run = extent.data_start
        for pos, op, length in _record_heads(f, extent.data_start, extent.data_end):
            if op == _CHUNK:
                if run < pos:
                    parts.append((run, pos))
                run = pos + 9 + length
                parts.append((pos, run))
        if run < extent.data_end:
            parts.append((run, extent.data_end))
    return parts


def _reader(path: Path, extent: Extent) -> Any:
    """rosbags' MCAP reader over the complete records only (its own scan, no summary)."""
    reader = _cut_reader(path, extent)
    reader.open()
    return reader


def _indexed_reader(path: Path) -> Any | None:
    """rosbags' MCAP reader over a file whose footer and summary survived, reading it chunk by
    chunk where the summary's chunk index puts them; None where there is no such index (a cut
    file: the walk from the header is all there is).

    A damaged middle (zeroed by a bad sector) stops the walk from the header, and rosbags' own
    scan leaves the file once one chunk's contents run past their end: every chunk after the
    damage was lost with it, though the summary says where each one starts and they are intact.
    A chunk that does not decode is skipped; its messages are counted lost against the
    summary's statistics (:func:`_count_lost`).
    """
    from rosbags.rosbag2.storage_mcap import McapReader

    class _ChunkReader(McapReader):  # type: ignore[misc]
        def messages(self, connections: Any, start: Any = None, stop: Any = None) -> Any:
            # In file order, as _CutReader: a recorder writes messages in arrival order.
            for chunk in sorted(self.chunks, key=lambda c: c.chunk_start_offset):
                self.data_start = chunk.chunk_start_offset
                self.data_end = chunk.chunk_start_offset + chunk.chunk_length
                try:
                    yield from self.messages_scan(connections, start, stop)
                except Exception:  # a damaged chunk: counted lost, not fatal
                    continue

    reader = _ChunkReader(path)
    try:
        reader.open()
    except Exception:  # no footer or summary: the walk from the header
        return None
    if not reader.chunks:
        reader.close()
        return None
    return reader


def trailing_zeros(path: Path) -> int:
    """How many zero bytes end ``path``: a file system that grew a file before a power cut
    leaves them where the data never landed. Counted as lost data, a tail of 500 kB of zeros
    read "its 500 kB written are lost" (a review). A cut that fell just after a record's own
    zero bytes loses that record with them: never a message copied with zeros for its end."""
    with path.open("rb") as f:
        end = f.seek(0, 2)
        pos = end
        while pos > 0:
            n = min(pos, 1 << 20)
            f.seek(pos - n)
            block = f.read(n)
            kept = len(block.rstrip(b"\0"))
            if kept:
                return end - (pos - n + kept)
            pos -= n
        return end


def bag_files(src: Path) -> list[Path]:
    """The storage files of a rosbag2 folder (in name order, as rosbag2 splits them: MCAP, or
    sqlite3 where there is no MCAP) or one such file."""
    if src.is_file():
        if src.suffix not in (".mcap", ".db3"):
            raise BagError(f"{src}: not a rosbag2 storage file (.mcap or .db3)")
        return [src]
    if not src.is_dir():
        raise BagError(f"{src}: no such bag folder or storage file")
    files = sorted(src.glob("*.mcap")) or sorted(src.glob("*.db3"))
    if not files:
        raise BagError(f"{src}: no .mcap or .db3 file in it: nothing to recover")
    return files


def _sqlite_reader(path: Path) -> Any:
    """A sqlite3 file describes its own topics; a killed recorder leaves it consistent (every
    message committed before the kill) and only ``metadata.yaml`` unwritten.

    Not quite where it wrote in WAL mode (``ros2 bag record --storage-preset-profile
    resilient``, the one chosen to survive a crash): messages committed since the last
    checkpoint lie in ``NAME.db3-wal``, which rosbags' reader (immutable) does not look at,
    and half a recording was left out with "every message committed copied" (a review). A
    copy of the file and its WAL is checkpointed and read instead; the recording itself is
    not touched."""
    import sqlite3

    wal = path.with_name(path.name + "-wal")
    if not (wal.is_file() and wal.stat().st_size > 0):
        reader = _tolerant_sqlite_reader(path)
        reader.open()
        return reader

    def checkpointed(tmp: Path) -> Path:
        copy = tmp / path.name
        for f in (path, wal, path.with_name(path.name + "-shm")):
            if f.is_file():
                _copy_prefix(f, tmp / f.name, f.stat().st_size)
        con = sqlite3.connect(copy)
        try:
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            con.close()
        return copy

    return _on_a_copy(path, checkpointed, _tolerant_sqlite_reader)


#: Ids probed past the last row read where a damaged page hides ``max(id)``: a recorder's ids
#: run without gaps, so this many unread in a row is the end of the table. An id past the end
#: is looked up on the table's last page: where that page is damaged it fails as a damaged row
#: does, and the rows of that page are lost uncounted, as a cut sqlite3 file's are.
_ID_GAP = 10_000


def _tolerant_sqlite_reader(path: Path) -> Any:
    """rosbags' sqlite3 reader, not yet opened, that opens a file with a damaged page of its
    messages table too. rosbags counts each topic's messages in one query over the whole
    table, which fails on the first unreadable page: a leaf page zeroed in a recording of 2000
    messages gave back none of them, said as "damaged before the cut" (a review). Where that
    fails, the topics are read on their own and the messages counted row by row, the damaged
    rows left out (:func:`_sqlite_rows` skips and counts them as it copies)."""
    from rosbags.interfaces import (
        Connection,
        ConnectionExtRosbag2,
        MessageDefinition,
        MessageDefinitionFormat,
    )
    from rosbags.rosbag2.metadata import parse_qos
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

    class _TolerantReader(Sqlite3Reader):  # type: ignore[misc]
        last_id: int | None = None  # the messages' largest id, found where max(id) fails

        def _open(self) -> None:
            try:
                super()._open()
            except Exception:  # a damaged page: rosbags' whole-table queries fail on it
                self._open_row_by_row()

        def _open_row_by_row(self) -> None:
            db: Any = self.dbconn
            cols = {str(c[1]) for c in db.execute("PRAGMA table_info(topics)")}
            defs: dict[str, MessageDefinition] = {}
            fmts = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
            with contextlib.suppress(Exception):  # definitions lost: the store's are used
                for name, enc, text in db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition "
                    "FROM message_definitions ORDER BY id"
                ):
                    if enc in fmts:
                        defs[str(name)] = MessageDefinition(fmts[enc], str(text))
            qos_col = "offered_qos_profiles" if "offered_qos_profiles" in cols else "''"
            hash_col = "type_description_hash" if "type_description_hash" in cols else "''"
            topics = list(
                db.execute(
                    f"SELECT id, name, type, serialization_format, {qos_col}, {hash_col} "
                    "FROM topics ORDER BY id"
                )
            )
            counts: dict[int, int] = dict.fromkeys((int(t[0]) for t in topics), 0)
            for row_id in self.ids():
                with contextlib.suppress(Exception):  # a damaged row: _sqlite_rows counts it
                    for (topic_id,) in db.execute(
                        "SELECT topic_id FROM messages WHERE id=?", (row_id,)
                    ):
                        if topic_id in counts:
                            counts[topic_id] += 1
            none = MessageDefinition(MessageDefinitionFormat.NONE, "")
            self.connections = [
                Connection(
                    int(cid),
                    str(topic),
                    str(msgtype),
                    defs.get(str(msgtype), none),
                    str(digest or ""),
                    counts[int(cid)],
                    ConnectionExtRosbag2(str(fmt), parse_qos(qos) if qos else []),
                    self,
                )
                for cid, topic, msgtype, fmt, qos, digest in topics
            ]  # (its schema, msgtypes and metadata, which nothing here reads, stay unset)

        def ids(self) -> range:
            """Every row id of the messages table, from 1 to its largest."""
            if self.last_id is None:
                db: Any = self.dbconn
                try:
                    (last,) = next(iter(db.execute("SELECT max(id) FROM messages")))
                    self.last_id = int(last or 0)
                except Exception:  # the table's last page is damaged: probe past it
                    self.last_id = self._probe_last_id()
            return range(1, self.last_id + 1)

        def _probe_last_id(self) -> int:
            db: Any = self.dbconn
            last = row_id = absent = 0
            while absent < _ID_GAP:
                row_id += 1
                try:
                    found = list(db.execute("SELECT 1 FROM messages WHERE id=?", (row_id,)))
                except Exception:  # damaged, or past the end (looked up on the last page)
                    found = []
                if found:
                    last, absent = row_id, 0
                else:
                    absent += 1
            return last

    return _TolerantReader(path)


def _copy_prefix(src: Path, dst: Path, n: int) -> None:
    """The first ``n`` bytes of ``src`` into ``dst``, a megabyte at a time (a recording of
    gigabytes read at once needed that much memory)."""
    with src.open("rb") as f, dst.open("wb") as g:
        left = n
        while left > 0:
            block = f.read(min(left, 1 << 20))
            if not block:
                break
            g.write(block)
            left -= len(block)


class TempSpaceError(BagError):
    """The temporary copy a recovery reads could not be made (its folder full, unwritable)."""


def _on_a_copy(path: Path, make: Any, open_reader: Any) -> Any:
    """``open_reader(make(tmp))`` on a copy made in a fresh temporary folder, which goes with
    the reader, or at once where anything fails (a copy left behind filled the temp disk).
    A copy that cannot be written is said as such, not as damage to the recording."""
    import tempfile
    import weakref

    tmp = Path(tempfile.mkdtemp(prefix="wheelgrid_bag_recover_"))
    try:
        try:
            copy = make(tmp)
        except OSError as exc:
            raise TempSpaceError(
                f"{path}: cannot make the copy it is read from in {tmp.parent} "
                f"({exc.strerror or exc}); free space there or set TMPDIR to a folder with "
                "room for the recording"
            ) from None
        reader = open_reader(copy)
        weakref.finalize(reader, shutil.rmtree, tmp, True)
        reader.open()
        return reader
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


#: Compressed bytes fed to a decompressor at a time: what a salvage counts as given back is
#: known to this much.
_FEED = 4096


def _decompressed_prefix(codec: str, data: bytes) -> list[tuple[int, bytes]] | None:
    """What a streaming decompressor gives for the first bytes of a compressed chunk cut off
    mid-way, as (compressed bytes fed, output) steps; None for a codec it does not know."""
    if codec == "zstd":
        try:
            from compression import zstd  # type: ignore[import-not-found]
        except ImportError:
            from backports import zstd  # type: ignore[import-not-found,no-redef]
        dec: Any = zstd.ZstdDecompressor()
    elif codec == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        dec = lz4.frame.LZ4FrameDecompressor()
    else:
        return None
    steps = []
    for at in range(0, len(data), _FEED):
        try:
            out = dec.decompress(data[at : at + _FEED])
        except Exception:  # damaged past here: what came out before stands
            break
        steps.append((min(at + _FEED, len(data)), out))
    return steps


def cut_chunk_records(
    path: Path, extent: Extent, channels: Collection[int] = ()
) -> tuple[bytes, int]:
    """The complete Schema, Channel and Message records inside the chunk the cut went through,
    and how many of the file's bytes after ``extent.data_end`` they account for: (b"", 0)
    where there is no such chunk or its compression is unknown. The walk from the header drops
    the chunk whole: a cut in a recording's first chunk gave back nothing, its first cloud and
    pose intact (a review). A chunk compressed with zstd (libmcap's default; rosbag2's
    ``zstd_fast`` and ``zstd_small`` presets) or lz4 is read as far as a streaming
    decompressor gets, which is up to the cut.

    The records end at a message on a channel neither ``channels`` (those of the complete
    records before) nor the chunk itself defines: a reader skips such a message without a
    word, so it and what follows count as lost bytes (a review's hand-made chunk with three
    messages on channel 999 reported nothing lost)."""
    with path.open("rb") as f:
        f.seek(extent.data_end)
        head = f.read(1 + 8 + 8 + 8 + 8 + 4 + 4)
        if len(head) < 41 or head[0] != _CHUNK:
            return b"", 0
        (name_len,) = struct.unpack("<I", head[37:41])
        name = f.read(name_len)
        sized = f.read(8)  # the records' byte count, then the records
        if len(name) < name_len or len(sized) < 8:
            return b"", 0
        codec = name.decode("utf-8", "replace")
        at = 41 + name_len + 8  # where the records begin, from data_end
        # never more than the file holds: a length field that lies (2^40, 2^64 - 1) made the
        # read itself fail (MemoryError, OverflowError) and the whole recovery with it
        left = max(0, extent.size - extent.data_end - at)
        stored = f.read(min(struct.unpack("<Q", sized)[0], left))
    if name_len:
        steps = _decompressed_prefix(codec, stored)
        if not steps:
            return b"", 0
        body = b"".join(out for _, out in steps)
    else:
        steps, body = [], stored
    out, pos, known = bytearray(), 0, set(channels)
    while pos + 9 <= len(body):
        op, length = body[pos], struct.unpack("<Q", body[pos + 1 : pos + 9])[0]
        end = pos + 9 + length
        if end > len(body) or op not in (_SCHEMA, _CHANNEL, _MESSAGE) or length < 2:
            break
        (channel,) = struct.unpack("<H", body[pos + 9 : pos + 11])  # its id, a message's channel
        if op == _CHANNEL:
            known.add(channel)
        elif op == _MESSAGE and channel not in known:
            break
        out += body[pos:end]
        pos = end
    if not out:
        return b"", 0
    if not name_len:
        return bytes(out), at + pos
    # the compressed bytes it took to make the records given back: within the feed that made
    # the last of them, in proportion (a block of lz4 can hold the end of a record and the
    # start of the one the cut went through)
    made = fed_before = 0
    for fed, chunk_out in steps:
        if made + len(chunk_out) >= pos:
            share = (pos - made) / max(1, len(chunk_out))
            return bytes(out), at + fed_before + math.ceil(share * (fed - fed_before))
        made += len(chunk_out)
        fed_before = fed
    return bytes(out), at + len(stored)


def _salvaged_reader(path: Path, extent: Extent, inner: bytes) -> Any:
    """A reader over a copy of ``path``'s complete records followed by ``inner`` (the cut
    chunk's complete records, unchunked, as MCAP allows); the copy goes with the reader."""

    def salvaged(tmp: Path) -> Path:
        copy = tmp / path.name
        _copy_prefix(path, copy, extent.data_end)
        with copy.open("ab") as g:
            g.write(inner)
        return copy

    ext = Extent(extent.data_start, extent.data_end + len(inner), 0, False)
    return _on_a_copy(path, salvaged, lambda copy: _cut_reader(copy, ext))


def _open_file(path: Path, res: Recovery) -> Any:
    """A reader over ``path``'s complete messages; what was cut off is counted in ``res``."""
    if path.suffix == ".db3":
        res.already_complete += 1
        return _sqlite_reader(path)
    indexed = _indexed_reader(path)
    if indexed is not None:  # footer and summary: nothing was cut off (damage: _count_lost)
        res.already_complete += 1
        return indexed
    ext = mcap_extent(path)
    res.already_complete += int(ext.complete)
    if ext.complete:
        return _reader(path, ext)
    reader = _reader(path, ext)
    res.damaged_chunks += len(reader.damaged)
    res.damaged_bytes += sum(b - a for a, b in reader.damaged)
    inner, used = cut_chunk_records(path, ext, [c.id for c in reader.connections])
    res.bytes_unwritten += ext.unwritten
    res.bytes_lost += ext.size - ext.data_end - used
    if not inner:
        return reader
    reader.close()
    return _salvaged_reader(path, ext, inner)


def recover(src: Path, out: Path, storage: str = "mcap", progress: bool = True) -> Recovery:
    """Copy every complete message of the recording ``src`` into a new bag ``out``."""
    files = bag_files(Path(src))
    if Path(out).exists():
        raise BagError(f"{out}: already exists; rosbag2 will not overwrite a bag")
    if storage not in ("sqlite3", "mcap"):
        raise BagError(f"storage must be sqlite3 or mcap, not {storage!r}")
    res = Recovery(files=[str(p) for p in files])
    readers: list[tuple[Path, Any]] = []
    try:
        for path in files:
            try:
                readers.append((path, _open_file(path, res)))
            except (BagError, ModuleNotFoundError):  # rosbags missing is no damaged bag
                raise
            except Exception as exc:  # a record inside the kept part does not decode
                what = (
                    "its tables of topics cannot be read, so none of its messages can"
                    if path.suffix == ".db3"
                    else "damaged before the cut, not only cut off"
                )
                raise BagError(f"{path}: {what} ({type(exc).__name__}: {exc})") from exc
        total = sum(int(c.msgcount) for _, r in readers for c in r.connections)
        if total == 0:
            raise BagError(f"{src}: no complete message before the cut: nothing to recover")
        _copy(readers, Path(out), storage, total if progress else 0, res)
    finally:
        for _, r in readers:
            r.close()
    _count_lost(Path(src), files, res)
    return res


def _copy(
    readers: list[tuple[Path, Any]], out: Path, storage: str, total: int, res: Recovery
) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(out, version=9, storage_plugin=plugin)
    writer.open()
    conns: dict[tuple[str, str], Any] = {}
    try:
        with Progress(total, "recover", "messages") as bar:
            for path, reader in readers:
                rows = (
                    _sqlite_rows(reader, res, store)
                    if path.suffix == ".db3"
                    else reader.messages(reader.connections)
                )
                try:
                    for conn, t_ns, data in rows:
                        key = (conn.topic, conn.msgtype)
                        if key not in conns:
                            try:
                                conns[key] = _connection(writer, conn, store)
                            except Exception as exc:  # not the file's damage: say what it is
                                raise BagError(
                                    f"{path}: cannot copy topic {conn.topic} ({conn.msgtype}): "
                                    f"{type(exc).__name__}: {exc}; the {res.messages} messages "
                                    f"before it are in {out}"
                                ) from exc
                        writer.write(conns[key], t_ns, data)
                        res.messages += 1
                        res.copied[str(path)] = res.copied.get(str(path), 0) + 1
                        res.topics[conn.topic] = res.topics.get(conn.topic, 0) + 1
                        res.start_ns = t_ns if res.messages == 1 else min(res.start_ns, t_ns)
                        res.end_ns = max(res.end_ns, t_ns)
                        if total:
                            bar.update()
                except (BagError, ModuleNotFoundError):
                    raise
                except Exception as exc:
                    raise BagError(
                        f"{path}: damaged before the cut, not only cut off "
                        f"({type(exc).__name__}: {exc}); the {res.messages} messages before "
                        f"it are in {out}"
                    ) from exc
    except BagError:
        writer.close()  # the messages before the damage are kept, and the error says where
        raise
    except BaseException:
        # Ctrl-C, a full disk: closed as it was, the part copied opened as a complete bag of
        # fewer messages, with nothing to say so (and a close that failed on the full disk
        # hid why). It is removed; the cause goes on.
        with contextlib.suppress(Exception):
            writer.close()
        shutil.rmtree(out, ignore_errors=True)
        raise
    writer.close()


def _sqlite_rows(reader: Any, res: Recovery, store: Any) -> Iterator[tuple[Any, int, bytes]]:
    """A sqlite3 file's messages row by row, in the order they were written, each row that
    does not read or decode skipped and counted in ``res.unreadable``. Read in one query, the
    copy ended at the first damaged page: 40 of 100 messages kept where 97 rows read one by
    one, and the missing ones never counted (a review)."""
    conns = {c.id: c for c in reader.connections}
    db = reader.dbconn
    for row_id in reader.ids():
        try:
            rows = list(
                db.execute("SELECT topic_id, timestamp, data FROM messages WHERE id=?", (row_id,))
            )
            if not rows:
                continue  # no row of that id (a recorder's deleted or never-written one)
            topic_id, t_ns, data = rows[0]
            conn = conns[topic_id]
            if conn.msgtype in store.fielddefs:
                store.deserialize_cdr(bytes(data), conn.msgtype)
        except Exception:
            res.unreadable += 1
            continue
        yield conn, int(t_ns), bytes(data)


def _connection(writer: Any, conn: Any, store: Any) -> Any:
    qos = list(getattr(conn.ext, "offered_qos_profiles", []) or [])
    if conn.msgtype in store.fielddefs:
        return writer.add_connection(
            conn.topic, conn.msgtype, typestore=store, offered_qos_profiles=qos
        )
    # A type this ROS distribution's store does not know: its definition travels from the file,
    # with its type hash. rosbags' writer refused the empty hash this passed (an AssertionError,
    # which every recording with a vendor's message type died of, reported as damage), and a
    # reader checks the hash against the definition, so it is the file's or computed from it.
    digest = str(getattr(conn, "digest", "") or "")
    rihs01 = digest if digest.startswith("RIHS01_") else _hash_of_definition(conn, store)
    return writer.add_connection(
        conn.topic, conn.msgtype, msgdef=conn.msgdef.data, rihs01=rihs01, offered_qos_profiles=qos
    )


def _hash_of_definition(conn: Any, store: Any) -> str:
    """The RIHS01 type hash of ``conn``'s type from the definition the file carries, its
    dependencies taken from there first and from ``store`` for the rest (as a reader does)."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    data = conn.msgdef.data
    if conn.msgdef.format == MessageDefinitionFormat.MSG:
        types = get_types_from_msg(data, conn.msgtype)
    elif conn.msgdef.format == MessageDefinitionFormat.IDL:
        sep = "=" * 80 + "\n"
        parts = [data]
        if data.startswith(sep):  # each dependency in a section of its own, as rosbag2 writes
            parts = [p.split("\n", 1)[1] for p in data.split(sep)[1:]]
        types = {}
        for idl in parts:
            types.update(get_types_from_idl(idl))
    else:
        raise ValueError("the file holds no definition of it")
    merged = get_typestore(Stores.EMPTY)
    merged.register({**store.fielddefs, **types})
    return str(merged.hash_rihs01(conn.msgtype))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="wheelgrid bag-recover",
        description="Copy the complete messages of a rosbag2 recording that was cut off (an "
        "MCAP file without its footer, a folder without metadata.yaml) into a new bag that every "
        "reader opens.",
    )
    p.add_argument("src", type=Path, help="the cut-off rosbag2 folder, or one .mcap/.db3 file")
    p.add_argument(
        "--out", type=out_folder, required=True, help="the new bag folder (must not exist)"
    )
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    args = p.parse_args(argv)
    try:
        res = recover(args.src, args.out, args.storage)
    except (BagError, OSError) as exc:
        print(f"wheelgrid bag-recover: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            f"wheelgrid bag-recover: interrupted; the part of {args.out} written is removed",
            file=sys.stderr,
        )
        return 130
    span = (res.end_ns - res.start_ns) / 1e9 if res.messages else 0.0
    topics = ", ".join(f"{t} {n}" for t, n in sorted(res.topics.items())) or "none"
    unknown = (
        f"every {'readable ' if res.unreadable else ''}message committed to "
        f"{', '.join(res.unlisted)} copied; no metadata.yaml lists "
        "how many were recorded, so any the recorder had not written out when it stopped "
        "cannot be counted"
    )
    state = (
        unknown
        if res.already_complete == len(res.files) and res.unlisted
        else "nothing was cut off"
        if res.already_complete == len(res.files)
        else f"the cut went through a record: its {res.bytes_lost / 1e3:.0f} kB written are lost"
        if res.bytes_lost
        else "the file ends after a complete record, without its footer"
    )
    if res.bytes_unwritten and res.already_complete < len(res.files):
        state += (
            f"; then {res.bytes_unwritten / 1e3:.0f} kB of zeros, space the file was given "
            "but never written (no data lost there)"
        )
    if res.lost:
        # a footer reached is no proof: a damaged middle ends the copy early all the same
        where = f"; not there: {', '.join(res.missing)}" if res.missing else ""
        state = (
            f"{res.lost} of the {res.listed} messages the recording lists (its summary, "
            f"metadata.yaml) are not in it: damaged or missing{where}"
            + ("" if res.already_complete == len(res.files) else f"; {state}")
        )
    if res.unreadable:
        state += f"; {res.unreadable} damaged row(s) skipped, the rows after them copied"
    if res.damaged_chunks:
        state += (
            f"; {res.damaged_chunks} damaged chunk(s) before the cut "
            f"({res.damaged_bytes / 1e3:.0f} kB) skipped, the records after them copied"
        )
    print(
        f"bag-recover: {res.messages} messages over {span:.1f} s ({topics}) from "
        f"{len(res.files)} file(s) -> {args.out}; {state}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
