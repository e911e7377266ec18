"""The mapping time (:mod:`wheelgrid_mapping.frame_clock`): a stamp far ahead of its arrival
is held back, a replay faster than real time is not, and the clock's jumps either way leave
the mapping time monotone and continuous."""

from __future__ import annotations

import pytest

from wheelgrid_mapping.frame_clock import AHEAD_CONFIRM, FrameClock


def _feed(clock: FrameClock, stamps: list[float], received: list[float | None]) -> list[str]:
    """Each frame checked and, unless held back, admitted (as :class:`Mapper` does with no
    keyframe interval and no clock going back): its verdict, "ok", "ahead" or "jump"."""
    said = []
    for i, (s, r) in enumerate(zip(stamps, received, strict=True)):
        v = clock.check(s, r)
        if v.ahead_s > 0:
            said.append("ahead")
            continue
        clock.admit(i, s, r, v.jumped_forward, 0.0)
        said.append("jump" if v.jumped_forward else "ok")
    return said


def test_one_stamp_far_ahead_is_held_back_and_the_stream_goes_on() -> None:
    clock = FrameClock()
    stamps = [0.0, 0.2, 0.4, 1e6, 0.6, 0.8]
    said = _feed(clock, stamps, [0.5 + 0.2 * i for i in range(6)])  # arrivals 0.2 s apart
    assert said == ["ok", "ok", "ok", "ahead", "ok", "ok"]
    assert clock.offset == 0.0 and clock.jumps == []


def test_a_replay_ten_times_faster_with_a_pause_in_it_is_no_alarm() -> None:
    """A 5 Hz bag with a 3 s pause replayed at --rate 10: the pause arrives in 0.3 s. Read
    against real time it is 2.7 s ahead; against the stream's pace it is on time."""
    stamps = [0.2 * i for i in range(8)] + [1.4 + 3.0 + 0.2 * i for i in range(4)]
    received = [100.0 + s / 10.0 for s in stamps]
    assert _feed(FrameClock(), stamps, received) == ["ok"] * 12
    unpaced = [100.0 + 0.013 * i for i in range(12)]  # as fast as the frames are processed
    assert _feed(FrameClock(), stamps, unpaced) == ["ok"] * 12


def test_a_clock_that_jumped_forward_is_taken_after_a_few_frames() -> None:
    """A publisher restarted on a clock 500 s later: the first frames on it are held back as
    bad stamps, then the new clock is taken and the mapping time goes on by the 0.2 s the
    arrivals say passed, not by 500 s (the jump check would let any pose through that)."""
    clock = FrameClock()
    stamps = [0.2 * i for i in range(5)] + [500.0 + 0.2 * i for i in range(5)]
    said = _feed(clock, stamps, [0.2 * i for i in range(10)])
    assert said == ["ok"] * 5 + ["ahead"] * (AHEAD_CONFIRM - 1) + ["jump"] + ["ok"] * 2
    (jump,) = clock.jumps
    k = 5 + AHEAD_CONFIRM - 1
    assert jump["frame"] == k
    # the frame before was stamped 0.8; arrivals say 0.2 * (k - 4) s passed since
    assert stamps[k] + clock.offset == pytest.approx(0.8 + 0.2 * (k - 4))
    assert jump["jump_s"] == pytest.approx(stamps[k] - (0.8 + 0.2 * (k - 4)))


def test_a_clock_that_goes_back_without_arrival_times_goes_on_by_the_usual_interval() -> None:
    """A Stray export has stamps only: a step back is a new time base all the same (the
    Mapper says so), and the mapping time goes on by the frames' usual interval."""
    clock = FrameClock()
    times = [clock.admit(i, 10.0 + 0.25 * i, None, False, 0.0) for i in range(4)]
    times += [clock.admit(4, 3.0, None, True, 0.0), clock.admit(5, 3.25, None, False, 0.0)]
    assert times == pytest.approx([10.0, 10.25, 10.5, 10.75, 11.0, 11.25])
    assert clock.jumps == [{"frame": 4, "stamp": 3.0, "jump_s": -8.0, "offset_s": 8.0}]


def test_a_frame_between_two_bad_stamps_forgets_the_first() -> None:
    """Two bad stamps apart, each on its own clock: neither is a new clock's start."""
    clock = FrameClock()
    stamps = [0.0, 0.2, 0.4, 900.0, 0.6, 5000.0, 0.8, 1.0]
    said = _feed(clock, stamps, [0.2 * i for i in range(8)])
    assert said == ["ok", "ok", "ok", "ahead", "ok", "ahead", "ok", "ok"]


def test_a_frame_delivered_late_does_not_make_the_frames_after_it_early() -> None:
    """A 1.6 s stall in delivery: the one frame of the backlog admitted (a busy node takes the
    newest of those queued, and drops the rest) arrived 1.6 s late. Predicted from it alone,
    the on-time frames after it were 1.2-1.3 s "ahead": held back, then taken for a clock jump
    (a review). Each recent frame predicts, and the latest prediction counts."""
    clock = FrameClock()
    stamps = [0.2 * i for i in range(12)]
    received = [s + 0.05 for s in stamps]
    received[6] += 1.6  # delivered late; the frames 7-13 it held up were dropped as busy
    stamps = stamps[:7] + [0.2 * i for i in range(14, 20)]
    received = received[:7] + [0.2 * i + 0.05 for i in range(14, 20)]
    assert _feed(clock, stamps, received) == ["ok"] * 13
    assert clock.offset == 0.0 and clock.jumps == []
