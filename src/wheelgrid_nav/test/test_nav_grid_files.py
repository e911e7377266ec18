"""`wheelgrid grid` and its files: map_server round trip, grid.png, exit codes and messages."""

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from wheelgrid_common.fileio import write_ply
from wheelgrid_common.map_io import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    read_map,
    to_occupancy_grid,
    write_map,
)
from wheelgrid_nav.cli_grid import main
from wheelgrid_nav.grid import build_grid
from wheelgrid_nav.grid_png import write_outputs
from wheelgrid_nav.grid_synth import paper_like_boxes, paper_like_expected, room_cloud, transform


@pytest.fixture(scope="module")
def map_ply(tmp_path_factory) -> str:
    cloud = transform(
        room_cloud(paper_like_boxes(), spacing=0.04), math.radians(-3.0), (-0.6, -6.6)
    )
    path = tmp_path_factory.mktemp("map") / "map.ply"
    write_ply(path, cloud)
    return str(path)


def test_files_round_trip_like_map_server(tmp_path):
    cloud = transform(room_cloud(paper_like_boxes(), spacing=0.04), math.radians(12.0), (1.0, 2.0))
    res = build_grid(cloud)
    # make sure all three values are exercised in the round trip
    res.grid.data[7, 7] = UNKNOWN
    files = write_outputs(res, tmp_path)
    assert {p.name for p in files.values()} == {
        "grid.yaml",
        "grid.pgm",
        "fine.yaml",
        "fine.pgm",
        "grid.png",
    }
    for name, original in (("grid.yaml", res.grid), ("fine.yaml", res.fine)):
        back = read_map(tmp_path / name)  # mirrors nav2_map_server's loader
        np.testing.assert_array_equal(back.data, original.data)
        assert back.resolution == pytest.approx(original.resolution)
        assert back.origin == pytest.approx(original.origin)
        doc = yaml.safe_load((tmp_path / name).read_text())
        assert doc["mode"] == "trinary" and doc["image"] == name.replace(".yaml", ".pgm")
    assert set(np.unique(read_map(tmp_path / "grid.yaml").data).tolist()) == {
        FREE,
        OCCUPIED,
        UNKNOWN,
    }
    assert read_map(tmp_path / "grid.yaml").origin[2] == pytest.approx(math.radians(12.0), abs=1e-3)


@pytest.mark.parametrize(
    ("size", "pixel_size"), [((2.4, 12.0), 0.05), ((9.6, 9.6), 0.05), ((6.0, 3.6), 0.4)]
)
def test_grid_png_shows_every_label_whole_and_a_true_metre(size, pixel_size):
    """A 2.4 x 12 m corridor's grid.png was 208 px wide: its panel titles printed over each
    other and the legend stopped after two of its five entries; at a 0.4 m pixel_size the
    "1 m" bar was 0.81 m; and the thin-obstacle guard's swatch was white, the free cells'
    colour, where its cells are drawn black (a review)."""
    from wheelgrid_nav.grid import GridConfig
    from wheelgrid_nav.grid_png import _LEGEND, _text_width, layout, render

    cfg = GridConfig(pixel_size=pixel_size, floor_fill=0, guard_line_length=1.2, unobserved_patch=0)
    res = build_grid(room_cloud([], size=size, spacing=0.04), cfg)
    plan = layout(res)
    width, height = plan.size
    boxes = [(x, y, x + _text_width(t), y + 11) for x, y, t in plan.texts]
    boxes += [(x, y, x + 10, y + 10) for x, y, _, _ in plan.legend]  # the swatches
    for x0, y0, x1, y1 in boxes:
        assert x0 >= 0 and x1 <= width and y0 >= 0 and y1 <= height, (boxes, plan.size)
    for i, a in enumerate(boxes):
        for b in boxes[i + 1 :]:
            apart = a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1]
            assert apart, (a, b)
    labels = [t for _, _, t in plan.texts]
    assert all(label in labels for _, _, label in _LEGEND)
    # the bar is 1 m at the picture's scale: canvas pixels per raster pixel / its size
    assert plan.bar == pytest.approx(plan.scale / pixel_size, abs=0.5)
    guard = next(fill for fill, _, label in _LEGEND if "guard" in label)
    assert guard == (0, 0, 0)  # as its cells are drawn: occupied
    picture = render(res)
    assert picture.size == plan.size


