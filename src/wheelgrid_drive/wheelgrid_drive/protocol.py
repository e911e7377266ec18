"""The wheelgrid motor-controller serial protocol (docs/serial-protocol.md), ROS-free.

Both ends use this module: the host link (link.py) and the simulated controller (motor_sim.py),
so a change to the wire format is one change. Every frame is::

    SOF(0xA5) LEN SEQ TYPE PAYLOAD[LEN] CRC16_HI CRC16_LO

CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over LEN..PAYLOAD. A reply carries the SEQ of the
request it answers. The decoder resynchronises on the next SOF after any damage and REPORTS the
damage (a :class:`DecodeError` item) instead of silently skipping it: the link must treat a
garbled reply as a failure, never ignore it.
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass
from enum import IntEnum

SOF = 0xA5
MAX_PAYLOAD = 64
HEADER_LEN = 4  # SOF LEN SEQ TYPE
FRAME_OVERHEAD = HEADER_LEN + 2

# Hard speed cap, enforced by the host (clamp) AND the controller (NAK): the paper drives the
# chair at 3 km/h "to match the system's processing performance"; nothing here may go faster.
MAX_SPEED_KMH = 3.0
MAX_SPEED_MM_S = int(MAX_SPEED_KMH / 3.6 * 1000.0)  # 833
MIN_SPEED_KMH = 0.1  # slower, a cell's move cannot end within the link's move timeout
MAX_DISTANCE_MM = 2000  # one grid cell is at most 2 m; anything longer is a corrupt command
MAX_POSE_M = 1_000_000.0  # |x|, |y| a SET_POSE may set: int32 mm holds 2147 km, with room to drive
DEFAULT_HEARTBEAT_TIMEOUT_S = 0.5
# A frame begun and not finished after this long with no byte arriving never will be: every
# frame is written whole (70 bytes at most, 6 ms at 115200 baud; a USB adapter's latency timer
# may pause a frame 16 ms). A stray SOF followed by a small LEN held every frame behind it,
# the e-stop's STOP too, until enough bytes came to fail the CRC (100-400 ms, up to 34 cm).
FRAME_GAP_S = 0.05


class MsgType(IntEnum):
    """Frame types. Host -> controller below 0x80, controller -> host from 0x80."""

    HEARTBEAT = 0x01  # reply STATUS; any valid frame also feeds the controller's watchdog
    STOP = 0x02  # reply ACK; motors stop at once, the running move ends as STOPPED
    STATUS_REQ = 0x03  # reply STATUS
    SET_POSE = 0x04  # payload POSE; reply ACK (NAK BUSY while moving)
    FORWARD = 0x10  # payload MOVE; reply ACK when accepted (not when finished)
    BACKWARD = 0x11
    LEFT_FORWARD = 0x12  # turn 90 deg counter-clockwise in place, then forward
    RIGHT_FORWARD = 0x13  # turn 90 deg clockwise in place, then forward
    ACK = 0x80  # payload: acknowledged TYPE (u8)
    NAK = 0x81  # payload: refused TYPE (u8), reason (u8)
    STATUS = 0x82  # payload STATUS


MOVE_TYPES = {
    "FORWARD": MsgType.FORWARD,
    "BACKWARD": MsgType.BACKWARD,
    "LEFT_FORWARD": MsgType.LEFT_FORWARD,
    "RIGHT_FORWARD": MsgType.RIGHT_FORWARD,
}
MOVE_NAMES = {v: k for k, v in MOVE_TYPES.items()}


class Nak(IntEnum):
    """Why the controller refused a (CRC-valid) frame."""

    BAD_LENGTH = 1
    UNKNOWN_TYPE = 2
    BUSY = 3  # a move is running: the host must wait for it (or STOP) first
    SPEED_OVER_CAP = 4
    BAD_DISTANCE = 5
    BAD_POSE = 6  # SET_POSE beyond MAX_POSE_M: the int32 mm STATUS pose could not report it


class State(IntEnum):
    IDLE = 0
    TURNING = 1
    DRIVING = 2


class Result(IntEnum):
    """Outcome of the last accepted move."""

    NONE = 0
    RUNNING = 1
    DONE = 2
    STOPPED = 3  # ended by a STOP frame
    WATCHDOG = 4  # ended by the controller itself: heartbeats stopped


FLAG_WATCHDOG = 0x01  # the heartbeat watchdog has stopped the motors (latched until next move)
FLAG_STOPPED = 0x02  # a STOP frame stopped the motors (latched until next move)

_MOVE = struct.Struct(">HH")  # distance mm, speed mm/s
_POSE = struct.Struct(">iii")  # x mm, y mm, yaw mrad
_STATUS = struct.Struct(">iiiBBBBH")  # x, y, yaw, state, last move seq, result, flags, rx errors


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (check value of b"123456789" is 0x29B1)."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


@dataclass(frozen=True)
class Frame:
    seq: int
    type: int
    payload: bytes = b""

    def encode(self) -> bytes:
        return encode(self.seq, self.type, self.payload)

    @property
    def type_name(self) -> str:
        try:
            return MsgType(self.type).name
        except ValueError:
            return f"0x{self.type:02X}"


@dataclass(frozen=True)
class DecodeError:
    """Damaged bytes on the wire: what was wrong and how many bytes were thrown away."""

    reason: str
    dropped: int


def encode(seq: int, mtype: int, payload: bytes = b"") -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes([len(payload), seq & 0xFF, int(mtype) & 0xFF]) + payload
    crc = crc16(body)
    return bytes([SOF]) + body + bytes([crc >> 8, crc & 0xFF])


class FrameDecoder:
    """Streaming decoder: feed raw bytes, get frames and decode errors in arrival order.

    A reader feeds it on every pass, with ``b""`` when nothing came, so that a frame cut off
    (``gap_s`` without a byte) is given up and the frames held behind it come out."""

    def __init__(self, gap_s: float = FRAME_GAP_S) -> None:
        self._buf = bytearray()
        self.gap_s = gap_s
        self._last_byte = 0.0  # monotonic time the newest held byte arrived

    def feed(self, data: bytes, now: float | None = None) -> list[Frame | DecodeError]:
        now = time.monotonic() if now is None else now
        out: list[Frame | DecodeError] = []
        if data:
            self._last_byte = now
            self._buf.extend(data)
            out.extend(self._scan())
        elif self._buf and now - self._last_byte >= self.gap_s:
            # Only on a read that found nothing: bytes a busy reader fetched late are the rest
            # of the frame, not a gap. Every byte held is older than the gap: drop each
            # unfinished frame's SOF in turn, as for a bad LEN (a real frame may start inside
            # it), until nothing is held.
            while self._buf:
                del self._buf[:1]
                out.append(DecodeError(f"frame cut off (no byte for {self.gap_s * 1e3:.0f} ms)", 1))
                out.extend(self._scan())
        return _merge_errors(out)

    def _scan(self) -> list[Frame | DecodeError]:
        out: list[Frame | DecodeError] = []
        buf = self._buf
        while buf:
            if buf[0] != SOF:
                idx = buf.find(bytes([SOF]))
                n = len(buf) if idx < 0 else idx
                del buf[:n]
                out.append(DecodeError("bytes outside a frame", n))
                continue
            if len(buf) < 2:
                break
            length = buf[1]
            if length > MAX_PAYLOAD:
                del buf[:1]
                out.append(DecodeError(f"length {length} > {MAX_PAYLOAD}", 1))
                continue
            total = FRAME_OVERHEAD + length
            if len(buf) < total:
                break
            body = bytes(buf[1 : HEADER_LEN + length])
            got = (buf[total - 2] << 8) | buf[total - 1]
            if crc16(body) != got:
                # Drop only the SOF: a real frame may start inside the damaged bytes.
                del buf[:1]
                out.append(DecodeError("CRC mismatch", 1))
                continue
            out.append(Frame(seq=buf[2], type=buf[3], payload=bytes(buf[4 : 4 + length])))
            del buf[:total]
        return out

    def pending(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)


def _merge_errors(items: list[Frame | DecodeError]) -> list[Frame | DecodeError]:
    """One damaged frame is one error, however many resync steps it took to skip it."""
    out: list[Frame | DecodeError] = []
    for item in items:
        prev = out[-1] if out else None
        if isinstance(item, DecodeError) and isinstance(prev, DecodeError):
            out[-1] = DecodeError(prev.reason, prev.dropped + item.dropped)
        else:
            out.append(item)
    return out


# ---- payloads --------------------------------------------------------------------------------


def kmh_to_mm_s(speed_kmh: float) -> int:
    """km/h -> protocol mm/s, clamped to the hard cap (never rounds up past it)."""
    if not math.isfinite(speed_kmh) or speed_kmh <= 0:
        raise ValueError(f"speed must be a positive number of km/h, got {speed_kmh!r}")
    return max(1, min(MAX_SPEED_MM_S, int(speed_kmh / 3.6 * 1000.0)))


def move_length_problem(distance_m: float, what: str = "cell size") -> str | None:
    """Why one MOVE cannot drive ``distance_m`` (m), else None: the frame carries whole
    millimetres up to MAX_DISTANCE_MM. Checked where a length comes in (a grid's cells, a
    step to a cell's centre) so it is refused there by name; at :func:`pack_move` it was a
    ValueError the runner did not expect (the drive node retried it every 50 ms)."""
    if not (math.isfinite(distance_m) and 1 <= round(distance_m * 1000) <= MAX_DISTANCE_MM):
        return (
            f"{what} {distance_m:g} m outside [0.001, {MAX_DISTANCE_MM / 1000:g}] m, the "
            "longest move the motor controller takes"
        )
    return None


def pack_move(distance_m: float, speed_kmh: float) -> bytes:
    if problem := move_length_problem(distance_m, "distance"):
        raise ValueError(problem)
    return _MOVE.pack(round(distance_m * 1000.0), kmh_to_mm_s(speed_kmh))


def unpack_move(payload: bytes) -> tuple[int, int]:
    """(distance mm, speed mm/s); struct.error if the length is wrong."""
    d, s = _MOVE.unpack(payload)
    return int(d), int(s)


def pack_pose(x: float, y: float, yaw: float) -> bytes:
    """``ValueError`` for a pose the controller could not hold (beyond ``MAX_POSE_M``, NaN),
    where ``struct`` raised its own error from deep inside a run."""
    if not (abs(x) <= MAX_POSE_M and abs(y) <= MAX_POSE_M and math.isfinite(yaw)):
        raise ValueError(f"pose ({x}, {y}, {yaw}) outside +-{MAX_POSE_M:g} m or not finite")
    yaw = math.atan2(math.sin(yaw), math.cos(yaw))
    return _POSE.pack(round(x * 1000.0), round(y * 1000.0), round(yaw * 1000.0))


def unpack_pose(payload: bytes) -> tuple[float, float, float]:
    x, y, yaw = _POSE.unpack(payload)
    return x / 1000.0, y / 1000.0, yaw / 1000.0


@dataclass(frozen=True)
class Status:
    """The controller's report: pose (its odometry), motion state and the last move's fate."""

    x: float
    y: float
    yaw: float
    state: State
    last_seq: int
    result: Result
    flags: int
    rx_errors: int

    @property
    def moving(self) -> bool:
        return self.state != State.IDLE

    @property
    def watchdog_tripped(self) -> bool:
        return bool(self.flags & FLAG_WATCHDOG)


def pack_status(s: Status) -> bytes:
    return _STATUS.pack(
        round(s.x * 1000.0),
        round(s.y * 1000.0),
        round(math.atan2(math.sin(s.yaw), math.cos(s.yaw)) * 1000.0),
        int(s.state),
        s.last_seq & 0xFF,
        int(s.result),
        s.flags & 0xFF,
        min(s.rx_errors, 0xFFFF),
    )


def unpack_status(payload: bytes) -> Status:
    """Parse a STATUS payload; ValueError on a wrong length or out-of-range enum."""
    try:
        x, y, yaw, state, seq, result, flags, errs = _STATUS.unpack(payload)
        return Status(
            x / 1000.0, y / 1000.0, yaw / 1000.0, State(state), seq, Result(result), flags, errs
        )
    except (struct.error, ValueError) as exc:
        raise ValueError(f"bad STATUS payload ({len(payload)} bytes): {exc}") from exc
