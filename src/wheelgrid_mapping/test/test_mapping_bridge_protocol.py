"""bridge_protocol: round trips, every rejection reason, and fuzzing of the decoder."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wheelgrid_mapping import bridge_protocol as bp
from wheelgrid_mapping.depth import (
    ARKIT_CAMERA_TO_OPTICAL,
    metres_to_millimetres,
    pose_from_xyz_quat,
)

K = np.array([[180.0, 0.0, 128.0], [0.0, 181.0, 96.0], [0.0, 0.0, 1.0]])  # for 256 x 192


def k_for(depth: np.ndarray) -> np.ndarray:
    """K with its principal point at the centre of ``depth`` (the decoder refuses one far off)."""
    h, w = depth.shape
    return np.array([[180.0, 0.0, w / 2], [0.0, 181.0, h / 2], [0.0, 0.0, 1.0]])


def _frame_bytes(w: int = 8, h: int = 6, **kw: object) -> bytes:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 5.0, (h, w)).astype(np.float32)
    return bp.encode_frame(1.5, k_for(depth), depth, **kw)  # type: ignore[arg-type]


def test_frame_round_trip_f32_with_confidence_and_pose() -> None:
    depth = np.array([[1.0, np.nan, 0.0], [2.5, 3.25, 4.0]], dtype=np.float32)
    conf = np.array([[2, 1, 0], [2, 2, 1]], dtype=np.uint8)
    pose = pose_from_xyz_quat(0.1, 1.2, -0.3, 0.1, 0.2, 0.3, 0.9)
    raw = bp.encode_frame(12.25, k_for(depth), depth, seq=7, confidence=conf, pose=pose)
    (f,) = bp.FrameDecoder().feed(raw)
    assert isinstance(f, bp.Frame)
    assert (f.stamp, f.seq, f.width, f.height) == (12.25, 7, 3, 2)
    np.testing.assert_allclose(f.K, k_for(depth))
    np.testing.assert_array_equal(f.confidence, conf)
    dm = f.depth_m()
    assert np.isnan(dm[0, 1]) and np.isnan(dm[0, 2]) and dm[1, 1] == 3.25
    np.testing.assert_allclose(f.pose_optical(), pose, atol=1e-12)


def test_u16_millimetres_and_arkit_axes_pose() -> None:
    depth_m = np.array([[1.2344, 0.0], [np.nan, 6.5]], dtype=np.float32)
    pose = pose_from_xyz_quat(0, 1, 0, 0, 0, 0, 1)
    raw = bp.encode_frame(
        3.0,
        k_for(depth_m),
        depth_m,
        pose=pose,
        pose_axes=bp.POSE_ARKIT,
        depth_encoding=bp.DEPTH_U16_MM,
    )
    (f,) = bp.FrameDecoder().feed(raw)
    assert f.depth.dtype == np.uint16 and f.depth.tolist() == [[1234, 0], [0, 6500]]
    assert f.confidence is None
    np.testing.assert_allclose(f.pose_optical(), pose @ ARKIT_CAMERA_TO_OPTICAL, atol=1e-12)
    (g,) = bp.FrameDecoder().feed(bp.encode_frame(3.0, k_for(depth_m), depth_m))
    assert g.pose is None and g.pose_optical() is None


def test_millimetre_depth_sent_as_float_metres_is_converted() -> None:
    """``encode_frame`` takes uint16 millimetres (a phone's depth PNG) and converts on the way
    to the encoding asked for. Asked for DEPTH_F32_M, it sent the millimetres as metres: a
    wall 1.5 m away arrived 1.5 km away."""
    mm = np.array([[1500, 0], [65535, 250]], dtype=np.uint16)
    raw = bp.encode_frame(3.0, k_for(mm), mm, depth_encoding=bp.DEPTH_F32_M)
    (f,) = bp.FrameDecoder().feed(raw)
    assert f.depth_encoding == bp.DEPTH_F32_M
    np.testing.assert_allclose(f.depth_m(), [[1.5, np.nan], [65.535, 0.25]], rtol=1e-6)


def test_a_float_depth_beyond_any_return_is_no_return() -> None:
    """A float frame's depth of 3e38 m (or inf) became a finite point 3e38 m away on
    /iphone/points; the mapper's range filter dropped it, but RViz or another stack got it.
    Beyond the 16-bit millimetres' ceiling a depth is no return, in both encodings: sent as
    DEPTH_U16_MM (`stream-stray`'s default, `import-stray`'s only encoding) 70 m and 3e38 m
    were clipped to 65,535 mm, a real-looking point 65.5 m away."""
    depth = np.array([[3e38, np.inf], [bp.MAX_DEPTH_M, 70.0], [-1.0, np.nan]], dtype=np.float32)
    for enc in (bp.DEPTH_F32_M, bp.DEPTH_U16_MM):
        (f,) = bp.FrameDecoder().feed(bp.encode_frame(3.0, k_for(depth), depth, depth_encoding=enc))
        dm = f.depth_m()
        assert np.isnan(dm[0]).all() and np.isnan(dm[1, 1]) and np.isnan(dm[2]).all(), enc
        assert dm[1, 0] == np.float32(bp.MAX_DEPTH_M), enc
    assert metres_to_millimetres(np.array([65.5354, 65.5356, 0.0004, 0.0006])).tolist() == [
        65535,
        0,
        0,
        1,
    ]


def test_intrinsics_of_the_rgb_image_are_refused_near_centre_ones_taken() -> None:
    """ARKit's K is for the 1920 x 1440 RGB image. Sent unscaled with a 256 x 192 depth, the
    frame was taken and a wall 2.7 m wide came out 0.36 m wide, off to one side."""
    depth = np.full((192, 256), 2.0, np.float32)
    rgb_k = np.array([[1400.0, 0.0, 960.0], [0.0, 1400.0, 720.0], [0.0, 0.0, 1.0]])
    dec = bp.FrameDecoder()
    assert dec.feed(bp.encode_frame(1.0, rgb_k, depth)) == []
    assert [e.reason for e in dec.errors] == ["bad_intrinsics"]
    assert "not scaled to the depth resolution" in str(dec.errors[0])
    scaled = rgb_k * [[256 / 1920], [192 / 1440], [1.0]]
    off = scaled.copy()
    off[:2, 2] += (0.2 * 256, -0.2 * 192)
    for k in (scaled, off):  # a principal point 20 % off the centre is still a camera's
        (f,) = bp.FrameDecoder().feed(bp.encode_frame(1.0, k, depth))
        np.testing.assert_allclose(f.K, k)


def test_stream_split_anywhere_and_hello_status() -> None:
    stream = bp.encode_hello("s3cret", "test") + _frame_bytes(seq=1) + _frame_bytes(seq=2)
    dec = bp.FrameDecoder()
    out: list[bp.Message] = []
    for i in range(len(stream)):  # one byte at a time
        out += dec.feed(stream[i : i + 1])
    assert out[0] == bp.Hello("s3cret", "test")
    assert [m.seq for m in out[1:]] == [1, 2]  # type: ignore[union-attr]
    assert dec.buffered == 0 and not dec.errors
    st_dec = bp.FrameDecoder(accept=(bp.MSG_STATUS,))
    assert st_dec.feed(bp.encode_status(bp.STATUS_BUSY, "busy")) == [bp.Status(2, "busy")]


def _patch_header(raw: bytes, fmt_index: int, value: object) -> bytes:
    fields = list(bp.FRAME_HEADER.unpack_from(raw, bp.PREFIX.size))
    fields[fmt_index] = value
    return (
        raw[: bp.PREFIX.size]
        + bp.FRAME_HEADER.pack(*fields)
        + raw[bp.PREFIX.size + bp.FRAME_HEADER.size :]
    )


@pytest.mark.parametrize(
    ("index", "value", "reason"),
    [
        (0, float("nan"), "bad_stamp"),
        (0, -1.0, "bad_stamp"),
        (0, 1e300, "bad_stamp"),  # finite, but no builtin_interfaces/Time holds it
        (0, 2.0**31 - 1, "bad_stamp"),
        (2, 0, "bad_size"),
        (2, 9, "size_mismatch"),
        (4, 0.0, "bad_intrinsics"),
        (6, float("inf"), "bad_intrinsics"),
        # finite and positive, but no camera's: its rays overflowed float32 into inf points
        (4, 1e-40, "bad_intrinsics"),
        (5, 1e9, "bad_intrinsics"),
        (6, -3e6, "bad_intrinsics"),
        # the 8 x 6 frame's K at 1920 x 1440 (not scaled to the depth): squashed clouds
        (6, 960.0, "bad_intrinsics"),
        (7, 720.0, "bad_intrinsics"),
        (15, 9, "bad_depth_encoding"),
        (15, bp.DEPTH_U16_MM, "size_mismatch"),
        (16, 5, "bad_confidence_encoding"),
        (17, 7, "bad_pose_axes"),
        (14, 5.0, "bad_pose"),  # qw: quaternion no longer unit
        (8, float("nan"), "bad_pose"),
        # finite, and on /iphone/odometry it stopped the mapper for good (a review)
        (8, 1e300, "bad_pose"),
    ],
)
def test_bad_frames_are_rejected_and_stream_stays_in_sync(
    index: int, value: object, reason: str
) -> None:
    pose = np.eye(4)
    bad = _patch_header(_frame_bytes(pose=pose), index, value)
    dec = bp.FrameDecoder()
    out = dec.feed(bad + _frame_bytes(seq=5))
    assert [m.seq for m in out] == [5]  # type: ignore[union-attr]
    (err,) = dec.pop_errors()
    assert err.reason == reason and not err.fatal and str(err)


def test_largest_stamp_still_publishable() -> None:
    from wheelgrid_mapping.iphone_bridge_node import stamp_to_msg

    stamp = np.nextafter(bp.MAX_STAMP_S, 0.0)
    (f,) = bp.FrameDecoder().feed(
        bp.encode_frame(stamp, k_for(np.ones((2, 2))), np.ones((2, 2), np.float32))
    )
    assert stamp_to_msg(f.stamp).sec == 2**31 - 2  # fits int32, nanoseconds did not carry


def test_feed_ordered_reports_errors_where_they_were() -> None:
    """The server counts bad messages *in a row*: it needs them in stream order."""
    bad = _patch_header(_frame_bytes(pose=np.eye(4)), 14, 0.0)  # |q| = 0: bad_pose
    dec = bp.FrameDecoder()
    items = dec.feed_ordered(bad + _frame_bytes(seq=1) + bad + bad + _frame_bytes(seq=2))
    kinds = [
        it.reason if isinstance(it, bp.ProtocolError) else getattr(it, "seq", None) for it in items
    ]
    assert kinds == ["bad_pose", 1, "bad_pose", "bad_pose", 2]
    assert dec.errors == []  # returned, not queued as well
    # feed() keeps its contract: messages returned, errors queued
    assert [m.seq for m in dec.feed(bad + _frame_bytes(seq=3))] == [3]  # type: ignore[union-attr]
    assert [e.reason for e in dec.pop_errors()] == ["bad_pose"]


def test_oversized_is_skipped_without_buffering() -> None:
    dec = bp.FrameDecoder(max_frame_bytes=1000)
    big = _frame_bytes(w=64, h=64)
    out = []
    for i in range(0, len(big), 100):
        out += dec.feed(big[i : i + 100])
        assert dec.buffered <= bp.PREFIX.size
    out += dec.feed(_frame_bytes(w=4, h=4, seq=3))
    assert [m.seq for m in out] == [3]  # type: ignore[union-attr]
    assert [e.reason for e in dec.pop_errors()] == ["oversized"]


def test_unknown_type_short_body_and_bad_hello() -> None:
    dec = bp.FrameDecoder()
    junk = bp.PREFIX.pack(bp.MAGIC, bp.VERSION, 99, 0, 3) + b"abc"
    short = bp.PREFIX.pack(bp.MAGIC, bp.VERSION, bp.MSG_FRAME, 0, 4) + b"abcd"
    hello = (
        bp.PREFIX.pack(bp.MAGIC, bp.VERSION, bp.MSG_HELLO, 0, 4) + struct.pack("<H", 900) + b"xx"
    )
    assert dec.feed(junk + short + hello) == []
    assert [e.reason for e in dec.pop_errors()] == ["unexpected_type", "short_frame", "bad_hello"]
    with pytest.raises(ValueError, match="token"):
        bp.encode_hello("x" * 300)


def test_bad_magic_and_version_are_fatal() -> None:
    dec = bp.FrameDecoder()
    with pytest.raises(bp.ProtocolError) as exc:
        dec.feed(b"GET / HTTP/1.1\r\n\r\n")
    assert exc.value.fatal and exc.value.reason == "bad_magic" and dec.failed
    with pytest.raises(bp.ProtocolError):
        dec.feed(_frame_bytes())  # stays failed
    dec2 = bp.FrameDecoder()
    good = _frame_bytes(seq=1)
    out = dec2.feed(good + bp.PREFIX.pack(bp.MAGIC, 2, bp.MSG_FRAME, 0, 0))
    assert [m.seq for m in out] == [1] and dec2.failed  # type: ignore[union-attr]
    with pytest.raises(bp.ProtocolError, match="bad_version"):
        dec2.feed(b"")


# ---- fuzzing: whatever arrives, the decoder returns/raises ProtocolError, never anything else,
# finishes, and holds at most one prefix + max_frame_bytes.
LIMIT = 4096
_VALID = [_frame_bytes(w=4, h=3, seq=i, pose=np.eye(4)) for i in range(3)] + [bp.encode_hello("t")]


def _run_decoder(chunks: list[bytes]) -> None:
    dec = bp.FrameDecoder(max_frame_bytes=LIMIT)
    for chunk in chunks:
        try:
            out = dec.feed(chunk)
        except bp.ProtocolError as exc:
            assert exc.fatal and dec.failed
            return
        assert dec.buffered <= bp.PREFIX.size + LIMIT
        for m in out:
            assert isinstance(m, bp.Frame | bp.Hello)
        for e in dec.pop_errors():
            assert isinstance(e, bp.ProtocolError) and e.reason


@settings(
    max_examples=300, database=None, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(st.lists(st.binary(max_size=300), max_size=20))
def test_fuzz_random_bytes(chunks: list[bytes]) -> None:
    _run_decoder(chunks)


@settings(
    max_examples=300, database=None, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    st.lists(st.sampled_from(range(len(_VALID))), min_size=1, max_size=4),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), max_size=8),
    st.integers(0, 10_000),
    st.integers(1, 500),
)
def test_fuzz_mutated_valid_stream(
    picks: list[int], flips: list[tuple[int, int]], cut: int, chunk: int
) -> None:
    """Valid messages with bytes overwritten, truncated, and split at random boundaries."""
    data = bytearray(b"".join(_VALID[i] for i in picks))
    for pos, val in flips:
        data[pos % len(data)] = val
    data = data[: max(1, len(data) - cut % len(data))]
    _run_decoder([bytes(data[i : i + chunk]) for i in range(0, len(data), chunk)])


@settings(max_examples=200, database=None, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 255), st.binary(max_size=64))
def test_fuzz_claimed_lengths(length: int, mtype: int, tail: bytes) -> None:
    """A peer claiming up to 4 GiB never makes the decoder buffer more than its limit."""
    _run_decoder([bp.PREFIX.pack(bp.MAGIC, bp.VERSION, mtype, 0, length) + tail, _VALID[0]])


def test_the_ranges_the_bridge_and_depth_to_cloud_declare_hold_every_valid_value_and_no_other():
    """Neither node's parameters carried a range (`ros2 param describe` showed none, and rqt
    drew no slider). Each declared range holds every value the node takes and no other: the
    bridge's network settings are checked where its server is made, before anything listens."""
    from wheelgrid_common.testing import check_declared_bounds
    from wheelgrid_mapping import depth_to_cloud_node as d2c
    from wheelgrid_mapping import iphone_bridge_node as bridge

    def check_bridge(cfg: bridge.BridgeConfig) -> None:
        bridge.check_config(cfg)
        bp.BridgeServer(
            lambda frame, client: None,
            lambda level, text: None,
            bind_address=cfg.bind_address,
            port=cfg.port,
            token=cfg.token,
            max_clients=cfg.max_clients,
            max_frame_bytes=cfg.max_frame_bytes,
            hello_timeout_s=cfg.hello_timeout_s,
            idle_timeout_s=cfg.idle_timeout_s,
            max_errors_in_row=cfg.max_errors_in_row,
        )

    assert check_declared_bounds(bridge.BridgeConfig, check_bridge) == [
        "hello_timeout_s",
        "idle_timeout_s",
        "max_clients",
        "max_errors_in_row",
        "max_frame_bytes",
        "min_confidence",
        "port",
    ]
    assert check_declared_bounds(d2c.DepthToCloudConfig, d2c.check_config) == [
        "min_confidence",
        "mm_scale",
        "queue_size",
        "sync_tolerance_s",
    ]
