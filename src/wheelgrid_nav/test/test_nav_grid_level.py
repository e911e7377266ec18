"""`wheelgrid grid --level`: a map made elsewhere (PCD, z up, its floor anywhere) levelled onto
z = 0 and gridded; PCL's real room scans where present."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from wheelgrid_common.fileio import read_cloud, write_ply
from wheelgrid_common.testing import shared_data
from wheelgrid_nav.cli_grid import main
from wheelgrid_nav.grid import build_grid
from wheelgrid_nav.grid_synth import paper_like_boxes, room_cloud, table
from wheelgrid_nav.level import LevelError, level_map

PCL_SCANS = shared_data("pcl-room-scans", Path(__file__).resolve().parents[3])


def rotation(axis: tuple[float, float, float], deg: float) -> np.ndarray:
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = math.radians(deg)
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * (K @ K)


def paper_room(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The paper's room with 4 mm of noise, and its floor points' mask."""
    pts = room_cloud(paper_like_boxes(), spacing=0.04)
    floor = np.abs(pts[:, 2]) < 1e-9
    return pts + rng.normal(0.0, 0.004, pts.shape), floor


@pytest.mark.parametrize("tilt", [0.0, 1.5, 6.0])
def test_a_tilted_raised_room_is_levelled_onto_its_floor(tilt: float) -> None:
    """The paper's room turned by ``tilt`` about a slanted horizontal axis and lifted 1.3 m
    (a laser scanner's origin): the floor comes back flat at z = 0, the grid is the one the
    room gives as it was, and the x axis (the walls' yaw) is kept."""
    rng = np.random.default_rng(3)
    room, floor_in = paper_room(rng)
    R = rotation((1.0, 0.4, 0.0), tilt)
    moved = room @ R.T + [0.2, -0.5, -1.3]
    level, info = level_map(moved)
    assert info.tilt_deg == pytest.approx(tilt, abs=0.05)
    assert np.abs(level[floor_in, 2]).max() < 0.02  # 4 mm noise, 9.6 m of floor
    assert abs(float(np.median(level[floor_in, 2]))) < 0.002
    assert info.rms_m < 0.006
    # what it turns is the tilt only: the levelled room is the true one moved along the floor
    heading = level[:, :2] - level[:, :2].mean(axis=0)
    truth = room[:, :2] - room[:, :2].mean(axis=0)
    assert np.abs(heading - truth).max() < 0.015 + 2.6 * math.sin(math.radians(tilt)) * 0.05
    assert (
        build_grid(level).grid.data.tolist()
        == build_grid(room + np.array([0.2, -0.5, 0.0])).grid.data.tolist()
    )
    # and the transform it reports is the one it applied
    T = info.matrix()
    np.testing.assert_allclose(moved @ T[:3, :3].T + T[:3, 3], level, atol=1e-9)


def test_the_floor_is_the_lowest_large_level_surface_not_the_largest() -> None:
    """A hall filled with 0.75 m tables, whose tops hold more points than the floor they hide,
    and a few stray returns under the floor: the floor is still the one chosen."""
    rng = np.random.default_rng(5)
    boxes = [
        b for x in (0.3, 2.7, 5.1) for y in (0.3, 2.7, 5.1) for b in table(x, x + 2.2, y, y + 2.2)
    ]
    room = room_cloud(boxes, size=(7.6, 7.6), spacing=0.04, ceiling=False)
    tops = np.abs(room[:, 2] - 0.75) < 1e-9
    floor = np.abs(room[:, 2]) < 1e-9
    room = np.vstack([room[~floor | (rng.random(len(room)) < 0.3)]])  # the floor half hidden
    assert tops.sum() > (np.abs(room[:, 2]) < 1e-9).sum()
    strays = rng.uniform([0, 0, -0.8], [7.6, 7.6, -0.3], (150, 3))
    _, info = level_map(np.vstack([room, strays]) + np.array([0.0, 0.0, 2.0]))
    assert info.floor_z == pytest.approx(2.0, abs=0.005)
    assert info.tilt_deg < 0.05


def test_a_map_that_is_not_z_up_is_refused_or_warned_of() -> None:
    """A floor leaning 25 deg is refused. A y-up export turned z-up has a wall at the bottom,
    as level as a floor: that cannot be told from the geometry alone, and the grid's own
    warning says the map rises 9.6 m above it."""
    room, _ = paper_room(np.random.default_rng(7))
    with pytest.raises(LevelError, match="z-up"):
        level_map(room @ rotation((0.0, 1.0, 0.0), 25.0).T)
    on_its_side, _ = level_map(room @ rotation((1.0, 0.0, 0.0), 90.0).T)
    assert any("rises 9.6 m" in w for w in build_grid(on_its_side).stats["warnings"])


def test_a_map_without_points_or_floor_is_refused() -> None:
    with pytest.raises(LevelError, match="no \\(finite\\) points"):
        level_map(np.full((10, 3), np.nan))
    with pytest.raises(LevelError, match="too few"):
        level_map(np.random.default_rng(1).random((50, 3)))


