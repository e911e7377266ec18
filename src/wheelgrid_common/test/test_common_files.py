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
