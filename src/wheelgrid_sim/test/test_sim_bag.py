"""simulate() output: bags readable by rosbags and rclpy, ground truth consistent with points."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common.bagio import POINTCLOUD2, BagReader
from wheelgrid_common.fileio import read_tum
from wheelgrid_common.map_io import FREE, read_map
from wheelgrid_common.pointcloud2 import read_fields
from wheelgrid_sim import FRAME_ID, ODOM_TOPIC, TOPIC, load_ground_truth, paper_scene, simulate
from wheelgrid_sim.cli import main as cli_main


def clouds_in_room(root: Path) -> list[np.ndarray]:
    """Each frame's finite points transformed to the room frame with poses.tum."""
    gt = load_ground_truth(root)
    out = []
    with BagReader(gt.bag) as reader:
        for i, (_, t_ns, msg) in enumerate(reader.messages([TOPIC])):
            assert t_ns / 1e9 == pytest.approx(gt.stamps[i], abs=1e-6)
            p = read_fields(msg)
            p = p[np.isfinite(p).all(axis=1)]
            T = gt.poses[i]
            out.append(p @ T[:3, :3].T + T[:3, 3])
    return out


@pytest.mark.parametrize("fixture", ["sim_clean", "sim_mcap"])
def test_bag_reads_back_with_rosbags(fixture: str, request: pytest.FixtureRequest) -> None:
    root: Path = request.getfixturevalue(fixture)
    gt = load_ground_truth(root)
    storage = "mcap" if fixture == "sim_mcap" else "sqlite3"
    assert list((root / "scan").glob("*.mcap" if storage == "mcap" else "*.db3"))
    holes = 0
    with BagReader(root / "scan") as reader:
        infos = {t.name: (t.msgtype, t.count) for t in reader.topics()}
        n = gt.truth["frames"]
        assert infos == {TOPIC: (POINTCLOUD2, n), ODOM_TOPIC: ("nav_msgs/msg/Odometry", n)}
        assert reader.pick_topic(None) == TOPIC
        for i, (_, t_ns, msg) in enumerate(reader.messages([TOPIC])):
            assert msg.header.frame_id == FRAME_ID
            stamp_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp_ns == t_ns
            assert (msg.height, msg.width) == (gt.camera.rows, gt.camera.cols)
            assert [f.name for f in msg.fields] == ["x", "y", "z"]
            assert all(f.datatype == 7 for f in msg.fields)  # FLOAT32
            assert msg.is_dense is False and msg.is_bigendian is False
            xyz = read_fields(msg)
            holes += int(np.isnan(xyz).any(axis=1).sum())  # organised: holes kept in place
            assert i < gt.truth["frames"]
    assert holes > 0
    np.testing.assert_allclose(
        gt.stamps, 1_700_000_000 + np.arange(gt.truth["frames"]) / gt.truth["rate"], atol=1e-6
    )


@pytest.mark.parametrize("fixture", ["sim_clean", "sim_mcap"])
def test_bag_deserialises_with_rclpy(fixture: str, request: pytest.FixtureRequest) -> None:
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    root: Path = request.getfixturevalue(fixture)
    with BagReader(root / "scan") as reader:
        n = 0
        for _, _, _, raw in reader.raw([TOPIC]):
            msg = deserialize_message(raw, PointCloud2)
            assert msg.header.frame_id == FRAME_ID and msg.is_dense is False
            assert len(msg.data) == msg.row_step * msg.height == msg.height * msg.width * 12
            ref = reader.reader.deserialize(raw, POINTCLOUD2)
            np.testing.assert_array_equal(read_fields(msg), read_fields(ref))
            n += 1
    assert n > 0


def test_noise_free_points_lie_on_box_surfaces(sim_clean: Path) -> None:
    gt = load_ground_truth(sim_clean)
    pts = np.concatenate(clouds_in_room(sim_clean))
    assert len(pts) > 10_000
    dist = gt.scene.distance_to_surfaces(pts)
    assert float(dist.max()) < 1e-3
    # And inside the room (walls, floor and ceiling are hit from the inside).
    x0, y0, x1, y1 = gt.scene.room
    assert (pts[:, 0] > x0 - 1e-3).all() and (pts[:, 0] < x1 + 1e-3).all()
    assert (pts[:, 1] > y0 - 1e-3).all() and (pts[:, 1] < y1 + 1e-3).all()
    assert (pts[:, 2] > -1e-3).all() and (pts[:, 2] < gt.scene.ceiling + 1e-3).all()


