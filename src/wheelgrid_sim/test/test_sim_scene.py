"""Scenes and their exact expected grids (the paper's layout), random scenes, trajectories."""

from __future__ import annotations

import json
import math
from collections import deque

import numpy as np
import pytest

from wheelgrid_common.map_io import FREE, OCCUPIED
from wheelgrid_sim import Scene, make_trajectory, paper_scene, random_scene
from wheelgrid_sim.trajectory import _knots, nominal_duration, nominal_frames, scene_path

PAPER_LAYOUT = [
    "......#.",
    "........",
    "........",
    "#####...",
    "....#...",
    "####....",
    "........",
    "........",
]


def layout(grid_data: np.ndarray) -> list[str]:
    return ["".join("#" if v == OCCUPIED else "." for v in row) for row in grid_data]


def shortest_paths(
    free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]
) -> tuple[int, int]:
    """(length, number of distinct shortest 4-connected paths) by BFS with path counting."""
    rows, cols = free.shape
    dist = np.full(free.shape, -1)
    count = np.zeros(free.shape, dtype=np.int64)
    dist[start], count[start] = 0, 1
    q = deque([start])
    while q:
        r, c = q.popleft()
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            n = (r + dr, c + dc)
            if 0 <= n[0] < rows and 0 <= n[1] < cols and free[n]:
                if dist[n] < 0:
                    dist[n] = dist[r, c] + 1
                    q.append(n)
                if dist[n] == dist[r, c] + 1:
                    count[n] += count[r, c]
    return int(dist[goal]), int(count[goal])


def test_paper_expected_grid_is_the_intended_layout() -> None:
    grid = paper_scene().expected_grid()
    assert grid.resolution == 1.2 and grid.origin == (0.0, 0.0, 0.0)
    assert layout(grid.data) == PAPER_LAYOUT
    # Cell geometry: row 0 is the top (largest y).
    np.testing.assert_allclose(grid.cell_center(0, 0), [0.6, 9.0])
    np.testing.assert_allclose(grid.cell_center(2, 0), [0.6, 6.6])


def test_paper_route_is_unique_and_is_table_ii() -> None:
    free = paper_scene().expected_grid().data == FREE
    length, n = shortest_paths(free, (2, 0), (6, 5))
    assert (length, n) == (9, 1)
    # The route right x5 along row 2 then down column 5 is free, so it is that unique path.
    route = [(2, c) for c in range(6)] + [(r, 5) for r in range(3, 7)]
    assert all(free[rc] for rc in route) and len(route) == length + 1


def test_paper_dimensions_match_the_paper() -> None:
    s = paper_scene()
    box = {b.label: b for b in s.boxes}
    assert box["table_B_top"].min[0] - box["table_A_top"].max[0] == pytest.approx(1.2012)
    assert box["table_A_top"].min[1] - box["table_row5_0_top"].max[1] == pytest.approx(1.6572)
    assert box["barrier1_bar"].max[2] == pytest.approx(0.77)
    assert box["barrier2_bar"].min[2] == pytest.approx(1.5116)
    # Interior faces of the shell lie exactly on the room boundary.
    assert box["wall_west"].max[0] == 0.0 and box["wall_east"].min[0] == 9.6
    assert box["floor"].max[2] == 0.0


def test_expected_grid_follows_safe_height_and_cell_size() -> None:
    s = paper_scene()
    taller = layout(s.expected_grid(safe_height=1.6).data)
    # Barrier 2 (underside 1.5116 m) now blocks row 4 from its post to the east wall.
    assert taller[4] == "....####"
    low = layout(s.expected_grid(safe_height=0.7).data)
    # Under a 0.7 m limit Barrier 1's bar (0.72-0.77 m) no longer counts: only cells holding its
    # posts (x 3.5 in column 2, x 5.85 in column 4) or table legs stay occupied.
    assert low[3] == "###.#..."
    fine = s.expected_grid(cell_size=0.6)
    assert fine.data.shape == (16, 16)
    # A 0.6 m cell between table A and B (x 1.2..1.8, y 4.8..5.4) is free: the gap is 1.2012 m.
    assert fine.data[fine.cell_of(1.5, 5.1)] == FREE
    odd = s.expected_grid(cell_size=1.0)  # 9.6 m is not a multiple: last cells reach the walls
    assert odd.data.shape == (10, 10)
    assert (odd.data[:, -1] == OCCUPIED).all() and (odd.data[0, :] == OCCUPIED).all()


def test_surface_points_are_on_surfaces_and_cover_thin_parts() -> None:
    s = paper_scene()
    pts = s.sample_surface_points(0.05)
    assert np.max(s.distance_to_surfaces(pts)) < 1e-9
    bar = next(b for b in s.boxes if b.label == "barrier2_bar")
    on_bar = (
        (pts[:, 0] >= bar.min[0])
        & (pts[:, 0] <= bar.max[0])
        & (pts[:, 1] >= bar.min[1])
        & (pts[:, 1] <= bar.max[1])
        & (pts[:, 2] >= bar.min[2])
        & (pts[:, 2] <= bar.max[2])
    )
    assert on_bar.sum() > 4 * (bar.max[0] - bar.min[0]) / 0.05
    assert pts[:, 2].min() >= 0.0 and not (np.abs(pts[:, 2]) < 1e-12).all()


