"""A simulated wheelchair motor controller speaking docs/serial-protocol.md on a pty.

Why a simulator rather than a mock: the host link must be exercised over a real tty (pyserial,
termios, a device that can vanish), against a controller that enforces the protocol's safety
rules itself -- above all, the heartbeat watchdog that stops the motors when the host dies.
The kinematic model is deliberately simple (turn in place at a fixed rate, then drive straight
at the commanded speed, optional Gaussian noise) but it reports a pose, so tests and the demo can
compare the actual path with the planned one (the paper's Fig. 14d).

It runs as a thread (:class:`MotorSim`, for tests) or as ``wheelgrid-motor-sim`` /
``wheelgrid motor-sim`` (:func:`main`). Faults on demand: drop, corrupt or delay frames, and
vanish (close the pty, as an unplugged USB adapter would).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import random
import select
import signal
import stat
import sys
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from wheelgrid_common.params import DefaultsHelpFormatter
from wheelgrid_drive import protocol as proto

_DEFAULT_POSE = (0.0, 0.0, 0.0)


#: Events the simulator keeps (the newest; between this and twice as many).
MAX_EVENTS = 100_000


@dataclass
class MotorSimConfig:
    """Simulator settings; every one is also a command-line flag of ``wheelgrid motor-sim``."""

    heartbeat_timeout: float = proto.DEFAULT_HEARTBEAT_TIMEOUT_S  # s without a valid frame -> stop
    turn_rate_deg_s: float = 60.0  # in-place turn rate of a chair (deg/s)
    time_scale: float = 1.0  # >1 runs the kinematics faster than real time (tests); not watchdog
    noise_m: float = 0.0  # std dev of each move's distance error (m)
    noise_deg: float = 0.0  # std dev of each turn's angle error (deg)
    seed: int = 0
    drop: float = 0.0  # probability of losing a frame, each direction
    corrupt: float = 0.0  # probability of damaging a frame, each direction
    delay: float = 0.0  # extra seconds before each reply
    tick: float = 0.005  # loop period (s): watchdog and kinematics resolution
    pose: tuple[float, float, float] = _DEFAULT_POSE  # initial x, y (m), yaw (rad)
    link: str | None = None  # create this symlink to the pty slave
    pose_log: str | None = None  # write the pose track here (CSV)


@dataclass
class _Segment:
    kind: str  # "turn" (value = signed rad) or "drive" (value = signed m)
    remaining: float
    sign: float


@dataclass
class SimEvent:
    """Something the controller did, with its monotonic time (for tests and the benchmark)."""

    t: float
    what: str  # "rx", "stop", "watchdog", "move", "nak", "rx_error", "done"
    seq: int = -1
    detail: str = ""


@dataclass
class _Pending:
    due: float
    data: bytes


def _absent_or_symlink(path: Path) -> bool:
    """One lstat: asked as "exists?" then "a symlink?", an old link removed in between (the
    simulator it belonged to stopping as a new one starts) read as a file, and the new one
    refused to start."""
    try:
        return stat.S_ISLNK(os.lstat(path).st_mode)
    except FileNotFoundError:
        return True


class MotorSim:
    """The simulated controller. ``start()`` opens the pty and the thread; ``stop()`` ends both."""

    def __init__(self, cfg: MotorSimConfig | None = None) -> None:
        self.cfg = cfg or MotorSimConfig()
        self.x, self.y, self.yaw = self.cfg.pose
        self.state = proto.State.IDLE
        self.result = proto.Result.NONE
        self.last_seq = 0
        self.flags = 0
        self.rx_errors = 0
        self.speed = 0.0  # m/s of the running move
        self.events: list[SimEvent] = []
        self.drop_rx_next = 0  # lose the next N received frames
        self.drop_tx_next = 0  # lose the next N replies
        self.corrupt_tx_next = 0  # damage the next N replies
        self.drop_stop_next = 0  # lose the next N STOP frames (a wire that garbles just those)
        self.drop_move_next = 0  # lose the next N move frames (FORWARD, LEFT_FORWARD, ...)
        self._segments: list[_Segment] = []
        # the last accepted move (seq, type, payload, reply): the only one a retry can repeat
        self._last_move: tuple[int, int, bytes, bytes] | None = None
        self._rng = random.Random(self.cfg.seed)
        self._decoder = proto.FrameDecoder()
        self._outbox: list[_Pending] = []
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self.slave_path = ""
        self._last_rx = time.monotonic()
        self._last_tick = time.monotonic()
        self._t0 = time.monotonic()
        self._log: TextIO | None = None
        self._last_log = -1.0

    # ---- life cycle ---------------------------------------------------------------------------

    def start(self) -> MotorSim:
        """Open the pty (and the pose log, the link) and start the thread. ``ValueError`` when
        ``link`` names something that is not a symlink: only an old link is replaced, never a
        file that happens to have the name (it used to be deleted)."""
        link = Path(self.cfg.link) if self.cfg.link else None
        if link is not None and not _absent_or_symlink(link):
            raise ValueError(f"--link {link}: exists and is not a symlink; not replaced")
        if self.cfg.pose_log:  # before the pty and the link: nothing to undo if it fails
            self._log = open(self.cfg.pose_log, "w", encoding="utf-8")  # noqa: SIM115
            self._log.write("t,x,y,yaw,state,result,last_seq\n")
        self._master, self._slave = os.openpty()
        # Raw mode at once: a cooked pty echoes and rewrites bytes before any client configures it.
        tty.setraw(self._slave)
        self.slave_path = os.ttyname(self._slave)
        if link is not None:
            try:
                with contextlib.suppress(FileNotFoundError):
                    link.unlink()
                link.symlink_to(self.slave_path)
            except OSError as exc:  # a folder that is not there: said as the pty's failure
                self.stop()
                raise ValueError(f"--link {link}: cannot make it: {exc.strerror}") from None
        self._last_rx = self._last_tick = self._t0 = time.monotonic()
        self._log_pose(force=True)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="motor-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """End the thread and release the pty (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        self._close_pty()
        if self._log is not None:
            self._log_pose(force=True)
            self._log.close()
            self._log = None

    def vanish(self) -> None:
        """Disappear like an unplugged adapter: the pty closes, the link path goes away."""
        with self._lock:
            self._halt(proto.Result.STOPPED, "vanished")
        self.stop()

    def __enter__(self) -> MotorSim:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _close_pty(self) -> None:
        # The link first, while this pty still holds its number: closed first, the number was
        # free for the next simulator's pty (one started as this one vanished), whose link to
        # the same /dev/pts/N then read as this one's and was removed, and the host never
        # found the controller again.
        if self.cfg.link and self._slave >= 0:  # (held: not closed before)
            link = Path(self.cfg.link)
            with contextlib.suppress(OSError):
                if link.is_symlink() and os.readlink(link) == self.slave_path:
                    link.unlink()
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    # ---- main loop ----------------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], self.cfg.tick)
            except (OSError, ValueError):
                break
            now = time.monotonic()
            data = b""
            if ready:
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    data = b""
            with self._lock:  # fed on every pass: a frame cut off is given up in time
                for item in self._decoder.feed(data, now):
                    self._handle(item, now)
            with self._lock:
                self._integrate(now)
                self._watchdog(now)
                self._flush(time.monotonic())  # replies go out in this pass unless delayed
                self._log_pose()

    def _flush(self, now: float) -> None:
        due = [p for p in self._outbox if p.due <= now]
        if not due:
            return
        self._outbox = [p for p in self._outbox if p.due > now]
        for p in due:
            with contextlib.suppress(OSError):
                os.write(self._master, p.data)

    def _send(self, seq: int, mtype: proto.MsgType, payload: bytes = b"") -> bytes:
        data = proto.encode(seq, mtype, payload)
        self._queue(data)
        return data

    def _queue(self, data: bytes) -> None:
        if self.drop_tx_next > 0:
            self.drop_tx_next -= 1
            return
        if self.cfg.drop and self._rng.random() < self.cfg.drop:
            return
        if self.corrupt_tx_next > 0 or (self.cfg.corrupt and self._rng.random() < self.cfg.corrupt):
            self.corrupt_tx_next = max(0, self.corrupt_tx_next - 1)
            damaged = bytearray(data)
            damaged[-3] ^= 0x5A  # a byte inside the CRC-covered body: the CRC must catch it
            data = bytes(damaged)
        self._outbox.append(_Pending(time.monotonic() + self.cfg.delay, data))

    def _event(self, what: str, seq: int = -1, detail: str = "", t: float | None = None) -> None:
        self.events.append(SimEvent(time.monotonic() if t is None else t, what, seq, detail))
        if len(self.events) > 2 * MAX_EVENTS:
            # the oldest half goes: every frame (each heartbeat) was kept for ever, ~5 MB an
            # hour for a simulator left running (a review); a list trimmed in place, so a
            # reader iterating it meanwhile never fails, as a deque's iterator would
            del self.events[:MAX_EVENTS]

    # ---- protocol -----------------------------------------------------------------------------

    def _handle(self, item: proto.Frame | proto.DecodeError, now: float) -> None:
        if isinstance(item, proto.DecodeError):
            self.rx_errors += 1
            self._event("rx_error", detail=item.reason, t=now)
            return
        if self.drop_rx_next > 0:
            self.drop_rx_next -= 1
            return
        if self.drop_stop_next > 0 and item.type == proto.MsgType.STOP:
            self.drop_stop_next -= 1
            return
        if self.drop_move_next > 0 and item.type in proto.MOVE_NAMES:
            self.drop_move_next -= 1
            return
        if self.cfg.drop and self._rng.random() < self.cfg.drop:
            return
        if self.cfg.corrupt and self._rng.random() < self.cfg.corrupt:
            self.rx_errors += 1  # damaged on the wire: the CRC would have rejected it
            self._event("rx_error", detail="injected corruption", t=now)
            return
        self._last_rx = now
        f = item
        self._event("rx", f.seq, f.type_name, t=now)
        t = f.type
        if t in (proto.MsgType.HEARTBEAT, proto.MsgType.STATUS_REQ):
            self._send(f.seq, proto.MsgType.STATUS, proto.pack_status(self.status()))
        elif t == proto.MsgType.STOP:
            self._halt(proto.Result.STOPPED, "STOP frame", t=now)
            self.flags |= proto.FLAG_STOPPED
            self._send(f.seq, proto.MsgType.ACK, bytes([t]))
        elif t == proto.MsgType.SET_POSE:
            if len(f.payload) != 12:
                self._nak(f, proto.Nak.BAD_LENGTH)
            elif self.state != proto.State.IDLE:
                self._nak(f, proto.Nak.BUSY)
            elif max(map(abs, proto.unpack_pose(f.payload)[:2])) > proto.MAX_POSE_M:
                self._nak(f, proto.Nak.BAD_POSE)  # STATUS could not report it after a move
            else:
                self.x, self.y, self.yaw = proto.unpack_pose(f.payload)
                self._log_pose(force=True)
                self._send(f.seq, proto.MsgType.ACK, bytes([t]))
        elif t in proto.MOVE_NAMES:
            self._move(f, now)
        else:
            self._nak(f, proto.Nak.UNKNOWN_TYPE)

    def _nak(self, f: proto.Frame, reason: proto.Nak) -> None:
        self._event("nak", f.seq, reason.name)
        self._send(f.seq, proto.MsgType.NAK, bytes([f.type & 0xFF, int(reason)]))

    def _move(self, f: proto.Frame, now: float) -> None:
        cached = self._last_move
        if cached is not None and cached[:3] == (f.seq, f.type, f.payload):
            # A retry of the move just handled (its reply was lost): answer again, never
            # execute twice -- a duplicated FORWARD would drive the chair one cell too far.
            # Only the LAST move can be retried (the host waits for each move), so an older
            # move whose SEQ came round again after the 256-value wrap is never mistaken.
            self._queue(cached[3])
            return
        if len(f.payload) != 4:
            self._nak(f, proto.Nak.BAD_LENGTH)
            return
        dist_mm, speed_mm_s = proto.unpack_move(f.payload)
        if speed_mm_s == 0 or speed_mm_s > proto.MAX_SPEED_MM_S:
            self._nak(f, proto.Nak.SPEED_OVER_CAP)
            return
        if not 0 < dist_mm <= proto.MAX_DISTANCE_MM:
            self._nak(f, proto.Nak.BAD_DISTANCE)
            return
        if self.state != proto.State.IDLE:
            self._nak(f, proto.Nak.BUSY)
            return
        name = proto.MOVE_NAMES[proto.MsgType(f.type)]
        dist = dist_mm / 1000.0
        if self.cfg.noise_m:
            dist += self._rng.gauss(0.0, self.cfg.noise_m)
        turn_err = 0.0
        if self.cfg.noise_deg:
            turn_err = math.radians(self._rng.gauss(0.0, self.cfg.noise_deg))
        segs: list[_Segment] = []
        if name == "LEFT_FORWARD":
            segs.append(_Segment("turn", abs(math.pi / 2 + turn_err), 1.0))
        elif name == "RIGHT_FORWARD":
            segs.append(_Segment("turn", abs(math.pi / 2 + turn_err), -1.0))
        segs.append(_Segment("drive", max(dist, 0.0), -1.0 if name == "BACKWARD" else 1.0))
        self._segments = segs
        self.speed = speed_mm_s / 1000.0
        self.state = proto.State.TURNING if segs[0].kind == "turn" else proto.State.DRIVING
        self.result = proto.Result.RUNNING
        self.last_seq = f.seq
        self.flags = 0
        self._last_tick = now
        self._event("move", f.seq, name, t=now)
        reply = self._send(f.seq, proto.MsgType.ACK, bytes([f.type]))
        self._last_move = (f.seq, f.type, f.payload, reply)
        self._log_pose(force=True)

    def status(self) -> proto.Status:
        with self._lock:
            return proto.Status(
                self.x,
                self.y,
                self.yaw,
                self.state,
                self.last_seq,
                self.result,
                self.flags,
                self.rx_errors,
            )

    # ---- physics and safety -------------------------------------------------------------------

    def _halt(self, result: proto.Result, why: str, t: float | None = None) -> None:
        was_moving = self.state != proto.State.IDLE
        self._segments = []
        self.state = proto.State.IDLE
        if was_moving:
            self.result = result
        self._event("stop", self.last_seq, why, t=t)
        self._log_pose(force=True)

    def _watchdog(self, now: float) -> None:
        silent = now - self._last_rx
        if self.state != proto.State.IDLE and silent > self.cfg.heartbeat_timeout:
            self._halt(proto.Result.WATCHDOG, f"no valid frame for {silent:.3f} s", t=now)
            self.flags |= proto.FLAG_WATCHDOG
            # to the microsecond: at 0.1 ms a silence just past the timeout read as equal to it
            self._event("watchdog", self.last_seq, f"{silent:.6f}", t=now)

    def _integrate(self, now: float) -> None:
        dt = (now - self._last_tick) * self.cfg.time_scale
        self._last_tick = now
        while self._segments and dt > 0:
            seg = self._segments[0]
            if seg.kind == "turn":
                rate = math.radians(self.cfg.turn_rate_deg_s)
                step = min(seg.remaining, rate * dt)
                self.yaw = math.atan2(
                    math.sin(self.yaw + seg.sign * step), math.cos(self.yaw + seg.sign * step)
                )
                used = step / rate
            else:
                step = min(seg.remaining, self.speed * dt)
                self.x += seg.sign * step * math.cos(self.yaw)
                self.y += seg.sign * step * math.sin(self.yaw)
                used = step / self.speed if self.speed > 0 else dt
            seg.remaining -= step
            dt -= used
            if seg.remaining <= 1e-9:
                self._segments.pop(0)
                if self._segments:
                    self.state = proto.State.DRIVING
                else:
                    self.state = proto.State.IDLE
                    self.result = proto.Result.DONE
                    self._event("done", self.last_seq, t=now)
                    self._log_pose(force=True)

    def _log_pose(self, force: bool = False) -> None:
        if self._log is None:
            return
        t = time.monotonic() - self._t0
        if not force and (self.state == proto.State.IDLE or t - self._last_log < 0.05):
            return
        self._last_log = t
        self._log.write(
            f"{t:.3f},{self.x:.4f},{self.y:.4f},{self.yaw:.4f},"
            f"{self.state.name},{self.result.name},{self.last_seq}\n"
        )
        self._log.flush()


# ---- command line ----------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wheelgrid motor-sim",
        description="Simulated wheelchair motor controller on a pty (docs/serial-protocol.md). "
        "Prints the pty device path; Ctrl-C ends it.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("--link", help="create this symlink to the pty slave (a stable port name)")
    p.add_argument("--pose-log", help="write the pose track (t,x,y,yaw,...) to this CSV")
    p.add_argument("--x", type=float, default=0.0, help="initial x (m)")
    p.add_argument("--y", type=float, default=0.0, help="initial y (m)")
    p.add_argument("--yaw", type=float, default=0.0, help="initial yaw (rad, 0 = +x)")
    p.add_argument(
        "--heartbeat-timeout",
        type=float,
        default=proto.DEFAULT_HEARTBEAT_TIMEOUT_S,
        help="stop the motors after this long without a valid frame (s)",
    )
    p.add_argument("--turn-rate", type=float, default=60.0, help="in-place turn rate (deg/s)")
    p.add_argument("--time-scale", type=float, default=1.0, help="kinematics speed-up factor")
    p.add_argument("--noise", type=float, default=0.0, help="distance noise std dev (m)")
    p.add_argument("--noise-deg", type=float, default=0.0, help="turn noise std dev (deg)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise, loss and damage")
    p.add_argument("--drop", type=float, default=0.0, help="frame loss probability")
    p.add_argument("--corrupt", type=float, default=0.0, help="frame damage probability")
    p.add_argument("--delay", type=float, default=0.0, help="reply delay (s)")
    p.add_argument("--vanish-after", type=float, default=0.0, help="close the pty after S seconds")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    floats = ("x", "y", "yaw", "heartbeat_timeout", "turn_rate", "time_scale", "noise")
    for name in (*floats, "noise_deg", "drop", "corrupt", "delay", "vanish_after"):
        if not math.isfinite(getattr(args, name)):  # a NaN timeout switched the watchdog off
            flag = name.replace("_", "-")
            print(f"wheelgrid motor-sim: --{flag} must be finite", file=sys.stderr)
            return 2
    for name in ("heartbeat_timeout", "turn_rate", "time_scale"):
        if getattr(args, name) <= 0:
            print(f"wheelgrid motor-sim: --{name.replace('_', '-')} must be > 0", file=sys.stderr)
            return 2
    for name in ("noise", "noise_deg", "delay"):
        if getattr(args, name) < 0:
            print(f"wheelgrid motor-sim: --{name.replace('_', '-')} must be >= 0", file=sys.stderr)
            return 2
    if max(abs(args.x), abs(args.y)) > proto.MAX_POSE_M:
        print(
            f"wheelgrid motor-sim: --x/--y must be within +-{proto.MAX_POSE_M:g} m (the STATUS "
            "pose is int32 mm)",
            file=sys.stderr,
        )
        return 2
    for name in ("drop", "corrupt"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            print(f"wheelgrid motor-sim: --{name} must be in [0, 1]", file=sys.stderr)
            return 2
    cfg = MotorSimConfig(
        heartbeat_timeout=args.heartbeat_timeout,
        turn_rate_deg_s=args.turn_rate,
        time_scale=args.time_scale,
        noise_m=args.noise,
        noise_deg=args.noise_deg,
        seed=args.seed,
        drop=args.drop,
        corrupt=args.corrupt,
        delay=args.delay,
        pose=(args.x, args.y, args.yaw),
        link=args.link,
        pose_log=args.pose_log,
    )
    done = threading.Event()
    # Both signals end it cleanly (pty closed, link removed). SIGINT explicitly: a shell starts
    # background jobs with SIGINT ignored, and managed_process stops children with SIGINT.
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    try:
        sim = MotorSim(cfg).start()
    except ValueError as exc:
        print(f"wheelgrid motor-sim: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        what = "the pose log" if exc.filename == args.pose_log else "a pty"
        print(f"wheelgrid motor-sim: cannot open {what}: {exc}", file=sys.stderr)
        return 1
    where = f" (link {args.link})" if args.link else ""
    print(f"wheelgrid motor-sim: pty {sim.slave_path}{where}")
    sys.stdout.flush()
    try:
        if args.vanish_after > 0 and not done.wait(args.vanish_after):
            print("wheelgrid motor-sim: vanishing (pty closed)", flush=True)
            sim.vanish()
            return 0
        while not done.wait(0.2):
            pass
    finally:
        sim.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
