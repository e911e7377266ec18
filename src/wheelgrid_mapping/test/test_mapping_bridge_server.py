"""BridgeServer over real TCP on 127.0.0.1 (no ROS): tokens, busy, malformed streams, limits."""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from wheelgrid_mapping import bridge_protocol as bp

K = np.array([[180.0, 0.0, 128.0], [0.0, 180.0, 96.0], [0.0, 0.0, 1.0]])


def frame(seq: int, w: int = 16, h: int = 12) -> bytes:
    depth = np.full((h, w), 1.5, dtype=np.float32)
    return bp.encode_frame(
        10.0 + seq / 60,
        K * [[1, 1, w / 256], [1, 1, h / 192], [1, 1, 1]],
        depth,
        seq=seq,
        pose=np.eye(4),
    )


class Recorder:
    def __init__(self) -> None:
        self.frames: list[bp.Frame] = []
        self.logs: list[tuple[str, str]] = []
        self.lock = threading.Lock()

    def on_frame(self, f: bp.Frame, client: int) -> None:
        with self.lock:
            self.frames.append(f)

    def log(self, level: str, text: str) -> None:
        with self.lock:
            self.logs.append((level, text))

    def logged(self, needle: str) -> bool:
        with self.lock:
            return any(needle in t for _, t in self.logs)


