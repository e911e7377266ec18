"""StrayExport on a hand-made export and on the real iPhone capture in ../shared/data."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from wheelgrid_mapping.depth import (
    ARKIT_CAMERA_TO_OPTICAL,
    arkit_pose_to_ros,
    depth_to_points,
    transform_points,
)
from wheelgrid_mapping.stray import StrayExport


def make_export(root: Path, n: int = 3, *, odometry: bool = True) -> Path:
    """A tiny Stray-format export: 8x6 depth (mm), confidence, K for 1920x1440, poses."""
    (root / "depth").mkdir(parents=True)
    (root / "confidence").mkdir()
    (root / "camera_matrix.csv").write_text("960.0, 0.0, 960.0\n0.0, 720.0, 720.0\n0.0, 0.0, 1.0")
    for i in range(n):
        d = np.full((6, 8), 1000 + 100 * i, dtype=np.uint16)
        d[0, 0] = 0
        Image.fromarray(d).save(root / "depth" / f"{i:06d}.png")
        c = np.full((6, 8), 2, dtype=np.uint8)
        c[1, 1] = 0
        Image.fromarray(c).save(root / "confidence" / f"{i:06d}.png")
    if odometry:
        lines = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
        lines += [f"{100 + i / 60:.6f}, {i:06d}, {0.1 * i}, 1.0, 0.0, 0, 0, 0, 1" for i in range(n)]
        (root / "odometry.csv").write_text("\n".join(lines) + "\n")
    return root


def replace_odometry_rows(cap: Path, rows: dict[int, str]) -> None:
    """Rewrite lines of ``cap``'s odometry.csv (line 0 is the header, line 1 frame 0)."""
    lines = (cap / "odometry.csv").read_text().splitlines()
    for i, text in rows.items():
        lines[i] = text
    (cap / "odometry.csv").write_text("\n".join(lines) + "\n")


def test_hand_made_export(tmp_path: Path) -> None:
    exp = StrayExport(make_export(tmp_path / "cap"))
    assert len(exp) == 3 and exp.has_poses
    frames = list(exp)
    f = exp.frame(2)
    assert [fr.index for fr in frames] == [0, 1, 2]
    assert f.depth.dtype == np.float32 and f.depth.shape == (6, 8)
    assert np.isnan(f.depth[0, 0]) and np.isclose(f.depth[3, 3], 1.2)
    assert f.confidence is not None and f.confidence.dtype == np.uint8 and f.confidence[1, 1] == 0
    # K scaled from 1920x1440 to 8x6: row 0 by 8/1920, row 1 by 6/1440
    np.testing.assert_allclose(f.K, [[4.0, 0, 4.0], [0, 3.0, 3.0], [0, 0, 1]])
    assert f.stamp == pytest.approx(100 + 2 / 60)
    assert f.pose is not None
    np.testing.assert_allclose(f.pose[:3, 3], [0.2, 1.0, 0.0])
    assert exp.stamp(1) == pytest.approx(frames[1].stamp)
    with pytest.raises(IndexError):
        exp.frame(3)


def test_export_without_odometry_has_no_pose(tmp_path: Path) -> None:
    exp = StrayExport(make_export(tmp_path / "cap", 2, odometry=False))
    f = exp.frame(1)
    assert not exp.has_poses and f.pose is None and f.stamp == pytest.approx(1 / 60)


def test_not_an_export_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not a folder"):
        StrayExport(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"not a Stray Scanner export \(missing depth"):
        StrayExport(tmp_path / "empty")
    cap = make_export(tmp_path / "bad")
    (cap / "odometry.csv").write_text("timestamp, frame, x, y, z, qx, qy, qz, qw\n1, 0, x\n")
    with pytest.raises(ValueError, match=r"odometry\.csv:2"):
        StrayExport(cap)
    (cap / "camera_matrix.csv").write_text("1, 2\n")
    with pytest.raises(ValueError, match="camera matrix"):
        StrayExport(cap)