def test_ground_truth_files_agree(sim_clean: Path) -> None:
    gt = load_ground_truth(sim_clean)
    assert gt.truth["start_cell"] == [2, 0] and gt.truth["goal_cell"] == [6, 5]
    grid = read_map(sim_clean / "expected_grid.yaml")
    np.testing.assert_array_equal(grid.data, paper_scene().expected_grid().data)
    assert grid.resolution == 1.2 and grid.origin == (0.0, 0.0, 0.0)
    assert grid.data[2, 0] == FREE and grid.data[6, 5] == FREE
    np.testing.assert_allclose(gt.camera.intrinsics(), gt.truth["camera"]["K"])
    assert gt.expected_grid_for(safe_height=1.6).data[4, 5] != FREE


def test_map_frame_convention(sim_clean: Path) -> None:
    gt = load_ground_truth(sim_clean)
    M = gt.map_from_room
    # A pure rotation about z plus a translation: the map is levelled like the room.
    np.testing.assert_allclose(M[2], [0, 0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-12)
    first = gt.poses_map[0]
    # Origin directly below the first camera pose; z keeps the height above the floor.
    np.testing.assert_allclose(first[:2, 3], [0.0, 0.0], atol=1e-6)
    assert first[2, 3] == pytest.approx(gt.poses[0][2, 3], abs=1e-6)
    # x = the first viewing direction projected on the floor.
    fwd = first[:3, 2]
    assert math.atan2(fwd[1], fwd[0]) == pytest.approx(0.0, abs=1e-6)
    assert fwd[0] > 0
    # poses_map.tum = map_from_room @ poses.tum for every frame.
    stamps_map, poses_map = read_tum(sim_clean / "poses_map.tum")
    np.testing.assert_array_equal(stamps_map, gt.stamps)
    np.testing.assert_allclose(poses_map, M @ gt.poses, atol=2e-6)


def test_bags_are_reproducible_bit_for_bit(tmp_path: Path) -> None:
    for name in ("a", "b"):
        simulate(tmp_path / name, seed=5, frames=3, rate=5.0, stride=8)
    a = (tmp_path / "a" / "scan" / "scan.db3").read_bytes()
    b = (tmp_path / "b" / "scan" / "scan.db3").read_bytes()
    assert a == b
    c = tmp_path / "c"
    simulate(c, seed=6, frames=3, rate=5.0, stride=8)
    assert (c / "scan" / "scan.db3").read_bytes() != a


def test_cli_writes_everything_and_refuses_to_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    argv = ["--seed", "2", "--frames", "3", "--rate", "2", "--stride", "8", "--out", str(out)]
    assert cli_main(argv) == 0
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert "wrote 3 frames" in summary and "MB" in summary and "8x8 grid" in summary
    for name in (
        "scene.json",
        "poses.tum",
        "poses_map.tum",
        "truth.json",
        "expected_grid.yaml",
        "expected_grid.pgm",
        "scan/metadata.yaml",
    ):
        assert (out / name).is_file(), name
    assert cli_main(argv) == 2
    assert "already exists" in capsys.readouterr().err
    assert cli_main(["--frames", "0", "--out", str(tmp_path / "x")]) == 2
    assert cli_main(["--stride", "0", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_cli_drives_the_path_at_the_chairs_speed_unless_told_otherwise(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The whole path is spread over the frames, so the frame count is a speed: by default the
    chair drives at 0.8 m/s (the README's; 120 frames used to drive it at 1.4), and a count
    that drives faster than the paper's 3 km/h says so and names the count that does not."""
    argv = ["--rate", "2", "--stride", "32", "--no-odometry", "--out"]
    assert cli_main([*argv, str(tmp_path / "a")]) == 0
    captured = capsys.readouterr()
    summary = captured.out.strip().splitlines()[-1]
    assert "wrote 84 frames (2 Hz" in summary and "driving 0.80 m/s" in summary, summary
    assert "warning" not in captured.err
    assert cli_main([*argv, str(tmp_path / "b"), "--frames", "30"]) == 0
    err = capsys.readouterr().err
    assert "drive the path at 2.30 m/s, faster than a chair's 3 km/h" in err, err
    assert "--frames 84 drives it at 0.8 m/s" in err
    # --back-to-start: the way back too, at the same speed, ending where it began
    assert cli_main([*argv, str(tmp_path / "c"), "--back-to-start"]) == 0
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert "wrote 149 frames (2 Hz" in summary and "driving 0.80 m/s" in summary, summary
    truth = json.loads((tmp_path / "c" / "truth.json").read_text())
    assert truth["back_to_start"] is True
    _, poses = read_tum(tmp_path / "c" / "poses.tum")
    np.testing.assert_allclose(poses[-1][:2, 3], poses[0][:2, 3], atol=1e-6)


def test_odometry_is_arkit_like(sim_clean: Path) -> None:
    """Gravity-aligned, starts at the first camera pose, drifts about a percent, never zero."""
    from wheelgrid_common.fileio import quat_to_matrix

    gt = load_ground_truth(sim_clean)
    odom_from_room = np.asarray(gt.truth["odom_from_room"])
    true = odom_from_room @ gt.poses
    est = []
    with BagReader(sim_clean / "scan") as reader:
        for _, t_ns, msg in reader.messages([ODOM_TOPIC]):
            assert (msg.header.frame_id, msg.child_frame_id) == ("odom", FRAME_ID)
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == t_ns
            assert msg.pose.covariance[0] == -1.0
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            T = np.eye(4)
            T[:3, :3] = quat_to_matrix(q.x, q.y, q.z, q.w)
            T[:3, 3] = (p.x, p.y, p.z)
            est.append(T)
    est_a = np.array(est)
    assert len(est_a) == len(true)
    np.testing.assert_allclose(est_a[0], true[0], atol=1e-6)
    np.testing.assert_allclose(true[0][:3, 3], 0.0, atol=1e-6)  # origin at the first camera
    # Gravity is exact: the optical y axis (down) has the same z component as the truth's.
    np.testing.assert_allclose(est_a[:, 2, :3], true[:, 2, :3], atol=1e-6)
    path = np.sum(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1))
    err = np.linalg.norm(est_a[-1, :3, 3] - true[-1, :3, 3])
    assert 0.0 < err < 0.05 * path + 0.05


def test_an_interrupted_simulation_leaves_no_bag_that_looks_complete(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C (or a full disk) mid-run left a bag that opened as complete with fewer frames
    than the ground truth beside it, and a rerun into the same --out was refused. What the run
    wrote goes; a file that was in --out before stays."""
    from wheelgrid_sim.simulate import simulate

    def stop_at(k: int):
        def on_frame(i: int) -> None:
            if i == k:
                raise KeyboardInterrupt

        return on_frame

    fresh = tmp_path / "fresh"
    with pytest.raises(KeyboardInterrupt):
        simulate(fresh, frames=6, stride=16, on_frame=stop_at(2))
    assert not fresh.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    with pytest.raises(KeyboardInterrupt):
        simulate(kept, frames=6, stride=16, on_frame=stop_at(2))
    assert [p.name for p in kept.iterdir()] == ["notes.txt"]
    assert simulate(kept, frames=3, stride=16).frames == 3  # the rerun is not refused
    assert cli_main(["--rate", "inf", "--out", str(tmp_path / "inf")]) == 2
    assert "--rate must be in [0.001, 1000] Hz" in capsys.readouterr().err
    # 1e-300 overflowed the stamps (exit 1, "failed"); a negative seed was a random room's
    # traceback (a review)
    assert cli_main(["--rate", "1e-300", "--out", str(tmp_path / "slow")]) == 2
    assert "--rate must be in [0.001, 1000] Hz" in capsys.readouterr().err
    for scene in ("random", "paper"):
        argv = ["--scene", scene, "--seed", "-5", "--frames", "3", "--out", str(tmp_path / "s")]
        assert cli_main(argv) == 2
        assert "--seed must be >= 0, not -5" in capsys.readouterr().err
    assert not (tmp_path / "slow").exists() and not (tmp_path / "s").exists()
    # the command: folder_problem made --out before simulate() looked, and an empty --out
    # stayed behind "removed"
    from wheelgrid_common.progress import Progress

    def ctrl_c(self: Progress, n: int = 1, **kw: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(Progress, "update", ctrl_c)
    assert cli_main(["--frames", "4", "--stride", "16", "--out", str(tmp_path / "cli")]) == 130
    assert "interrupted; what it wrote is removed" in capsys.readouterr().err
    assert not (tmp_path / "cli").exists()
