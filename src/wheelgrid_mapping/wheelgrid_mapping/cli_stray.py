"""``wheelgrid stream-stray`` and ``wheelgrid import-stray``: Stray Scanner exports as a live
phone or as a bag.

``stream-stray`` plays an export through the bridge protocol in real time (``--rate`` is a speed
factor), standing in for the phone so the whole live path (TCP, bridge, DDS, mapper) can be run
and measured without one. ``import-stray`` writes the same topics the bridge publishes into a
rosbag2 bag, stamped with the capture's own timestamps, using the same message builder
(:func:`wheelgrid_mapping.iphone_bridge_node.frame_messages`), so offline and live runs agree.

Both time a frame by the latest time its place in capture order allows
(:meth:`wheelgrid_mapping.stray.StrayExport.captured_by`; a frame's own stamp unless it is
stamped after the frames that follow it): ``stream-stray`` paces its sending by it, and
``import-stray`` makes it the bag's log time (when a recorder would have got the frame). One
timestamp an hour ahead in odometry.csv held the stream for that hour, and went to the end of
the bag with a log time an hour on, where nothing could tell it from a pause. Its header keeps
the stamp as the export has it, so the mapper can hold it back.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from wheelgrid_common.fileio import folder_problem, out_folder
from wheelgrid_mapping.bridge_protocol import (
    DEPTH_F32_M,
    DEPTH_U16_MM,
    POSE_OPTICAL,
    Frame,
    connect,
    encode_frame,
    parting_status,
    status_words,
)
from wheelgrid_mapping.depth import check_min_confidence, confidence_loss, metres_to_millimetres
from wheelgrid_mapping.stray import StrayExport, StrayFrame

TOKEN_ENV = "WHEELGRID_BRIDGE_TOKEN"
#: A wait this long for the next frame's slot (a pause in the capture) is spent disconnected:
#: the bridge closes a connection idle for its idle_timeout_s (5 s by default), and the rest
#: of a capture with a 6 s pause was never sent, exit 1 (a review). The protocol's answer: a
#: client that pauses longer reconnects (docs/iphone-protocol.md).
#: How long stream-stray waits for a bridge that does not listen yet, and how often it tries.
CONNECT_WAIT_S = 10.0
CONNECT_RETRY_S = 0.2
PAUSE_RECONNECT_S = 2.0


class _UsageError(Exception):
    """Bad input: exit code 2 with this one-line message."""


def _fail(code: int, text: str) -> int:
    print(f"wheelgrid: {text}", file=sys.stderr)
    return code


MIN_RATE, MAX_RATE = 0.1, 1000.0  # --rate: slower than 0.1, a 5 Hz capture trips idle_timeout_s


def parse_host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    # isdigit() alone takes "²" (and int() then fails): ASCII digits only
    if not sep or not host or not (port.isascii() and port.isdigit()) or not 0 < int(port) < 65536:
        raise _UsageError(f"--to must be HOST:PORT (e.g. 127.0.0.1:8765), not {text!r}")
    return host.strip("[]"), int(port)


def stray_to_frame(sf: StrayFrame, seq: int) -> Frame:
    """A Stray frame as the bridge would receive it (uint16 mm depth, optical-axes pose)."""
    return Frame(
        stamp=sf.stamp,
        seq=seq,
        K=sf.K,
        depth=metres_to_millimetres(sf.depth),  # exact for Stray's mm depth
        depth_encoding=DEPTH_U16_MM,
        confidence=sf.confidence,
        pose=sf.pose,
        pose_axes=POSE_OPTICAL if sf.pose is not None else 0,
    )


def _frame_range(exp: StrayExport, start: int, frames: int | None) -> range:
    if start < 0 or start >= len(exp):
        raise _UsageError(f"--start {start} outside 0..{len(exp) - 1} ({len(exp)} frames)")
    if frames is not None and frames < 1:
        raise _UsageError("--frames must be >= 1")
    end = len(exp) if frames is None else min(len(exp), start + frames)
    return range(start, end)


def _check_out_parent(out: Path) -> None:
    """The bag's parent folder made (or found writable) before any frame is read: rosbag2
    makes the bag folder itself, and a typo under a file failed as 'import failed', exit 1."""
    problem = folder_problem(out.absolute().parent)
    if problem:
        raise _UsageError(f"--out {out}: {problem}")


def _open_export(path: str) -> StrayExport:
    try:
        return StrayExport(path)
    except ValueError as exc:
        raise _UsageError(str(exc)) from exc


@dataclass
class StreamStats:
    frames_sent: int = 0
    bytes_sent: int = 0
    wall_s: float = 0.0
    capture_s: float = 0.0
    late_frames: int = 0  # sent more than 50 ms after their real-time slot
    max_lag_s: float = 0.0
    skipped: int = 0  # frames whose images do not read: not sent, as a phone drops a frame
    reconnects: int = 0  # pauses in the capture longer than PAUSE_RECONNECT_S (see there)


class BridgeClosedError(ConnectionError):
    """The bridge ended the stream: its text says why, where the bridge said it."""


def _closed_text(sock: socket.socket, exc: OSError, sent: int, total: int) -> str:
    status = parting_status(sock)
    said = status_words(status) if status else f"without a status ({exc.strerror or exc})"
    return f"the bridge closed the connection after {sent} of {total} frames: {said}"


def stream_export(
    exp: StrayExport,
    host: str,
    port: int,
    *,
    rate: float = 1.0,
    token: str = "",
    indices: range | None = None,
    depth_encoding: int = DEPTH_U16_MM,
    wait: float = 0.0,
) -> StreamStats:
    """Send frames of ``exp`` to a bridge, paced by their capture times / ``rate`` (0 = no
    pacing). Raises ConnectionError/OSError when the bridge refuses or goes away; nobody
    listening is waited for up to ``wait`` seconds first (a bridge still starting)."""
    idx = indices if indices is not None else range(len(exp))
    stats = StreamStats()
    if not idx:
        return stats
    name = f"stream-stray {exp.path.name}"
    deadline, said = time.monotonic() + wait, False
    while True:
        try:
            sock = connect(host, port, token=token, name=name)
            break
        except ConnectionRefusedError:
            # `wheelgrid launch --iphone &` then this at once: the bridge listens ~3 s later,
            # and the README's own lines failed, "nothing listens" (a review)
            if time.monotonic() >= deadline:
                raise
            if not said:
                print(
                    f"stream-stray: waiting up to {wait:g} s for a bridge on {host}:{port}",
                    file=sys.stderr,
                    flush=True,
                )
                said = True
            time.sleep(CONNECT_RETRY_S)
    try:
        t_first = exp.captured_by(idx[0])
        t0 = time.monotonic()
        for seq, i in enumerate(idx):
            sf = exp.frame_or_warn(i)
            if sf is None:
                stats.skipped += 1
                continue
            data = encode_frame(
                sf.stamp,
                sf.K,
                sf.depth,
                seq=seq,
                confidence=sf.confidence,
                pose=sf.pose,
                pose_axes=POSE_OPTICAL,
                depth_encoding=depth_encoding,
            )
            if rate > 0:
                slot = t0 + (exp.captured_by(i) - t_first) / rate
                wait = slot - time.monotonic()
                if wait > PAUSE_RECONNECT_S:
                    sock.close()
                    time.sleep(wait)
                    try:
                        sock = connect(host, port, token=token, name=name)
                    except ConnectionRefusedError:
                        # said as "nothing listens ... after 10 s", with no wait and 15 frames
                        # sent (a review)
                        raise BridgeClosedError(
                            f"the bridge went away during a pause in the capture, after "
                            f"{stats.frames_sent} of {len(idx)} frames"
                        ) from None
                    stats.reconnects += 1
                elif wait > 0:
                    time.sleep(wait)
                lag = time.monotonic() - slot
                stats.max_lag_s = max(stats.max_lag_s, lag)
                stats.late_frames += lag > 0.05
            try:
                sock.sendall(data)
            except OSError as exc:
                text = _closed_text(sock, exc, stats.frames_sent, len(idx))
                raise BridgeClosedError(text) from None
            stats.frames_sent += 1
            stats.bytes_sent += len(data)
        stats.capture_s = exp.captured_by(idx[-1]) - t_first
        stats.wall_s = time.monotonic() - t0
    finally:
        sock.close()
    return stats


def stream_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(
        prog="wheelgrid stream-stray",
        description="Play a Stray Scanner export to an iphone_bridge over TCP, in real time "
        "(stands in for the phone).",
    )
    ap.add_argument("dir", help="Stray Scanner export folder (depth/, camera_matrix.csv, ...)")
    ap.add_argument("--to", default="127.0.0.1:8765", help="bridge HOST:PORT [127.0.0.1:8765]")
    ap.add_argument("--rate", type=float, default=1.0, help="speed factor, 0 = unpaced [1.0]")
    ap.add_argument("--token", default=None, help=f"bridge token [env {TOKEN_ENV}]")
    ap.add_argument("--frames", type=int, default=None, help="send at most N frames")
    ap.add_argument(
        "--wait",
        type=float,
        default=CONNECT_WAIT_S,
        help=f"wait this long for a bridge that is not listening yet, s [{CONNECT_WAIT_S:g}]",
    )
    ap.add_argument("--start", type=int, default=0, help="first frame position [0]")
    ap.add_argument(
        "--depth-encoding", choices=("u16", "f32"), default="u16", help="wire depth [u16 mm]"
    )
    args = ap.parse_args(argv)
    try:
        host, port = parse_host_port(args.to)
        if not (args.rate == 0 or MIN_RATE <= args.rate <= MAX_RATE):  # NaN too
            # 1e-300 overflowed the sleep until a frame's slot
            raise _UsageError(
                f"--rate must be 0 (unpaced) or {MIN_RATE:g}..{MAX_RATE:g}, not {args.rate}"
            )
        if not 0.0 <= args.wait <= 3600.0:  # NaN too
            raise _UsageError(f"--wait must be in 0..3600 s, not {args.wait}")
        exp = _open_export(args.dir)
        idx = _frame_range(exp, args.start, args.frames)
    except _UsageError as exc:
        return _fail(2, str(exc))
    token = args.token if args.token is not None else os.environ.get(TOKEN_ENV, "")
    enc = DEPTH_U16_MM if args.depth_encoding == "u16" else DEPTH_F32_M
    try:
        stats = stream_export(
            exp,
            host,
            port,
            rate=args.rate,
            token=token,
            indices=idx,
            depth_encoding=enc,
            wait=args.wait,
        )
    except KeyboardInterrupt:
        return _fail(130, "interrupted")  # as import-stray and every other command
    except ConnectionRefusedError:
        return _fail(
            1,
            f"nothing listens on {host}:{port}"
            + (f" after {args.wait:g} s" if args.wait else "")
            + " (is the bridge running: `wheelgrid launch --iphone`?)",
        )
    except BridgeClosedError as exc:
        return _fail(1, f"streaming to {host}:{port} stopped: {exc}")
    except (OSError, ConnectionError) as exc:
        return _fail(1, f"streaming to {host}:{port} failed: {exc}")
    print(
        f"sent {stats.frames_sent} frames ({stats.bytes_sent / 1e6:.1f} MB) in "
        f"{stats.wall_s:.2f} s (capture {stats.capture_s:.2f} s, rate {args.rate}); "
        f"late > 50 ms: {stats.late_frames}, max lag {stats.max_lag_s * 1000:.1f} ms"
        + (f"; {stats.skipped} unreadable frames skipped" if stats.skipped else "")
        + (
            f"; reconnected {stats.reconnects} time(s) after a pause in the capture"
            if stats.reconnects
            else ""
        )
    )
    return 0


def import_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(
        prog="wheelgrid import-stray",
        description="Write a Stray Scanner export as a rosbag2 bag with the iphone_bridge's "
        "topics, stamped with the capture's timestamps.",
    )
    ap.add_argument("dir", help="Stray Scanner export folder")
    ap.add_argument("--out", type=out_folder, required=True, help="new bag folder to write")
    ap.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3")
    ap.add_argument("--frames", type=int, default=None, help="write at most N frames")
    ap.add_argument("--start", type=int, default=0, help="first frame position [0]")
    ap.add_argument(
        "--min-confidence", type=int, default=1, help="confidence a point needs (0-2) [1]"
    )
    ap.add_argument("--dense", action="store_true", help="dense clouds instead of organised")
    args = ap.parse_args(argv)
    from wheelgrid_common.bagio import BagError, BagWriter
    from wheelgrid_common.progress import Progress
    from wheelgrid_mapping.iphone_bridge_node import frame_messages

    try:
        try:  # 5 made every point NaN, silently
            check_min_confidence(args.min_confidence, "--min-confidence")
        except ValueError as exc:
            raise _UsageError(str(exc)) from None
        if loss := confidence_loss(args.min_confidence):
            print(f"wheelgrid import-stray: warning: {loss}", file=sys.stderr)
        exp = _open_export(args.dir)
        idx = _frame_range(exp, args.start, args.frames)
        if Path(args.out).exists():
            raise _UsageError(f"{args.out}: already exists; rosbag2 will not overwrite a bag")
        _check_out_parent(Path(args.out))
    except _UsageError as exc:
        return _fail(2, str(exc))
    if not exp.has_poses:
        print(
            "wheelgrid import-stray: warning: no odometry.csv: the frames are stamped at 60 Hz "
            "from 0, and the bag has no /iphone/odometry (no --prior arkit for it)",
            file=sys.stderr,
        )
    elif note := exp.missing_poses_note():
        print(
            f"wheelgrid import-stray: warning: {note}; the bag has no /iphone/odometry for those",
            file=sys.stderr,
        )
    counts: dict[str, int] = {}
    skipped = 0
    unfiltered = 0  # frames with no confidence image: --min-confidence cannot apply
    t0 = time.monotonic()
    log_ns = 0
    try:
        with BagWriter(args.out, args.storage) as bag, Progress(len(idx), "import-stray") as bar:
            for seq, i in enumerate(idx):
                sf = exp.frame_or_warn(i)
                if sf is None:
                    skipped += 1
                    bar.update()
                    continue
                unfiltered += int(sf.confidence is None and args.min_confidence > 0)
                frame = stray_to_frame(sf, seq)
                # never before the frame before it: a recorder gets frames in capture order, and
                # a frame stamped 10 s back, logged at its stamp, went first in the bag and began
                # the map there (its header keeps the stamp, which the mapper then skips; a review)
                log_ns = max(log_ns, round(exp.captured_by(i) * 1e9))
                for topic, msgtype, msg in frame_messages(
                    frame, frame.stamp, min_confidence=args.min_confidence, organized=not args.dense
                ):
                    bag.write(topic, msgtype, log_ns, msg)
                    counts[topic] = counts.get(topic, 0) + 1
                bar.update()
    except BagError as exc:
        return _fail(2, str(exc))
    except (Exception, KeyboardInterrupt) as exc:
        # A bag cut short (a full disk: sqlite3.OperationalError, which is no OSError, came out
        # as a traceback; Ctrl-C) was left behind with a metadata.yaml, opening as if complete.
        # --out did not exist before this run (checked above): the part written goes.
        shutil.rmtree(args.out, ignore_errors=True)
        if isinstance(exc, ModuleNotFoundError):  # rosbags not installed: said by `wheelgrid`
            raise
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else "import failed"
        detail = "" if isinstance(exc, KeyboardInterrupt) else f" ({type(exc).__name__}: {exc})"
        return _fail(
            130 if isinstance(exc, KeyboardInterrupt) else 1,
            f"{what}{detail}; the part of {args.out} written is removed, no bag was made",
        )
    if skipped == len(idx):
        # an empty bag, exit 0, which `wheelgrid map` then refused as "no topic" (a review)
        shutil.rmtree(args.out, ignore_errors=True)
        return _fail(2, f"none of the {len(idx)} frames read (see above); no bag was made")
    if unfiltered:
        print(
            f"wheelgrid import-stray: warning: {unfiltered} of {len(idx) - skipped} frames have "
            f"no confidence image (confidence/): --min-confidence {args.min_confidence} was not "
            "applied to their clouds, and their low-confidence returns are in them",
            file=sys.stderr,
        )
    listing = ", ".join(f"{t} {n}" for t, n in sorted(counts.items()))
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(
        f"wrote {len(idx) - skipped} frames to {args.out} ({args.storage}, {size / 1e6:.1f} MB) "
        f"in {time.monotonic() - t0:.1f} s: {listing}"
        + (f"; {skipped} unreadable frames skipped" if skipped else "")
    )
    return 0