def test_cli_writes_the_paper_grid(map_ply, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([map_ply, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "8 x 8 cells of 1.2 m" in text
    grid = read_map(out / "grid.yaml")
    np.testing.assert_array_equal(grid.data == OCCUPIED, paper_like_expected())
    assert (grid.data != UNKNOWN).all()
    # the origin is the room corner (0, 0) in the map frame, the yaw the walls' direction
    assert grid.origin[2] == pytest.approx(math.radians(-3.0), abs=1e-3)
    corner = transform(np.zeros((1, 3)), math.radians(-3.0), (-0.6, -6.6))[0]
    assert grid.origin[:2] == pytest.approx(tuple(corner[:2]), abs=0.02)
    fine = read_map(out / "fine.yaml")
    assert fine.resolution == pytest.approx(0.05) and fine.origin[2] == 0.0
    with Image.open(out / "grid.png") as im:
        assert im.format == "PNG"
        w, h = im.size
        assert w > 3 * h / 2  # three panels side by side
        # panel (c) holds black (occupied) and white (free) cells
        colours = {c for _, c in im.convert("RGB").getcolors(maxcolors=1 << 16)}
        assert (0, 0, 0) in colours and (255, 255, 255) in colours


def test_cli_flags_and_config(map_ply, tmp_path):
    # --safe-height above Barrier 2 makes its row occupied
    out = tmp_path / "high"
    assert main([map_ply, "--out", str(out), "--safe-height", "1.6", "-q"]) == 0
    assert (read_map(out / "grid.yaml").data[4, 4:] == OCCUPIED).all()
    # a ROS params file for the node works for the CLI too (node-only keys are accepted)
    cfg = tmp_path / "params.yaml"
    cfg.write_text(
        yaml.safe_dump({"grid": {"ros__parameters": {"alignment": "map", "output_dir": "/tmp/x"}}})
    )
    out2 = tmp_path / "cfg"
    assert main([map_ply, "--out", str(out2), "--config", str(cfg), "--no-png", "-q"]) == 0
    assert read_map(out2 / "grid.yaml").origin[2] == 0.0
    assert not (out2 / "grid.png").exists()


def test_cli_warns_of_a_map_that_rises_higher_than_a_room(tmp_path, capsys):
    room = room_cloud(paper_like_boxes(), spacing=0.05)
    path = _ply_points(tmp_path, "side.ply", room[:, [0, 2, 1]])  # y up: on its side
    assert main([path, "--out", str(tmp_path / "out"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "wheelgrid grid: warning: the map rises 9.6 m above its floor" in err


def test_cli_warns_of_a_grid_with_no_free_cell(tmp_path, capsys):
    """The real iPhone capture (a 4.5 x 4 m room, a table and chairs) gives 3 x 3 cells, all
    occupied: exit 0, and every plan on it then failed with no word why."""
    rng = np.random.default_rng(5)
    floor = np.column_stack([rng.uniform(0, 3.6, (40000, 2)), np.zeros(40000)])
    clutter = np.column_stack([rng.uniform(0, 3.6, (40000, 2)), rng.uniform(0.2, 1.0, 40000)])
    path = _ply_points(tmp_path, "crowded.ply", np.vstack([floor, clutter]))
    assert main([path, "--out", str(tmp_path / "out"), "--quiet", "--alignment", "map"]) == 0
    captured = capsys.readouterr()
    assert "0 free" in captured.out and " map points (" in captured.out, captured.out
    assert "wheelgrid grid: warning: no free cell: no route can be planned" in captured.err


def test_cli_summary_gives_the_origin_in_metres(map_ply, tmp_path, capsys):
    """The one-line summary gave the grid's origin as two bare numbers, its unit unsaid."""
    assert main([map_ply, "--out", str(tmp_path / "out"), "--no-png"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert re.search(r"origin -?\d+\.\d{3} -?\d+\.\d{3} m\)", line), line


def _ply_points(tmp_path, name, points):
    path = tmp_path / name
    write_ply(path, np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return str(path)


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", "no such map file"),
        ("folder", "a folder, not a PLY or PCD map file; `wheelgrid map --out` wrote"),
        ("garbage", "not a readable PLY"),
        ("truncated", "not a readable PLY"),
        (
            "cutpcd",
            "c.pcd: not a readable PCD point cloud: 1 point lines, where its header lists 2",
        ),
        ("empty", "no (finite) points"),
        ("above", "above the safe height"),
        ("nofloor", "no floor found"),
        ("onlyfloor", "only floor"),
        ("badconfig", "bad config"),
        ("outfile", "cannot make the folder"),  # refused before the work, not after it
    ],
)
def test_cli_bad_input_exits_2_with_one_line(tmp_path, capsys, case, message):
    args = ["--out", str(tmp_path / "out")]
    if case == "missing":
        path = str(tmp_path / "nope.ply")
    elif case == "folder":  # the map command's --out folder instead of its map.ply
        (tmp_path / "m").mkdir()
        _ply_points(tmp_path / "m", "map.ply", [[0, 0, 0.5]])
        path = str(tmp_path / "m")
    elif case == "garbage":
        path = str(tmp_path / "garbage.ply")
        (tmp_path / "garbage.ply").write_bytes(b"\x00\x01 definitely not a ply")
    elif case == "truncated":
        path = _ply_points(tmp_path, "t.ply", np.zeros((100, 3)))
        raw = (tmp_path / "t.ply").read_bytes()
        (tmp_path / "t.ply").write_bytes(raw[:-50])
    elif case == "cutpcd":
        path = str(tmp_path / "c.pcd")
        head = "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 2\nDATA ascii\n"
        (tmp_path / "c.pcd").write_text(head + "1 2 3\n")
    elif case == "empty":
        path = _ply_points(tmp_path, "e.ply", np.empty((0, 3)))
    elif case == "above":
        path = _ply_points(tmp_path, "a.ply", [[0, 0, 2.0], [1, 0, 2.5]])
    elif case == "nofloor":
        path = _ply_points(tmp_path, "n.ply", [[x, 0, 0.8] for x in range(100)])
    elif case == "onlyfloor":
        path = _ply_points(
            tmp_path, "f.ply", [[x / 10, y / 10, 0] for x in range(60) for y in range(60)]
        )
    elif case == "outfile":
        path = _ply_points(tmp_path, "ok.ply", [[0, 0, 0]])
        (tmp_path / "afile").write_text("x")
        args = ["--out", str(tmp_path / "afile" / "out")]
    else:
        path = _ply_points(tmp_path, "ok.ply", [[0, 0, 0]])
        bad = tmp_path / "bad.yaml"
        bad.write_text("safe_hieght: 1.5\n")
        args += ["--config", str(bad)]
    assert main([path, *args]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    if case in ("garbage", "truncated", "cutpcd"):
        assert err.count(path) == 1, err  # named once (the reader's message named it too)
    assert not (tmp_path / "out" / "grid.yaml").exists()


def test_cli_refuses_an_empty_out(tmp_path, capsys, monkeypatch):
    """``--out ""`` (an unset shell variable) is the current folder to Path: it wrote the
    grid files wherever the shell stood, exit 0."""
    monkeypatch.chdir(tmp_path)
    path = _ply_points(tmp_path, "ok.ply", [[0, 0, 0]])
    with pytest.raises(SystemExit) as exc:
        main([path, "--out", ""])
    assert exc.value.code == 2
    assert "empty folder name" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.ply"]


def test_a_failed_write_keeps_the_whole_old_set_of_grid_files(tmp_path, monkeypatch):
    """grid.yaml/pgm, fine.yaml/pgm and grid.png are one grid's files. Each pair was replaced
    on its own and grid.png written in place: a full disk while writing fine.pgm (the largest
    map) left the new grid.yaml beside the old fine.yaml (Nav2's /map of another scan), and
    one while writing grid.png left a cut-off picture beside the new grid."""
    import wheelgrid_common.map_io as map_io
    import wheelgrid_nav.grid_png as grid_png

    first = build_grid(room_cloud(paper_like_boxes(), spacing=0.04))
    write_outputs(first, tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    second = build_grid(
        transform(room_cloud(paper_like_boxes(), spacing=0.04), math.radians(8.0), (1.0, 2.0))
    )
    real_write_pgm = map_io.write_pgm

    def fine_fills_the_disk(path, pixels):
        if "fine" in path.name:
            path.write_bytes(b"P5\n")  # cut off, as by ENOSPC
            raise OSError(28, "No space left on device")
        real_write_pgm(path, pixels)

    monkeypatch.setattr(map_io, "write_pgm", fine_fills_the_disk)
    with pytest.raises(OSError, match="No space"):
        write_outputs(second, tmp_path)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    monkeypatch.setattr(map_io, "write_pgm", real_write_pgm)

    class CutOffPicture:
        def save(self, path, format=None):
            Path(path).write_bytes(b"\x89PNG\r\n")
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(grid_png, "render", lambda result: CutOffPicture())
    with pytest.raises(OSError, match="No space"):
        write_outputs(second, tmp_path)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_no_png_leaves_no_picture_of_another_grid(map_ply, tmp_path):
    """``--no-png`` into a folder of an earlier run left that run's grid.png beside the new
    grid: a person checking the picture before the chair moves saw another grid's cells."""
    out = tmp_path / "out"
    assert main([map_ply, "--out", str(out), "-q"]) == 0
    assert (out / "grid.png").is_file()
    assert main([map_ply, "--out", str(out), "-q", "--no-png", "--safe-height", "1.6"]) == 0
    assert (read_map(out / "grid.yaml").data[4, 4:] == OCCUPIED).all()
    assert not (out / "grid.png").exists()


def _nav2_map_server_load(yaml_path):
    """nav2_map_server's loader (map_io.cpp loadMapYaml + loadMapFromFile, trinary, 8-bit
    gray) written out independently of wheelgrid_common.map_io: image path relative to the
    YAML's folder, occ = 1 - shade, ``occupied_thresh < occ`` occupied, ``occ < free_thresh``
    free, else unknown, and image row y stored at OccupancyGrid row ``height - y - 1``.
    Returns (data as a flat list, width, height, resolution, origin)."""
    doc = yaml.safe_load(Path(yaml_path).read_text())
    for key in ("image", "resolution", "origin", "free_thresh", "occupied_thresh", "negate"):
        assert key in doc, key  # Nav2 requires each of them
    assert len(doc["origin"]) == 3 and doc["mode"] == "trinary" and doc["negate"] == 0
    image = doc["image"]
    path = Path(image) if image.startswith("/") else Path(yaml_path).parent / image
    magic, size, maxval, body = path.read_bytes().split(b"\n", 3)
    width, height = (int(v) for v in size.split())
    assert magic == b"P5" and maxval == b"255" and len(body) == width * height
    data = [0] * (width * height)
    for y in range(height):
        for x in range(width):
            occ = 1.0 - body[y * width + x] / 255.0
            if doc["occupied_thresh"] < occ:
                cell = 100
            elif occ < doc["free_thresh"]:
                cell = 0
            else:
                cell = -1
            data[width * (height - y - 1) + x] = cell
    return data, width, height, doc["resolution"], doc["origin"]


def _occupancy_at(msg, x, y):
    """The value an OccupancyGrid gives the map point (x, y) (REP: cell (0, 0) at the origin
    pose, rows along its y axis), or None outside."""
    o = msg.info.origin
    yaw = 2.0 * math.atan2(o.orientation.z, o.orientation.w)
    dx, dy = x - o.position.x, y - o.position.y
    gx = math.cos(yaw) * dx + math.sin(yaw) * dy
    gy = -math.sin(yaw) * dx + math.cos(yaw) * dy
    i, j = math.floor(gx / msg.info.resolution), math.floor(gy / msg.info.resolution)
    if not (0 <= i < msg.info.width and 0 <= j < msg.info.height):
        return None
    return msg.data[j * msg.info.width + i]


def test_files_and_topics_agree_with_nav2_map_server_and_the_table_ii_cells(tmp_path):
    """What a Nav2 map_server would publish from grid.yaml and fine.yaml is, cell for cell, the
    OccupancyGrid the grid node publishes; our own reader gives the same cells; and a room
    point lands, on the published grid, in the (row, col) the planner calls it (row 0 the top,
    down = row + 1). A turned, non-square room, a folder and file names with spaces, and a
    second write over the first."""
    yaw, shift = math.radians(12.0), (1.0, 2.0)
    out = tmp_path / "saved maps"
    boxes = paper_like_boxes()
    write_outputs(build_grid(room_cloud(boxes, spacing=0.04)), out)  # to be overwritten
    res = build_grid(
        transform(room_cloud(boxes, size=(9.6, 7.2), spacing=0.04), yaw, shift),
        frame_id="map",
    )
    res.grid.data[0, 1] = UNKNOWN  # all three values
    write_outputs(res, out)
    assert res.grid.data.shape == (6, 8)
    for name, grid in (("grid.yaml", res.grid), ("fine.yaml", res.fine)):
        data, width, height, resolution, origin = _nav2_map_server_load(out / name)
        msg = to_occupancy_grid(grid)
        assert (width, height) == (msg.info.width, msg.info.height) == grid.data.shape[::-1]
        assert data == list(msg.data)
        assert resolution == msg.info.resolution and msg.header.frame_id == "map"
        assert origin == pytest.approx([*grid.origin])
        back = read_map(out / name)
        np.testing.assert_array_equal(back.data, grid.data)
        assert back.origin == pytest.approx(grid.origin)
        assert {-1, 0, 100} <= set(data) or name == "fine.yaml"
    # the same grid under a file name with a space, map_server's image path beside it
    write_map(out / "my grid.yaml", res.grid)
    assert yaml.safe_load((out / "my grid.yaml").read_text())["image"] == "my grid.pgm"
    assert _nav2_map_server_load(out / "my grid.yaml")[0] == list(to_occupancy_grid(res.grid).data)
    # a room point in cell (r, c) of the room (row 0 along the top wall, y = 7.2 m) is there
    # on the published grid, and in (r, c) of Grid.cell_of
    msg = to_occupancy_grid(res.grid)
    for r in range(6):
        for c in range(8):
            room = np.array([[(c + 0.5) * 1.2, 7.2 - (r + 0.5) * 1.2, 0.0]])
            x, y = transform(room, yaw, shift)[0, :2]
            assert res.grid.cell_of(x, y) == (r, c)
            assert _occupancy_at(msg, x, y) == res.grid.data[r, c]
