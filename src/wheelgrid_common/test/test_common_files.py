"""map_server YAML+PGM written as Nav2 writes it and read back as Nav2 reads it; PLY; TUM."""

import math

import numpy as np
import pytest

from wheelgrid_common.fileio import (
    matrix_to_quat,
    quat_to_matrix,
    read_ply,
    read_tum,
    write_ply,
    write_together,
    write_tum,
)
from wheelgrid_common.map_io import (
    Grid,
    from_occupancy_grid,
    read_map,
    to_occupancy_grid,
    write_map,
)
from wheelgrid_common.params import field, from_mapping, load_yaml


def test_map_round_trip_keeps_free_occupied_and_unknown(tmp_path):
    data = np.array([[0, 100, -1], [-1, 0, 0]], dtype=np.int8)
    grid = Grid(data, 1.2, (-0.6, 1.0, 0.3))
    write_map(tmp_path / "g.yaml", grid)
    back = read_map(tmp_path / "g.yaml")
    assert back.data.tolist() == data.tolist()
    assert back.resolution == 1.2 and back.origin == pytest.approx((-0.6, 1.0, 0.3))
    pgm = (tmp_path / "g.pgm").read_bytes()
    assert pgm.startswith(b"P5\n3 2\n255\n") and list(pgm[-6:]) == [254, 0, 205, 205, 254, 254]


def test_occupancy_grid_message_rows_start_at_the_bottom():
    data = np.array([[100, 0], [0, -1]], dtype=np.int8)  # image row 0 = top
    msg = to_occupancy_grid(Grid(data, 0.5, (1.0, 2.0, math.pi / 2)))
    assert list(msg.data) == [0, -1, 100, 0]
    back = from_occupancy_grid(msg)
    assert back.data.tolist() == data.tolist() and back.origin[2] == pytest.approx(math.pi / 2)
    # an origin quaternion off unit length is the same yaw (a third of unit length read 5.6
    # deg for 90, and put start and goal in other cells)
    q = msg.info.origin.orientation
    q.z, q.w = 0.3 * q.z, 0.3 * q.w
    assert from_occupancy_grid(msg).origin[2] == pytest.approx(math.pi / 2)
    # an origin rolled 180 deg is a mirror image: it read as yaw 0, and routes went out that
    # the real origin put outside the grid (a review)
    q.x, q.y, q.z, q.w = 1.0, 0.0, 0.0, 0.0
    with pytest.raises(ValueError, match=r"tilts the grid 180\.0 deg out of the floor"):
        from_occupancy_grid(msg)
    q.x, q.w = 0.001, 1.0  # 0.1 deg: another tool's rounding, read as yaw 0
    assert from_occupancy_grid(msg).origin[2] == pytest.approx(0.0)


def test_a_huge_quaternion_is_the_rotation_it_points_to_not_the_identity():
    """A quaternion of 1e200 (a corrupt bag's exponent) overflowed the norm to infinity and
    divided to zeros: an identity, which every rigidity check passes, where it was a half turn."""
    np.testing.assert_allclose(quat_to_matrix(1e200, 0, 0, 0), np.diag([1.0, -1.0, -1.0]))
    half = np.sqrt(0.5)
    np.testing.assert_allclose(
        quat_to_matrix(0, 0, 1e160, 1e160), quat_to_matrix(0, 0, half, half), atol=1e-12
    )
    assert np.isnan(quat_to_matrix(np.nan, 0, 0, 1)).all()
    with pytest.raises(ValueError, match="zero quaternion"):
        quat_to_matrix(0, 0, 0, 0)


def test_cell_centres_and_lookup_agree_with_rotation():
    grid = Grid(np.zeros((4, 5), np.int8), 1.2, (1.0, -2.0, 0.4))
    xy = grid.cell_center(1, 3)
    assert grid.cell_of(*xy) == (1, 3)
    assert Grid(np.zeros((4, 5), np.int8), 1.0).cell_center(0, 0).tolist() == [0.5, 3.5]


def test_ply_and_tum_round_trip(tmp_path):
    pts = np.random.default_rng(1).normal(size=(100, 3))
    write_ply(tmp_path / "m.ply", pts)
    np.testing.assert_allclose(read_ply(tmp_path / "m.ply"), pts.astype(np.float32))
    (tmp_path / "bad.ply").write_bytes((tmp_path / "m.ply").read_bytes()[:-20])
    with pytest.raises(ValueError, match="truncated"):
        read_ply(tmp_path / "bad.ply")
    poses = np.repeat(np.eye(4)[None], 2, axis=0)
    poses[1, :3, :3] = quat_to_matrix(0.1, 0.2, 0.3, 0.9)
    poses[1, :3, 3] = [1, 2, 3]
    write_tum(tmp_path / "t.tum", np.array([0.0, 0.5]), poses)
    _, back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back, poses, atol=1e-6)
    assert np.allclose(quat_to_matrix(*matrix_to_quat(poses[1, :3, :3])), poses[1, :3, :3])


