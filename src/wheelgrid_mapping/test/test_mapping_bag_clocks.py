"""``wheelgrid map --prior arkit`` on a bag whose clouds and odometry are stamped on different
clocks, or whose odometry covers only part of the scan: the frames without a prior must be
said, not mapped geometry-only without a word."""

import json
from pathlib import Path

import pytest

from wheelgrid_common.bagio import BagReader, BagWriter
from wheelgrid_mapping import cli_map

SCAN = Path(__file__).resolve().parents[3] / "bags" / "paper_room" / "scan"


def _bag(out: Path, odom_shift_s: float, odom_keep: int | None = None, frames: int = 6) -> Path:
    """The paper room's first ``frames`` clouds with its odometry, the odometry's header
    stamps moved by ``odom_shift_s`` (another clock) and only its first ``odom_keep`` kept."""
    if not (SCAN / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    shift = round(odom_shift_s * 1e9)
    clouds = odoms = 0
    with BagReader(SCAN) as src, BagWriter(out) as w:
        for topic, msgtype, t_ns, raw in src.raw(["/iphone/points", "/iphone/odometry"]):
            if topic == "/iphone/points":
                if clouds >= frames:
                    continue
                clouds += 1
            else:
                odoms += 1
                if odom_keep is not None and odoms > odom_keep:
                    continue
                msg = ts.deserialize_cdr(raw, msgtype)
                st = msg.header.stamp
                ns = st.sec * 1_000_000_000 + st.nanosec + shift
                st.sec, st.nanosec = divmod(ns, 1_000_000_000)
                raw = bytes(ts.serialize_cdr(msg, msgtype))
            w.write(topic, msgtype, t_ns, raw)
    return out


def _run(bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[str, dict]:
    out = tmp_path / "map"
    argv = [str(bag), "--out", str(out), "--prior", "arkit", "--no-loop-closure"]
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
