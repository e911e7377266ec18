"""wheelgrid import-stray / stream-stray: bags with the bridge's topics, exit codes, streaming."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common.bagio import BagReader
from wheelgrid_common.pointcloud2 import read_fields
from wheelgrid_common.testing import free_port
from wheelgrid_mapping import bridge_protocol as bp
from wheelgrid_mapping.cli_stray import import_main, stream_main
from wheelgrid_mapping.depth import arkit_pose_to_ros, depth_to_points
from wheelgrid_mapping.stray import StrayExport

TOPICS = {
    "/iphone/depth/image": "sensor_msgs/msg/Image",
    "/iphone/depth/camera_info": "sensor_msgs/msg/CameraInfo",
    "/iphone/confidence/image": "sensor_msgs/msg/Image",
    "/iphone/points": "sensor_msgs/msg/PointCloud2",
    "/iphone/odometry": "nav_msgs/msg/Odometry",
}


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_import_stray_writes_bridge_topics(
    tmp_path: Path, storage: str, stray_capture: Path
) -> None:
    cap = stray_capture
    out = tmp_path / "bag"
    assert (
        import_main(
            [str(cap), "--out", str(out), "--storage", storage, "--start", "100", "--frames", "12"]
        )
        == 0
    )
    exp = StrayExport(cap)
    with BagReader(out) as bag:
        infos = {t.name: (t.msgtype, t.count) for t in bag.topics()}
        assert infos == {t: (m, 12) for t, m in TOPICS.items()}
        clouds = [(t, m) for _, t, m in bag.messages(["/iphone/points"])]
        odoms = [(t, m) for _, t, m in bag.messages(["/iphone/odometry"])]
    stamps = [exp.stamp(i) for i in range(100, 112)]
    np.testing.assert_allclose([t * 1e-9 for t, _ in clouds], stamps, atol=1e-6)
    _, c0 = clouds[0]
    m0 = c0.header.stamp
    assert m0.sec + 1e-9 * m0.nanosec == pytest.approx(stamps[0], abs=1e-6)
    f = exp.frame(100)
    want = depth_to_points(f.depth, f.K, f.confidence, min_confidence=1)
    got = read_fields(c0)
    assert (c0.height, c0.width) == (192, 256)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-5)
    p = odoms[0][1].pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], arkit_pose_to_ros(f.pose)[:3, 3], atol=1e-9)  # type: ignore[arg-type]
    assert odoms[0][1].header.frame_id == "odom"


def test_import_stray_summary_gives_the_bags_size_and_the_time(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """Its one-line summary gave counts only, where `wheelgrid simulate`'s gives the bag's size
    and the seconds it took (the whole capture makes a 696 MB bag)."""
    out = tmp_path / "bag"
    assert import_main([str(stray_capture), "--out", str(out), "--frames", "3"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.match(
        rf"wrote 3 frames to {re.escape(str(out))} \(sqlite3, \d+\.\d MB\) in \d+\.\d s: ", line
    ), line


def test_import_stray_not_an_export_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert import_main([str(tmp_path), "--out", str(tmp_path / "b")]) == 2
    assert "not a Stray Scanner export" in capsys.readouterr().err


def test_import_stray_bad_input_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    (tmp_path / "exists").mkdir()
    cap = stray_capture
    assert import_main([str(cap), "--out", str(tmp_path / "exists")]) == 2
    assert "already exists" in capsys.readouterr().err
    assert import_main([str(cap), "--out", str(tmp_path / "c"), "--start", "5000"]) == 2
    assert "--start" in capsys.readouterr().err
    # a bag folder below a regular file: one line and exit 2 before any frame (was exit 1)
    (tmp_path / "file").write_text("")
    assert import_main([str(cap), "--out", str(tmp_path / "file" / "bag")]) == 2
    assert "cannot make the folder" in capsys.readouterr().err


def _first_frames(capture: Path, cap: Path, n: int) -> Path:
    """A copy of the capture's first ``n`` depth and confidence images and its intrinsics,
    without odometry.csv: an export small enough to break on purpose."""
    import shutil

    for sub in ("depth", "confidence"):
        (cap / sub).mkdir(parents=True)
        for i in range(n):
            shutil.copy(capture / sub / f"{i:06d}.png", cap / sub)
    shutil.copy(capture / "camera_matrix.csv", cap)
    return cap


def test_import_stray_skips_an_unreadable_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """A broken depth PNG costs its frame, said on stderr and in the summary; the bag holds
    the others (it used to end the import there with exit 1)."""
    cap = _first_frames(stray_capture, tmp_path / "cap", 4)
    (cap / "depth" / "000002.png").write_bytes(b"\x89PNG cut off")
    out = tmp_path / "bag"
    assert import_main([str(cap), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "frame 2 skipped" in captured.err and "1 unreadable frames skipped" in captured.out
    assert "no odometry.csv" in captured.err  # this copy has none: no prior in the bag, said
    assert "wrote 3 frames" in captured.out
    with BagReader(out) as bag:
        assert {t.name: t.count for t in bag.topics()}["/iphone/points"] == 3


def test_poses_missing_from_odometry_csv_are_said_by_import_and_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """A capture cut short writes depth first: import-stray was silent about the frames with no
    pose, where wheelgrid map warned; both now say so. The bag keeps every frame; the map fails
    those without a pose once a frame has had one (a run with a prior places none by ICP
    alone)."""
    from wheelgrid_mapping import cli_map

    cap = _first_frames(stray_capture, tmp_path / "cap", 4)
    rows = (stray_capture / "odometry.csv").read_text().splitlines()[:3]  # header + 2 poses
    (cap / "odometry.csv").write_text("\n".join(rows) + "\n")
    want = "odometry.csv has no pose for 2 of 4 depth frames"
    assert import_main([str(cap), "--out", str(tmp_path / "bag")]) == 0
    captured = capsys.readouterr()
    assert f"import-stray: warning: {want}; the bag has no /iphone/odometry" in captured.err
    assert "wrote 4 frames" in captured.out
    cli_map.main([str(cap), "--out", str(tmp_path / "map"), "--prior", "arkit"])
    assert f"wheelgrid map: warning: {want}; once a frame has had its prior, those fail" in (
        capsys.readouterr().err
    )
    report = json.loads((tmp_path / "map" / "report.json").read_text())
    assert report["failure_reasons"].get("no pose prior") == 2, report["failure_reasons"]


def test_frames_without_confidence_are_said_by_import_and_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """An export without its confidence images was mapped with ARKit's confidence filter off,
    silently: 2.65x the map points on the real capture's first 20 frames, with report.json
    still giving min_confidence 1. import-stray took --min-confidence 2 and ignored it."""
    import json
    import shutil

    from wheelgrid_mapping import cli_map

    cap = _first_frames(stray_capture, tmp_path / "cap", 4)
    (cap / "confidence" / "000001.png").unlink()
    assert cli_map.main([str(cap), "--out", str(tmp_path / "map")]) == 0
    assert "1 of 4 frames had no ARKit confidence" in capsys.readouterr().err
    frames = json.loads((tmp_path / "map" / "report.json").read_text())["frames"]
    assert frames["without_confidence"] == 1 and frames["with_confidence"] == 3
    shutil.rmtree(cap / "confidence")
    out = tmp_path / "bag"
    assert import_main([str(cap), "--out", str(out), "--min-confidence", "2"]) == 0
    err = capsys.readouterr().err
    assert "4 of 4 frames have no confidence image" in err and "--min-confidence 2" in err
    # and what level 2 costs thin obstacles where confidence is there: said at once
    assert "warning: min_confidence 2 keeps only ARKit's high-confidence pixels" in err


def test_stream_stray_exit_codes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    cap = stray_capture
    assert stream_main([str(tmp_path), "--to", "127.0.0.1:9"]) == 2
    assert stream_main([str(cap), "--to", "nohostport"]) == 2
    assert "HOST:PORT" in capsys.readouterr().err
    assert stream_main([str(cap), "--rate", "-1"]) == 2
    port = free_port()  # nobody listening
    argv = [str(cap), "--to", f"127.0.0.1:{port}", "--frames", "1", "--wait", "0"]
    assert stream_main(argv) == 1
    err = capsys.readouterr().err
    assert f"nothing listens on 127.0.0.1:{port}" in err and "launch --iphone" in err, err
    assert stream_main([*argv[:-1], "0.5"]) == 1
    err = capsys.readouterr().err
    assert "waiting up to 0.5 s" in err and "nothing listens" in err and "after 0.5 s" in err
    assert stream_main([str(cap), "--wait", "nan"]) == 2
    # each of these was a traceback: int("²"), an overflowed sleep until a frame's slot
    assert stream_main([str(cap), "--to", "127.0.0.1:\u00b2"]) == 2
    assert stream_main([str(cap), "--rate", "1e-300"]) == 2
    assert "--rate must be 0 (unpaced) or 0.1..1000" in capsys.readouterr().err
    assert import_main([str(cap), "--out", str(tmp_path / "b"), "--min-confidence", "5"]) == 2
    assert "--min-confidence must be 0, 1 or 2" in capsys.readouterr().err


def test_stream_stray_to_something_that_is_not_a_bridge_is_one_line(
    capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """A wrong --to that reaches a web server: its answer is not the bridge's protocol, which
    used to end stream-stray with a ProtocolError traceback."""
    import socket
    import threading

    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]

    def answer() -> None:
        conn, _ = srv.accept()
        with conn:
            conn.recv(4096)
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")

    t = threading.Thread(target=answer, daemon=True)
    t.start()
    try:
        rc = stream_main([str(stray_capture), "--to", f"127.0.0.1:{port}", "--frames", "1"])
    finally:
        t.join(5.0)
        srv.close()
    assert rc == 1
    err = capsys.readouterr().err
    assert "does not answer as a wheelgrid bridge" in err and "Traceback" not in err, err


def test_stream_stray_sends_decodable_frames_with_token(
    capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """--start/--frames/--token over real TCP to a BridgeServer; frames equal the export's."""
    cap = stray_capture
    got: list[bp.Frame] = []
    srv = bp.BridgeServer(lambda f, c: got.append(f), lambda lv, t: None, port=0, token="tk")
    srv.start()
    try:
        assert stream_main([str(cap), "--to", f"127.0.0.1:{srv.port}", "--frames", "3"]) == 1
        assert "wrong token" in capsys.readouterr().err
        args = [
            str(cap),
            "--to",
            f"127.0.0.1:{srv.port}",
            "--token",
            "tk",
            "--start",
            "40",
            "--frames",
            "6",
            "--rate",
            "4",
        ]
        assert stream_main(args) == 0
        assert "sent 6 frames" in capsys.readouterr().out
        deadline = time.monotonic() + 5
        while len(got) < 6 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        srv.stop()
    exp = StrayExport(cap)
    assert [f.seq for f in got] == list(range(6))
    for f, i in zip(got, range(40, 46), strict=True):
        sf = exp.frame(i)
        assert f.stamp == sf.stamp
        np.testing.assert_array_equal(np.isnan(f.depth_m()), np.isnan(sf.depth))
        np.testing.assert_allclose(f.depth_m(), sf.depth, atol=1e-6)
        np.testing.assert_array_equal(f.confidence, sf.confidence)
        np.testing.assert_allclose(f.pose_optical(), sf.pose, atol=1e-9)