def test_tum_writes_no_negative_zero(tmp_path):
    """Two replays of one bag whose poses differ by 1e-17 m must write the same file."""
    pose = np.eye(4)
    pose[:3, 3] = [-1e-17, 1e-17, -3e-7]
    write_tum(tmp_path / "a.tum", np.array([1.0]), pose[None])
    pose[:3, 3] = [1e-17, -1e-17, 3e-7]
    write_tum(tmp_path / "b.tum", np.array([1.0]), pose[None])
    a = (tmp_path / "a.tum").read_text()
    assert a == (tmp_path / "b.tum").read_text()
    assert "-0.0" not in a and a.split()[1:4] == ["0.000000"] * 3


def test_config_from_yaml_checks_types_and_names(tmp_path):
    from dataclasses import dataclass

    @dataclass
    class Cfg:
        safe_height: float = field(1.5, "drop points above this", "m")
        cells: int = field(8, "cells per side")

    (tmp_path / "c.yaml").write_text("grid:\n  ros__parameters:\n    safe_height: 2\n")
    assert load_yaml(Cfg, tmp_path / "c.yaml").safe_height == 2.0
    with pytest.raises(ValueError, match="unknown"):
        from_mapping(Cfg, {"safe_hieght": 1.0})
    with pytest.raises(ValueError, match="integer"):
        from_mapping(Cfg, {"cells": 1.5})
    with pytest.raises(ValueError, match="expected a mapping of parameter: value, got 5"):
        from_mapping(Cfg, 5)  # type: ignore[arg-type]
    (tmp_path / "c.yaml").write_text("grid: 2.0\n")
    with pytest.raises(ValueError, match="section 'grid' must be a mapping"):
        load_yaml(Cfg, tmp_path / "c.yaml", section="grid")
    # an empty section is its defaults, as in the mapping YAML (it raised "got None")
    (tmp_path / "c.yaml").write_text("grid:\nplanner:\n  episodes: 5\n")
    assert load_yaml(Cfg, tmp_path / "c.yaml", section="grid") == Cfg()
    (tmp_path / "c.yaml").write_text("grid:\n  safe_height: [2\n")
    with pytest.raises(ValueError, match=r"c.yaml: not valid YAML at line 3, column 1"):
        load_yaml(Cfg, tmp_path / "c.yaml", section="grid")


def test_long_metadata_stays_one_yaml_comment(tmp_path):
    grid = Grid(np.zeros((2, 2), np.int8), 1.2, meta={"note": "x" * 300, "cells": list(range(60))})
    write_map(tmp_path / "g.yaml", grid)
    text = (tmp_path / "g.yaml").read_text()
    assert sum(line.startswith("# wheelgrid:") for line in text.splitlines()) == 1
    assert read_map(tmp_path / "g.yaml").data.tolist() == [[0, 0], [0, 0]]


