"""The iPhone bridge wire protocol, version 1 (ROS-free): encoder and streaming decoder.

A phone (or ``wheelgrid stream-stray`` standing in for one) sends depth frames over TCP to the
``iphone_bridge`` node. Every message is length-prefixed, so a receiver always knows where the
next message starts and can skip one it does not want without buffering it; the full layout is
in docs/iphone-protocol.md. Untrusted bytes arrive here, so the decoder:

- never allocates more than ``max_frame_bytes`` (+ a 12-byte prefix) whatever the peer claims;
- rejects malformed messages with a :class:`ProtocolError` whose ``reason`` is a stable code
  (for log-once) and whose text says what was wrong;
- tells recoverable problems (a well-framed message with bad content or too big: skipped, the
  stream stays in sync) from fatal ones (bad magic/version: the framing itself is lost, the
  connection must close).

All integers and floats are little-endian.
"""

from __future__ import annotations

import contextlib
import functools
import hmac
import ipaddress
import itertools
import math
import selectors
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from wheelgrid_mapping.depth import (
    MAX_DEPTH_M,
    check_intrinsics,
    metres_to_millimetres,
    principal_point_problem,
)
from wheelgrid_mapping.se3 import MAX_TRANSLATION_M

MAGIC = b"WGIP"
VERSION = 1

# Message types.
MSG_HELLO = 1  # client -> bridge, first message: token and client name
MSG_FRAME = 2  # client -> bridge: one depth frame
MSG_STATUS = 3  # bridge -> client: accepted / rejected (+ reason)

# Depth encodings.
DEPTH_F32_M = 1  # float32 metres, 0/NaN = no return
DEPTH_U16_MM = 2  # uint16 millimetres, 0 = no return
DEPTH_BYTES = {DEPTH_F32_M: 4, DEPTH_U16_MM: 2}
# Confidence encodings.
CONF_NONE = 0
CONF_U8 = 1  # ARKit confidence 0 low, 1 medium, 2 high
# Which camera axes the pose's rotation is expressed in.
POSE_NONE = 0  # no pose (tracking lost): the frame is still usable as a cloud
POSE_OPTICAL = 1  # world <- camera with x right, y down, z forward (OpenCV/ROS optical)
POSE_ARKIT = 2  # world <- camera with ARKit's axes x right, y up, z backward (camera.transform)

# Status codes.
STATUS_OK = 0
STATUS_BAD_TOKEN = 1
STATUS_BUSY = 2
STATUS_PROTOCOL_ERROR = 3
STATUS_SHUTDOWN = 4  # the bridge is stopping: sent to every connection before it closes
STATUS_NAMES = {
    STATUS_OK: "OK",
    STATUS_BAD_TOKEN: "BAD_TOKEN",
    STATUS_BUSY: "BUSY",
    STATUS_PROTOCOL_ERROR: "PROTOCOL_ERROR",
    STATUS_SHUTDOWN: "SHUTDOWN",
}

# Limits. Defaults fit an iPhone (256x192) with a wide margin; receivers may lower them.
MAX_FRAME_BYTES = 8 * 1024 * 1024  # largest message body accepted (bytes)
MAX_DIMENSION = 4096  # largest width or height (pixels)
MAX_TOKEN_BYTES = 256
MAX_NAME_BYTES = 256
MAX_STATUS_TEXT_BYTES = 1024
# Stamps become builtin_interfaces/Time (int32 seconds, and a fraction that may round up to
# the next second): anything at or past this would overflow when published.
MAX_STAMP_S = float(2**31 - 1)

PREFIX = struct.Struct("<4sBBHI")  # magic, version, type, flags (0), body length
# stamp, seq, width, height, fx, fy, cx, cy, tx, ty, tz, qx, qy, qz, qw,
# depth encoding, confidence encoding, pose axes, reserved
FRAME_HEADER = struct.Struct("<dIHH4d7dBBBB")
_U16 = struct.Struct("<H")
# Bounds for a receiver's ``max_frame_bytes``: below the largest HELLO a phone may be unable to
# say hello at all; above the largest valid frame (4096 x 4096 float32 depth + confidence) a
# limit only lets a peer make the receiver buffer more.
MAX_HELLO_BYTES = 2 + MAX_TOKEN_BYTES + 2 + MAX_NAME_BYTES
MIN_FRAME_LIMIT = max(MAX_HELLO_BYTES, FRAME_HEADER.size + 5)
MAX_FRAME_LIMIT = FRAME_HEADER.size + MAX_DIMENSION * MAX_DIMENSION * (4 + 1)


class ProtocolError(ValueError):
    """A message that cannot be used. ``reason`` is a stable code; ``fatal`` = stream lost."""

    def __init__(self, reason: str, detail: str, *, fatal: bool = False) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
        self.fatal = fatal


@dataclass(frozen=True)
class Hello:
    token: str
    name: str


@dataclass(frozen=True)
class Status:
    code: int
    text: str