def test_scene_json_round_trip() -> None:
    s = paper_scene()
    back = Scene.from_json(json.loads(s.dumps()))
    assert back.boxes == s.boxes and back.room == s.room and back.barriers == s.barriers


@pytest.mark.parametrize("seed", [0, 1, 2, 5, 13])
def test_random_scene_is_valid(seed: int) -> None:
    s = random_scene(seed)
    again = random_scene(seed)
    assert s.boxes == again.boxes
    w, h = s.room[2], s.room[3]
    for size in (w, h):
        assert 6.0 <= size <= 10.0 and abs(size / 1.2 - round(size / 1.2)) < 1e-9
    grid = s.expected_grid()
    assert grid.data.shape == (round(h / 1.2), round(w / 1.2))
    ring = np.ones(grid.data.shape, bool)
    ring[1:-1, 1:-1] = False
    assert (grid.data[ring] == FREE).all()
    assert (grid.data == OCCUPIED).any()
    _, poses = make_trajectory(s, 40, 5.0, seed)
    for p in poses:
        assert s.is_free_at(p[0, 3], p[1, 3], 0.3, 1.3)


def test_random_scenes_have_bars_above_and_below_the_safe_height() -> None:
    above = below = 0
    for seed in range(10):
        for bar in random_scene(seed).barriers.values():
            above += bar["bottom"] > 1.5
            below += bar["top"] < 1.5
    assert above > 0 and below > 0


def test_paper_trajectory_is_wheelchair_like() -> None:
    s = paper_scene()
    stamps, poses = make_trajectory(s, 210, 5.0, 7)
    assert stamps[0] == 1_700_000_000 and np.allclose(np.diff(stamps), 0.2)
    np.testing.assert_allclose(poses[0, :2, 3], [0.6, 6.6])
    fwd = poses[:, :3, 2]
    assert fwd[0, 0] > 0.9 and abs(fwd[0, 1]) < 0.1  # first view along +x
    heights = poses[:, 2, 3]
    assert heights.min() >= 0.9 and heights.max() <= 1.2
    pitch = np.degrees(np.arcsin(-fwd[:, 2]))
    assert pitch.min() >= 15.0 - 1e-6 and pitch.max() <= 25.0 + 1e-6
    speed = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) * 5.0
    assert speed.max() < 0.85 and np.median(speed[speed > 0.01]) > 0.75
    for p in poses:
        assert s.is_free_at(p[0, 3], p[1, 3], 0.35, 1.3)
    for rot in poses[:, :3, :3]:
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)


def test_a_path_back_to_the_start_ends_where_it_began() -> None:
    """``back_to_start`` (a scan that closes its loop): the paper route and a random room's lap
    go on to their start, the chair's heading as it began, as clear of obstacles and as slow
    as the route before, which they follow unchanged up to its end. The phone's sweep about
    that heading goes on: its last view is off its first by up to the sweep (the CLI's help
    said "facing as it began"; a review)."""
    from wheelgrid_sim.trajectory import SWEEP_AMPLITUDE

    for s in (paper_scene(), random_scene(3)):
        plain = nominal_duration(s)
        total = nominal_duration(s, back_to_start=True)
        assert total > plain
        n = nominal_frames(total, 5.0)
        _, poses = make_trajectory(s, n, 5.0, 7, back_to_start=True)
        np.testing.assert_allclose(poses[-1, :2, 3], poses[0, :2, 3], atol=1e-9)
        start, segs = scene_path(s, back_to_start=True)
        end = _knots(start, segs)[-1]  # the chair's heading (the phone sweeps about it)
        assert math.remainder(end.heading - start[2], math.tau) == pytest.approx(0.0, abs=1e-12)
        views = [math.atan2(p[1, 2], p[0, 2]) for p in (poses[0], poses[-1])]  # optical z
        off = abs(math.remainder(views[1] - views[0], math.tau))
        assert off <= SWEEP_AMPLITUDE + math.radians(2)  # the sweep, a degree's roll tremor
        if s.name == "paper":
            assert math.degrees(off) == pytest.approx(32, abs=0.5)  # as the help says
        before = _knots(*scene_path(s))
        assert _knots(start, segs)[: len(before)] == before  # the same route up to its old end
        speed = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) * 5.0
        assert speed.max() < 0.85
        for p in poses:
            assert s.is_free_at(p[0, 3], p[1, 3], 0.35 if s.name == "paper" else 0.3, 1.3)


def test_distance_to_surfaces_counts_only_faces_seen_from_inside_the_room() -> None:
    """The shell boxes' outer faces (behind the walls, under the floor slab, on top of the
    ceiling) are no surface a scanner in the room can see: a map point 20 cm behind a wall is
    20 cm off the truth, not on it (it used to measure 0 from the wall box's far face)."""
    s = paper_scene()
    pts = np.array(
        [
            [-0.2, 5.0, 1.0],  # on the west wall box's outer face
            [-0.15, 5.0, 1.0],  # 15 cm into the west wall (5 cm from its outer face)
            [5.0, 5.0, -0.2],  # under the floor slab
            [9.85, 2.0, 1.0],  # 5 cm beyond the east wall box
            [5.0, 7.0, 2.9],  # on the ceiling box's top face
            [-0.03, 5.0, 1.0],  # 3 cm behind the west wall's inner face: a noisy wall point
        ]
    )
    np.testing.assert_allclose(
        s.distance_to_surfaces(pts), [0.2, 0.15, 0.2, 0.25, 0.2, 0.03], atol=1e-9
    )