def test_a_zero_quaternion_pose_is_all_nan_for_the_mapper_to_refuse():
    from types import SimpleNamespace as Ns

    from wheelgrid_common.fileio import pose_or_nan

    T = pose_or_nan(Ns(x=1.0, y=2.0, z=3.0), Ns(x=0.0, y=0.0, z=0.0, w=2.0))
    np.testing.assert_allclose(T, [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    assert np.isnan(pose_or_nan(Ns(x=1.0, y=2.0, z=3.0), Ns(x=0.0, y=0.0, z=0.0, w=0.0))).all()


def test_ply_elements_before_the_vertices_and_cut_ascii_bodies(tmp_path):
    """A sensor element before the vertices used to shift every coordinate (a garbage cloud
    whose grid was all free); an ASCII body shorter than its header read as half a room."""
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    head = b"ply\nformat binary_little_endian 1.0\nelement sensor 2\nproperty float id\n"
    verts = b"element vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    body = np.array([7, 8], "<f4").tobytes() + pts.tobytes()
    (tmp_path / "s.ply").write_bytes(head + verts + b"end_header\n" + body)
    np.testing.assert_array_equal(read_ply(tmp_path / "s.ply"), pts)
    ascii_head = "ply\nformat ascii 1.0\nelement camera 1\nproperty float f\n" + verts.decode()
    lines = "\n".join(" ".join(f"{v:g}" for v in p) for p in pts)
    (tmp_path / "a.ply").write_text(ascii_head + "end_header\n5\n" + lines + "\n")
    np.testing.assert_array_equal(read_ply(tmp_path / "a.ply"), pts)
    (tmp_path / "a.ply").write_text(ascii_head + "end_header\n5\n" + lines.split("\n")[0])
    with pytest.raises(ValueError, match="truncated \\(1 of 4 vertex lines\\)"):
        read_ply(tmp_path / "a.ply")
    (tmp_path / "n.ply").write_bytes(verts.replace(b"4", b"-1").join([b"ply\nformat ascii 1.0\n",
                                                                       b"end_header\n"]))  # fmt: skip
    with pytest.raises(ValueError, match="negative count"):
        read_ply(tmp_path / "n.ply")


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        ("free_thresh: 1.5\n", "need 0 <= free_thresh < occupied_thresh <= 1"),
        ("free_thresh: 0.7\n", "need 0 <= free_thresh < occupied_thresh <= 1"),
        ("origin: null\n", "origin must be [x, y, yaw]"),
        ("origin: [0]\n", "origin must be [x, y, yaw]"),
        ("origin: [0, .nan, 0]\n", "origin must be [x, y, yaw]"),
        ("negate: null\n", "negate must be 0 or 1"),
        ("occupied_thresh: null\n", "occupied_thresh must be a finite number"),
        ("mode: fuzzy\n", "mode must be trinary, scale or raw"),
    ],
)
def test_a_map_yaml_that_would_misread_cells_is_refused(tmp_path, yaml_text, message):
    write_map(tmp_path / "g.yaml", Grid(np.array([[0, 100, -1]], np.int8), 1.2))
    head = "image: g.pgm\nresolution: 1.2\n"
    (tmp_path / "bad.yaml").write_text(head + yaml_text)
    with pytest.raises(ValueError, match=message.replace("[", "\\[")):
        read_map(tmp_path / "bad.yaml")
    for res in ("0", "-1.2", "null"):
        (tmp_path / "bad.yaml").write_text(f"image: g.pgm\nresolution: {res}\n")
        with pytest.raises(ValueError, match="resolution must be"):
            read_map(tmp_path / "bad.yaml")


def test_map_savers_unknown_gray_stays_unknown_whatever_free_thresh(tmp_path):
    """Nav2's map_saver writes free_thresh 0.25, at which its own unknown gray (205, an
    occupancy of 0.196) would read as free: for a wheelchair it stays unknown."""
    write_map(tmp_path / "g.yaml", Grid(np.array([[0, 100, -1]], np.int8), 1.2))
    (tmp_path / "n.yaml").write_text("image: g.pgm\nresolution: 1.2\nfree_thresh: 0.25\n")
    assert read_map(tmp_path / "n.yaml").data.tolist() == [[0, 100, -1]]


def test_the_unknown_gray_is_occupied_where_occupied_thresh_makes_it_so(tmp_path):
    """With occupied_thresh at or under 0.196 Nav2 reads the unknown gray occupied (205, or 50 with
    negate 1: occupancy 0.196 either way); it was unknown here whatever the thresholds, and a plan could start in that cell
    (an unknown start cell is allowed) though Nav2 calls it occupied (a review)."""
    (tmp_path / "m.pgm").write_bytes(b"P5\n3 1\n255\n\xcd\xfe\xfe")
    base = "image: m.pgm\nmode: trinary\nresolution: 1.2\norigin: [0.0, 0.0, 0.0]\n"
    (tmp_path / "low.yaml").write_text(base + "occupied_thresh: 0.15\nfree_thresh: 0.1\n")
    assert read_map(tmp_path / "low.yaml").data.tolist() == [[100, 0, 0]]
    # negate: 1, whose unknown gray is 255 - 205 = 50 (occupancy 0.196 again), black free
    (tmp_path / "neg.yaml").write_text(
        base + "negate: 1\noccupied_thresh: 0.15\nfree_thresh: 0.1\n"
    )
    (tmp_path / "m.pgm").write_bytes(b"P5\n3 1\n255\n\x32\x00\x00")
    assert read_map(tmp_path / "neg.yaml").data.tolist() == [[100, 0, 0]]
    # the defaults: unknown, as map_saver meant it
    (tmp_path / "def.yaml").write_text(base)
    (tmp_path / "m.pgm").write_bytes(b"P5\n3 1\n255\n\xcd\xfe\xfe")
    assert read_map(tmp_path / "def.yaml").data.tolist() == [[-1, 0, 0]]