def wait_for(pred: Callable[[], bool], timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


@contextmanager
def server(**kw: object) -> Iterator[tuple[bp.BridgeServer, Recorder]]:
    rec = Recorder()
    srv = bp.BridgeServer(rec.on_frame, rec.log, port=0, **kw)  # type: ignore[arg-type]
    srv.start()
    try:
        yield srv, rec
    finally:
        srv.stop()


def test_frames_arrive_in_order() -> None:
    with server() as (srv, rec):
        sock = bp.connect("127.0.0.1", srv.port, name="t")
        with sock:
            sock.sendall(b"".join(frame(i) for i in range(30)))
        assert wait_for(lambda: len(rec.frames) == 30)
        assert [f.seq for f in rec.frames] == list(range(30))
        assert srv.frames_received == 30 and srv.messages_rejected == 0


def test_non_loopback_needs_a_token() -> None:
    with pytest.raises(ValueError, match="without a token"):
        bp.BridgeServer(lambda f, c: None, lambda lv, t: None, bind_address="0.0.0.0")
    assert bp.is_loopback("127.0.0.1") and bp.is_loopback("::1") and not bp.is_loopback("0.0.0.0")


def test_token_checked() -> None:
    with server(token="open sesame") as (srv, rec):
        with pytest.raises(ConnectionError, match="wrong token"):
            bp.connect("127.0.0.1", srv.port, token="guess")
        with pytest.raises(ConnectionError, match="wrong token"):
            bp.connect("127.0.0.1", srv.port)
        with bp.connect("127.0.0.1", srv.port, token="open sesame") as sock:
            sock.sendall(frame(0))
            assert wait_for(lambda: len(rec.frames) == 1)
        assert srv.clients_refused == 2


def test_second_client_is_busy_unless_configured() -> None:
    with server() as (srv, _):
        with (
            bp.connect("127.0.0.1", srv.port),
            pytest.raises(ConnectionError, match="another client"),
        ):
            bp.connect("127.0.0.1", srv.port)
        # after the first leaves, a new one is welcome
        assert wait_for(lambda: srv.clients == 0)
        bp.connect("127.0.0.1", srv.port).close()
    with (
        server(max_clients=2) as (srv, rec),
        bp.connect("127.0.0.1", srv.port) as a,
        bp.connect("127.0.0.1", srv.port) as b,
    ):
        a.sendall(frame(1))
        b.sendall(frame(2))
        assert wait_for(lambda: len(rec.frames) == 2)


def test_garbage_closes_the_connection_but_not_the_server() -> None:
    with server() as (srv, rec):
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            reply = s.recv(4096)  # a STATUS naming the problem, then EOF
            assert bp.FrameDecoder(accept=(bp.MSG_STATUS,)).feed(reply)[0].code == (
                bp.STATUS_PROTOCOL_ERROR
            )
            assert s.recv(4096) == b""
        assert rec.logged("bad_magic")
        with bp.connect("127.0.0.1", srv.port) as sock:  # still serving
            sock.sendall(frame(5))
            assert wait_for(lambda: len(rec.frames) == 1)


def test_a_peer_that_has_not_said_hello_cannot_make_the_bridge_hold_a_frame() -> None:
    """Before HELLO only a HELLO of at most MAX_HELLO_BYTES is taken: a peer with no token
    that declared a message of the frame limit (8 MB) and sent all but its last byte made the
    bridge hold it until the HELLO timeout, eight connections at a time, on any interface."""
    big = bp.PREFIX.pack(bp.MAGIC, bp.VERSION, bp.MSG_HELLO, 0, 8_000_000)
    frame_first = bp.PREFIX.pack(bp.MAGIC, bp.VERSION, bp.MSG_FRAME, 0, 8_000_000)
    with server(token="secret", hello_timeout_s=30.0) as (srv, rec):
        for prefix, said in ((big, "more than"), (frame_first, "before HELLO")):
            with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
                s.sendall(prefix + bytes(60_000))
                s.settimeout(5)
                reply = s.recv(4096)  # a STATUS naming the problem, then EOF, at once
                status = bp.FrameDecoder(accept=(bp.MSG_STATUS,)).feed(reply)[0]
                assert status.code == bp.STATUS_PROTOCOL_ERROR and said in status.text
            assert wait_for(lambda: not srv._clients)
        # a phone that sends its HELLO and its first frame in one write is still served
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            s.sendall(bp.encode_hello("secret", "phone") + frame(1))
            assert wait_for(lambda: len(rec.frames) == 1)


def test_frame_before_hello_and_silent_client_are_dropped() -> None:
    with server(hello_timeout_s=0.3) as (srv, rec):
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            s.sendall(frame(0))
            assert wait_for(lambda: rec.logged("before HELLO"))
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            assert wait_for(lambda: rec.logged("no HELLO"))
            s.settimeout(5)
            data = b""
            while chunk := s.recv(4096):
                data += chunk
        assert rec.frames == []


def test_bad_and_oversized_frames_are_skipped_connection_kept() -> None:
    with server(max_frame_bytes=4000) as (srv, rec):
        big = frame(1, w=64, h=48)  # ~15 kB > limit
        bad = bytearray(frame(2))
        bad[bp.PREFIX.size + 12 : bp.PREFIX.size + 14] = (0).to_bytes(2, "little")  # width 0
        with bp.connect("127.0.0.1", srv.port) as sock:
            sock.sendall(big + bytes(bad) + frame(3))
            assert wait_for(lambda: len(rec.frames) == 1)
        assert rec.frames[0].seq == 3 and srv.messages_rejected == 2
        assert rec.logged("oversized") and rec.logged("bad_size")


def test_too_many_bad_messages_disconnect() -> None:
    with server(max_errors_in_row=3) as (srv, rec):
        junk = bp.PREFIX.pack(bp.MAGIC, bp.VERSION, bp.MSG_FRAME, 0, 4) + b"abcd"
        with bp.connect("127.0.0.1", srv.port) as sock:
            sock.sendall(junk * 10)
            assert wait_for(lambda: rec.logged("bad messages in a row"))
        assert wait_for(lambda: srv.clients == 0)


def test_on_frame_exception_is_logged_not_fatal() -> None:
    rec = Recorder()

    def boom(f: bp.Frame, client: int) -> None:
        raise RuntimeError("publisher gone")

    srv = bp.BridgeServer(boom, rec.log, port=0)
    srv.start()
    try:
        with bp.connect("127.0.0.1", srv.port) as sock:
            sock.sendall(frame(0) + frame(1))
            assert wait_for(lambda: srv.frames_received == 2)
        assert rec.logged("publisher gone")
    finally:
        srv.stop()


def bad_pose_frame(seq: int = 99) -> bytes:
    """A well-framed FRAME whose quaternion is zero: rejected as bad_pose, stream kept."""
    raw = frame(seq)
    fields = list(bp.FRAME_HEADER.unpack_from(raw, bp.PREFIX.size))
    fields[11:15] = [0.0, 0.0, 0.0, 0.0]
    head = bp.PREFIX.size + bp.FRAME_HEADER.size
    return raw[: bp.PREFIX.size] + bp.FRAME_HEADER.pack(*fields) + raw[head:]


def read_status(sock: socket.socket, timeout: float = 3.0) -> bp.Status | None:
    """The first STATUS the bridge sends, or None if it closes without one."""
    sock.settimeout(timeout)
    dec = bp.FrameDecoder(accept=(bp.MSG_STATUS,))
    while data := sock.recv(4096):
        for m in dec.feed(data):
            assert isinstance(m, bp.Status)
            return m
    return None


def test_a_logger_that_raises_does_not_kill_the_server() -> None:
    """rclpy raised from the node's log callback on the first warning; the server thread died
    and every later client timed out. The server must survive its own logging."""
    rec = Recorder()

    def rclpy_like(level: str, text: str) -> None:
        if level != "info":
            raise ValueError("Logger severity cannot be changed between calls.")
        rec.log(level, text)

    srv = bp.BridgeServer(rec.on_frame, rclpy_like, port=0, token="t")
    srv.start()
    try:
        with pytest.raises(ConnectionError, match="wrong token"):  # a warning
            bp.connect("127.0.0.1", srv.port, token="x", timeout=2)
        with bp.connect("127.0.0.1", srv.port, token="t", timeout=2) as sock:
            sock.sendall(bad_pose_frame() + frame(1))  # another warning, then a good frame
            assert wait_for(lambda: len(rec.frames) == 1, 2)
        assert wait_for(lambda: srv.clients == 0, 2)
        with bp.connect("127.0.0.1", srv.port, token="t", timeout=2) as sock:  # still serving
            sock.sendall(frame(2))
            assert wait_for(lambda: len(rec.frames) == 2, 2)
        assert srv.messages_rejected == 1
    finally:
        srv.stop()


def test_client_silent_after_hello_is_dropped_and_the_phone_gets_back_in() -> None:
    """A phone that loses Wi-Fi mid-frame sends no FIN: its slot must free up, not be held
    forever while its reconnect is refused as busy; a steady stream is never idle."""
    with server(idle_timeout_s=0.4) as (srv, rec):
        with bp.connect("127.0.0.1", srv.port, name="streaming", timeout=2) as sock:
            for i in range(8):  # 10 Hz for 0.8 s: twice the idle timeout, never idle
                sock.sendall(frame(i))
                time.sleep(0.1)
            assert wait_for(lambda: len(rec.frames) == 8, 2) and srv.clients == 1
        assert wait_for(lambda: srv.clients == 0, 2)
        lost = bp.connect("127.0.0.1", srv.port, name="lost wifi", timeout=2)
        with lost:
            half = frame(9)
            lost.sendall(half[: len(half) // 2])
            t0 = time.monotonic()
            status = read_status(lost)
            assert status is not None and "idle" in status.text
            assert time.monotonic() - t0 < 2.0
            with bp.connect("127.0.0.1", srv.port, name="back", timeout=2) as sock:
                sock.sendall(frame(10))
                assert wait_for(lambda: len(rec.frames) == 9, 2)
        assert rec.logged("sent nothing for") and srv.clients_timed_out == 1


def test_a_byte_now_and_then_does_not_hold_the_slot() -> None:
    """The idle timeout was reset by any byte: a client that sent one every so often (a stuck
    sender, or one holding the slot on purpose) kept the phone out as busy."""
    with server(idle_timeout_s=0.5) as (srv, rec):
        with bp.connect("127.0.0.1", srv.port, name="trickle", timeout=2) as slow:
            half = frame(1)
            t0 = time.monotonic()
            for i in range(12):  # a byte every 0.15 s: never 0.5 s silent
                try:
                    slow.sendall(half[i : i + 1])
                except OSError:
                    break
                time.sleep(0.15)
                if srv.clients == 0:
                    break
            status = read_status(slow)
            assert status is not None and "idle" in status.text, status
            assert time.monotonic() - t0 < 1.5
        with bp.connect("127.0.0.1", srv.port, name="phone", timeout=2) as sock:
            sock.sendall(frame(2))
            assert wait_for(lambda: len(rec.frames) == 1, 2)


def test_connections_without_hello_do_not_keep_the_phone_out() -> None:
    """Silent pre-HELLO sockets (a port scan, a stuck app) count against the pending bound,
    not against max_clients: the phone's HELLO is accepted at once."""
    with server(hello_timeout_s=5.0) as (srv, rec):
        silent = [
            socket.create_connection(("127.0.0.1", srv.port), timeout=2)
            for _ in range(bp.MAX_PENDING + 2)
        ]
        try:
            assert wait_for(lambda: len(srv._clients) == bp.MAX_PENDING, 2)
            with bp.connect("127.0.0.1", srv.port, name="phone", timeout=2) as sock:
                sock.sendall(frame(1))
                assert wait_for(lambda: len(rec.frames) == 1, 2)
            # the oldest silent ones were told why they were dropped
            first = read_status(silent[0])
            assert first is not None and first.code == bp.STATUS_BUSY
        finally:
            for s in silent:
                s.close()


def test_errors_in_a_row_means_consecutive_messages() -> None:
    """Bad and good alternating is never two bad in a row, however the bytes are chunked."""
    with server(max_errors_in_row=3) as (srv, rec):
        with bp.connect("127.0.0.1", srv.port, timeout=2) as sock:
            sock.sendall(b"".join(bad_pose_frame() + frame(i) for i in range(30)))
            assert wait_for(lambda: len(rec.frames) == 30, 3)
            assert srv.clients == 1 and srv.messages_rejected == 30
            sock.sendall(bad_pose_frame() * 4)  # now four in a row: closed
            status = read_status(sock)
            assert status is not None and status.text == "too many bad messages"
        assert not rec.logged("30 bad messages")


def test_rejected_messages_logged_once_per_reason_and_client_but_all_counted() -> None:
    with server() as (srv, rec):
        for client in range(2):
            with bp.connect("127.0.0.1", srv.port, name=f"c{client}", timeout=2) as sock:
                short = bp.PREFIX.pack(bp.MAGIC, bp.VERSION, bp.MSG_FRAME, 0, 4) + b"abcd"
                for i in range(50):
                    sock.sendall(bad_pose_frame() * 10 + short + frame(i))
                assert wait_for(lambda c=client: len(rec.frames) == 50 * (c + 1), 5)
            assert wait_for(lambda: srv.clients == 0, 2)
        with rec.lock:
            lines = [t for _, t in rec.logs]
        assert sum("message rejected: bad_pose" in t for t in lines) == 2  # once per client
        assert sum("message rejected: short_frame" in t for t in lines) == 2
        assert srv.messages_rejected == 2 * 550
        assert srv.rejected_by_reason == {"bad_pose": 1000, "short_frame": 100}
        assert sum("bad_pose x500, short_frame x50" in t for t in lines) == 2  # on leaving


@pytest.mark.parametrize(
    "kw",
    [
        {"port": -1},
        {"port": 70_000},
        {"port": "8765"},
        {"max_clients": 0},
        {"hello_timeout_s": float("nan")},
        {"hello_timeout_s": -1.0},
        {"hello_timeout_s": float("inf")},
        {"idle_timeout_s": 0.0},
        {"idle_timeout_s": float("nan")},
        {"max_frame_bytes": 0},
        {"max_frame_bytes": -5},
        {"max_frame_bytes": bp.MAX_HELLO_BYTES - 1},  # the longest HELLO would be oversized
        {"max_frame_bytes": bp.MAX_FRAME_LIMIT + 1},
        {"max_errors_in_row": 0},
        {"max_errors_in_row": -1},
        {"token": "x" * (bp.MAX_TOKEN_BYTES + 1)},  # no HELLO could carry it
    ],
)
def test_bad_settings_are_refused_before_listening(kw: dict[str, object]) -> None:
    with pytest.raises(ValueError, match=next(iter(kw))):
        bp.BridgeServer(lambda f, c: None, lambda lv, t: None, **kw)  # type: ignore[arg-type]


def test_client_ids_are_unique_and_disconnect_is_reported() -> None:
    """The node keys per-connection state (the clock offset) by the id given to on_frame; it
    must never be reused, and on_disconnect lets the node forget it."""
    rec = Recorder()
    seen: list[int] = []
    gone: list[int] = []
    srv = bp.BridgeServer(lambda f, c: seen.append(c), rec.log, port=0, on_disconnect=gone.append)
    srv.start()
    try:
        for i in range(5):
            with bp.connect("127.0.0.1", srv.port, timeout=2) as sock:
                sock.sendall(frame(i))
                assert wait_for(lambda n=i: len(seen) == n + 1, 2)
            assert wait_for(lambda n=i: len(gone) == n + 1, 2)
        assert len(set(seen)) == 5 and gone == seen
    finally:
        srv.stop()


# ---- fuzzing the running server over TCP: it must keep serving whatever a client sends ------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@pytest.fixture(scope="module")
def fuzz_server() -> Iterator[tuple[bp.BridgeServer, Recorder]]:
    with server(max_frame_bytes=20_000, hello_timeout_s=1.0, max_clients=4) as pair:
        yield pair


_HELLO = bp.encode_hello("", "fuzz")


@settings(
    max_examples=40,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    st.booleans(),
    st.lists(st.sampled_from([frame(0), frame(1, w=64, h=48), frame(2, w=100, h=100)]), max_size=3),
    st.lists(st.tuples(st.integers(0, 50_000), st.integers(0, 255)), max_size=6),
    st.binary(max_size=200),
)
def test_fuzz_server_survives_any_stream(
    fuzz_server: tuple[bp.BridgeServer, Recorder],
    hello: bool,
    frames: list[bytes],
    flips: list[tuple[int, int]],
    tail: bytes,
) -> None:
    srv, _ = fuzz_server
    data = bytearray((_HELLO if hello else b"") + b"".join(frames) + tail)
    for pos, val in flips:
        if data:
            data[pos % len(data)] = val
    # the server may close on us before everything is sent: allowed
    with (
        socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s,
        contextlib.suppress(OSError),
    ):
        s.sendall(bytes(data))
    # whatever happened, a well-behaved client is still served
    before = srv.frames_received
    with bp.connect("127.0.0.1", srv.port, name="check") as sock:
        sock.sendall(frame(7))
        assert wait_for(lambda: srv.frames_received > before)
    for c in list(srv._clients.values()):
        assert c.decoder.buffered <= bp.PREFIX.size + srv.max_frame_bytes


def test_a_new_connection_does_not_change_the_clients_a_reader_is_counting() -> None:
    """The node's 1 Hz status timer reads ``clients`` (a loop over the connections) from its
    own thread. The server thread added each new connection to that same dict in place, and a
    reader mid-loop got 'RuntimeError: dictionary changed size during iteration' (seen within
    seconds of reconnects), out of the timer: the bridge node died. A connection now comes in
    as a new dict, as one that leaves already went, so a loop in progress never sees it."""
    with server() as (srv, _rec):
        seen_by_a_reader = srv._clients  # what a loop in progress iterates over
        with socket.create_connection(("127.0.0.1", srv.port)) as s:
            assert wait_for(lambda: len(srv._clients) == 1)
            assert len(seen_by_a_reader) == 0
            assert srv.clients == 0  # not said HELLO yet
            s.sendall(bp.encode_hello())
            assert wait_for(lambda: srv.clients == 1)


def test_a_phone_that_leaves_mid_frame_is_said_to_have_lost_it() -> None:
    """A phone whose connection dropped half-way through a frame (Wi-Fi gone, the app
    killed) lost that frame with no word but "disconnected", as if it had left between
    frames: the log now names the unfinished message and its size."""
    with server() as (srv, rec):
        whole, half = frame(0), frame(1)
        with bp.connect("127.0.0.1", srv.port, name="phone") as sock:
            sock.sendall(whole + half[: len(half) // 2])
            assert wait_for(lambda: len(rec.frames) == 1)
        assert wait_for(lambda: rec.logged("disconnected"))
        said = [(lv, t) for lv, t in rec.logs if "disconnected" in t]
        assert said[0][0] == "warn", said
        assert f"{len(half) // 2} B of an unfinished message" in said[0][1], said
        with bp.connect("127.0.0.1", srv.port, name="tidy") as sock:  # between frames: info
            sock.sendall(frame(2))
            assert wait_for(lambda: len(rec.frames) == 2)
        assert wait_for(lambda: rec.logged("(tidy) disconnected"))
        assert [lv for lv, t in rec.logs if "(tidy) disconnected" in t] == ["info"]


def test_a_phone_whose_connection_is_reset_mid_frame_is_said_to_have_lost_it() -> None:
    """A reset (the app killed with the bridge's STATUS still unread, SO_LINGER 0 here) ends
    in a read error, not a clean close: the log said "read failed" and nothing of the frame
    begun."""
    with server() as (srv, rec):
        half = frame(0)
        sock = bp.connect("127.0.0.1", srv.port, name="phone")
        sock.sendall(half[: len(half) // 2])
        assert wait_for(lambda: any(c.decoder.buffered for c in list(srv._clients.values())))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()  # RST
        assert wait_for(lambda: rec.logged("read failed"))
        said = [t for lv, t in rec.logs if "read failed" in t and lv == "warn"]
        assert f"{len(half) // 2} B of an unfinished message" in said[0], said
