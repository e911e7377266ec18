"""The mapping time of each frame: its stamp, checked against when it arrived (ROS-free).

A frame's header stamp drives the jump check (a chair moves at most ``max_speed`` times the
time between two frames), the keyframe interval, the loop closure's submaps and
``trajectory.tum``. Two faults in that stamp used to pass unseen:

* **a frame stamped in the future** (one bad stamp from a driver, a bit flip in a recorder):
  its dt of hours let any pose through the jump check, and the file's stamps went back at the
  next frame. Where a frame's receipt time is known (a bag's log time, the node's clock when
  the cloud arrived), a frame stamped more than :data:`AHEAD_WINDOW` further on than the
  stream's pace since the frame before predicts is held back: skipped and counted. The pace
  is read from the last frames (stamp seconds per receipt second), so a bag replayed at
  ``--rate 10``, or unpaced, with a pause in it is no false alarm; the window grows with the
  pace. A clock that really jumped forward (a publisher restarted on another clock) is taken
  once :data:`AHEAD_CONFIRM` frames in a row agree on it, so the map never stops for good.
* **a clock that goes back** (a publisher restarted, a clock set): the frames after it were
  mapped on their own stamps, and ``trajectory.tum`` went back in time, which no TUM reader
  takes. The mapping time now goes on from the frame before: each jump shifts the later
  stamps by one offset, so the trajectory stays monotone and continuous; the report lists
  every jump with its offset, so a user can undo it. The pipeline takes a clock that went back
  on its second frame in a row (one frame stamped back, a driver's 0, is a bad stamp:
  ``pipeline.BEHIND_CONFIRM``).

A Stray export has no arrival times; its capture order stands in for them (a frame was
taken no later than the frames after it: :meth:`.stray.StrayExport.captured_by`), which
holds back one stamp far ahead and leaves a real pause a pause. Being on the stamps' own
clock, it holds back such a frame among the first two as well, before any pace is known
(``receipts_on_stamp_clock``): one bad stamp on frame 0 or 1 shifted every line of
trajectory.tum by its lead and cost the frames after it (a review). Without either (the API
called with stamps only) a stamp far ahead cannot be told from a pause in the stream and is
taken as it comes; the clock going back is still caught from the stamps alone.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

# A frame stamped this much further on than the stream's pace since the frame before predicts
# (seconds of the stamps' clock, times the pace where a replay runs faster than real time) is
# stamped ahead: a healthy stream's latency varies by milliseconds to a few hundred of them.
AHEAD_WINDOW = 1.0
# This many frames in a row ahead, agreeing with each other on the new clock (within the
# window), are a clock that jumped forward, not a bad stamp: the last of them is mapped.
AHEAD_CONFIRM = 3
# The pace (stamp seconds per receipt second) is read over this many admitted frames.
PACE_FRAMES = 10
# The interval assumed between two frames at a jump when nothing better is known (s).
DEFAULT_INTERVAL = 0.1


@dataclass
class Verdict:
    """What :meth:`FrameClock.check` made of one frame's stamp."""

    ahead_s: float = 0.0  # > 0: stamped this far ahead of the stream's pace; hold it back
    jumped_forward: bool = False  # the clock jumped forward (confirmed): a new time base