def test_a_broken_image_fails_its_frame_only(tmp_path: Path) -> None:
    """The resolution comes from the first image that reads; a broken one raises ValueError
    naming its file when its frame is read (every reader skips that frame), not an
    UnidentifiedImageError; depth frames odometry.csv has no row for are counted."""
    cap = make_export(tmp_path / "cap", 4)
    (cap / "depth" / "000000.png").write_bytes(b"\x89PNG cut off")
    (cap / "confidence" / "000002.png").write_bytes(b"")
    rows = (cap / "odometry.csv").read_text().splitlines()
    (cap / "odometry.csv").write_text("\n".join(rows[:3]) + "\n")  # frames 0 and 1 only
    exp = StrayExport(cap)
    assert (exp.height, exp.width) == (6, 8) and exp.frames_without_pose == 2
    with pytest.raises(ValueError, match=r"depth/000000\.png: cannot read the image"):
        exp.frame(0)
    with pytest.raises(ValueError, match=r"confidence/000002\.png: cannot read the image"):
        exp.frame(2)
    assert exp.frame(1).pose is not None and exp.frame(3).pose is None


def test_a_first_depth_image_of_another_size_or_an_8_bit_one_fails_its_frame_only(
    tmp_path: Path,
) -> None:
    """The first image that read set the export's resolution: one 16 x 12 first frame made
    every other frame "differ from the first frame's", the whole capture unreadable (a review,
    on the real capture). The most common size of the first few sets it now. An 8-bit depth
    PNG was read as millimetres, 0-255 mm, its frames failing registration with no word of
    the file; it is refused as its frame is read, naming the file and its type."""
    cap = make_export(tmp_path / "cap", 4)
    Image.fromarray(np.full((12, 16), 1000, np.uint16)).save(cap / "depth" / "000000.png")
    Image.fromarray(np.full((6, 8), 200, np.uint8)).save(cap / "depth" / "000002.png")
    exp = StrayExport(cap)
    assert (exp.height, exp.width) == (6, 8)
    np.testing.assert_allclose(exp.K, [[4.0, 0, 4.0], [0, 3.0, 3.0], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"000000\.png: shape \(12, 16\) differs from the "
                       r"export's depth resolution \(6, 8\)"):  # fmt: skip
        exp.frame(0)
    with pytest.raises(ValueError, match=r"000002\.png: depth must be 16-bit millimetres.*uint8"):
        exp.frame(2)
    assert exp.frame(1).depth.shape == exp.frame(3).depth.shape == (6, 8)
    for i in range(4):  # no size in the majority: the first that reads
        Image.fromarray(np.full((6 + 2 * i, 8), 1000, np.uint16)).save(
            cap / "depth" / f"{i:06d}.png"
        )
    assert (StrayExport(cap).height, StrayExport(cap).width) == (6, 8)
    # three odd ones first of ten: the first five that read outvoted the other seven with
    # three, and every frame of the export was refused (a review: 37 good frames of 40)
    cap = make_export(tmp_path / "cap10", 10)
    for i in range(3):
        Image.fromarray(np.full((12, 16), 1000, np.uint16)).save(cap / "depth" / f"{i:06d}.png")
    assert (StrayExport(cap).height, StrayExport(cap).width) == (6, 8)
    # a PNG whose header declares 30000 x 30000 pixels (PIL's decompression bomb error, no
    # OSError): a traceback for every command on the export, now its frame fails alone
    import struct
    import zlib

    def png_chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    ihdr = struct.pack(">IIBBBBB", 30000, 30000, 16, 0, 0, 0, 0)
    (cap / "depth" / "000005.png").write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + png_chunk(b"IHDR", ihdr)
        + png_chunk(b"IDAT", zlib.compress(b""))
        + png_chunk(b"IEND", b"")
    )
    exp = StrayExport(cap)
    assert (exp.height, exp.width) == (6, 8)
    with pytest.raises(ValueError, match=r"000005\.png: cannot read the image"):
        exp.frame(5)
    assert exp.frame(6).depth.shape == (6, 8)


def test_a_16_bit_png_opened_as_32_bit_is_read_as_millimetres(tmp_path: Path, monkeypatch) -> None:
    """Pillow before 10.3 (Ubuntu 24.04's, under an apt ROS Jazzy) opens a 16-bit PNG as mode
    I, int32: the 8-bit refusal took every depth image of a real capture for "not 16-bit"
    there (a review, with Pillow 10.2). Whole numbers within 16 bits read as millimetres; an
    8-bit image is still refused."""
    from wheelgrid_mapping import stray

    cap = make_export(tmp_path / "cap", 2)
    real = stray._read_image

    def as_old_pillow(path: Path) -> np.ndarray:
        out = real(path)
        return out.astype(np.int32) if out.dtype == np.uint16 else out

    monkeypatch.setattr(stray, "_read_image", as_old_pillow)
    exp = StrayExport(cap)
    assert np.isclose(exp.frame(1).depth[3, 3], 1.1)
    Image.fromarray(np.full((6, 8), 200, np.uint8)).save(cap / "depth" / "000001.png")
    with pytest.raises(ValueError, match="not uint8"):
        exp.frame(1)


