"""Frames prepared one ahead in a second process: the same map as one process, nothing lost."""

from __future__ import annotations

import numpy as np
import pytest

from wheelgrid_common.testing import body_frame_room
from wheelgrid_mapping.pipeline import FrameOutcome, Mapper, MapperConfig
from wheelgrid_mapping.prefetch import FramePipeline


def frames(n: int = 8) -> list[tuple[np.ndarray, float]]:
    """A sensor backing away from a furnished corner, 5 cm a frame at 5 Hz; frame 3 comes
    0.05 s after frame 2 (a keyframe interval of 0.1 s skips it) and frame 5 is all NaN."""
    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        pts = body_frame_room(rng, True) - [0.05 * i, 0.0, 0.0]
        stamp = i * 0.2 if i != 3 else 0.45
        if i == 5:
            pts = np.full_like(pts, np.nan)
        out.append((pts, stamp))
    return out


def mapper() -> Mapper:
    return Mapper(cfg=MapperConfig(level_min_frames=2, min_frame_interval=0.1))


def reference() -> tuple[Mapper, list[tuple[float, str]]]:
    m = mapper()
    seen = [(t, m.add_frame(p, t, "base_link").status) for p, t in frames()]
    return m, seen


def run(pipe: FramePipeline, given: list[tuple[np.ndarray, float]]) -> list[tuple[float, str]]:
    seen: list[tuple[float, FrameOutcome]] = []
    for pts, stamp in given:
        seen.extend(pipe.push(pts, stamp, "base_link"))
    seen.extend(pipe.flush())
    return [(t, o.status) for t, o in seen]


def assert_same_map(a: Mapper, b: Mapper) -> None:
    assert a.stamps == b.stamps
    # KISS-ICP's two threads sum in varying order: the same map to the last bits
    np.testing.assert_allclose(np.array(a.poses_odom), np.array(b.poses_odom), atol=1e-9)
    ra, rb = a.report(), b.report()
    assert ra["frames"] == rb["frames"] and ra["points"] == rb["points"]
    np.testing.assert_allclose(a.map_points(), b.map_points(), atol=1e-6)


@pytest.mark.parametrize("ahead", [True, False])
def test_frames_prepared_ahead_make_the_map_add_frame_makes(ahead: bool) -> None:
    ref, ref_seen = reference()
    m = mapper()
    with FramePipeline(m, ahead) as pipe:
        assert pipe.ahead == ahead
        seen = run(pipe, frames())
    assert not pipe.ahead  # leaving the block ended the second process
    # every frame has its outcome once, in order, skipped and empty ones included
    assert sorted(seen) == sorted(ref_seen)
    assert [s for _, s in ref_seen].count("skipped") == 1
    assert [s for _, s in ref_seen].count("empty") == 1
    assert_same_map(ref, m)
    assert m.timings["preprocess_s"] > 0


def test_a_frame_that_raises_is_its_own_error_and_the_next_ones_are_mapped() -> None:
    given = frames()
    given.insert(4, (np.zeros(10), 0.7))  # 10 numbers: no (N, 3) cloud
    m = mapper()
    with FramePipeline(m, True) as pipe:
        seen = run(pipe, given)
        assert pipe.ahead  # the second process survives a bad frame
    assert (0.7, "error") in seen
    ref, _ = reference()
    assert m.stamps == ref.stamps  # and every good frame is mapped as before
    assert m.frames_read == ref.frames_read + 1