@dataclass(frozen=True)
class Frame:
    """One depth frame as sent by the phone.

    ``pose`` is ARKit world (y up) <- camera, with the camera axes given by ``pose_axes``;
    :meth:`pose_optical` always returns the optical-axes version (or None).
    """

    stamp: float  # seconds, the phone's clock
    seq: int
    K: np.ndarray  # (3, 3)
    depth: np.ndarray  # (H, W) float32 metres or uint16 millimetres (see depth_encoding)
    depth_encoding: int
    confidence: np.ndarray | None = None  # (H, W) uint8
    pose: np.ndarray | None = None  # (4, 4)
    pose_axes: int = POSE_NONE

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    def depth_m(self) -> np.ndarray:
        """Depth as float32 metres with NaN where there was no return (0, NaN, or beyond
        :data:`MAX_DEPTH_M`)."""
        if self.depth_encoding == DEPTH_U16_MM:
            d = self.depth.astype(np.float32) * np.float32(0.001)
        else:
            d = self.depth.astype(np.float32, copy=True)
        d[~((d > 0) & (d <= np.float32(MAX_DEPTH_M)))] = np.nan
        return d

    def pose_optical(self) -> np.ndarray | None:
        from wheelgrid_mapping.depth import ARKIT_CAMERA_TO_OPTICAL

        if self.pose is None or self.pose_axes == POSE_NONE:
            return None
        if self.pose_axes == POSE_ARKIT:
            return self.pose @ ARKIT_CAMERA_TO_OPTICAL
        return self.pose.copy()


def _prefix(msg_type: int, body_len: int) -> bytes:
    return PREFIX.pack(MAGIC, VERSION, msg_type, 0, body_len)


def _short_str(data: str, limit: int, what: str) -> bytes:
    raw = data.encode("utf-8")
    if len(raw) > limit:
        raise ValueError(f"{what} is {len(raw)} bytes; at most {limit}")
    return _U16.pack(len(raw)) + raw


def encode_hello(token: str = "", name: str = "") -> bytes:
    body = _short_str(token, MAX_TOKEN_BYTES, "token") + _short_str(name, MAX_NAME_BYTES, "name")
    return _prefix(MSG_HELLO, len(body)) + body


def encode_status(code: int, text: str = "") -> bytes:
    raw = text.encode("utf-8")[:MAX_STATUS_TEXT_BYTES]
    body = bytes([code]) + _U16.pack(len(raw)) + raw
    return _prefix(MSG_STATUS, len(body)) + body


