"""Wire format: CRC, framing, resynchronisation after damage, payloads and the speed cap."""

import pytest

from wheelgrid_drive import protocol as proto


def test_crc16_ccitt_false_check_value():
    assert proto.crc16(b"123456789") == 0x29B1


def test_round_trip_split_at_every_byte():
    frames = [
        proto.Frame(7, proto.MsgType.FORWARD, proto.pack_move(1.2, 3.0)),
        proto.Frame(8, proto.MsgType.HEARTBEAT),
        proto.Frame(255, proto.MsgType.STATUS, bytes(range(18))),
    ]
    wire = b"".join(f.encode() for f in frames)
    for cut in range(len(wire) + 1):
        dec = proto.FrameDecoder()
        out = dec.feed(wire[:cut]) + dec.feed(wire[cut:])
        assert out == frames
        assert dec.pending() == 0


def test_documented_example_frame():
    # docs/serial-protocol.md: FORWARD seq 7, 1200 mm at 833 mm/s.
    data = proto.encode(7, proto.MsgType.FORWARD, proto.pack_move(1.2, 3.0))
    assert data[:8] == bytes.fromhex("A5040710 04B00341".replace(" ", ""))
    assert int.from_bytes(data[8:], "big") == proto.crc16(data[1:8])


def test_damage_is_reported_and_the_next_frame_still_decodes():
    good = proto.Frame(3, proto.MsgType.ACK, bytes([0x10]))
    bad = bytearray(proto.Frame(2, proto.MsgType.ACK, bytes([0x10])).encode())
    bad[3] ^= 0x01  # flips the type: CRC must catch it
    dec = proto.FrameDecoder()
    out = dec.feed(b"\x00\x13junk" + bytes(bad) + good.encode())
    errors = [o for o in out if isinstance(o, proto.DecodeError)]
    assert errors, "damage must be reported, not skipped silently"
    assert out[-1] == good
    assert all(isinstance(o, proto.DecodeError) for o in out[:-1])


def test_oversize_length_resyncs():
    good = proto.Frame(1, proto.MsgType.STOP)
    dec = proto.FrameDecoder()
    out = dec.feed(bytes([proto.SOF, 200]) + good.encode())
    assert isinstance(out[0], proto.DecodeError) and out[-1] == good


def test_a_frame_cut_off_is_given_up_after_the_gap_and_frames_held_behind_it_come_out():
    """A stray SOF and a LEN of 64 or less claimed the next 70 bytes: the STOP just behind it
    waited until enough heartbeats came to fail the CRC (100-400 ms on the wire)."""
    stop = proto.Frame(9, proto.MsgType.STOP)
    dec = proto.FrameDecoder()
    assert dec.feed(bytes([proto.SOF, 0x40]) + stop.encode(), now=10.0) == []
    assert dec.feed(b"", now=10.0 + proto.FRAME_GAP_S * 0.9) == []  # not yet a gap
    out = dec.feed(b"", now=10.0 + proto.FRAME_GAP_S)
    assert isinstance(out[0], proto.DecodeError) and "frame cut off" in out[0].reason
    assert out[1:] == [stop] and dec.pending() == 0
    # Two unfinished frames, one behind the other, both given up: nothing is held after.
    assert dec.feed(bytes([proto.SOF, 0x30, proto.SOF, 0x20, 1, 2]), now=20.0) == []
    out = dec.feed(b"", now=21.0)
    assert len(out) == 1 and isinstance(out[0], proto.DecodeError) and dec.pending() == 0


def test_the_rest_of_a_frame_fetched_late_by_a_busy_reader_is_not_a_gap():
    """Only a read that found nothing gives a frame up: the bytes a reader fetched long after
    they came are the rest of the frame."""
    frame = proto.Frame(4, proto.MsgType.STATUS, bytes(range(18)))
    wire = frame.encode()
    dec = proto.FrameDecoder()
    assert dec.feed(wire[:5], now=1.0) == []
    assert dec.feed(wire[5:], now=2.0) == [frame]


def test_speed_is_capped_at_3_kmh_and_distance_bounded():
    assert proto.MAX_SPEED_MM_S == 833
    assert proto.unpack_move(proto.pack_move(1.2, 3.0)) == (1200, 833)
    assert proto.unpack_move(proto.pack_move(1.2, 20.0)) == (1200, 833)  # clamped, never faster
    assert proto.unpack_move(proto.pack_move(0.6, 1.8)) == (600, 500)
    with pytest.raises(ValueError):
        proto.pack_move(0.0, 3.0)
    with pytest.raises(ValueError):
        proto.pack_move(2.5, 3.0)
    with pytest.raises(ValueError):
        proto.pack_move(1.2, float("nan"))


def test_status_and_pose_round_trip():
    st = proto.Status(
        1.234, -5.678, -1.571, proto.State.DRIVING, 42, proto.Result.RUNNING, proto.FLAG_WATCHDOG, 3
    )
    back = proto.unpack_status(proto.pack_status(st))
    assert back == st and back.moving and back.watchdog_tripped
    assert proto.unpack_pose(proto.pack_pose(0.6, -3.0, 3.0)) == (0.6, -3.0, 3.0)
    with pytest.raises(ValueError):
        proto.unpack_status(b"\x00" * 5)
    bad_state = bytearray(proto.pack_status(st))
    bad_state[12] = 9
    with pytest.raises(ValueError):
        proto.unpack_status(bytes(bad_state))