class FrameClock:
    """Maps each admitted frame's stamp to a continuous mapping time (``stamp + offset``)."""

    def __init__(self, receipts_on_stamp_clock: bool = False) -> None:
        # receipts on the stamps' own clock, a frame's stamp never after it (a Stray export's
        # capture order): a lead is a bad stamp from the first frame on
        self.receipts_on_stamp_clock = receipts_on_stamp_clock
        self.offset = 0.0  # mapping time = stamp + offset (changes at each clock jump only)
        # (stamp, receipt) of the last admitted frames since the last jump: the stream's pace,
        # which a replay faster than real time (``--rate``, unpaced) sets, not the sensor
        self._recent: deque[tuple[float, float]] = deque(maxlen=PACE_FRAMES)
        self._suspects: list[float] = []  # stamp - pace * receipt of the frames held back
        self._last_time: float | None = None  # mapping time of the last admitted frame
        self._intervals: deque[float] = deque(maxlen=9)  # between admitted frames (s)
        self.jumps: list[dict[str, Any]] = []

    def _pace(self) -> float | None:
        """Stamp seconds per receipt second over the recent admitted frames; None before two
        frames moved both."""
        if len(self._recent) < 2:
            return None
        s0, r0 = self._recent[0]
        # the fastest the stamps went from the first: one frame delivered late (a stall) read
        # slow over the span it ends, and on-time frames after it seemed early
        paces = [(s - s0) / (r - r0) for s, r in list(self._recent)[1:] if r > r0 and s > s0]
        return max(paces) if paces else None

    def check(self, stamp: float, received: float | None) -> Verdict:
        """Whether ``stamp`` is further on than the stream's pace since the last admitted frame
        predicts for the time its receipt says passed (never without receipt times, nor
        before two frames have set the pace)."""
        pace = self._pace()
        if received is None:
            return Verdict()
        if pace is None:
            lead = float(stamp) - float(received)
            if self.receipts_on_stamp_clock and lead > AHEAD_WINDOW:
                return Verdict(ahead_s=lead)
            return Verdict()
        window = AHEAD_WINDOW * max(pace, 1.0)
        # From each recent frame, the latest prediction: one delivered late (a stall in the
        # bridge or DDS, the node's worker busy) predicted the frames after it too early, and
        # on-time frames were held back as "ahead", then taken for a clock jump (a review)
        r = float(received)
        predicted = max(s + pace * max(r - rk, 0.0) for s, rk in self._recent)
        ahead = float(stamp) - predicted
        if ahead <= window:
            self._suspects.clear()
            return Verdict()
        base = float(stamp) - pace * float(received)  # where the new clock starts, if it is one
        if self._suspects and abs(base - self._suspects[0]) > window:
            self._suspects.clear()
        self._suspects.append(base)
        if len(self._suspects) < AHEAD_CONFIRM:
            return Verdict(ahead_s=ahead)
        self._suspects.clear()
        return Verdict(jumped_forward=True)

    def interval(self) -> float:
        """The usual interval between admitted frames: the lower median of the last ones, so
        that one pause (or one stamp far ahead, without arrival times to tell it) among few
        intervals is not it; :data:`DEFAULT_INTERVAL` before any."""
        if not self._intervals:
            return DEFAULT_INTERVAL
        return sorted(self._intervals)[(len(self._intervals) - 1) // 2]

    def admit(
        self, index: int, stamp: float, received: float | None, jumped: bool, min_gap: float
    ) -> float:
        """The mapping time of an admitted frame; ``jumped``: its stamp is on a new time base
        (the clock went back, or forward as :meth:`check` confirmed), and the mapping time
        goes on from the frame before it by the time the stream's pace says passed, else by
        the usual interval between frames (at least ``min_gap``)."""
        stamp = float(stamp)
        if jumped and self._last_time is not None:
            gap = 0.0
            pace = self._pace()
            if received is not None and pace is not None:
                gap = pace * (float(received) - self._recent[-1][1])
            if gap <= 0.0:
                gap = self.interval()
            gap = max(gap, min_gap, 1e-3)
            old = self.offset
            self.offset = self._last_time + gap - stamp
            self.jumps.append(
                {
                    "frame": index,
                    "stamp": stamp,
                    "jump_s": round(old - self.offset, 6),  # the clock's own step, + forward
                    "offset_s": round(self.offset, 6),
                }
            )
        if jumped:
            self._recent.clear()
        t_map = stamp + self.offset
        if self._last_time is not None and not jumped:
            self._intervals.append(t_map - self._last_time)
        self._last_time = t_map
        if received is not None:
            self._recent.append((stamp, float(received)))
        return t_map