def encode_frame(
    stamp: float,
    K: np.ndarray,
    depth: np.ndarray,
    *,
    seq: int = 0,
    confidence: np.ndarray | None = None,
    pose: np.ndarray | None = None,
    pose_axes: int = POSE_OPTICAL,
    depth_encoding: int | None = None,
) -> bytes:
    """Encode one frame; ``depth`` float (metres) or uint16 (millimetres).

    ``depth_encoding`` converts on the way: float depth sent as DEPTH_U16_MM is rounded to mm
    (NaN, inf and beyond 65.535 m -> 0 = no return), uint16 depth sent as DEPTH_F32_M is
    scaled to metres (0 stays 0 = no return; it went out as metres unscaled, 1000x too far).
    ``pose`` is ARKit world <- camera in ``pose_axes``.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    h, w = d.shape
    if not (0 < h <= MAX_DIMENSION and 0 < w <= MAX_DIMENSION):
        raise ValueError(f"depth {w}x{h} outside 1..{MAX_DIMENSION}")
    enc = depth_encoding or (DEPTH_U16_MM if d.dtype == np.uint16 else DEPTH_F32_M)
    if enc == DEPTH_F32_M:
        metres = d.astype(np.float32) * np.float32(0.001) if d.dtype == np.uint16 else d
        payload = np.ascontiguousarray(metres, dtype="<f4").tobytes()
    elif enc == DEPTH_U16_MM:
        mm = d if d.dtype == np.uint16 else metres_to_millimetres(d)
        payload = np.ascontiguousarray(mm, dtype="<u2").tobytes()
    else:
        raise ValueError(f"unknown depth encoding {enc}")
    conf_enc = CONF_NONE
    if confidence is not None:
        c = np.asarray(confidence)
        if c.shape != d.shape:
            raise ValueError(f"confidence {c.shape} differs from depth {d.shape}")
        payload += np.ascontiguousarray(c, dtype=np.uint8).tobytes()
        conf_enc = CONF_U8
    k = np.asarray(K, dtype=np.float64)
    if pose is None:
        pose_axes = POSE_NONE
        t: tuple[float, ...] = (0.0, 0.0, 0.0)
        q: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)
    else:
        from wheelgrid_common.fileio import matrix_to_quat

        p = np.asarray(pose, dtype=np.float64)
        t = tuple(float(v) for v in p[:3, 3])
        q = matrix_to_quat(p[:3, :3])
    header = FRAME_HEADER.pack(
        float(stamp),
        int(seq) & 0xFFFFFFFF,
        w,
        h,
        k[0, 0],
        k[1, 1],
        k[0, 2],
        k[1, 2],
        *t,
        *q,
        enc,
        conf_enc,
        pose_axes,
        0,
    )
    body_len = len(header) + len(payload)
    return _prefix(MSG_FRAME, body_len) + header + payload


def _read_short_str(body: bytes, pos: int, limit: int, what: str) -> tuple[str, int]:
    if pos + 2 > len(body):
        raise ProtocolError("bad_hello", f"{what} length missing")
    (n,) = _U16.unpack_from(body, pos)
    pos += 2
    if n > limit or pos + n > len(body):
        raise ProtocolError("bad_hello", f"{what} of {n} bytes (limit {limit}, {len(body)} B body)")
    try:
        return body[pos : pos + n].decode("utf-8"), pos + n
    except UnicodeDecodeError as exc:
        raise ProtocolError("bad_hello", f"{what} is not UTF-8") from exc


def decode_hello(body: bytes) -> Hello:
    token, pos = _read_short_str(body, 0, MAX_TOKEN_BYTES, "token")
    name, pos = _read_short_str(body, pos, MAX_NAME_BYTES, "name")
    if pos != len(body):
        raise ProtocolError("bad_hello", f"{len(body) - pos} trailing bytes")
    return Hello(token, name)


def decode_status(body: bytes) -> Status:
    if len(body) < 3:
        raise ProtocolError("bad_status", f"body of {len(body)} bytes")
    (n,) = _U16.unpack_from(body, 1)
    if 3 + n != len(body):
        raise ProtocolError("bad_status", f"text length {n} does not match body {len(body)}")
    return Status(body[0], body[3:].decode("utf-8", "replace"))


def decode_frame(body: bytes) -> Frame:
    """Parse and validate a FRAME body; ProtocolError (recoverable) on any inconsistency."""
    if len(body) < FRAME_HEADER.size:
        raise ProtocolError(
            "short_frame", f"{len(body)} B body, the header alone is {FRAME_HEADER.size} B"
        )
    (stamp, seq, w, h, fx, fy, cx, cy, *tq, enc, conf_enc, axes, _res) = FRAME_HEADER.unpack_from(
        body
    )
    if not (math.isfinite(stamp) and 0 <= stamp < MAX_STAMP_S):
        # checked here, not at publish time: a stamp ROS cannot hold raised out of publish
        raise ProtocolError(
            "bad_stamp",
            f"stamp {stamp!r} is not a time in [0, {MAX_STAMP_S:.0f}) s "
            "(builtin_interfaces/Time holds int32 seconds)",
        )
    if not (0 < w <= MAX_DIMENSION and 0 < h <= MAX_DIMENSION):
        raise ProtocolError("bad_size", f"{w}x{h} outside 1..{MAX_DIMENSION}")
    # Finite and positive was all: fx = 1e-40 passed, its rays overflowed float32, and the
    # organised cloud went out full of inf (check_intrinsics says what a camera's are).
    try:
        check_intrinsics(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    except ValueError as exc:
        raise ProtocolError("bad_intrinsics", str(exc)) from None
    problem = principal_point_problem(cx, cy, w, h)
    if problem:
        raise ProtocolError("bad_intrinsics", problem)
    if enc not in DEPTH_BYTES:
        raise ProtocolError("bad_depth_encoding", f"depth encoding {enc} (known: 1 f32, 2 u16)")
    if conf_enc not in (CONF_NONE, CONF_U8):
        raise ProtocolError("bad_confidence_encoding", f"confidence encoding {conf_enc}")
    if axes not in (POSE_NONE, POSE_OPTICAL, POSE_ARKIT):
        raise ProtocolError("bad_pose_axes", f"pose axes {axes} (known: 0, 1, 2)")
    n = w * h
    need = FRAME_HEADER.size + n * DEPTH_BYTES[enc] + (n if conf_enc == CONF_U8 else 0)
    if len(body) != need:
        raise ProtocolError(
            "size_mismatch", f"{w}x{h} with these encodings needs a {need} B body, got {len(body)}"
        )
    pose = None
    if axes != POSE_NONE:
        tx, ty, tz, qx, qy, qz, qw = tq
        qn = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw) if all(map(math.isfinite, tq)) else 0
        if not all(math.isfinite(v) for v in tq) or abs(qn - 1.0) > 1e-3:
            raise ProtocolError("bad_pose", f"pose t={tq[:3]} q={tq[3:]} (|q| must be 1)")
        if max(abs(tx), abs(ty), abs(tz)) > MAX_TRANSLATION_M:
            # finite, and passed on to /iphone/odometry it stopped the mapper for good
            raise ProtocolError(
                "bad_pose", f"pose t={tq[:3]} is over {MAX_TRANSLATION_M:g} m from the origin"
            )
        from wheelgrid_mapping.depth import pose_from_xyz_quat

        pose = pose_from_xyz_quat(tx, ty, tz, qx, qy, qz, qw)
    off = FRAME_HEADER.size
    dt = "<f4" if enc == DEPTH_F32_M else "<u2"
    depth = np.frombuffer(body, dtype=dt, count=n, offset=off).reshape(h, w)
    depth = depth.astype(np.float32 if enc == DEPTH_F32_M else np.uint16)  # native, owned
    off += n * DEPTH_BYTES[enc]
    conf = None
    if conf_enc == CONF_U8:
        conf = np.frombuffer(body, dtype=np.uint8, count=n, offset=off).reshape(h, w).copy()
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return Frame(
        stamp=stamp,
        seq=seq,
        K=K,
        depth=depth,
        depth_encoding=enc,
        confidence=conf,
        pose=pose,
        pose_axes=axes,
    )


Message = Hello | Frame | Status


class FrameDecoder:
    """Incremental decoder for a byte stream: ``feed(chunk) -> list of complete messages``.

    Recoverable problems (bad content, oversized body, unknown type) drop that one message and
    are queued in :attr:`errors` (take them with :meth:`pop_errors`); the stream stays usable.
    :meth:`feed_ordered` returns them instead, in stream order among the messages, for a
    receiver that must tell "bad, good, bad" from "bad, bad, bad".
    A fatal problem (bad magic or version) raises ProtocolError(fatal=True) -- deferred to the
    next ``feed`` if messages were already decoded in this call -- and :attr:`failed` stays true.
    Memory is bounded by ``max_frame_bytes`` plus one prefix, whatever the peer sends.
    """

    def __init__(
        self,
        max_frame_bytes: int = MAX_FRAME_BYTES,
        accept: tuple[int, ...] = (MSG_HELLO, MSG_FRAME),
        hello_first: bool = False,
    ) -> None:
        self.max_frame_bytes = int(max_frame_bytes)
        self.accept = accept
        # The bridge's side of a connection: until a HELLO has been read, only a HELLO of at
        # most MAX_HELLO_BYTES is taken, and anything else ends the stream at its prefix. A
        # peer with no token made the bridge hold a whole frame's worth (8 MB, up to 80 MB)
        # per connection before it had said who it was.
        self.hello_first = hello_first
        self._buf = bytearray()
        self._skip = 0  # bytes of an oversized body still to discard
        self._fatal: ProtocolError | None = None
        self.errors: list[ProtocolError] = []
        self.bytes_in = 0
        self.messages_out = 0

    @property
    def failed(self) -> bool:
        return self._fatal is not None

    @property
    def fatal(self) -> ProtocolError | None:
        """The error that lost the framing, once :attr:`failed`."""
        return self._fatal

    @property
    def buffered(self) -> int:
        """Bytes held right now (for memory-bound checks)."""
        return len(self._buf)

    def pop_errors(self) -> list[ProtocolError]:
        out, self.errors = self.errors, []
        return out

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        out: list[Message] = []
        for item in self.feed_ordered(data):
            if isinstance(item, ProtocolError):
                self.errors.append(item)
            else:
                out.append(item)
        if not out and self._fatal is not None:
            raise self._fatal  # nothing decoded to hand over first: fail now
        return out

    def feed_ordered(self, data: bytes | bytearray | memoryview) -> list[Message | ProtocolError]:
        """Like :meth:`feed`, but each recoverable error is an item of the list, where its
        message was in the stream (nothing goes to :attr:`errors`). A fatal error is raised,
        deferred to the next call if this one already has items to return."""
        if self._fatal is not None:
            raise self._fatal
        self.bytes_in += len(data)
        out: list[Message | ProtocolError] = []
        view = memoryview(data)
        while True:
            if self._skip:
                n = min(self._skip, len(view))
                self._skip -= n
                view = view[n:]
                if self._skip:
                    break
            # the prefix first: nothing the peer claims is trusted before it is checked
            take = max(0, min(PREFIX.size - len(self._buf), len(view)))
            self._buf += view[:take]
            view = view[take:]
            if len(self._buf) < PREFIX.size:
                break
            magic, version, mtype, _flags, length = PREFIX.unpack_from(self._buf)
            if magic != MAGIC:
                return self._fail(out, "bad_magic", f"expected {MAGIC!r}, got {bytes(magic)!r}")
            if version != VERSION:
                return self._fail(out, "bad_version", f"protocol version {version}, want {VERSION}")
            if self.hello_first and mtype != MSG_HELLO:
                return self._fail(out, "frame_before_hello", f"message type {mtype} before HELLO")
            if self.hello_first and length > MAX_HELLO_BYTES:
                return self._fail(
                    out,
                    "oversized_hello",
                    f"HELLO of {length} B, more than {MAX_HELLO_BYTES} B, before HELLO",
                )
            if length > self.max_frame_bytes:
                out.append(
                    ProtocolError(
                        "oversized",
                        f"message of {length} B exceeds the {self.max_frame_bytes} B limit",
                    )
                )
                self._buf.clear()
                self._skip = length
                continue
            take = min(PREFIX.size + length - len(self._buf), len(view))
            self._buf += view[:take]
            view = view[take:]
            if len(self._buf) < PREFIX.size + length:
                break
            body = bytes(self._buf[PREFIX.size : PREFIX.size + length])
            self._buf.clear()
            if mtype not in self.accept:
                out.append(ProtocolError("unexpected_type", f"message type {mtype} skipped"))
                continue
            try:
                if mtype == MSG_FRAME:
                    out.append(decode_frame(body))
                elif mtype == MSG_HELLO:
                    out.append(decode_hello(body))
                    self.hello_first = False
                else:
                    out.append(decode_status(body))
                self.messages_out += 1
            except ProtocolError as exc:
                out.append(exc)
        return out

    def _fail(
        self, out: list[Message | ProtocolError], reason: str, detail: str
    ) -> list[Message | ProtocolError]:
        self._fatal = ProtocolError(reason, detail, fatal=True)
        self._buf.clear()
        if out:
            return out
        raise self._fatal


# ---- the receiving side: a small TCP server (ROS-free; the node only publishes) -------------


def is_loopback(address: str) -> bool:
    """True for addresses only this machine can reach (127.0.0.0/8, ::1, localhost)."""
    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


# Connections that have not sent HELLO yet. They do not count against ``max_clients`` (a port
# scan or a stuck socket must not keep the phone out); this bounds them instead, and when it is
# reached the oldest one makes room for the newest, so a phone that connects and says HELLO at
# once always gets in.
MAX_PENDING = 8
# A cause that repeats (the same bad message at 60 Hz, a client retrying a wrong token) is
# logged at once, then at most this often, with how many were held back.
LOG_REPEAT_S = 60.0


class _LogOnce:
    """First occurrence of each key now, then at most one per ``period`` s."""

    def __init__(self, period: float = LOG_REPEAT_S) -> None:
        self.period = period
        self._seen: dict[str, tuple[float, int]] = {}  # key -> (last logged, held back since)

    def __call__(self, key: str, now: float) -> int | None:
        """None: hold this one back; else how many were held back since the key's last line."""
        last, held = self._seen.get(key, (-math.inf, 0))
        if now - last < self.period:
            self._seen[key] = (last, held + 1)
            return None
        self._seen[key] = (now, 0)
        return held


