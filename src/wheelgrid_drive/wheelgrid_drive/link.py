"""The host side of the motor-controller link (pyserial), ROS-free.

Safety rules this class implements (docs/serial-protocol.md, "host duties"):

* Every request waits for its reply with a timeout and is retried with the SAME sequence
  number, so the controller can recognise a retry and never executes a move twice.
* A request is retried only on the connection it was first sent on (STOP alone goes out on
  any): a port lost while it waits fails it, even when the port is back by the time it would
  retry. A move retried on a reopened port ran after that port's STOP -- the chair drove off
  on its own after a link fault, to a controller that had no move to take it for a retry of.
* A garbled reply (CRC/framing damage), a reply of the wrong type, a NAK, or a reply to a
  sequence number nobody is waiting for is logged and counts as a failure -- never ignored.
* A vanished port (USB unplugged, pty closed) is detected by the reader thread, reported, and
  reconnected by the heartbeat thread; the first thing sent after a reconnection is STOP.
* A heartbeat thread keeps the controller's watchdog fed; if this process dies, the heartbeats
  stop and the controller stops the motors on its own.
* STOP on every doubt: a move that fails, times out, is aborted or ends in any way but DONE is
  followed by STOP.
* A STOP the controller did not acknowledge silences the link: no heartbeat and no other
  request goes out (only STOP retries, after the controller's watchdog has had time to fire),
  so its watchdog stops the motors. The heartbeats fed it while the STOP went unheard, and a
  moving chair drove on to the end of its cell.

One reader thread owns the port's input and routes replies to waiters by sequence number, so a
STOP can be sent while another thread waits for a reply (an e-stop never queues behind a poll).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from wheelgrid_drive import protocol as proto

log = logging.getLogger("wheelgrid_drive.link")
# A library's logger: the link's users say its events themselves (``on_event``: the CLI prints
# them, the node logs them, throttled where they repeat). Without a handler of its own,
# logging's last-resort handler printed each one again, ten heartbeat failures a second from a
# controller that no longer answers (a review). A caller that configures logging still sees
# them (they propagate).
log.addHandler(logging.NullHandler())


class LinkError(RuntimeError):
    """The controller did not do what was asked (timeout, NAK, garbled reply, lost port).

    ``seq``: the sequence number of the move the controller had acknowledged when the error
    came (the chair may have moved part of it), else None: a record of the failed step must
    say that the move was under way, not only which request failed after it."""

    seq: int | None = None


class LinkAbortedError(LinkError):
    """A move was aborted by the caller (e-stop, new plan); STOP has been sent."""


@dataclass
class _Waiter:
    mtype: int
    event: threading.Event = field(default_factory=threading.Event)
    frame: proto.Frame | None = None
    error: str = ""


@dataclass
class LinkStats:
    sent: int = 0
    replies: int = 0
    retries: int = 0
    timeouts: int = 0
    garbled: int = 0
    unexpected: int = 0
    naks: int = 0
    disconnects: int = 0
    reconnects: int = 0
    stops: int = 0


EventCallback = Callable[[str, str], None]  # (kind, message)


def _default_serial_factory(port: str, baud: int) -> Any:
    import serial

    return serial.Serial(port, baud, timeout=0.02, write_timeout=0.5, exclusive=True)


MAX_BAUD = 12_000_000  # an FTDI high-speed adapter's fastest
HEARTBEAT_PERIOD_S = 0.1  # 5x faster than the controller's 0.5 s watchdog (protocol duty 3)
# after an unacknowledged STOP the link says nothing this long, twice the controller's watchdog,
# before it tries STOP again
STOP_SILENCE_S = 2.0 * proto.DEFAULT_HEARTBEAT_TIMEOUT_S
RECONNECT_PERIOD_S = 0.5  # a vanished port is tried again this often (protocol duty 5)


def _open_reason(exc: BaseException) -> str:
    """The OS's own reason a port did not open, once: pyserial wraps the OSError in a message
    that repeats its errno and the path ("[Errno 2] could not open port X: [Errno 2] No such
    file or directory: 'X'")."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.strerror and type(seen).__module__ == "builtins":
            return seen.strerror
        seen = seen.__cause__ or seen.__context__
    return str(exc)


class MotorLink:
    """A connection to the motor controller on ``port``. Thread-safe.

    ``on_status(Status)`` is called from the heartbeat thread with every status report;
    ``on_event(kind, message)`` with every problem and recovery ("garbled", "timeout",
    "unexpected", "nak", "vanished", "reconnected", "stop", ...), so a CLI can print and a node
    can publish diagnostics.
    """

    def __init__(
        self,
        port: str,
        baud: int = 115200,
        *,
        reply_timeout: float = 0.1,
        retries: int = 3,
        heartbeat_period: float = HEARTBEAT_PERIOD_S,
        reconnect_period: float = RECONNECT_PERIOD_S,
        on_status: Callable[[proto.Status], None] | None = None,
        on_event: EventCallback | None = None,
        serial_factory: Callable[[str, int], Any] = _default_serial_factory,
    ) -> None:
        check_link_settings(baud, reply_timeout, retries, heartbeat_period, reconnect_period)
        self.port = port
        self.baud = baud
        self.reply_timeout = reply_timeout
        self.retries = retries
        self.heartbeat_period = heartbeat_period
        self.reconnect_period = reconnect_period
        self.on_status = on_status
        self.on_event = on_event
        self.stats = LinkStats()
        self.last_status: proto.Status | None = None
        self.last_status_time = 0.0
        self.opened_at = 0.0  # when the port was last opened (monotonic)
        self._factory = serial_factory
        self._ser: Any = None
        self._decoder = proto.FrameDecoder()
        self._write_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._pending: dict[int, _Waiter] = {}
        self._seq = 0
        self._last_move_seq: int | None = None
        self._closing = threading.Event()
        self._reader: threading.Thread | None = None
        self._heartbeat: threading.Thread | None = None
        self._stop_owed_at: float | None = None  # when a STOP went unacknowledged (monotonic)
        # A reopened port takes nothing but STOP until one is acknowledged (host duty 5): a
        # request of another thread could otherwise go out between the reopening and its STOP.
        self._stop_first = False
        # Counts every opening and every loss of the port: a caller that notes it before a
        # sequence of moves tells from a change that the link was lost meanwhile (see
        # runner.run_steps), even when the port was reopened before it looked.
        self.connection = 0

    @property
    def stop_owed(self) -> bool:
        """A STOP went unacknowledged and none has been since: the link is silent."""
        return self._stop_owed_at is not None

    # ---- connection ---------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._ser is not None

    def silent_for(self) -> float:
        """Seconds since the controller last reported its status, or since the port opened
        before its first report: an open port says nothing of whether anyone answers on it."""
        return time.monotonic() - max(self.last_status_time, self.opened_at)

    def open(self) -> MotorLink:
        """Open the port and start the reader; LinkError if it cannot be opened."""
        self._closing.clear()
        self._open_port()
        return self

    def _open_port(self, stop_first: bool = False) -> None:
        try:
            ser = self._factory(self.port, self.baud)
        except ModuleNotFoundError:  # pyserial not installed: no port to wait for
            raise
        except Exception as exc:  # pyserial raises SerialException/OSError/ValueError
            raise LinkError(f"cannot open {self.port}: {_open_reason(exc)}") from exc
        with contextlib.suppress(Exception):
            ser.reset_input_buffer()  # stale bytes from before us are not replies to us
        self._decoder = proto.FrameDecoder()
        with self._state_lock:
            self._stop_first = stop_first
            self._ser = ser
            self.opened_at = time.monotonic()
            self.connection += 1
            # Whoever drove the controller while the port was away (a second host, a
            # `wheelgrid drive` run) moved its last accepted SEQ: the next move reads it from
            # STATUS again, else one with that SEQ was taken for a retry and ACKed unmoved.
            self._last_move_seq = None
        self._reader = threading.Thread(
            target=self._read_loop, args=(ser,), name="motor-link-reader", daemon=True
        )
        self._reader.start()

    def close(self, stop: bool = True) -> None:
        """Stop the chair (unless told not to), end the threads, close the port."""
        if stop and self.connected:
            self.stop()
        self._closing.set()
        for th in (self._heartbeat, self._reader):
            if th is not None and th is not threading.current_thread():
                th.join(timeout=2.0)
        self._heartbeat = None
        self._drop_port("closed", report=False)

    def __enter__(self) -> MotorLink:
        return self if self.connected else self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _emit(self, kind: str, message: str, level: int = logging.WARNING) -> None:
        log.log(level, "%s: %s", kind, message)
        if self.on_event is not None:
            try:
                self.on_event(kind, message)
            except Exception:  # a broken observer must not break the safety path
                log.exception("on_event callback failed")

    def _drop_port(self, why: str, report: bool = True, lost: Any = None) -> None:
        """Close the port (only if it is still ``lost``, when given: a failure of an old
        connection must not close the one that replaced it)."""
        with self._state_lock:
            if lost is not None and self._ser is not lost:
                return
            ser, self._ser = self._ser, None
            if ser is not None:
                self.connection += 1
        if ser is None:
            return
        with contextlib.suppress(Exception):
            ser.close()
        if report:
            self.stats.disconnects += 1
            self._emit("vanished", f"port {self.port} lost: {why}", logging.ERROR)
        self._fail_pending(f"port lost: {why}")

    def _fail_pending(self, why: str) -> None:
        with self._state_lock:
            waiters = list(self._pending.values())
        for w in waiters:
            if not w.event.is_set():
                w.error = why
                w.event.set()

    def reconnect(self) -> bool:
        """Try once to reopen the port; on success send STOP first (we lost track of it)."""
        if self.connected:
            return True
        try:
            self._open_port(stop_first=True)
        except LinkError as exc:
            log.debug("reconnect failed: %s", exc)
            return False
        self._emit("reconnected", f"port {self.port} reopened; sending STOP", logging.WARNING)
        self.stop()
        self.stats.reconnects += 1  # counted once its STOP went out: the port takes requests
        return True

    # ---- reader thread ------------------------------------------------------------------------

    def _read_loop(self, ser: Any) -> None:
        while not self._closing.is_set() and self._ser is ser:
            try:
                data = ser.read(max(1, ser.in_waiting))
            except Exception as exc:  # SerialException / OSError(EIO) when the device vanishes
                if not self._closing.is_set():  # dropped only if it is still the port
                    self._drop_port(str(exc), lost=ser)
                return
            # fed after every read, b"" on the port's 20 ms timeout: a reply cut off is given up
            # in time, and the replies held behind it come out
            for item in self._decoder.feed(data):
                self._dispatch(item)

    def _dispatch(self, item: proto.Frame | proto.DecodeError) -> None:
        if isinstance(item, proto.DecodeError):
            self.stats.garbled += 1
            self._emit("garbled", f"damaged reply bytes ({item.reason}, {item.dropped} dropped)")
            # We cannot know whose reply was damaged: every waiter fails this attempt.
            self._fail_pending(f"garbled reply: {item.reason}")
            return
        with self._state_lock:
            waiter = self._pending.get(item.seq)
        if waiter is None or waiter.event.is_set():
            self.stats.unexpected += 1
            self._emit("unexpected", f"reply {item.type_name} seq {item.seq} matches no request")
            self._fail_pending(f"unexpected {item.type_name} seq {item.seq}")
            return
        self.stats.replies += 1
        waiter.frame = item
        waiter.event.set()

    # ---- requests -----------------------------------------------------------------------------

    def _next_seq(self, avoid: int | None = None) -> int:
        """Next sequence number; never ``avoid`` (the last move's: protocol rule 4 treats a
        move with the last move's SEQ, type and payload as a retry, so a NEW move must differ)."""
        with self._state_lock:
            self._seq = (self._seq + 1) & 0xFF
            if self._seq == avoid:
                self._seq = (self._seq + 1) & 0xFF
            return self._seq

    def _write(self, data: bytes, ser: Any = None, abort: threading.Event | None = None) -> None:
        """Write on the current port, or only on ``ser`` when given: a write on a connection
        since lost fails (on the closed port object itself if it is lost meanwhile), never
        reaching the port that replaced it. With ``abort`` set by the time the write lock is
        held, nothing is written: an e-stop sets its flag before it writes its STOP under the
        same lock, so a move is either on the wire before that STOP or never."""
        current = self._ser
        if current is None:
            raise LinkError(f"port {self.port} is not connected")
        if ser is None:
            ser = current
        elif ser is not current:
            raise LinkError(f"port {self.port} was lost since this request began")
        try:
            with self._write_lock:
                if abort is not None and abort.is_set():
                    raise LinkAbortedError(
                        f"not sent: aborted (e-stop or a newer job) before it reached {self.port}"
                    )
                ser.write(data)
                ser.flush()
        except LinkAbortedError:
            raise  # nothing written: the port is fine
        except Exception as exc:
            self._drop_port(f"write failed: {exc}", lost=ser)
            raise LinkError(f"write to {self.port} failed: {exc}") from exc
        self.stats.sent += 1

    def _check_reply(self, mtype: int, frame: proto.Frame) -> str:
        """'' if ``frame`` is a well-formed answer to a request of ``mtype``, else why not."""
        if mtype in (proto.MsgType.HEARTBEAT, proto.MsgType.STATUS_REQ):
            if frame.type != proto.MsgType.STATUS:
                return f"expected STATUS, got {frame.type_name}"
            try:
                proto.unpack_status(frame.payload)
            except ValueError as exc:
                return str(exc)
            return ""
        if frame.type == proto.MsgType.NAK:
            if len(frame.payload) != 2 or frame.payload[0] != mtype:
                return f"NAK payload {frame.payload.hex() or 'empty'} does not name 0x{mtype:02X}"
            return ""  # a well-formed refusal; the caller turns it into an error
        if frame.type != proto.MsgType.ACK:
            return f"expected ACK/NAK, got {frame.type_name}"
        if frame.payload != bytes([mtype]):
            return f"ACK names type {frame.payload.hex() or 'nothing'}, not 0x{mtype:02X}"
        return ""

    def request(
        self,
        mtype: proto.MsgType,
        payload: bytes = b"",
        retries: int | None = None,
        avoid_seq: int | None = None,
        abort: threading.Event | None = None,
        connection: int | None = None,
    ) -> proto.Frame:
        """Send one request and return its valid reply (ACK, NAK or STATUS), retrying on failure.

        Raises LinkError when no valid reply came after all attempts or the port is lost (a
        request other than STOP is never retried on a reopened port: a retried move would start
        the chair after the reconnection's STOP), and for anything but STOP while a STOP is
        owed (:attr:`stop_owed`): any valid frame feeds the controller's watchdog, which must
        be left to stop the motors. LinkAbortedError, and nothing (more) written, once
        ``abort`` is set (see :meth:`_write`). ``connection``: the :attr:`connection` count the
        caller's checks were made on; a request other than STOP is not sent on any later one
        (a plan step checked on the old port went out on the reopened one).
        """
        is_stop = mtype == proto.MsgType.STOP
        with self._state_lock:
            # one look at all three: read apart, a port reopened between them (its STOP still
            # to go first) was taken as this request's connection, and a move went out before
            # that STOP
            stop_first, ser, now = self._stop_first, self._ser, self.connection
        if connection is not None and now != connection and not is_stop:
            raise LinkError(
                f"{mtype.name} not sent: port {self.port} was lost since the checks this "
                "request rests on"
            )
        if stop_first and not is_stop and self._stop_owed_at is None:
            raise LinkError(
                f"{mtype.name} not sent: port {self.port} was just reopened, and its first frame "
                "is the STOP, not yet acknowledged"
            )
        if self._stop_owed_at is not None and not is_stop:
            raise LinkError(
                f"{mtype.name} not sent: a STOP went unacknowledged, and the link stays silent "
                "until one is, so that the controller's watchdog stops the motors"
            )
        # ``ser``: the connection this request belongs to (STOP: any)
        if ser is None and not is_stop:
            raise LinkError(f"{mtype.name} not sent: port {self.port} is not connected")
        seq = self._next_seq(avoid_seq)
        data = proto.encode(seq, mtype, payload)
        attempts = 1 + (self.retries if retries is None else retries)
        last = ""
        for attempt in range(attempts):
            if attempt and not is_stop and self._ser is not ser:
                last = f"{last}; port lost, not retried on another connection"
                break
            if attempt:
                self.stats.retries += 1
            waiter = _Waiter(int(mtype))
            with self._state_lock:
                self._pending[seq] = waiter
            try:
                self._write(data, None if is_stop else ser, abort)
                if not waiter.event.wait(self.reply_timeout):
                    self.stats.timeouts += 1
                    last = f"no reply within {self.reply_timeout * 1000:.0f} ms"
                    self._emit("timeout", f"{mtype.name} seq {seq}: {last}", logging.INFO)
                    continue
            finally:
                with self._state_lock:
                    self._pending.pop(seq, None)
            if waiter.frame is None:
                last = waiter.error or "failed"
                if not self.connected:
                    break
                continue
            why = self._check_reply(int(mtype), waiter.frame)
            if why:
                self.stats.unexpected += 1
                last = why
                self._emit("unexpected", f"{mtype.name} seq {seq}: {why}")
                continue
            return waiter.frame
        raise LinkError(f"{mtype.name} seq {seq}: {last} ({attempts} attempt(s))")

    def stop(self) -> bool:
        """Send STOP (retried); True if the controller acknowledged it. Never raises."""
        self.stats.stops += 1
        try:
            frame = self.request(proto.MsgType.STOP)
        except LinkError as exc:
            why = str(exc) or "no reply"  # never empty: empty is acknowledged
        else:
            why = "" if frame.type == proto.MsgType.ACK else f"answered type {frame.type:#04x}"
        if not why:
            if self._stop_owed_at is not None:
                self._emit("stop", "STOP acknowledged: the link speaks again", logging.WARNING)
            self._stop_owed_at = None
            self._stop_first = False
            return True
        self._stop_owed_at = time.monotonic()
        self._emit(
            "stop",
            f"STOP not acknowledged: {why}; the link falls silent so that the controller's "
            f"watchdog stops the motors, STOP again within {STOP_SILENCE_S:g} s",
            logging.ERROR,
        )
        return False

    def status(self, connection: int | None = None) -> proto.Status:
        frame = self.request(proto.MsgType.STATUS_REQ, connection=connection)
        return self._got_status(frame)

    def _got_status(self, frame: proto.Frame) -> proto.Status:
        st = proto.unpack_status(frame.payload)
        self.last_status = st
        self.last_status_time = time.monotonic()
        if self.on_status is not None:
            try:
                self.on_status(st)
            except Exception:
                log.exception("on_status callback failed")
        return st

    def set_pose(self, x: float, y: float, yaw: float) -> None:
        """Tell the controller (simulator) where it is; LinkError on NAK/failure."""
        frame = self.request(proto.MsgType.SET_POSE, proto.pack_pose(x, y, yaw))
        if frame.type == proto.MsgType.NAK:
            raise LinkError(f"SET_POSE refused: {_nak_reason(frame)}")

    def move(
        self,
        action: str,
        distance_m: float,
        speed_kmh: float,
        abort: threading.Event | None = None,
        connection: int | None = None,
    ) -> int:
        """Start a move; returns its sequence number once ACKed. STOP + LinkError otherwise
        (LinkAbortedError where ``abort`` was set before the move reached the wire; LinkError
        where the port was reopened since ``connection``, see :meth:`request`)."""
        if action not in proto.MOVE_TYPES:
            raise ValueError(f"unknown action {action!r}")
        payload = proto.pack_move(distance_m, min(speed_kmh, proto.MAX_SPEED_KMH))
        mtype = proto.MOVE_TYPES[action]
        try:
            if self._last_move_seq is None:
                # A new link (a new process) numbers its frames from 1, but the controller
                # remembers the last move it accepted, from whoever sent it: a first move with
                # that SEQ, type and payload would be taken as its retry and ACKed without
                # moving (protocol rule 4), and the host would plan on from the wrong cell.
                # So the first move avoids the SEQ the controller reports.
                self._last_move_seq = self.status(connection).last_seq
            frame = self.request(
                mtype, payload, avoid_seq=self._last_move_seq, abort=abort, connection=connection
            )
        except LinkError:
            # The controller may have accepted this move (its ACKs lost) or not: which move
            # it remembers is unknown, so the next move reads it from STATUS again. Avoiding
            # the older SEQ, a later identical move with this one's SEQ was taken for its
            # retry and reported DONE without driving.
            self._last_move_seq = None
            self.stop()
            raise
        if frame.type == proto.MsgType.NAK:
            # A refused move is not remembered (rule 4 keeps the last ACCEPTED one), so the
            # SEQ to avoid stays that of the move before it.
            self.stats.naks += 1
            why = _nak_reason(frame)
            self._emit("nak", f"{action} refused: {why}", logging.ERROR)
            self.stop()
            raise LinkError(f"{action} refused by the controller: {why}")
        self._last_move_seq = frame.seq
        return frame.seq

    def wait_done(
        self,
        seq: int,
        timeout: float,
        abort: threading.Event | None = None,
        poll: float = 0.02,
        connection: int | None = None,
    ) -> proto.Status:
        """Poll STATUS until move ``seq`` is DONE; anything else -> STOP + LinkError (a port
        reopened since ``connection`` too: see :meth:`request`)."""
        deadline = time.monotonic() + timeout
        while True:
            if abort is not None and abort.is_set():
                self.stop()
                raise LinkAbortedError(f"move seq {seq} aborted")
            try:
                st = self.status(connection)
            except LinkError:
                self.stop()
                raise
            if st.last_seq != seq:
                self.stop()
                raise LinkError(f"controller reports move seq {st.last_seq}, expected {seq}")
            if st.result == proto.Result.DONE:
                return st
            if st.result != proto.Result.RUNNING:
                self.stop()
                raise LinkError(f"move seq {seq} ended {st.result.name}, not DONE")
            if time.monotonic() > deadline:
                self.stop()
                raise LinkError(f"move seq {seq} not done within {timeout:.1f} s")
            if abort is not None:
                abort.wait(poll)
            else:
                time.sleep(poll)

    def execute(
        self,
        action: str,
        distance_m: float,
        speed_kmh: float,
        timeout: float | None = None,
        abort: threading.Event | None = None,
        connection: int | None = None,
    ) -> tuple[int, proto.Status]:
        """Start a move and wait until it is done: ``(seq, final status)``. ``connection``:
        see :meth:`move`."""
        if abort is not None and abort.is_set():
            raise LinkAbortedError(f"{action} not started: aborted")
        seq = self.move(action, distance_m, speed_kmh, abort, connection)
        if timeout is None:
            timeout = move_timeout(distance_m, speed_kmh)
        try:
            return seq, self.wait_done(seq, timeout, abort, connection=connection)
        except LinkError as exc:
            exc.seq = seq
            raise

    # ---- heartbeat ----------------------------------------------------------------------------

    def start_heartbeat(self) -> None:
        """Start the thread that feeds the controller's watchdog and reconnects a lost port."""
        if self._heartbeat is not None:
            return
        self._heartbeat = threading.Thread(
            target=self._heartbeat_loop, name="motor-link-heartbeat", daemon=True
        )
        self._heartbeat.start()

    def _heartbeat_loop(self) -> None:
        next_reconnect = 0.0
        while not self._closing.wait(self.heartbeat_period):
            if not self.connected:
                now = time.monotonic()
                if now >= next_reconnect:
                    next_reconnect = now + self.reconnect_period
                    self.reconnect()
                continue
            owed = self._stop_owed_at
            if owed is not None:  # silent, so the watchdog fires; then STOP again
                if time.monotonic() - owed >= STOP_SILENCE_S:
                    self.stop()
                continue
            try:
                self._got_status(self.request(proto.MsgType.HEARTBEAT, retries=1))
            except LinkError as exc:
                self._emit("heartbeat", f"heartbeat failed: {exc}")


def _nak_reason(frame: proto.Frame) -> str:
    if len(frame.payload) != 2:
        return f"malformed NAK ({frame.payload.hex()})"
    try:
        return proto.Nak(frame.payload[1]).name
    except ValueError:
        return f"reason {frame.payload[1]}"


def check_link_settings(
    baud: int,
    reply_timeout: float,
    retries: int,
    heartbeat_period: float = HEARTBEAT_PERIOD_S,
    reconnect_period: float = RECONNECT_PERIOD_S,
) -> None:
    """``ValueError`` naming the first setting the link cannot run with. Unchecked, a NaN or
    huge timeout killed the heartbeat thread (OverflowError), ``retries`` -1 never sent a
    frame (STOP included), and a heartbeat slower than the controller's watchdog would let it
    stop the chair in the middle of every move."""
    if baud <= 0:
        raise ValueError(f"baud must be > 0, not {baud}")
    if baud > MAX_BAUD:  # past int32 the OS's own words were "signed integer is greater..."
        raise ValueError(f"baud must be <= {MAX_BAUD} (a fast USB serial adapter's), not {baud}")
    if not 0.0 < reply_timeout <= 10.0:
        raise ValueError(f"reply_timeout must be in (0, 10] s, not {reply_timeout}")
    if not 0 <= retries <= 20:
        raise ValueError(f"retries must be in 0..20, not {retries}")
    watchdog = proto.DEFAULT_HEARTBEAT_TIMEOUT_S
    if not 0.0 < heartbeat_period <= watchdog / 2:
        raise ValueError(
            f"heartbeat_period must be in (0, {watchdog / 2:g}] s (half the controller's "
            f"{watchdog:g} s watchdog), not {heartbeat_period}"
        )
    if not 0.0 < reconnect_period <= 60.0:
        raise ValueError(f"reconnect_period must be in (0, 60] s, not {reconnect_period}")


def move_timeout(distance_m: float, speed_kmh: float, turn_s: float = 6.0) -> float:
    """Generous time a move may take: twice the driving time plus a 90 deg turn budget."""
    v = max(min(speed_kmh, proto.MAX_SPEED_KMH), 0.1) / 3.6
    return 2.0 * distance_m / v + turn_s + 2.0
