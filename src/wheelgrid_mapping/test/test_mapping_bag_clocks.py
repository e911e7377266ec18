"""``wheelgrid map --prior arkit`` on a bag whose clouds and odometry are stamped on different
clocks, or whose odometry covers only part of the scan: the frames without a prior must be
said, not mapped geometry-only without a word. And stamps that jump, in a bag and in a Stray
export (which has no log time: its frame counter is the second clock)."""

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wheelgrid_common.fileio import read_tum
from wheelgrid_common.testing import edit_bag
from wheelgrid_mapping import cli_map
from wheelgrid_mapping.stray import StrayExport

SCAN = Path(__file__).resolve().parents[3] / "bags" / "paper_room" / "scan"
CLOUDS, ODOMETRY = "/iphone/points", "/iphone/odometry"


def _bag(
    out: Path,
    odom_shift_s: float,
    odom_keep: int | None = None,
    frames: int = 6,
    shift: Callable[[str, int], float] | None = None,
) -> Path:
    """The paper room's first ``frames`` clouds with its odometry, the odometry's header
    stamps moved by ``odom_shift_s`` (another clock) and only its first ``odom_keep`` kept;
    ``shift(topic, k)`` moves the k-th message of a topic's header stamp further (its log
    time, when the recorder got it, stays)."""
    if not (SCAN / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")

    def keep(topic: str, k: int) -> bool:
        return k < frames and (topic == CLOUDS or odom_keep is None or k < odom_keep)

    def moved(topic: str) -> Callable[[int, Any], None]:
        def edit(k: int, msg: Any) -> None:
            by = (odom_shift_s if topic == ODOMETRY else 0.0) + (shift(topic, k) if shift else 0.0)
            st = msg.header.stamp
            ns = st.sec * 1_000_000_000 + st.nanosec + round(by * 1e9)
            st.sec, st.nanosec = divmod(ns, 1_000_000_000)

        return edit

    topics = [CLOUDS, ODOMETRY]
    return edit_bag(SCAN, out, topics=topics, keep=keep, edits={t: moved(t) for t in topics})


def _run(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple[str, dict]:
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure", *extra]
    cli_map.main(argv)
    err = capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {}
    return err, rep


def test_odometry_on_another_clock_than_the_clouds_is_said(tmp_path, capsys) -> None:
    """Odometry stamped 1000 s off the clouds (the phone's uptime against the ROS clock): no
    frame found a prior within 0.1 s and the map was made geometry-only, without a word."""
    err, _ = _run(_bag(tmp_path / "bag", 1000.0), tmp_path, capsys)
    assert "6 of 6 frames had no odometry message within 0.1 s" in err
    assert "another clock" in err


def test_odometry_that_ends_early_is_counted(tmp_path, capsys) -> None:
    """Odometry for the first frames only (a recorder that lost the topic): the frames after
    it register without a prior, and that is said and reported."""
    err, rep = _run(_bag(tmp_path / "bag", 0.0, odom_keep=3), tmp_path, capsys)
    assert "3 of 6 frames had no odometry message within 0.1 s" in err
    assert "another clock" not in err
    if rep:
        assert rep["prior"]["frames_without"] == 3


def test_matching_odometry_says_nothing(tmp_path, capsys) -> None:
    err, rep = _run(_bag(tmp_path / "bag", 0.0), tmp_path, capsys)
    assert "no odometry message" not in err
    if rep:
        assert rep["prior"]["frames_without"] == 0


def test_odometry_of_another_frame_than_the_clouds_is_not_used_and_said(tmp_path, capsys):
    """Odometry of base_link, not of the camera the clouds are in (a REP-105 odom, which the
    README suggests as a prior): `wheelgrid map` read its poses as the camera's, one mount
    off, and made a map with doubled surfaces levelled 6 deg off, exit 0, no word (a
    review); the node did not use them. Neither does the CLI now: said and counted."""
    if not (SCAN / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")

    def rename(k: int, msg: Any) -> None:
        msg.child_frame_id = "base_link"
        msg.pose.pose.position.z -= 0.7  # where base_link would be: the mount's offset

    def keep(topic: str, k: int) -> bool:
        return k < 6

    bag = edit_bag(
        SCAN, tmp_path / "bag", topics=[CLOUDS, ODOMETRY], keep=keep, edits={ODOMETRY: rename}
    )
    err, rep = _run(bag, tmp_path, capsys)
    assert (
        "6 of 6 frames' odometry poses are of frame 'base_link', the clouds of "
        "'iphone_depth_optical_frame': the prior is not used" in err
    )
    assert "had no odometry message" not in err  # they had one: of another frame
    if rep:
        assert rep["prior"]["frames_of_another_frame"] == 6
        assert rep["prior"]["frames_without"] == 0


def test_a_cloud_stamped_far_ahead_of_its_log_time_is_skipped(tmp_path, capsys) -> None:
    """One cloud stamped 11.6 days ahead (a bad stamp from a driver): its dt let any pose
    through the jump check, and trajectory.tum went back in time at the next frame. The bag's
    log time says it came 0.2 s after the frame before: it is skipped, said and counted, and
    the frames after it map as if it had not come."""
    err, rep = _run(
        _bag(tmp_path / "bag", 0.0, frames=8, shift=lambda t, k: 1e6 if k == 4 else 0.0),
        tmp_path,
        capsys,
    )
    assert "stamped 1000000.00 s ahead" in err
    fr = rep["frames"]
    assert fr["stamped_ahead"] == 1 and fr["skipped"] == 1 and fr["clock_jumps"] == 0
    assert fr["used"] == 7 and fr["failed"] == 0
    assert rep["mapping_time"] == {"offset_s": 0.0, "jumps": []}
    stamps, _ = read_tum(tmp_path / "map" / "trajectory.tum")
    assert np.allclose(stamps - stamps[0], [0.0, 0.2, 0.4, 0.6, 1.0, 1.2, 1.4])


def test_a_clock_that_goes_back_leaves_the_trajectory_monotone(tmp_path, capsys) -> None:
    """The clouds and their odometry from the fifth on stamped 100 s earlier (a publisher
    restarted on another clock): those frames were mapped on their own stamps, and
    trajectory.tum went back in time, which no TUM reader takes. The second frame in a row on
    the new clock starts a new time base (the first is held back: one alone is a bad stamp),
    and the mapping time goes on from the frame before by the time the log says passed;
    report.json gives the offset, and every frame still found its prior."""
    err, rep = _run(
        _bag(tmp_path / "bag", 0.0, frames=8, shift=lambda t, k: -100.0 if k >= 4 else 0.0),
        tmp_path,
        capsys,
    )
    assert "no odometry message" not in err
    assert "frame 4 (and any like it): skipped: stamped 99.80 s before the frame before" in err
    fr = rep["frames"]
    assert fr["clock_jumps"] == 1 and fr["used"] == 7 and fr["skipped"] == 1
    assert fr["stamped_behind"] == 1 and fr["after_gap"] == 0 and fr["failed"] == 0
    (jump,) = rep["mapping_time"]["jumps"]
    assert jump["frame"] == 5 and jump["jump_s"] == pytest.approx(-100.0, abs=1e-6)
    assert rep["mapping_time"]["offset_s"] == pytest.approx(100.0, abs=1e-6)
    stamps, _ = read_tum(tmp_path / "map" / "trajectory.tum")
    assert np.allclose(np.diff(stamps), [0.2, 0.2, 0.2, 0.4, 0.2, 0.2], atol=1e-6)


def _stray_every_third(capture: Path, out: Path, frames: int, ahead: dict[int, float]) -> Path:
    """The real capture's first ``frames`` x 3 frames, every third kept (Stray's own numbers,
    as an export thinned by hand keeps them), the k-th kept row of odometry.csv stamped
    ``ahead[k]`` seconds later."""
    import shutil

    for sub in ("depth", "confidence"):
        (out / sub).mkdir(parents=True)
        for i in range(0, 3 * frames, 3):
            shutil.copy(capture / sub / f"{i:06d}.png", out / sub)
    shutil.copy(capture / "camera_matrix.csv", out)
    header, *rows = (capture / "odometry.csv").read_text().splitlines()
    kept = [header]
    for row in rows[: 3 * frames : 3]:
        t, rest = row.split(",", 1)
        k = len(kept) - 1
        kept.append(f"{float(t) + ahead.get(k, 0.0)!r},{rest}")
    (out / "odometry.csv").write_text("\n".join(kept) + "\n")
    return out


def test_a_stray_frame_stamped_behind_early_costs_only_itself(
    tmp_path, capsys, stray_capture: Path
) -> None:
    """Frame 2 stamped 2 s back: its stamp, the minimum of the next frames', was taken as when
    frames 0 and 1 were captured at the latest, and they were skipped as stamped ahead while
    frame 2 began the map (a review). The lower median of the frames after a frame is its
    bound: only frame 2 is skipped, as stamped behind."""
    cap = _stray_every_third(stray_capture, tmp_path / "cap", 16, {2: -2.0})
    err, rep = _run(cap, tmp_path, capsys)
    fr = rep["frames"]
    assert fr["stamped_ahead"] == 0 and fr["stamped_behind"] == 1, err
    assert fr["used"] == 15 and fr["after_gap"] == 0, fr
    stamps, _ = read_tum(tmp_path / "map" / "trajectory.tum")
    want = [StrayExport(cap).stamp(i) for i in range(16) if i != 2]
    np.testing.assert_allclose(stamps, want, atol=1e-6)


@pytest.mark.parametrize("bad", [8, 0, 1])
def test_a_stray_frame_stamped_far_ahead_is_skipped_by_its_place_in_capture_order(
    tmp_path, capsys, stray_capture: Path, bad: int
) -> None:
    """One row of odometry.csv stamped an hour ahead. An export has no log time, so the frame
    read as a pause in the capture: it was registered as after a dropout, and every later stamp
    in trajectory.tum came an hour late (report: a clock jump, offset 3600 s). Stray numbers
    frames in capture order, so it was taken before the frame after it: it is skipped, said and
    counted, and the others keep their own stamps. On frame 0 or 1, before two frames had set
    the stream's pace, it was not checked: the frames after it were taken as a clock gone back
    and every line of trajectory.tum came shifted (a review)."""
    cap = _stray_every_third(stray_capture, tmp_path / "cap", 16, {bad: 3600.0})
    err, rep = _run(cap, tmp_path, capsys)
    # (the next one's 0.05 s)
    assert f"frame {bad} (and any like it): skipped: stamped 3599.9" in err, err
    fr = rep["frames"]
    assert fr["stamped_ahead"] == 1 and fr["skipped"] == 1 and fr["clock_jumps"] == 0
    assert fr["used"] == 15 and fr["after_gap"] == 0
    assert rep["mapping_time"] == {"offset_s": 0.0, "jumps": []}
    stamps, _ = read_tum(tmp_path / "map" / "trajectory.tum")
    want = [StrayExport(cap).stamp(i) for i in range(16) if i != bad]
    np.testing.assert_allclose(stamps, want, atol=1e-6)


def test_a_stray_capture_that_stalled_stays_a_pause(tmp_path, capsys, stray_capture: Path) -> None:
    """Every row from the eighth on 2 s later (the app stalled and went on): a real pause,
    which the frame's place in capture order cannot tell from a jump of the clock. No frame is
    skipped, the first after it is registered as after a dropout, and every frame keeps its
    own stamp (the gap stays in trajectory.tum)."""
    cap = _stray_every_third(stray_capture, tmp_path / "cap", 16, {k: 2.0 for k in range(8, 16)})
    _, rep = _run(cap, tmp_path, capsys)
    fr = rep["frames"]
    assert fr["stamped_ahead"] == 0 and fr["skipped"] == 0 and fr["clock_jumps"] == 0
    assert fr["used"] == 16 and fr["after_gap"] == 1
    stamps, _ = read_tum(tmp_path / "map" / "trajectory.tum")
    np.testing.assert_allclose(stamps, [StrayExport(cap).stamp(i) for i in range(16)], atol=1e-6)


def test_import_and_stream_stray_time_a_frame_stamped_far_ahead_by_capture_order(
    tmp_path, capsys, stray_capture: Path
) -> None:
    """The same export through import-stray and stream-stray. The import wrote the bad frame
    with a log time an hour on (the end of the bag, where it read as a pause); the stream held
    the phone's next frame back for that hour. Both now time it by its place in capture order:
    the bag's log time lets `wheelgrid map` hold it back, and the stream plays in its 0.75 s."""
    from wheelgrid_common.bagio import BagReader
    from wheelgrid_mapping import bridge_protocol as bp
    from wheelgrid_mapping.cli_stray import import_main, stream_export

    cap = _stray_every_third(stray_capture, tmp_path / "cap", 16, {8: 3600.0})
    bag = tmp_path / "bag"
    assert import_main([str(cap), "--out", str(bag)]) == 0
    with BagReader(bag) as r:
        clouds = list(r.messages([CLOUDS]))
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, _, m in clouds]
    logged = [t * 1e-9 for _, t, _ in clouds]
    assert stamps[8] - stamps[7] > 3599.0  # the header keeps the export's stamp
    assert np.all(np.diff(logged) >= 0) and logged[8] <= logged[9]
    np.testing.assert_allclose(np.delete(logged, 8), np.delete(stamps, 8), atol=1e-6)
    err, rep = _run(bag, tmp_path, capsys)
    assert "stamped 3599.9" in err and rep["frames"]["stamped_ahead"] == 1

    got: list[bp.Frame] = []
    srv = bp.BridgeServer(lambda f, c: got.append(f), lambda lv, t: None, port=0)
    srv.start()
    try:
        stats = stream_export(StrayExport(cap), "127.0.0.1", srv.port, rate=1.0)
    finally:
        srv.stop()
    assert stats.frames_sent == 16 and stats.capture_s < 1.0
    assert stats.wall_s < 30.0  # an hour before; the frames' own pace is 0.75 s


def test_two_bad_stamps_in_a_row_are_no_dropout_of_the_stream(tmp_path, capsys) -> None:
    """Two clouds in a row with bad stamps (one an hour ahead, the next 1000 s back), both
    skipped: the hole they left in the stamps was read as a dropout of the stream, and the
    frames after it failed to the end (56 of 120 in a review's run). The log times say the
    stream never stopped: nothing after them fails."""
    bad = {20: 3600.0, 21: -1000.0}
    err, rep = _run(
        _bag(
            tmp_path / "bag",
            0.0,
            frames=40,
            shift=lambda t, k: bad.get(k, 0.0) if t == CLOUDS else 0.0,
        ),
        tmp_path,
        capsys,
    )
    fr = rep["frames"]
    assert fr["stamped_ahead"] == 1 and fr["stamped_behind"] == 1, err
    assert fr["after_gap"] == 0 and fr["failed"] == 0 and fr["used"] == 38, fr