def test_the_cli_levels_writes_the_transform_and_drops_a_stale_one(tmp_path, capsys) -> None:
    """`--level` prints what it did and writes levelling.yaml beside the grid; a later run
    without it removes that file, which would describe another grid."""
    room, _ = paper_room(np.random.default_rng(9))
    src = tmp_path / "raised.ply"
    write_ply(src, room @ rotation((0.3, 1.0, 0.0), 2.0).T + [0.0, 0.0, 0.9])
    out = tmp_path / "g"
    assert main([str(src), "--out", str(out), "--level", "-q"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 1  # -q: the summary line only
    assert main([str(src), "--out", str(out), "--level"]) == 0
    said = capsys.readouterr()
    assert re.search(r"levelled: floor found at z = 0\.\d+ m, leaning 2\.00 deg", said.out)
    doc = yaml.safe_load((out / "levelling.yaml").read_text())
    assert doc["tilt_deg"] == pytest.approx(2.0, abs=0.05)
    T = np.array(doc["levelled_from_source"])
    lifted = read_cloud(src) @ T[:3, :3].T + T[:3, 3]
    assert abs(float(np.median(lifted[np.abs(lifted[:, 2]) < 0.05, 2]))) < 0.003
    # without --level: no floor at z = 0, and the error says what to do
    assert main([str(src), "--out", str(out), "-q"]) == 2
    assert "no floor found" in (err := capsys.readouterr().err) and "--level" in err
    assert (out / "levelling.yaml").exists()  # nothing was written: the old set stands
    # a map levelled already (the same room, as `wheelgrid map` writes it) without --level
    flat = tmp_path / "flat.ply"
    write_ply(flat, room)
    assert main([str(flat), "--out", str(out), "-q"]) == 0
    assert not (out / "levelling.yaml").exists()  # it described the grid before


@pytest.mark.skipif(
    not (PCL_SCANS / "room_scan1.pcd").exists(), reason="../shared/data/pcl-room-scans: absent"
)
def test_pcl_real_room_scans_are_levelled_and_gridded(tmp_path, capsys) -> None:
    """PCL's two real laser scans of one room (binary_compressed PCD, z up, the floor 1.27 m
    under the scanner): the floor `--level` finds agrees with Open3D's RANSAC plane on each
    scan's lowest points, each grid has floor seen and cells not free, and the two grids'
    walls differ by the yaw between the scans (40.9 deg, SOURCE.md's registration)."""
    import open3d as o3d

    from wheelgrid_common.map_io import FREE, read_map

    yaws = []
    # the README's figures: occupied, free, unknown cells (room_scan1's read 2 free, 14
    # unknown until the unseen-patch opening of 2026-11-30, and the README kept saying so)
    counts = {"room_scan1.pcd": (6, 8, 32, 1, 15), "room_scan2.pcd": (11, 8, 49, 4, 35)}
    for name in ("room_scan1.pcd", "room_scan2.pcd"):
        src = PCL_SCANS / name
        pts = read_cloud(src)
        low = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[pts[:, 2] < -1.1]))
        o3d.utility.random.seed(0)
        model, _ = low.segment_plane(0.02, 3, 1000)
        n_ransac = np.asarray(model[:3]) * np.sign(model[2])
        out = tmp_path / name
        assert main([str(src), "--out", str(out), "--level", "-q"]) == 0, capsys.readouterr().err
        doc = yaml.safe_load((out / "levelling.yaml").read_text())
        n_ours = np.array(doc["levelled_from_source"])[2, :3]  # the row that gives levelled z
        assert math.degrees(math.acos(min(1.0, float(n_ours @ n_ransac)))) < 0.3, name
        assert doc["floor_z_in_source_m"] == pytest.approx(-1.27, abs=0.02)
        assert doc["floor_rms_m"] < 0.015
        grid = read_map(out / "grid.yaml")
        fine = read_map(out / "fine.yaml")
        assert (fine.data == FREE).mean() > 0.05  # floor seen around the scanner
        assert grid.data.size >= 20 and (grid.data != FREE).any()
        got = (*grid.data.shape, *(int((grid.data == v).sum()) for v in (100, FREE, -1)))
        assert got == counts[name], (name, got)
        yaws.append(math.degrees(grid.origin[2]))
    turn = (yaws[0] - yaws[1]) % 90.0
    assert turn == pytest.approx(40.9, abs=0.5), yaws


@pytest.mark.parametrize("share", [0.03, 0.12])
def test_returns_under_a_tilted_floor_do_not_leave_it_leaning(share: float) -> None:
    """A few per cent of a scan's returns under its floor (a glossy floor's reflections, a
    mirror's): the floor of a map tilted 8 deg is still turned flat, not part of the way (it
    was left leaning 5 deg, its far side 0.4 m off z = 0, with no word of doubt)."""
    rng = np.random.default_rng(11)
    room, floor_in = paper_room(rng)
    k = int(share * len(room))
    under = rng.uniform([0.0, 0.0, -3.0], [room[:, 0].max(), room[:, 1].max(), -0.05], (k, 3))
    moved = np.vstack([room, under]) @ rotation((1.0, 0.4, 0.0), 8.0).T + [0.0, 0.0, -1.2]
    level, info = level_map(moved)
    assert info.tilt_deg == pytest.approx(8.0, abs=0.1)
    assert np.abs(level[: len(room)][floor_in, 2]).max() < 0.02


def test_a_stray_far_point_does_not_exhaust_memory_or_move_the_floor() -> None:
    """One garbage point far away (1e9 m; a tool's FLT_MAX for "no return") beside a room: the
    floor is found as without it (the height histograms spanned the point: 373 GiB asked for,
    or a cast overflow and a ValueError that ended `wheelgrid grid --level` in a traceback)."""
    room, floor_in = paper_room(np.random.default_rng(13))
    moved = room @ rotation((1.0, 0.4, 0.0), 4.0).T + [0.0, 0.0, -1.3]
    _, clean = level_map(moved)
    for far in ([0.0, 0.0, 1e9], [0.0, 0.0, -1e9], [3.4e38, 3.4e38, 3.4e38], [1e7, -1e7, 0.0]):
        level, info = level_map(np.vstack([moved, far]))
        assert info.tilt_deg == pytest.approx(clean.tilt_deg, abs=0.01), far
        assert info.floor_z == pytest.approx(clean.floor_z, abs=0.005), far
        assert np.abs(level[: len(room)][floor_in, 2]).max() < 0.02, far