def test_pgm_samples_above_maxval_or_a_zero_maxval_are_refused(tmp_path):
    (tmp_path / "g.yaml").write_text("image: g.pgm\nresolution: 1.2\n")
    for pgm, message in (
        (b"P2\n3 1\n100\n254 0 205\n", "exceeds maxval 100"),  # scaled past 255: unknown free
        (b"P5\n3 1\n0\n\xfe\x00\xcd", "bad PGM header"),  # ZeroDivisionError before
        (b"P2\n3 1\n255\n254 0\n", "truncated"),
        # each of these was numpy's or int()'s own message, or a dump of the raw bytes
        (b"P5\n3 2\n255\n\xfe\x00", "truncated \\(2 of 6 pixels\\)"),
        (b"P2\n3 1\n255\n\xfe\x00\xcd\x01", "pixels are not numbers"),
        (b"P5\nthree 1\n255\n\xfe\x00\xcd", "size and maxval are not numbers"),
        (b"P5\n3", "not a PGM"),
        (b"\x89PNG\r\n\x1a\n", "not a PGM"),
    ):
        (tmp_path / "g.pgm").write_bytes(pgm)
        with pytest.raises(ValueError, match=message):
            read_map(tmp_path / "g.yaml")


def test_progress_finish_gives_the_count_known_after_the_last_update():
    """The mapper registers its last frame after the bar reached it: the last line read
    "942/942 frames ... used 941" where the summary said 942 used."""
    import io

    from wheelgrid_common.progress import Progress

    out = io.StringIO()
    with Progress(2, "mapping", "frames", stream=out) as bar:
        bar.update(1, postfix="used 0")
        bar.update(1, postfix="used 1")
        bar.finish("used 2")
        bar.finish("used 2")  # nothing new: no line more
    lines = out.getvalue().splitlines()
    assert lines[-1].startswith("mapping [") and lines[-1].endswith("used 2"), lines
    assert sum(line.endswith("used 2") for line in lines) == 1


def test_progress_on_a_terminal_clears_what_a_shorter_line_leaves():
    """The bar redraws with "\r", which goes back but writes over only as far as the new line
    reaches: on a terminal "... used 194" stayed where the line had become "... used 19"."""
    import io

    from wheelgrid_common.progress import Progress

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    out = Tty()
    bar = Progress(20, "mapping", "frames", stream=out)
    bar.postfix = "used 194 of a long postfix"
    bar._draw(bar.start + 1.0, end="\r")
    bar.postfix = "used 19"
    bar._draw(bar.start + 1.0, end="\r")
    screen = ""
    for part in out.getvalue().split("\r")[:-1]:  # a terminal: each part over the last
        screen = part + screen[len(part) :]
    assert screen.rstrip().endswith("used 19"), screen


