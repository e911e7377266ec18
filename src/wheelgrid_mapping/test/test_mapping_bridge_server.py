"""BridgeServer over real TCP on 127.0.0.1 (no ROS): tokens, busy, malformed streams, limits."""

from __future__ import annotations

import contextlib
import socket
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
    return bp.encode_frame(10.0 + seq / 60, K, depth, seq=seq, pose=np.eye(4))


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