# bytes that count as progress towards a message for the idle timeout, short of a whole one
IDLE_PROGRESS_BYTES = 64 * 1024


@dataclass
class _Client:
    sock: socket.socket
    addr: str
    decoder: FrameDecoder
    connected_at: float
    ident: int  # never reused, unlike id(): per-connection state keyed by it cannot leak
    last_rx: float  # monotonic time of the last progress (idle timeout): see IDLE_PROGRESS_BYTES
    rx_since: int = 0  # bytes received since last_rx was set
    authed: bool = False
    name: str = ""
    errors_in_row: int = 0  # consecutive bad messages, in stream order
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> count
    log_once: _LogOnce = field(default_factory=_LogOnce)


def _as_int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an integer, not {value!r}")
    return int(value)


def _as_seconds(name: str, value: object) -> float:
    """A timeout: finite and > 0 (NaN never expired, so a stuck client was never dropped)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.number):
        raise ValueError(f"{name} must be a number of seconds, not {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite time > 0 s, not {v}")
    return v


class BridgeServer:
    """Accepts phones over TCP, checks their token, decodes frames, hands them to ``on_frame``.

    One thread with a selector serves the listening socket and every client, so a slow or
    hostile client can at worst fill its own bounded decoder. Nothing a client sends can raise
    out of the thread, and neither can a failing ``log``: every problem becomes a log line
    (``log(level, text)``, once per cause and client, then at most every
    :data:`LOG_REPEAT_S`; the counters count them all) and, when the stream is unusable (bad
    magic/version, bad token, no HELLO in time, nothing received for ``idle_timeout_s``, too
    many bad messages in a row), the connection is closed. ``on_disconnect(client)`` is called
    when a client that had said HELLO goes. Binding beyond loopback requires a token. Bad
    settings raise ValueError here, before anything listens.
    """

    def __init__(
        self,
        on_frame: Callable[[Frame, int], None],
        log: Callable[[str, str], None],
        *,
        bind_address: str = "127.0.0.1",
        port: int = 0,
        token: str = "",
        max_clients: int = 1,
        max_frame_bytes: int = MAX_FRAME_BYTES,
        hello_timeout_s: float = 5.0,
        idle_timeout_s: float = 5.0,
        max_errors_in_row: int = 20,
        on_disconnect: Callable[[int], None] | None = None,
    ) -> None:
        if not is_loopback(bind_address) and not token:
            raise ValueError(
                f"refusing to listen on {bind_address} without a token: anyone on the network "
                "could inject depth frames; set a shared token or bind to 127.0.0.1"
            )
        port = _as_int("port", port)
        if not 0 <= port <= 65535:
            raise ValueError(f"port must be 0..65535 (0 = any free port), not {port}")
        if len(token.encode("utf-8")) > MAX_TOKEN_BYTES:
            raise ValueError(f"token is longer than {MAX_TOKEN_BYTES} B: no HELLO could carry it")
        if _as_int("max_clients", max_clients) < 1:
            raise ValueError("max_clients must be >= 1")
        max_frame_bytes = _as_int("max_frame_bytes", max_frame_bytes)
        if not MIN_FRAME_LIMIT <= max_frame_bytes <= MAX_FRAME_LIMIT:
            raise ValueError(
                f"max_frame_bytes must be {MIN_FRAME_LIMIT}..{MAX_FRAME_LIMIT} (a HELLO needs "
                f"up to {MAX_HELLO_BYTES} B, the largest valid frame is {MAX_FRAME_LIMIT} B), "
                f"not {max_frame_bytes}"
            )
        if _as_int("max_errors_in_row", max_errors_in_row) < 1:
            raise ValueError(f"max_errors_in_row must be >= 1, not {max_errors_in_row}")
        self.hello_timeout_s = _as_seconds("hello_timeout_s", hello_timeout_s)
        self.idle_timeout_s = _as_seconds("idle_timeout_s", idle_timeout_s)
        self.on_frame = on_frame
        self.on_disconnect = on_disconnect
        self.log = log
        self.bind_address = bind_address
        self.requested_port = port
        self.token = token
        self.max_clients = int(max_clients)
        self.max_frame_bytes = max_frame_bytes
        self.max_errors_in_row = int(max_errors_in_row)
        self.port = 0
        self.frames_received = 0
        self.rejected_by_reason: dict[str, int] = {}  # every rejected message, by reason
        self.clients_accepted = 0
        self.clients_refused = 0
        self.clients_timed_out = 0  # no HELLO in time, or idle after it
        # replaced, never changed in place: other threads read it
        self._clients: dict[int, _Client] = {}
        self._ids = itertools.count(1)
        self._log_once = _LogOnce()  # causes that are not one client's (refusals, probes)
        self._listener: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._sel = selectors.DefaultSelector()
        self._stop = False

    @property
    def clients(self) -> int:
        return sum(1 for c in self._clients.values() if c.authed)

    def start(self) -> None:
        family = socket.AF_INET6 if ":" in self.bind_address else socket.AF_INET
        lst = socket.socket(family, socket.SOCK_STREAM)
        try:
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            lst.bind((self.bind_address, self.requested_port))
            lst.listen(4)
        except BaseException:
            lst.close()
            raise
        lst.setblocking(False)
        self.port = int(lst.getsockname()[1])
        self._listener = lst
        self._sel.register(lst, selectors.EVENT_READ, None)
        self._thread = threading.Thread(target=self._run, name="iphone-bridge-tcp", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop = True
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for c in list(self._clients.values()):
            # said before the close: a sender then tells "the bridge stopped" from a crash
            # (stream-stray reported a clean stop as "connection reset by peer")
            self._close(c, (STATUS_SHUTDOWN, "the bridge is stopping"))
        if self._listener is not None:
            self._sel.close()
            self._listener.close()
            self._listener = None

    def _log(self, level: str, text: str) -> None:
        """``log``, which must not take the thread down: a logger that raised (rclpy refuses a
        call site that changes severity) once killed the server on its first warning, and its
        error handler, logging again, could not catch that."""
        try:
            self.log(level, text)
        except Exception as exc:
            with contextlib.suppress(Exception):
                print(f"bridge [{level}] {text} (logger failed: {exc!r})", file=sys.stderr)

    def _log_limited(self, c: _Client | None, key: str, level: str, text: str) -> None:
        held = (self._log_once if c is None else c.log_once)(key, time.monotonic())
        if held is not None:
            self._log(level, text + (f" ({held} more like it not logged)" if held else ""))

    def _run(self) -> None:
        while not self._stop:
            try:
                events = self._sel.select(timeout=0.1)
            except (OSError, ValueError):
                break  # the selector was closed: stop() is under way
            for key, _ in events:
                client: _Client | None = key.data
                if client is None:
                    self._guarded(self._accept, None)
                else:
                    self._guarded(functools.partial(self._read, client), client)
            self._guarded(self._expire, None)

    def _guarded(self, step: Callable[[], None], c: _Client | None) -> None:
        try:
            step()
        except Exception as exc:  # never let a client kill the server thread
            self._log("error", f"bridge: unexpected {type(exc).__name__}: {exc}")
            if c is not None:
                with contextlib.suppress(Exception):
                    self._close(c, None)

    def _expire(self) -> None:
        now = time.monotonic()
        for c in list(self._clients.values()):
            if not c.authed and now - c.connected_at > self.hello_timeout_s:
                self.clients_timed_out += 1
                self._log_limited(
                    None,
                    "no_hello",
                    "warn",
                    f"bridge: {c.addr} sent no HELLO in {self.hello_timeout_s} s; closing",
                )
                self._close(c, (STATUS_PROTOCOL_ERROR, "no HELLO in time"))
            elif c.authed and now - c.last_rx > self.idle_timeout_s:
                # a phone that lost Wi-Fi sends no FIN: without this it held the slot forever
                # and its reconnect was refused as busy
                self.clients_timed_out += 1
                self._log(
                    "warn",
                    f"bridge: {c.addr} ({c.name!r}) sent nothing for {self.idle_timeout_s} s; "
                    "closing (it may reconnect)",
                )
                self._close(c, (STATUS_PROTOCOL_ERROR, "idle timeout"))

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            sock, addr = self._listener.accept()
        except BlockingIOError:  # the peer gave up between select and accept
            return
        peer = f"{addr[0]}:{addr[1]}"
        pending = [c for c in self._clients.values() if not c.authed]
        if len(pending) >= MAX_PENDING:
            oldest = min(pending, key=lambda c: c.connected_at)
            self.clients_refused += 1
            self._log_limited(
                None,
                "pending",
                "warn",
                f"bridge: {MAX_PENDING} connections waiting for HELLO; "
                f"dropped the oldest, {oldest.addr}",
            )
            self._close(oldest, (STATUS_BUSY, "too many connections waiting for HELLO"))
        sock.setblocking(False)
        now = time.monotonic()
        decoder = FrameDecoder(self.max_frame_bytes, hello_first=True)
        c = _Client(sock, peer, decoder, now, next(self._ids), now)
        # a new dict, never changed in place (as _close does): the node's status timer loops
        # over it from another thread (``clients``), and an insert under that loop raised
        # "dictionary changed size during iteration" out of the timer and ended the node
        self._clients = {**self._clients, sock.fileno(): c}
        self._sel.register(sock, selectors.EVENT_READ, c)
        self._log("info", f"bridge: connection from {peer}")

    def _send(self, c: _Client, data: bytes) -> None:
        sock = c.sock
        try:
            sock.settimeout(1.0)
            sock.sendall(data)
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                sock.setblocking(False)

    def _close(self, c: _Client, status: tuple[int, str] | None) -> None:
        if not any(v is c for v in self._clients.values()):
            return  # already closed
        if status is not None:
            self._send(c, encode_status(*status))
        with contextlib.suppress(KeyError, ValueError, OSError):
            self._sel.unregister(c.sock)
        with contextlib.suppress(OSError):
            c.sock.close()
        if c.rejected:
            counts = ", ".join(f"{r} x{n}" for r, n in sorted(c.rejected.items()))
            self._log("info", f"bridge: {c.addr} ({c.name or 'unnamed'}) had rejected: {counts}")
        if c.authed and self.on_disconnect is not None:
            try:
                self.on_disconnect(c.ident)
            except Exception as exc:
                self._log("error", f"bridge: disconnect hook failed: {exc}")
        # Last: `clients` drops only once the summary is logged and the hook has run, so a
        # caller that waits for it to drop sees everything about the client that left.
        self._clients = {k: v for k, v in self._clients.items() if v is not c}

    def _read(self, c: _Client) -> None:
        try:
            data = c.sock.recv(1 << 16)
        except BlockingIOError:
            return
        except OSError as exc:
            # a reset (the app killed with a STATUS unread) loses a frame begun as surely as
            # a clean close does, and said so only there
            partial = c.decoder.buffered
            lost = f", {partial} B of an unfinished message (a frame) dropped" if partial else ""
            self._log("warn", f"bridge: {c.addr} read failed ({exc}){lost}; closing")
            self._close(c, None)
            return
        if not data:
            partial = c.decoder.buffered
            if partial:  # Wi-Fi gone or the app killed half-way: the frame is lost, and said
                self._log(
                    "warn",
                    f"bridge: {c.addr} ({c.name or 'unnamed'}) disconnected mid-message: "
                    f"{partial} B of an unfinished message (a frame) dropped",
                )
            else:
                self._log("info", f"bridge: {c.addr} ({c.name or 'unnamed'}) disconnected")
            self._close(c, None)
            return
        try:
            items = c.decoder.feed_ordered(data)
        except ProtocolError as exc:
            self._unusable(c, exc)
            return
        # Progress, not any byte, keeps a client: a whole message, or IDLE_PROGRESS_BYTES of
        # one (a big frame on slow Wi-Fi). A byte every few seconds held the only slot, and
        # the phone was refused as busy.
        c.rx_since += len(data)
        if items or c.rx_since >= IDLE_PROGRESS_BYTES:
            c.last_rx = time.monotonic()
            c.rx_since = 0
        for item in items:
            if isinstance(item, ProtocolError):
                ok = self._rejected(c, item)
            elif isinstance(item, Hello):
                ok = self._hello(c, item)
            elif isinstance(item, Frame):
                ok = self._frame(c, item)
            else:
                ok = True
            if not ok:
                return  # closed
        if c.decoder.fatal is not None:  # after the good messages before it
            self._unusable(c, c.decoder.fatal)

    @property
    def messages_rejected(self) -> int:
        # a copy first: the node reads this from its own thread while the server counts
        return sum(self.rejected_by_reason.copy().values())

    def _count_rejected(self, reason: str) -> None:
        self.rejected_by_reason[reason] = self.rejected_by_reason.get(reason, 0) + 1

    def _unusable(self, c: _Client, exc: ProtocolError) -> None:
        self._count_rejected(exc.reason)
        self._log_limited(
            None,
            f"fatal:{exc.reason}",
            "error",
            f"bridge: {c.addr} sent an unusable stream ({exc}); closing",
        )
        self._close(c, (STATUS_PROTOCOL_ERROR, str(exc)))

    def _rejected(self, c: _Client, err: ProtocolError) -> bool:
        self._count_rejected(err.reason)
        c.rejected[err.reason] = c.rejected.get(err.reason, 0) + 1
        c.errors_in_row += 1
        self._log_limited(c, err.reason, "warn", f"bridge: {c.addr} message rejected: {err}")
        if c.errors_in_row > self.max_errors_in_row:
            self._log(
                "error", f"bridge: {c.addr}: {c.errors_in_row} bad messages in a row; closing"
            )
            self._close(c, (STATUS_PROTOCOL_ERROR, "too many bad messages"))
            return False
        return True

    def _hello(self, c: _Client, m: Hello) -> bool:
        if c.authed:
            return True
        if self.token and not hmac.compare_digest(m.token.encode(), self.token.encode()):
            self.clients_refused += 1
            self._log_limited(
                None,
                "bad_token",
                "warn",
                f"bridge: {c.addr} ({m.name!r}) gave a wrong token; closing",
            )
            self._close(c, (STATUS_BAD_TOKEN, "wrong token"))
            return False
        if self.clients >= self.max_clients:
            self.clients_refused += 1
            self._log_limited(
                None,
                "busy",
                "warn",
                f"bridge: refused {c.addr} ({m.name!r}): {self.max_clients} client(s) already",
            )
            self._close(c, (STATUS_BUSY, "another client is connected"))
            return False
        c.authed, c.name = True, m.name
        self.clients_accepted += 1
        self._log("info", f"bridge: {c.addr} accepted as {m.name!r}")
        self._send(c, encode_status(STATUS_OK, "ok"))
        return True

    def _frame(self, c: _Client, m: Frame) -> bool:
        if not c.authed:
            self._log_limited(
                None, "frame_first", "warn", f"bridge: {c.addr} sent a frame before HELLO; closing"
            )
            self._close(c, (STATUS_PROTOCOL_ERROR, "HELLO first"))
            return False
        c.errors_in_row = 0
        self.frames_received += 1
        try:
            self.on_frame(m, c.ident)
        except Exception as exc:
            self._log_limited(
                c,
                f"publish:{type(exc).__name__}",
                "error",
                f"bridge: frame {m.seq} not published: {exc}",
            )
        return True


def parting_status(sock: socket.socket, timeout: float = 1.0) -> Status | None:
    """The STATUS a bridge sent before it closed a sender's connection (stopping, idle timeout,
    a protocol error), read after a send failed: None where it sent none (it crashed, or the
    network went). Linux keeps bytes received before the peer's reset readable."""
    dec = FrameDecoder(accept=(MSG_STATUS,))
    last: Status | None = None
    deadline = time.monotonic() + timeout
    with contextlib.suppress(OSError, ProtocolError):
        while (left := deadline - time.monotonic()) > 0:
            sock.settimeout(left)
            data = sock.recv(4096)
            if not data:
                break
            for m in dec.feed(data):
                if isinstance(m, Status) and m.code != STATUS_OK:
                    last = m
    return last


def status_words(status: Status) -> str:
    return f"{status.text} (status {STATUS_NAMES.get(status.code, status.code)})"


def connect(
    host: str, port: int, token: str = "", name: str = "", timeout: float = 5.0
) -> socket.socket:
    """Open a sender connection: HELLO, then wait for the bridge's STATUS; ConnectionError if
    it refuses (the text says why: busy, wrong token). Returns the connected socket."""
    sock = socket.create_connection((host, port), timeout=timeout)
    try:
        sock.sendall(encode_hello(token, name))
        dec = FrameDecoder(accept=(MSG_STATUS,))
        while True:
            data = sock.recv(4096)
            if not data:
                raise ConnectionError(f"{host}:{port} closed the connection without a status")
            try:
                got = dec.feed(data)
            except ProtocolError as exc:  # an HTTP server, an SSH port: a user's wrong --to
                raise ConnectionError(
                    f"{host}:{port} does not answer as a wheelgrid bridge ({exc})"
                ) from None
            for m in got:
                assert isinstance(m, Status)
                if m.code != STATUS_OK:
                    raise ConnectionError(f"{host}:{port} refused: {m.text} (status {m.code})")
                sock.settimeout(None)
                return sock
    except BaseException:
        sock.close()
        raise