def _world_cloud(exp: StrayExport, i: int, arkit_camera_axes: bool = False) -> np.ndarray:
    f = exp.frame(i)
    assert f.pose is not None
    pts = depth_to_points(f.depth, f.K, f.confidence, min_confidence=2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    T = f.pose @ ARKIT_CAMERA_TO_OPTICAL if arkit_camera_axes else f.pose
    return transform_points(arkit_pose_to_ros(T), pts)


def test_real_capture_reads(stray_capture: Path) -> None:
    exp = StrayExport(stray_capture)
    assert len(exp) == 942 and exp.has_poses
    f = exp.frame(0)
    assert f.depth.shape == (192, 256)
    assert 0.4 < np.nanmin(f.depth) < np.nanmax(f.depth) < 7.0
    assert f.confidence is not None and set(np.unique(f.confidence)) <= {0, 1, 2}
    np.testing.assert_allclose(f.K[0, 0], 1352.0168 * 256 / 1920)
    np.testing.assert_allclose(f.K[1, 2], 722.88153 * 192 / 1440)
    stamps = [exp.stamp(i) for i in range(len(exp))]
    assert np.all(np.diff(stamps) > 0)
    assert stamps[-1] - stamps[0] == pytest.approx(15.7, abs=0.1)


def test_real_capture_floor_is_flat_and_level_in_ros_frame(stray_capture: Path) -> None:
    """Fused with ARKit poses and turned z-up, the floor is one level plane below the camera."""
    exp = StrayExport(stray_capture)
    P = np.concatenate([_world_cloud(exp, i) for i in range(0, len(exp), 30)])
    z = P[:, 2]
    hist, edges = np.histogram(z, bins=np.arange(z.min(), z.max() + 0.02, 0.02))
    # the floor: the lowest well-populated 2 cm slab (occupied by >= 1 % of all points)
    floor_z = edges[np.nonzero(hist >= 0.01 * P.shape[0])[0][0]] + 0.01
    floor = P[np.abs(z - floor_z) < 0.06]
    c = floor.mean(axis=0)
    _, _, vt = np.linalg.svd(floor - c, full_matrices=False)
    normal = vt[2]
    tilt_deg = np.degrees(np.arccos(abs(normal[2])))
    residual = np.abs((floor - c) @ normal)
    rms, med = float(np.sqrt(np.mean(residual**2))), float(np.median(residual))
    cam_z = arkit_pose_to_ros(exp.frame(0).pose)[2, 3]  # type: ignore[arg-type]
    assert floor.shape[0] > 10_000
    assert tilt_deg < 2.0, f"floor tilt {tilt_deg:.2f} deg"
    # iPhone LiDAR depth noise is ~1-2 cm; a wrong pose convention smears the floor by dm
    assert med < 0.02 and rms < 0.03, f"floor plane residual median {med:.3f} m RMS {rms:.3f} m"
    assert 0.8 < cam_z - floor_z < 2.0  # a phone held at chest height above that floor
    # the ceiling (SOURCE.md: ~2.65 m) is above the floor, i.e. z really is up
    top = edges[np.nonzero(hist >= 0.01 * P.shape[0])[0][-1]]
    assert 2.3 < top - floor_z < 3.0


def test_real_capture_walls_of_different_frames_line_up(stray_capture: Path) -> None:
    """Frames 1-2 s apart overlap to a few cm with the optical convention, not with ARKit axes."""
    import open3d as o3d

    exp = StrayExport(stray_capture)

    def pcd(p: np.ndarray) -> o3d.geometry.PointCloud:
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(0.03)

    for a, b in [(0, 120), (540, 660), (240, 300)]:
        fractions = {}
        for axes in (False, True):
            A, B = pcd(_world_cloud(exp, a, axes)), pcd(_world_cloud(exp, b, axes))
            d = np.asarray(B.compute_point_cloud_distance(A))
            fractions[axes] = float(np.mean(d < 0.05))
        assert fractions[False] > 0.6, f"frames {a},{b}: only {fractions[False]:.2f} within 5 cm"
        assert fractions[True] < fractions[False] - 0.3, fractions


def test_frames_after_a_short_odometry_csv_keep_their_order(stray_capture: Path, tmp_path) -> None:
    """A capture cut short writes depth past odometry.csv's last row. Those frames' stamps were
    extrapolated at 60 Hz from the first row: over 900 frames of the real capture (really
    59.93 Hz) that put frame 900 15 ms before frame 899, a clock that went back (a mapper
    restarts its keyframe clock there, a stream paces on it). They go on from the last row."""
    from wheelgrid_mapping.stray import StrayExport

    export = tmp_path / "cut"
    (export / "depth").mkdir(parents=True)
    (export / "camera_matrix.csv").write_bytes((stray_capture / "camera_matrix.csv").read_bytes())
    for src in sorted((stray_capture / "depth").glob("*.png"))[:905]:
        (export / "depth" / src.name).symlink_to(src)
    lines = (stray_capture / "odometry.csv").read_text().splitlines()
    (export / "odometry.csv").write_text("\n".join(lines[:901]) + "\n")  # rows of frames 0..899
    ex = StrayExport(export)
    stamps = [ex.stamp(i) for i in range(len(ex))]
    assert len(stamps) == 905 and ex.frames_without_pose == 5
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert stamps[900] - stamps[899] == pytest.approx(1 / 60, abs=1e-6)


def test_a_nan_or_zero_quaternion_pose_row_costs_its_frame_its_pose_only(tmp_path: Path) -> None:
    """ARKit's pose of one frame, NaN or a zero quaternion in odometry.csv, refused the whole
    export (exit 2 from map, import-stray and stream-stray), where a bag's NaN pose prior costs
    its frame only. Such a row now gives its frame no pose, is counted with the frames lacking
    one, and keeps its timestamp; a row that is not numbers at all still refuses the file."""
    cap = make_export(tmp_path / "cap", 4)
    replace_odometry_rows(
        cap,
        {
            2: "100.016667, 000001, nan, 1.0, 0.0, 0, 0, 0, 1",
            3: "100.033333, 000002, 0.2, 1.0, 0.0, 0, 0, 0, 0",
        },
    )
    exp = StrayExport(cap)
    assert exp.has_poses and exp.frames_without_pose == 2
    assert exp.missing_poses_note() == (
        "odometry.csv has no pose for 2 of 4 depth frames (2 of its rows NaN or a zero quaternion)"
    )
    assert exp.frame(1).pose is None and exp.frame(2).pose is None
    assert exp.frame(0).pose is not None and exp.frame(3).pose is not None
    assert exp.frame(2).stamp == pytest.approx(100.033333)


def test_a_timestamp_a_ros_stamp_cannot_hold_costs_its_frame_its_row(tmp_path: Path) -> None:
    """A corrupt timestamp of 3e9 s (or a negative one) was taken as the frame's stamp, and
    `import-stray` wrote it into the bag's headers as sec = -1294967296 (1928: int32 seconds
    wrap), where the live bridge refuses such a stamp. The row now counts as missing: the frame
    keeps its place between its neighbours, without a pose."""
    cap = make_export(tmp_path / "cap", 4)
    replace_odometry_rows(
        cap,
        {
            2: "3000000000.0, 000001, 0.1, 1.0, 0.0, 0, 0, 0, 1",
            3: "-5.0, 000002, 0.2, 1.0, 0.0, 0, 0, 0, 1",
        },
    )
    exp = StrayExport(cap)
    assert exp.frames_without_pose == 2
    stamps = [exp.frame(i).stamp for i in range(4)]
    assert stamps[0] == pytest.approx(100.0) and stamps[3] == pytest.approx(100.05)
    assert stamps[0] < stamps[1] < stamps[2] < stamps[3]
    assert exp.frame(1).pose is None and exp.frame(2).pose is None


def test_two_odometry_rows_that_disagree_on_a_frame_cost_it_its_pose(tmp_path: Path) -> None:
    """Two rows for one frame number (an export concatenated, an app's retry) read as the last
    row's pose, silently: which of the two is ARKit's is not known, and a wrong prior moves the
    frame. The frame now gets no pose and the note says why; a repeated identical row is one."""
    cap = make_export(tmp_path / "cap", 4)
    rows = (cap / "odometry.csv").read_text().splitlines()
    rows.insert(3, "100.016667, 000001, 0.6, 1.0, 0.0, 0, 0, 0, 1")  # frame 1 again, 0.5 m off
    rows.append(rows[4])  # frame 2's row twice, the same
    (cap / "odometry.csv").write_text("\n".join(rows) + "\n")
    exp = StrayExport(cap)
    assert exp.frame(1).pose is None
    assert exp.frame(2).pose is not None and exp.frame(2).pose[0, 3] == pytest.approx(0.2)
    assert exp.frames_without_pose == 1
    assert exp.missing_poses_note() == (
        "odometry.csv has no pose for 1 of 4 depth frames (1 frame with rows that disagree)"
    )
    assert exp.frame(1).stamp == pytest.approx(100.016667)


def test_a_camera_matrix_of_another_resolution_is_refused(tmp_path: Path) -> None:
    """camera_matrix.csv is scaled from Stray's 1920x1440 RGB image to the depth resolution.
    One for another resolution (already at the depth's, or a 4K video's) was scaled all the
    same: a K off by 7.5x or 2x, every cloud silently stretched. Its principal point, far from
    the RGB image's centre, now refuses the export with a clear error."""
    cap = make_export(tmp_path / "cap", 2)
    for text in (
        "4.0, 0.0, 4.0\n0.0, 3.0, 3.0\n0.0, 0.0, 1.0",  # already at the 8x6 depth resolution
        "2704.0, 0.0, 1924.1\n0.0, 2704.0, 1445.8\n0.0, 0.0, 1.0",  # a 3840x2880 video
    ):
        (cap / "camera_matrix.csv").write_text(text)
        with pytest.raises(ValueError, match=r"camera_matrix\.csv: principal point .* 1920x1440"):
            StrayExport(cap)


def test_an_odometry_csv_cut_off_mid_row_or_empty_costs_only_those_poses(tmp_path: Path) -> None:
    """A capture cut short (the phone full, the app killed) writes depth first, and its
    odometry.csv may end mid-row, or be empty. Either refused the whole export (exit 2): a
    partial last line (no newline after it) now costs its frame the pose only; an empty file
    is one without poses. A complete line that is not 9 numbers still refuses the file."""
    cap = make_export(tmp_path / "cap", 4)
    text = (cap / "odometry.csv").read_text()
    (cap / "odometry.csv").write_text(text[: text.rindex(",")])  # frame 3's row, cut off
    exp = StrayExport(cap)
    assert exp.has_poses and exp.frames_without_pose == 1 and exp.frame(3).pose is None
    assert exp.frame(2).pose is not None
    (cap / "odometry.csv").write_text("")
    exp = StrayExport(cap)
    assert not exp.has_poses and exp.frame(0).pose is None
    (cap / "odometry.csv").write_text(text[: text.rindex(",")] + "\n")  # a whole bad line
    with pytest.raises(ValueError, match=r"odometry\.csv:5: bad odometry row"):
        StrayExport(cap)


@pytest.mark.parametrize("frame", ["1.5", "-1"])
def test_an_odometry_row_whose_frame_number_is_no_frame_s_is_refused(
    tmp_path: Path, frame: str
) -> None:
    """A frame number 1.5 was cut to 1: frame 1 took that row's pose, silently (exit 0)."""
    cap = make_export(tmp_path / "cap", 3)
    text = (cap / "odometry.csv").read_text()
    (cap / "odometry.csv").write_text(text.replace(", 000001,", f", {frame},"))
    with pytest.raises(ValueError, match=r"odometry\.csv:3: bad odometry row .*no frame's"):
        StrayExport(cap)


@pytest.mark.parametrize("name", ["odometry.csv", "camera_matrix.csv"])
def test_an_unreadable_odometry_or_camera_matrix_is_a_clear_error(
    tmp_path: Path, name: str
) -> None:
    """A file of the export that cannot be read (no permission; here a folder in its place)
    raised OSError, which no command catches: a traceback instead of one line and exit 2."""
    cap = make_export(tmp_path / "cap", 2)
    (cap / name).unlink()
    (cap / name).mkdir()
    with pytest.raises(ValueError, match=rf"{name}: cannot read it"):
        StrayExport(cap)


def test_prior_arkit_on_an_odometry_csv_without_a_pose_says_it_is_there(tmp_path: Path, capsys):
    """An empty odometry.csv (or one of NaN rows) read "which this export lacks", and the user
    looked for a file that is there (a review)."""
    from wheelgrid_mapping import cli_map

    none = make_export(tmp_path / "none", odometry=False)
    assert cli_map.main([str(none), "--out", str(tmp_path / "o"), "--prior", "arkit"]) == 2
    assert "which this export lacks" in capsys.readouterr().err
    empty = make_export(tmp_path / "empty")
    (empty / "odometry.csv").write_text("")
    assert cli_map.main([str(empty), "--out", str(tmp_path / "o"), "--prior", "arkit"]) == 2
    assert "holds, but with no usable pose" in capsys.readouterr().err
