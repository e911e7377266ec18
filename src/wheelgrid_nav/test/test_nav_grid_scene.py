"""The grid on the team simulator's scenes against their exact ground truth.

Exact surface points (what a perfect scanner inside the room sees) must give the exact truth on
the paper scene, in the room frame and in the mapper's map frame; on random scenes (bars above
and below the safe height) an occupied-in-truth cell must never come out free. The bundled bag
(noise, wild returns, flying pixels) fused with its true poses must keep that safety property
and still open the paper's route under Barrier 2.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common.map_io import FREE, OCCUPIED, UNKNOWN
from wheelgrid_nav.grid import build_grid, grid_text

sim_scene = pytest.importorskip("wheelgrid_sim.scene")

BAG_DIR = Path(__file__).resolve().parents[3] / "bags" / "paper_room"
SPACING = 0.04


def interior_points(scene, spacing: float = SPACING) -> np.ndarray:
    return scene.interior_surface_points(spacing)


def apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def danger(result, expected) -> np.ndarray:
    """Cells occupied in truth but not occupied in the grid (free or unknown would both be a
    failure of the truth comparison; free is the dangerous one)."""
    assert result.grid.data.shape == expected.data.shape, grid_text(result.grid)
    return (expected.data == OCCUPIED) & (result.grid.data == FREE)


@pytest.fixture(scope="module")
def paper():
    return sim_scene.paper_scene()


def test_paper_scene_exact_truth(paper):
    res = build_grid(interior_points(paper))
    expected = paper.expected_grid(safe_height=1.5, floor_clearance=0.05, cell_size=1.2)
    assert res.grid.data.shape == (8, 8)
    np.testing.assert_array_equal(res.grid.data, expected.data, err_msg=grid_text(res.grid))
    # the paper's features, spelled out
    assert (res.grid.data[3, 0:5] == OCCUPIED).all()  # tables A, B and Barrier 1
    assert res.grid.data[3, 5] == FREE  # past the end of Barrier 1
    assert (res.grid.data[4, 5:8] == FREE).all()  # under Barrier 2 (1.5116 m)
    assert (res.grid.data[5, 0:4] == OCCUPIED).all()  # second row of tables
    assert res.grid.origin == pytest.approx((0.0, 0.0, 0.0), abs=0.01)


def test_paper_scene_in_the_mapper_frame(paper):
    """The mapper's map frame (origin below the first pose at room (0.6, 6.6)): same cells."""
    map_from_room = np.eye(4)
    map_from_room[:2, 3] = (-0.6, -6.6)
    if (BAG_DIR / "truth.json").exists():
        import json

        map_from_room = np.asarray(
            json.loads((BAG_DIR / "truth.json").read_text())["map_from_room"]
        )
    res = build_grid(apply(map_from_room, interior_points(paper)))
    expected = paper.expected_grid()
    np.testing.assert_array_equal(res.grid.data, expected.data, err_msg=grid_text(res.grid))
    corner = apply(map_from_room, np.zeros((1, 3)))[0]
    assert res.grid.origin[:2] == pytest.approx(tuple(corner[:2]), abs=0.02)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_random_scenes_never_mark_an_occupied_cell_free(seed):
    scene = sim_scene.random_scene(seed)
    # rotate the scene into a map frame at an arbitrary heading and offset
    yaw = math.radians(7.0 * seed - 15.0)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:2, 3] = (1.5 * seed - 3.0, 0.7 * seed)
    res = build_grid(apply(T, interior_points(scene)))
    expected = scene.expected_grid()
    bad = danger(res, expected)
    assert not bad.any(), f"free in grid, occupied in truth: {np.argwhere(bad).tolist()}"
    assert not (res.grid.data == UNKNOWN).any()
    # bars that block (below 1.5 m) occupy their cells, bars above the band do not block
    for label, bar in scene.barriers.items():
        box = next(b for b in scene.boxes if b.label == label)
        cx, cy = (box.min[0] + box.max[0]) / 2, (box.min[1] + box.max[1]) / 2
        r = int((scene.room[3] - cy) // 1.2)
        c = int((cx - scene.room[0]) // 1.2)
        if bar["blocks_chair"]:
            assert res.grid.data[r, c] == OCCUPIED, label
    # sanity: most truth-free cells are free (the grid is useful, not all-occupied)
    truth_free = expected.data == FREE
    assert np.count_nonzero(res.grid.data[truth_free] == FREE) >= 0.85 * truth_free.sum()


def test_random_scenes_cover_both_barrier_cases():
    kinds = set()
    for seed in range(6):
        kinds |= {b["blocks_chair"] for b in sim_scene.random_scene(seed).barriers.values()}
    assert kinds == {True, False}


# --- the bundled bag: noise, wild returns, flying pixels ------------------------------------


def _voxel(points: np.ndarray, size: float) -> np.ndarray:
    keys = np.floor(points / size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def _drop_depth_edges(xyz: np.ndarray) -> np.ndarray:
    """Organised (rows, cols, 3) -> valid points away from depth discontinuities (range jump
    > 5 cm + 3 % to a 4-neighbour): every pixel at an edge, a cruder cut than the mapper's
    optional mixed-pixel test (``preprocess.mixed_pixels``), which keeps a thin obstacle's own
    edge pixels."""
    rng = np.linalg.norm(xyz, axis=2)
    valid = np.isfinite(rng)
    r = np.where(valid, rng, np.inf)
    thr = 0.05 + 0.03 * np.where(valid, rng, 0.0)
    jump = np.zeros(r.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        d0 = np.abs(r[1:] - r[:-1])
        d1 = np.abs(r[:, 1:] - r[:, :-1])
    big0 = np.isfinite(d0) & (d0 > np.minimum(thr[1:], thr[:-1]))
    big1 = np.isfinite(d1) & (d1 > np.minimum(thr[:, 1:], thr[:, :-1]))
    jump[1:] |= big0
    jump[:-1] |= big0
    jump[:, 1:] |= big1
    jump[:, :-1] |= big1
    return xyz[valid & ~jump]


@pytest.fixture(scope="module")
def bag_frames():
    if not (BAG_DIR / "scan" / "metadata.yaml").exists():
        pytest.skip(f"{BAG_DIR}: bundled bag not present")
    sim = pytest.importorskip("wheelgrid_sim.simulate")
    from wheelgrid_common.bagio import BagReader
    from wheelgrid_common.pointcloud2 import read_xyz

    gt = sim.load_ground_truth(BAG_DIR)
    frames = []
    with BagReader(BAG_DIR / "scan") as bag:
        for i, (_, _, msg) in enumerate(bag.messages([gt.truth["topic"]])):
            xyz = read_xyz(msg, drop_invalid=False).reshape(msg.height, msg.width, 3)
            frames.append((gt.poses_map[i], xyz))
    return gt, frames


def _fuse(frames, filt) -> np.ndarray:
    pts = np.concatenate([apply(T, filt(xyz)) for T, xyz in frames])
    return _voxel(pts, 0.02)  # like the mapper's map voxel


def test_bag_fused_raw_is_never_unsafe(bag_frames):
    gt, frames = bag_frames
    res = build_grid(_fuse(frames, lambda xyz: xyz[np.isfinite(xyz).all(axis=2)]))
    assert not danger(res, gt.expected_grid).any(), grid_text(res.grid)


def test_bag_fused_without_flying_pixels_opens_the_paper_route(bag_frames):
    gt, frames = bag_frames
    res = build_grid(_fuse(frames, _drop_depth_edges))
    g = res.grid.data
    assert not danger(res, gt.expected_grid).any(), grid_text(res.grid)
    assert (g[gt.expected_grid.data == OCCUPIED] == OCCUPIED).all(), grid_text(res.grid)
    # the paper's route: right along row 2 (after the start cell, which the camera stood on
    # and never saw), then down column 5 under Barrier 2
    assert (g[2, 1:6] == FREE).all(), grid_text(res.grid)
    assert (g[3:7, 5] == FREE).all(), grid_text(res.grid)
    assert (g[4, 5:8] == FREE).all(), grid_text(res.grid)
    # the grid is the room's: 8 x 8, corner at the room's (0, 0) in the map frame
    corner = apply(gt.map_from_room, np.zeros((1, 3)))[0]
    assert res.grid.origin[:2] == pytest.approx(tuple(corner[:2]), abs=0.05)