@pytest.mark.parametrize("ahead", [True, False])
def test_each_outcome_names_its_own_frame_by_number(ahead: bool) -> None:
    """The outcomes come back one frame late, a frame skipped at admission ahead of the one in
    preparation: matched to their frames by stamp, two clouds stamped alike swapped numbers
    (the CLI kept a queue per stamp for it). Each outcome carries its frame's input number:
    a repeat (skipped), a frame that raises (error) and the numbers given, not counted."""
    given = frames(6)
    given.insert(2, (given[1][0].copy(), given[1][1]))  # frame 1 delivered twice
    given.insert(5, (np.zeros(10), 0.7))  # 10 numbers: no (N, 3) cloud
    numbers = [100 + 3 * k for k in range(len(given))]  # not the mapper's own count
    m = mapper()
    with FramePipeline(m, ahead) as pipe:
        seen: list[tuple[float, FrameOutcome]] = []
        for (pts, stamp), number in zip(given, numbers, strict=True):
            seen.extend(pipe.push(pts, stamp, "base_link", number=number))
        seen.extend(pipe.flush())
    by_number = {o.number: o for _, o in seen}
    assert sorted(by_number) == numbers  # each frame once, under its own number
    assert by_number[numbers[2]].cause == "out_of_order"  # the repeat, not frame 1
    assert by_number[numbers[1]].status == "used"
    assert by_number[numbers[5]].status == "error"
    stamps = {o.number: t for t, o in seen}
    assert [stamps[n] for n in numbers] == [t for _, t in given]


def test_the_second_process_dying_loses_no_frame() -> None:
    given = frames()
    m = mapper()
    with FramePipeline(m, True) as pipe:
        seen = run(pipe, given[:3])
        assert pipe._worker is not None
        pipe._worker.proc.kill()  # with frame 2 in it
        pipe._worker.proc.join(5.0)
        for pts, stamp in given[3:]:
            seen.extend((t, o.status) for t, o in pipe.push(pts, stamp, "base_link"))
        seen.extend((t, o.status) for t, o in pipe.flush())
        assert not pipe.ahead and "second one failed" in pipe.note
    ref, ref_seen = reference()
    assert sorted(seen) == sorted(ref_seen)
    assert_same_map(ref, m)


def test_a_reset_drops_the_frame_in_preparation_and_its_answer() -> None:
    given = frames()
    m = mapper()
    with FramePipeline(m, True) as pipe:
        run(pipe, given[:2])
        pipe.push(*given[6], "base_link")  # in the second process now
        assert pipe.pending
        pipe.discard()
        m.reset()
        assert not pipe.pending
        seen = run(pipe, given)  # the answer for the dropped frame is not read as frame 0's
    ref, ref_seen = reference()
    assert sorted(seen) == sorted(ref_seen)
    assert_same_map(ref, m)


def test_close_ends_the_second_process() -> None:
    pipe = FramePipeline(mapper(), True)
    assert pipe._worker is not None
    proc = pipe._worker.proc
    pipe.push(*frames()[0], "base_link")
    pipe.flush()
    peak = pipe.worker_peak_bytes()  # its own pages (Linux), not those it was forked with
    assert peak is not None and 20 * 2**20 < peak < 2**30
    pipe.close()
    assert pipe.worker_peak_bytes() is None
    assert not proc.is_alive() and proc.exitcode is not None


@pytest.mark.parametrize("ahead", [True, False])
def test_a_frame_is_pending_until_its_outcome_is_counted(
    ahead: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``flush`` cleared ``pending`` before it added the frame: a reader that saw nothing
    pending (the mapper node's worker, a test waiting for the node to settle) read the counts
    while the last frame was still being registered, and one CI run saw the outcomes add up to
    3 of 4 frames received."""
    m = mapper()
    seen_pending: list[bool] = []
    real = Mapper.add_prepared

    with FramePipeline(m, ahead) as pipe:

        def watched(
            self: Mapper,
            prep: object,
            prior: object = None,
            after_gap: object = None,
            dropped_priors: object = None,
        ) -> FrameOutcome:
            seen_pending.append(pipe.pending)
            return real(self, prep, prior, after_gap, dropped_priors)  # type: ignore[arg-type]

        monkeypatch.setattr(Mapper, "add_prepared", watched)
        run(pipe, frames(3))
        assert not pipe.pending  # and cleared once added
    assert seen_pending and all(seen_pending), seen_pending