def test_a_map_image_given_for_its_yaml_says_which_to_give(tmp_path):
    """grid.pgm given where grid.yaml belongs read as YAML: "unacceptable character #x0000"."""
    write_map(tmp_path / "g.yaml", Grid(np.zeros((2, 3), dtype=np.int8), 1.0, (0.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match=r"g\.pgm: an image, not a map_server YAML: give"):
        read_map(tmp_path / "g.pgm")


def test_files_written_together_keep_the_old_set_when_one_fails(tmp_path):
    """A map_server YAML and its PGM (a map and its report) are replaced together or not at
    all: a write that failed mid-way left a cut-off file beside its old partner."""
    grid = Grid(np.zeros((2, 3), dtype=np.int8), 1.0, (0.0, 0.0, 0.0))
    write_map(tmp_path / "g.yaml", grid)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def full_disk(path):
        path.write_bytes(b"P5\n3 2")  # cut off, as by ENOSPC
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_together(
            {tmp_path / "g.pgm": full_disk, tmp_path / "g.yaml": lambda p: p.write_text("x")}
        )
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no .partial left
    write_map(tmp_path / "g.yaml", Grid(np.full((4, 5), 100, dtype=np.int8), 0.5, (1, 2, 0)))
    back = read_map(tmp_path / "g.yaml")
    assert back.data.shape == (4, 5) and (back.data == 100).all()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.pgm", "g.yaml"]


def test_files_written_together_keep_the_old_set_when_one_cannot_be_replaced(tmp_path, monkeypatch):
    """The targets were replaced one by one: where a later one could not be (a folder in its
    place; another user's file in a sticky /tmp, made to fail here), the ones before it were
    new and it old: a 0.6 m grid.yaml and grid.pgm beside a 1.2 m grid.png (a review). The
    replaced ones are put back, and a target that did not exist before is removed again."""
    import os

    from wheelgrid_common import fileio

    old = {"a.txt": "old a", "b.txt": "old b"}
    for name, text in old.items():
        (tmp_path / name).write_text(text)
    (tmp_path / "c.txt").mkdir()
    (tmp_path / "c.txt" / "inside").write_text("kept")
    writers = {tmp_path / n: (lambda t: lambda p: p.write_text(t))(f"new {n}")
               for n in ("a.txt", "b.txt", "c.txt")}  # fmt: skip
    with pytest.raises(IsADirectoryError, match=r"c\.txt"):
        write_together(writers)
    assert {n: (tmp_path / n).read_text() for n in old} == old
    assert (tmp_path / "c.txt" / "inside").read_text() == "kept"

    real_replace = os.replace

    def refuses_b(src, dst):
        if os.path.basename(dst) == "b.txt":
            raise PermissionError(1, "Operation not permitted", str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(fileio.os, "replace", refuses_b)
    writers = {tmp_path / n: (lambda t: lambda p: p.write_text(t))(f"new {n}")
               for n in ("new.txt", "a.txt", "b.txt")}  # fmt: skip
    with pytest.raises(PermissionError):
        write_together(writers)
    assert {n: (tmp_path / n).read_text() for n in old} == old  # a.txt put back
    assert not (tmp_path / "new.txt").exists()  # made, then taken away again
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt", "c.txt"]

    def interrupted_at_b(src, dst):  # a Ctrl-C between two replaces: it left a new map.ply
        if os.path.basename(dst) == "b.txt":  # beside the old report, the old map gone
            raise KeyboardInterrupt
        real_replace(src, dst)

    monkeypatch.setattr(fileio.os, "replace", interrupted_at_b)
    with pytest.raises(KeyboardInterrupt):
        write_together(writers)
    assert {n: (tmp_path / n).read_text() for n in old} == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt", "c.txt"]
    monkeypatch.setattr(fileio.os, "replace", real_replace)
    write_together(writers)
    assert (tmp_path / "b.txt").read_text() == "new b.txt"


def test_a_binary_file_given_as_a_yaml_is_one_clear_error(tmp_path):
    """A map.ply given where the grid's YAML belongs: 'utf-8' codec can't decode byte 0xf9."""
    write_ply(tmp_path / "map.ply", np.ones((10, 3)) * np.pi)
    with pytest.raises(ValueError, match=r"map\.ply: not a YAML file"):
        read_map(tmp_path / "map.ply")


def _png(path, pixels, mode=None):
    from PIL import Image

    Image.fromarray(np.asarray(pixels), mode).save(path)


_NAV2_HEAD = "resolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"


def test_colour_and_16_bit_images_read_as_nav2_map_server_reads_them(tmp_path):
    """map_server averages R, G and B and scales any bit depth: PIL's convert("L") weighted
    the channels (yellow, unknown for Nav2, read as free) and clipped 16-bit samples (map_saver's
    unknown gray 205 read as white, i.e. free)."""
    _png(tmp_path / "c.png", np.array([[[255, 255, 0], [0, 255, 0], [254, 254, 254]]], np.uint8))
    (tmp_path / "c.yaml").write_text(
        "image: c.png\nmode: trinary\n" + _NAV2_HEAD + "occupied_thresh: 0.65\nfree_thresh: 0.25\n"
    )
    # yellow: mean 170, occupancy 0.333 -> unknown; green: mean 85, 0.667 -> occupied
    assert read_map(tmp_path / "c.yaml").data.tolist() == [[-1, 100, 0]]
    _png(tmp_path / "d.png", np.array([[205 * 257, 254 * 257, 0]], np.uint16))
    (tmp_path / "d.yaml").write_text("image: d.png\n" + _NAV2_HEAD)
    assert read_map(tmp_path / "d.yaml").data.tolist() == [[-1, 0, 100]]


def test_an_image_past_pillows_pixel_limit_is_one_clear_error(tmp_path, monkeypatch):
    """A few KB of PNG that unpacks to over ~179 M pixels (Pillow's DecompressionBombError)
    came out of read_map as a traceback, exit 1, from `wheelgrid plan` (a review). Pillow's
    own limit, lowered here so that a small image passes it, is read as one ValueError."""
    from PIL import Image

    _png(tmp_path / "c.png", np.zeros((20, 20), np.uint8))
    (tmp_path / "c.yaml").write_text("image: c.png\n" + _NAV2_HEAD)
    assert read_map(tmp_path / "c.yaml").data.shape == (20, 20)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # 400 pixels: over twice the limit
    with pytest.raises(ValueError, match=r"c\.png: too large to read as a map"):
        read_map(tmp_path / "c.yaml")


def test_transparent_pixels_read_as_nav2_map_server_reads_them(tmp_path):
    """Nav2's map_saver writes scale mode's unknown cells as transparent gray (0.5): map_server
    reads any pixel that is not opaque as unknown there, and in trinary mode averages the
    alpha in with R, G and B. With alpha dropped the gray read as a cost of 61, or as free
    under a free_thresh above 0.498; a transparent white read as free."""
    scale = np.array(
        [[[128, 128, 128, 0], [255, 255, 255, 255], [0, 0, 0, 255], [153, 153, 153, 255]]],
        np.uint8,
    )
    _png(tmp_path / "s.png", scale)
    thresholds = "occupied_thresh: 0.65\nfree_thresh: 0.25\n"
    (tmp_path / "s.yaml").write_text("image: s.png\nmode: scale\n" + _NAV2_HEAD + thresholds)
    # map_saver's cell 40 is gray 0.6 = 153: occupancy 0.4, rint(100 * 0.15 / 0.4) = 38
    assert read_map(tmp_path / "s.yaml").data.tolist() == [[-1, 0, 100, 38]]
    (tmp_path / "s2.yaml").write_text(
        "image: s.png\nmode: scale\n" + _NAV2_HEAD + "occupied_thresh: 0.65\nfree_thresh: 0.55\n"
    )
    assert read_map(tmp_path / "s2.yaml").data[0, 0] == -1
    _png(tmp_path / "t.png", np.array([[[255, 255, 255, 0], [254, 254, 254, 255]]], np.uint8))
    (tmp_path / "t.yaml").write_text("image: t.png\nmode: trinary\n" + _NAV2_HEAD + thresholds)
    # (255 * 3 + 0) / 4 = 191.25: occupancy 0.25, not below free_thresh -> unknown
    assert read_map(tmp_path / "t.yaml").data.tolist() == [[-1, 0]]


def test_raw_mode_reads_values_as_nav2_map_server_does(tmp_path):
    """map_server's raw mode takes the pixel value as the cell's, rounded, and ignores negate:
    negated here, a raw unknown (255) read as free (0)."""
    (tmp_path / "r.pgm").write_bytes(b"P2\n4 1\n255\n0 100 255 101\n")
    (tmp_path / "r.yaml").write_text(
        "image: r.pgm\nmode: raw\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 1\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.25\n"
    )
    assert read_map(tmp_path / "r.yaml").data.tolist() == [[0, 100, -1, -1]]
    (tmp_path / "r16.pgm").write_bytes(b"P2\n2 1\n65535\n25800 25600\n")  # 100.39 and 99.61
    (tmp_path / "r16.yaml").write_text(
        (tmp_path / "r.yaml").read_text().replace("r.pgm", "r16.pgm")
    )
    assert read_map(tmp_path / "r16.yaml").data.tolist() == [[100, 100]]


def test_folders_named_with_a_tilde_are_under_the_users_home(tmp_path, monkeypatch):
    """``--out=~/run`` (bash expands no ``~`` after ``=``) and a node's ``output_dir: ~/maps``
    made a folder literally named ``~`` in the current folder."""
    from wheelgrid_common.fileio import out_folder, user_folder

    monkeypatch.setenv("HOME", str(tmp_path))
    assert out_folder("~/run") == tmp_path / "run"
    assert user_folder("~/maps") == tmp_path / "maps"
    monkeypatch.chdir(tmp_path)
    assert user_folder("maps") == tmp_path / "maps"  # relative: to where it was started
    # ``~maps`` is user maps's home: with no such user pathlib raised RuntimeError, which no
    # node caught (~/save_map killed the mapper); an OSError that says what was meant
    with pytest.raises(FileNotFoundError, match=r"no user 'nosuchuser_wg'.*~/nosuchuser_wg"):
        user_folder("~nosuchuser_wg")
    import argparse  # and --out ~nosuchuser_wg/run: a traceback, now argparse's exit 2

    with pytest.raises(argparse.ArgumentTypeError, match="no user 'nosuchuser_wg'"):
        out_folder("~nosuchuser_wg/run")


def _pcd(path, fields, rows, kind="ascii", sizes=None, types=None, declared=None):
    """A PCD file written by hand, as PCL lays it out."""
    sizes = sizes or [4] * len(fields)
    types = types or ["F"] * len(fields)
    n = len(rows) if declared is None else declared
    head = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join('1' for _ in fields)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {kind}\n"
    )
    if kind == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows).encode()
    else:
        dt = np.dtype(
            [
                (f"f{k}", f"<{t.lower()}{z}")
                for k, (t, z) in enumerate(zip(types, sizes, strict=True))
            ]
        )
        body = np.array([tuple(r) for r in rows], dtype=dt).tobytes()
    path.write_bytes(head.encode() + body)
    return path


@pytest.mark.parametrize("kind", ["ascii", "binary", "binary_compressed"])
def test_pcd_files_read_as_open3d_writes_them(tmp_path, kind):
    """The three PCD bodies PCL writes, from Open3D's own writer: the same points, NaN rows
    (an organised cloud's pixels without a return) kept for the caller to drop."""
    import open3d as o3d

    from wheelgrid_common.fileio import read_cloud

    rng = np.random.default_rng(4)
    pts = rng.uniform(-5, 5, (500, 3)).astype(np.float32).astype(np.float64)
    pts[7] = np.nan
    path = tmp_path / f"{kind}.pcd"
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    assert o3d.io.write_point_cloud(
        str(path), cloud, write_ascii=kind == "ascii", compressed=kind == "binary_compressed"
    )
    got = read_cloud(path)
    assert got.shape == (500, 3)
    np.testing.assert_allclose(got, pts, rtol=1e-6, equal_nan=True)


def test_pcd_extra_fields_and_types_are_skipped_by_their_sizes(tmp_path):
    """x y z among other fields of other sizes (intensity as a double, a ring as a uint16): the
    binary body is read by the header's layout, not as 12-byte points."""
    from wheelgrid_common.fileio import read_cloud

    rows = [(7.5, 1.0, 2.0, 3, 3.0), (8.5, 4.0, 5.0, 9, 6.0)]
    fields = ["intensity", "x", "y", "ring", "z"]
    path = _pcd(
        tmp_path / "b.pcd", fields, rows, "binary", [8, 4, 4, 2, 4], ["F", "F", "F", "U", "F"]
    )
    np.testing.assert_allclose(read_cloud(path), [[1, 2, 3], [4, 5, 6]])
    path = _pcd(tmp_path / "a.pcd", fields, rows, "ascii")
    np.testing.assert_allclose(read_cloud(path), [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize("kind", ["ascii", "binary"])
def test_a_cut_off_pcd_is_an_error_not_fewer_or_invented_points(tmp_path, kind):
    """Open3D filled a cut-off ascii file's missing points with whatever its memory held
    (values like 1e-312: points at the origin, on the floor of a map)."""
    from wheelgrid_common.fileio import read_cloud

    path = _pcd(tmp_path / "cut.pcd", ["x", "y", "z"], [(1, 2, 3), (4, 5, 6)], kind, declared=3)
    with pytest.raises(
        ValueError, match=r"cut\.pcd: (2 point lines, where its header lists 3|cut off)"
    ):
        read_cloud(path)


def test_a_damaged_ascii_pcd_says_which_line_in_the_files_own_terms(tmp_path):
    """numpy reads the ascii body; its messages counted rows from 0 and ended in advice on its
    own arguments ("use `usecols`")."""
    from wheelgrid_common.fileio import read_cloud

    rows = [(1, 2, 3), (4, 5, 6), (7, 8, 9)]
    path = _pcd(tmp_path / "mid.pcd", ["x", "y", "z"], rows, "ascii")
    text = path.read_bytes()
    path.write_bytes(text[: text.rindex(b" ")])  # cut off in the last line's last number
    with pytest.raises(ValueError, match=r"mid\.pcd: point line 3 holds 2 values, not 3 \(cut"):
        read_cloud(path)
    path.write_bytes(text.replace(b"5", b"x"))
    with pytest.raises(ValueError, match=r"mid\.pcd: point line 2: 'x\.0' is no number$"):
        read_cloud(path)
    path.write_bytes(text + b"\n\n")  # blank lines at the end are no points
    np.testing.assert_allclose(read_cloud(path), rows)


def test_a_damaged_compressed_pcd_and_non_pcds_are_errors_that_name_the_file(tmp_path):
    import open3d as o3d

    from wheelgrid_common.fileio import read_cloud

    good = tmp_path / "c.pcd"
    pts = np.random.default_rng(2).uniform(-5, 5, (1000, 3))  # incompressible: 12 kB of body
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    assert o3d.io.write_point_cloud(str(good), cloud, compressed=True)
    cut = tmp_path / "cut.pcd"
    cut.write_bytes(good.read_bytes()[:-200])
    with pytest.raises(ValueError, match=r"cut\.pcd: (0 of the 1000 points|cut off)"):
        read_cloud(cut)
    not_pcd = tmp_path / "notes.pcd"
    not_pcd.write_text("hello\n")
    with pytest.raises(ValueError, match="not a PCD file"):
        read_cloud(not_pcd)
    no_xyz = _pcd(tmp_path / "rgb.pcd", ["rgb", "label"], [(1, 2)])
    with pytest.raises(ValueError, match="hold no x y z"):
        read_cloud(no_xyz)
    odd = _pcd(tmp_path / "odd.pcd", ["x", "y", "z"], [(1, 2, 3)], "binary", [2, 4, 4])
    with pytest.raises(ValueError, match="bad PCD header"):
        read_cloud(odd)  # a 2-byte float: no PCL type


def test_a_compressed_pcd_header_cannot_ask_for_more_memory_than_its_body_holds(tmp_path):
    """POINTS 10^12 over a 24-byte binary_compressed body: refused from the body's own sizes
    before Open3D is asked (it sized its cloud from POINTS: std::bad_alloc, or with enough
    memory promised, a machine swapping for a file of a few bytes)."""
    from wheelgrid_common.fileio import read_cloud

    path = tmp_path / "big.pcd"
    head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
    body = np.array([16, 24], "<u4").tobytes() + bytes(16)
    path.write_bytes(
        (head + "POINTS {n}\nDATA binary_compressed\n").format(n=10**12).encode() + body
    )
    with pytest.raises(ValueError, match=r"big\.pcd: .*10{12}|big\.pcd: .*1000000000000"):
        read_cloud(path)


def test_pcd_without_points_or_with_a_zero_count_is_read_or_refused_in_one_line(tmp_path):
    """POINTS 0 is an empty cloud in ascii as in binary (ascii said "point lines of ()
    values"); COUNT 0 on x is a bad header, not an IndexError."""
    from wheelgrid_common.fileio import read_cloud

    for kind in ("ascii", "binary"):
        path = _pcd(tmp_path / f"empty_{kind}.pcd", ["x", "y", "z"], [], kind)
        assert read_cloud(path).shape == (0, 3)
    path = tmp_path / "zero.pcd"
    path.write_bytes(
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 0 1 1\nWIDTH 1\nHEIGHT 1\n"
        b"POINTS 1\nDATA binary\n" + bytes(8)
    )
    with pytest.raises(ValueError, match="bad PCD header"):
        read_cloud(path)


def test_a_new_folder_is_never_one_an_earlier_run_wrote_into(tmp_path):
    """The mapper's rescue save on exit went to a fixed on_exit/, and a second session's scan
    replaced the first one's there. A folder that exists is taken, even empty (another
    process's, made and not yet written): the next gets a UTC time."""
    import threading

    from wheelgrid_common.fileio import new_folder

    base = tmp_path / "out" / "on_exit"
    assert new_folder(base) == base and base.is_dir()  # the parent is made too
    (base / "map.ply").write_text("first")
    second = new_folder(base)
    assert second.name.startswith("on_exit_") and second.name.endswith("Z") and second.is_dir()
    third = new_folder(base)  # within the same second: a counter
    assert third not in (base, second) and third.name.startswith("on_exit_") and third.is_dir()
    assert (base / "map.ply").read_text() == "first"
    race = tmp_path / "race" / "on_exit"
    claimed: list = []
    threads = [threading.Thread(target=lambda: claimed.append(new_folder(race))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(claimed)) == 8, claimed  # eight savers at once: eight folders
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError):
        new_folder(tmp_path / "file" / "on_exit")


def test_in_scale_mode_a_shade_just_past_free_thresh_is_not_free(tmp_path):
    """map_server's scale mode rounds a shade just past free_thresh to 0: wheelgrid's own
    unknown gray 205 (occupancy 0.19608 against free_thresh 0.196) read free in a grid whose
    YAML said ``mode: scale``, and the planner routed through it. Between the thresholds is
    never free (1 at least); below free_thresh still is, and the rest is scaled as before."""
    (tmp_path / "g.pgm").write_bytes(b"P2\n3 1\n255\n205 254 0\n")
    (tmp_path / "g.yaml").write_text(
        "image: g.pgm\nmode: scale\nresolution: 1.2\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    data = read_map(tmp_path / "g.yaml").data.tolist()
    assert data == [[1, 0, 100]], data