def test_stream_stray_says_so_when_the_bridge_stops_under_it(
    capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """A bridge stopped mid-stream (Ctrl-C on `wheelgrid launch --iphone`) closed the
    connection without a word, and stream-stray reported "Connection reset by peer" as if the
    network had failed."""
    import threading

    third = threading.Event()
    got: list[int] = []

    def on_frame(f: bp.Frame, c: object) -> None:
        got.append(f.seq)
        if len(got) == 3:
            third.set()

    srv = bp.BridgeServer(on_frame, lambda lv, t: None, port=0)
    srv.start()
    stopper = threading.Thread(target=lambda: third.wait(30) and srv.stop(), daemon=True)
    stopper.start()
    try:
        args = [str(stray_capture), "--to", f"127.0.0.1:{srv.port}", "--frames", "120"]
        assert stream_main(args) == 1
    finally:
        stopper.join(30)
        srv.stop()
    err = capsys.readouterr().err
    assert "the bridge closed the connection after " in err, err
    assert "of 120 frames: the bridge is stopping (status SHUTDOWN)" in err, err
    assert "reset" not in err.lower(), err


def test_parting_status_reads_what_the_bridge_said_before_it_closed() -> None:
    """Said, it is read even after the peer's reset; not said, there is nothing to read."""
    import socket

    for said in (True, False):
        a, b = socket.socketpair()
        with a, b:
            if said:
                a.sendall(bp.encode_status(bp.STATUS_PROTOCOL_ERROR, "idle timeout"))
            a.close()
            st = bp.parting_status(b, timeout=2.0)
        if said:
            assert st is not None
            assert bp.status_words(st) == "idle timeout (status PROTOCOL_ERROR)"
        else:
            assert st is None


def _with_odometry(capture: Path, cap: Path, times: list[float]) -> None:
    """odometry.csv for ``cap``'s frames from the capture's own rows, retimed to ``times``."""
    rows = (capture / "odometry.csv").read_text().splitlines()
    body = [r.split(",", 1)[1] for r in rows[1 : 1 + len(times)]]
    lines = [rows[0], *(f"{t:.6f},{rest}" for t, rest in zip(times, body, strict=True))]
    (cap / "odometry.csv").write_text("\n".join(lines) + "\n")


def test_stream_stray_reconnects_across_a_pause_the_bridge_would_time_out(
    capsys: pytest.CaptureFixture[str], stray_capture: Path, tmp_path: Path, monkeypatch
) -> None:
    """stream-stray slept through a pause in the capture on an open connection, the bridge
    closed it as idle (5 s), and the rest of the capture was never sent, exit 1 (a review).
    It now waits out a long pause disconnected and connects again, as the protocol says."""
    from wheelgrid_mapping import cli_stray

    cap = _first_frames(stray_capture, tmp_path / "cap", 6)
    _with_odometry(stray_capture, cap, [100.0, 100.1, 100.2, 101.7, 101.8, 101.9])
    monkeypatch.setattr(cli_stray, "PAUSE_RECONNECT_S", 0.5)
    got: list[bp.Frame] = []
    srv = bp.BridgeServer(lambda f, c: got.append(f), lambda lv, t: None, port=0,
                          idle_timeout_s=1.0)  # fmt: skip
    srv.start()
    try:
        assert stream_main([str(cap), "--to", f"127.0.0.1:{srv.port}"]) == 0
        out = capsys.readouterr().out
        deadline = time.monotonic() + 5
        while len(got) < 6 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        srv.stop()
    assert "sent 6 frames" in out and "reconnected 1 time(s) after a pause" in out, out
    assert len(got) == 6


def test_frames_stamped_before_the_clock_began_are_skipped_not_the_import(
    capsys: pytest.CaptureFixture[str], stray_capture: Path, tmp_path: Path
) -> None:
    """Frames before odometry.csv's first row take its time extrapolated back at 60 Hz: with
    the ARKit clock just started that went below 0, and import-stray failed whole ("stamp
    -0.25 s outside 0 .. 2^31 s", the bag removed) while the bridge dropped them quietly (a
    review). Such frames are skipped, said and counted; the rest are imported."""
    cap = _first_frames(stray_capture, tmp_path / "cap", 8)
    rows = (stray_capture / "odometry.csv").read_text().splitlines()
    body = [r.split(",", 1)[1] for r in rows[1:9]]
    # rows for frames 4..7 only, the clock at 0.02 s for frame 4: frames 0..3 extrapolate < 0
    kept = [f"{0.02 + (k - 4) / 60:.6f},{body[k]}" for k in range(4, 8)]
    (cap / "odometry.csv").write_text("\n".join([rows[0], *kept]) + "\n")
    out = tmp_path / "bag"
    assert import_main([str(cap), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "frame 0 skipped" in captured.err and "no time a ROS stamp holds" in captured.err
    # frame 3 lies 3.3 ms after the clock began: kept
    assert "wrote 5 frames" in captured.out and "3 unreadable" in captured.out, captured.out


def test_stream_stray_waits_for_a_bridge_that_is_still_starting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], stray_capture: Path
) -> None:
    """`wheelgrid launch --iphone &` then `wheelgrid stream-stray` at once, as the README
    shows: the bridge listens some seconds later, and the stream failed at once, "nothing
    listens" (a review). It waits up to --wait (10 s) for the bridge."""
    import threading

    from wheelgrid_mapping import bridge_protocol as bp

    port = free_port()
    got: list[object] = []
    srv = bp.BridgeServer(lambda f, c: got.append(f), lambda lv, t: None, port=port)
    later = threading.Timer(1.0, srv.start)
    later.start()
    try:
        argv = [str(stray_capture), "--to", f"127.0.0.1:{port}", "--frames", "2", "--rate", "0"]
        assert stream_main(argv) == 0, capsys.readouterr().err
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        later.join()
        srv.stop()
    out = capsys.readouterr()
    assert "waiting up to 10 s" in out.err and "sent 2 frames" in out.out
    assert got  # the bridge received them


def test_stream_stray_says_the_bridge_went_away_during_a_pause(
    capsys: pytest.CaptureFixture[str], stray_capture: Path, tmp_path: Path, monkeypatch
) -> None:
    """The bridge stopped during a pause in the capture: stream-stray said "nothing listens
    ... after 10 s" (it had not waited, had sent 3 frames, and the bridge had been running; a
    review). It says the bridge went away, after how many frames."""
    from wheelgrid_mapping import cli_stray

    cap = _first_frames(stray_capture, tmp_path / "cap", 6)
    _with_odometry(stray_capture, cap, [100.0, 100.1, 100.2, 101.7, 101.8, 101.9])
    monkeypatch.setattr(cli_stray, "PAUSE_RECONNECT_S", 0.5)
    got: list[bp.Frame] = []
    srv = bp.BridgeServer(lambda f, c: got.append(f), lambda lv, t: None, port=0)
    srv.start()
    closed = cli_stray.connect

    def stop_the_bridge_first(*args, **kwargs):
        if got:  # the reconnect after the pause: the bridge is gone by then
            srv.stop()
        return closed(*args, **kwargs)

    monkeypatch.setattr(cli_stray, "connect", stop_the_bridge_first)
    try:
        assert stream_main([str(cap), "--to", f"127.0.0.1:{srv.port}"]) == 1
    finally:
        srv.stop()
    err = capsys.readouterr().err
    assert "the bridge went away during a pause in the capture, after 3 of 6 frames" in err, err
    assert "nothing listens" not in err


def test_import_stray_logs_frames_in_capture_order_and_refuses_an_export_of_no_frame(
    capsys: pytest.CaptureFixture[str], stray_capture: Path, tmp_path: Path
) -> None:
    """A frame stamped 10 s back was logged at its stamp, first in the bag, and began the map
    there (mapped from the export it is skipped; a review): log times never go back in capture
    order. An export whose every frame fails to read wrote an empty bag, exit 0."""
    cap = _first_frames(stray_capture, tmp_path / "cap", 6)
    _with_odometry(stray_capture, cap, [100.0, 100.1, 100.2, 90.3, 100.4, 100.5])
    assert import_main([str(cap), "--out", str(tmp_path / "bag")]) == 0
    with BagReader(tmp_path / "bag") as r:
        clouds = list(r.messages(["/iphone/points"]))
    logged = [t * 1e-9 for _, t, _ in clouds]
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, _, m in clouds]
    assert np.all(np.diff(logged) >= 0) and logged[0] == pytest.approx(100.0)
    assert stamps[3] == pytest.approx(90.3)  # the header keeps the bad stamp
    for png in (cap / "depth").glob("*.png"):
        png.write_bytes(png.read_bytes()[:2000])  # headers read, pixels do not
    capsys.readouterr()
    assert import_main([str(cap), "--out", str(tmp_path / "bag2")]) == 2
    assert "none of the 6 frames read" in capsys.readouterr().err
    assert not (tmp_path / "bag2").exists()
