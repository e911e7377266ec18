"""``wheelgrid map --prior arkit`` on a bag whose clouds and odometry are stamped on different
clocks, or whose odometry covers only part of the scan: the frames without a prior must be
said, not mapped geometry-only without a word."""

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common.bagio import BagReader, BagWriter
from wheelgrid_common.fileio import read_tum
from wheelgrid_mapping import cli_map

SCAN = Path(__file__).resolve().parents[3] / "bags" / "paper_room" / "scan"


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
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    clouds = odoms = 0
    with BagReader(SCAN) as src, BagWriter(out) as w:
        for topic, msgtype, t_ns, raw in src.raw(["/iphone/points", "/iphone/odometry"]):
            if topic == "/iphone/points":
                if clouds >= frames:
                    continue
                k, clouds = clouds, clouds + 1
                moved = 0.0
            else:
                k, odoms = odoms, odoms + 1
                if (odom_keep is not None and odoms > odom_keep) or k >= frames:
                    continue
                moved = odom_shift_s
            moved += shift(topic, k) if shift is not None else 0.0
            if moved:
                msg = ts.deserialize_cdr(raw, msgtype)
                st = msg.header.stamp
                ns = st.sec * 1_000_000_000 + st.nanosec + round(moved * 1e9)
                st.sec, st.nanosec = divmod(ns, 1_000_000_000)
                raw = bytes(ts.serialize_cdr(msg, msgtype))
            w.write(topic, msgtype, t_ns, raw)
    return out


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
    trajectory.tum went back in time, which no TUM reader takes. The mapping time goes on from
    the frame before by the time the log says passed; report.json gives the offset, and every
    frame still found its prior."""
    err, rep = _run(
        _bag(tmp_path / "bag", 0.0, frames=8, shift=lambda t, k: -100.0 if k >= 4 else 0.0),
        tmp_path,
        capsys,
    )
    assert "no odometry message" not in err
    fr = rep["frames"]
    assert fr["clock_jumps"] == 1 and fr["used"] == 8 and fr["skipped"] == 0
    (jump,) = rep["mapping_time"]["jumps"]
    assert jump["frame"] == 4 and jump["jump_s"] == pytest.approx(-100.0, abs=1e-6)
    assert rep["mapping_time"]["offset_s"] == pytest.approx(100.0, abs=1e-6)
    stamps, _ = read_tum(tmp_path / "map" / "trajectory.tum")
    assert np.allclose(np.diff(stamps), 0.2, atol=1e-6)
