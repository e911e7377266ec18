"""The safe grid core on hand-made data: height band, eqs 8-10, unknown cells, the thin-obstacle
guard, drops, wall alignment, extent/phase and the boundary rule, bad input."""

import math
import re

import numpy as np
import pytest

from wheelgrid_common.map_io import FREE, OCCUPIED, UNKNOWN
from wheelgrid_nav.grid import (
    GridConfig,
    GridError,
    build_grid,
    cell_density,
    classify_density,
    continuous_obstacles,
    height_classes,
    linear_obstacles,
    project,
    thin_obstacle_guard,
    wall_yaw,
)
from wheelgrid_nav.grid_synth import (
    Box,
    paper_like_boxes,
    paper_like_expected,
    room_cloud,
    sample_box,
    transform,
)

SPACING = 0.04  # coarse enough to keep each cloud build in milliseconds


@pytest.fixture(scope="module")
def paper_cloud() -> np.ndarray:
    return room_cloud(paper_like_boxes(), spacing=SPACING)


def occupied(result) -> np.ndarray:
    return result.grid.data == OCCUPIED


# --- height band (the paper's safe height δ = 1.5 m) -------------------------------------------


def test_height_classes_band_edges():
    cfg = GridConfig()
    z = np.array([-0.3, -0.05, 0.0, 0.05, 0.0501, 0.77, 1.5, 1.5116, 2.6])
    # floor, floor, floor, floor (<= clearance), band, band, band (== safe height), above, above
    assert height_classes(z, cfg).tolist() == [2, 0, 0, 0, 1, 1, 1, 3, 3]


def test_bar_at_77cm_blocks_and_bar_at_151cm_is_removed():
    # Two 5 cm bars across row 1 of a 3.6 x 3.6 m room: one whose top is at 0.77 m in column 0,
    # one whose underside is at 1.5116 m in column 2 (the paper's Barriers 1 and 2).
    boxes = [
        Box(0.1, 1.1, 1.775, 1.825, 0.72, 0.77),
        Box(2.5, 3.5, 1.775, 1.825, 1.5116, 1.5616),
    ]
    res = build_grid(room_cloud(boxes, size=(3.6, 3.6), spacing=SPACING))
    assert res.grid.data.shape == (3, 3)
    assert res.grid.data[1, 0] == OCCUPIED
    assert res.grid.data[1, 2] == FREE
    assert np.count_nonzero(occupied(res)) == 1
    # Raise the safe height above Barrier 2: now it blocks too.
    res_high = build_grid(
        room_cloud(boxes, size=(3.6, 3.6), spacing=SPACING), GridConfig(safe_height=1.6)
    )
    assert res_high.grid.data[1, 2] == OCCUPIED


def test_orthographic_projection_drops_z():
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, 0.0]])
    np.testing.assert_array_equal(project(pts), [[1.0, 2.0], [-4.0, 5.0]])


# --- eqs 9 and 10 on hand-made images -------------------------------------------------------------


def test_eq9_density_per_tile():
    img = np.zeros((4, 6), dtype=bool)
    img[0, 0] = True  # tile (0,0): 1 of 4
    img[0:2, 2:4] = True  # tile (0,1): 4 of 4
    img[3, 5] = img[2, 4] = True  # tile (1,2): 2 of 4
    np.testing.assert_allclose(cell_density(img, 2, 2), [[0.25, 1.0, 0.0], [0.0, 0.0, 0.5]])
    # m x n tiles that are not square follow the same sum / (m n)
    np.testing.assert_allclose(cell_density(img, 4, 3), [[3 / 12, 4 / 12]])
    with pytest.raises(ValueError):
        cell_density(img, 3, 3)


def test_eq10_threshold_is_strict():
    density = np.array([[0.0, 0.05, 0.0501, 1.0]])
    # sigma <= delta -> free (False), sigma > delta -> obstacle (True)
    assert classify_density(density, 0.05).tolist() == [[False, False, True, True]]


# --- the thin-obstacle guard --------------------------------------------------------------------


def test_guard_on_hand_made_image():
    obs = np.zeros((6, 6), dtype=bool)
    counts = np.zeros((6, 6), dtype=np.int64)
    obs[1, 0:3] = True  # a short bar, 3 points a pixel, in tile (0,0) of 3x3 tiles
    counts[1, 0:3] = 3
    obs[4, 4] = True  # a lone speckle with one point in tile (1,1)
    counts[4, 4] = 1
    obs[4, 1] = True  # a thin pole: one pixel, many points, tile (1,0)
    counts[4, 1] = 12
    solid = continuous_obstacles(obs, counts, min_points=6)
    assert solid[1, 0:3].all() and solid[4, 1] and not solid[4, 4]
    guard = thin_obstacle_guard(obs, counts, 3, 3, min_points=6)
    assert guard.tolist() == [[True, False], [True, False]]
    # eq 10 alone misses the bar and the pole: densities 3/9 and 1/9 are below δ = 0.5
    assert not classify_density(cell_density(obs, 3, 3), 0.5).any()


def test_guard_catches_a_thin_bar_that_density_misses():
    # A 3 cm bar at 0.9 m across the middle cell, inside one pixel row: 21 of 576 pixels,
    # 3.6 % < δ = 5 %.
    boxes = [Box(1.3, 2.3, 1.76, 1.79, 0.85, 0.88)]
    cloud = room_cloud(boxes, size=(3.6, 3.6), spacing=SPACING)
    res = build_grid(cloud)
    assert res.density[1, 1] <= res.config.density_threshold
    assert res.grid.data[1, 1] == OCCUPIED and res.guard[1, 1]
    assert np.count_nonzero(occupied(res)) == 1
    paper_only = build_grid(cloud, GridConfig(thin_obstacle_guard=False))
    assert paper_only.grid.data[1, 1] == FREE  # what eq 10 alone would tell the chair


def test_guard_catches_a_lone_5cm_post_and_ignores_a_speckle():
    post = Box(0.5, 0.55, 0.5, 0.55, 0.0, 1.2)  # cell (2, 0) of a 3.6 m room
    cloud = room_cloud([post], size=(3.6, 3.6), spacing=SPACING)
    speckle = np.array([[2.9, 2.9, 0.8]])  # one noise point in cell (0, 2)
    res = build_grid(np.vstack([cloud, speckle]))
    assert res.grid.data[2, 0] == OCCUPIED
    assert res.grid.data[0, 2] == FREE
    assert np.count_nonzero(occupied(res)) == 1


def test_drop_below_the_floor_blocks():
    floor_hole = sample_box(Box(1.5, 2.1, 1.5, 2.1, -0.4, -0.3), SPACING)  # a pit, cell (1,1)
    cloud = room_cloud([], size=(3.6, 3.6), spacing=SPACING)
    res = build_grid(np.vstack([cloud, floor_hole]))
    assert res.grid.data[1, 1] == OCCUPIED
    assert np.count_nonzero(occupied(res)) == 1


@pytest.mark.parametrize("drop_depth", [0.0, -0.1, 0.7])
def test_a_drop_depth_that_reads_a_pit_as_floor_is_refused(drop_depth):
    """A 60 cm pit filling cell (1, 1), its floor seen only at its bottom: ``drop_depth`` 0
    ("disables"), a negative one or 0.7 m made every point of its bottom observed floor, and
    the cell free. Like ``floor_clearance`` (a kerb up), a step down deeper than 15 cm is an
    obstacle the chair cannot take."""
    cloud = room_cloud([], size=(3.6, 3.6), spacing=SPACING)
    over_pit = (np.abs(cloud[:, 0] - 1.8) < 0.6) & (np.abs(cloud[:, 1] - 1.8) < 0.6)
    pit = sample_box(Box(1.2, 2.4, 1.2, 2.4, -0.6, -0.6), SPACING)
    points = np.vstack([cloud[~(over_pit & (cloud[:, 2] == 0.0))], pit])
    assert build_grid(points).grid.data[1, 1] == OCCUPIED
    with pytest.raises(ValueError, match="drop_depth must be in"):
        build_grid(points, GridConfig(drop_depth=drop_depth))


@pytest.mark.parametrize("safe_height", [0.5, 0.7, 0.89])
def test_a_safe_height_below_a_seated_user_is_refused(safe_height):
    """A counter top at 72-75 cm over cell (1, 1), held by the wall or by legs outside the cell
    (a kitchen counter, a wide desk). ``safe_height`` is the top of the seated user in the
    chair (the paper's δ): points below it count. Set to 0.5 or 0.7 m (any value above
    ``floor_clearance`` passed), the top was removed and the cells under it came out free:
    the chair was sent under a counter at its user's chest. No wheelchair user sits lower
    than 0.9 m, and with 0.9 m the top stays."""
    cloud = room_cloud([Box(1.2, 2.4, 1.2, 2.4, 0.72, 0.75)], size=(3.6, 3.6), spacing=SPACING)
    assert build_grid(cloud).grid.data[1, 1] == OCCUPIED
    assert build_grid(cloud, GridConfig(safe_height=0.9)).grid.data[1, 1] == OCCUPIED
    with pytest.raises(ValueError, match=r"safe_height must be >= 0\.9 m"):
        build_grid(cloud, GridConfig(safe_height=safe_height))


# --- unknown is not free ------------------------------------------------------------------------


def test_unobserved_cells_are_unknown_not_free():
    cloud = room_cloud([], size=(4.8, 2.4), spacing=SPACING, ceiling=True)
    # The floor of the right half was never seen (only the ceiling above it, and the foot of
    # the walls, which is what keeps the right half inside the grid).
    seen = ~((cloud[:, 2] == 0.0) & (cloud[:, 0] > 2.4))
    res = build_grid(cloud[seen])
    assert res.grid.data.tolist() == [[FREE, FREE, UNKNOWN, UNKNOWN]] * 2
    # With the floor of one column of cells half hidden, those cells are unknown.
    cloud2 = cloud[~((cloud[:, 2] == 0.0) & (cloud[:, 0] > 0.6) & (cloud[:, 0] < 1.2))]
    res2 = build_grid(cloud2)
    assert res2.grid.data.shape == (2, 4)
    assert res2.grid.data[0, 0] == UNKNOWN and res2.grid.data[1, 0] == UNKNOWN
    assert (res2.grid.data[:, 1:] == FREE).all()
    assert not (res2.grid.data == OCCUPIED).any()


# --- extent, phase and the boundary rule ----------------------------------------------------------


def test_paper_room_in_the_mapper_frame(paper_cloud):
    # The mapper's frame: room shifted by (-0.6, -6.6) and a small heading error.
    cloud = transform(paper_cloud, math.radians(-2.0), (-0.6, -6.6))
    res = build_grid(cloud)
    assert res.grid.data.shape == (8, 8)
    np.testing.assert_array_equal(occupied(res), paper_like_expected())
    assert (res.grid.data != UNKNOWN).all()
    assert res.yaw == pytest.approx(math.radians(-2.0), abs=math.radians(0.05))
    # The grid's lower-left corner is the room's corner (0, 0) seen in the map frame.
    corner = transform(np.zeros((1, 3)), math.radians(-2.0), (-0.6, -6.6))[0]
    assert res.grid.origin[:2] == pytest.approx(tuple(corner[:2]), abs=0.02)


def test_walls_do_not_occupy_border_cells_but_near_obstacles_do():
    near = Box(1.5, 2.0, 0.15, 0.3, 0.0, 0.9)  # 15 cm off the south wall: content of (2, 1)
    res = build_grid(room_cloud([near], size=(3.6, 3.6), spacing=SPACING))
    assert res.grid.data.tolist() == [[FREE] * 3, [FREE] * 3, [FREE, OCCUPIED, FREE]]
    assert res.boundary.any()  # the walls were seen, and taken as the boundary


def test_the_boundary_strip_is_bounded_and_what_stands_against_a_wall_beyond_it_blocks():
    # A 16 cm deep cabinet against the south wall reaches past the 15 cm strip: its cell blocks.
    # A 14 cm one is inside the strip and is taken for the wall (the documented cost).
    for depth, cell in ((0.16, OCCUPIED), (0.14, FREE)):
        cab = Box(1.5, 2.0, 0.0, depth, 0.0, 1.0)
        res = build_grid(room_cloud([cab], size=(3.6, 3.6), spacing=SPACING))
        assert res.grid.data[2, 1] == cell, (depth, res.grid.data)
    # A strip of a whole cell made every border cell's content "wall": the paper room's tables
    # at (3, 0) and (5, 0) read free. It is refused.
    with pytest.raises(ValueError, match=r"boundary_margin must be <= 0\.2 m"):
        build_grid(room_cloud(paper_like_boxes(), spacing=SPACING), GridConfig(boundary_margin=1.2))
    assert GridConfig(boundary_margin=0.2).validate() is None


def test_walls_stay_boundary_when_the_grid_overflows_the_floor():
    # A 3.45 m wide room snaps to 3 cells (3.6 m): the grid reaches ~7.5 cm past each side
    # wall, so the walls lie inside the grid -- still boundary, not obstacles in the border
    # cells. (3.4 m, 10 cm past, is at the most a grid may overhang walls: the chair's 10 cm
    # clearance in its cell; test_a_border_cell_holds_the_chair_between_walls.)
    res = build_grid(room_cloud([], size=(3.45, 3.6), spacing=SPACING))
    assert res.grid.data.shape == (3, 3)
    assert (res.grid.data == FREE).all(), res.grid.data
    assert res.boundary[:, :2].any() and res.boundary[:, -2:].any()


def test_floor_unseen_under_a_bench_does_not_widen_the_strip_past_20_cm_on_any_side():
    """A bench 25 cm deep along the west wall hides the floor under it. The grid's overrun of
    the floor, halved onto both sides, widened the strip to 25 cm on both: the bench and a
    22 cm cabinet standing on seen floor against the east wall read free. The strip is now
    taken side by side and never over MAX_BOUNDARY_MARGIN (20 cm), the chair's side clearance."""
    for depth in (0.22, 0.27):
        bench = Box(0.0, 0.25, 0.0, 3.6, 0.0, 0.45)
        cabinet = Box(4.8 - depth, 4.8, 1.6, 2.1, 0.0, 1.0)
        cloud = room_cloud([bench, cabinet], size=(4.8, 3.6), spacing=0.03)
        cloud = cloud[~((cloud[:, 2] <= 0.05) & (cloud[:, 0] < 0.25))]  # no floor under it
        res = build_grid(cloud)
        assert res.grid.data.shape == (3, 4)
        assert (res.grid.data[:, 0] == OCCUPIED).all(), (depth, res.grid.data)  # the bench
        assert res.grid.data[1, 3] == OCCUPIED, (depth, res.grid.data)  # the cabinet
        mid = res.boundary.shape[0] // 2
        inner = np.flatnonzero(~res.boundary[mid])
        assert inner.min() * 0.05 <= 0.2 and (res.boundary.shape[1] - 1 - inner.max()) * 0.05 <= 0.2


def test_a_grid_short_of_its_walls_has_no_wall_strip_at_that_edge():
    """A 3.3 m room snaps down to two cells, 45 cm inside each wall: the 15 cm strip at the
    grid's edge lay on open floor, and a post standing there, on seen floor, was taken for a
    wall."""
    post = Box(0.50, 0.55, 1.6, 1.65, 0.0, 1.0)
    res = build_grid(room_cloud([post], size=(3.3, 3.6), spacing=0.03))
    assert res.grid.data.shape == (3, 2) and res.grid.origin[0] == pytest.approx(0.45, abs=0.01)
    assert res.grid.data[1, 0] == OCCUPIED, res.grid.data


def test_grid_phase_survives_a_missing_floor_strip():
    # Floor points stop 12 cm short of the east wall (e.g. never scanned there).
    cloud = room_cloud([Box(0.1, 1.1, 0.1, 1.1, 0.0, 0.75)], size=(3.6, 3.6), spacing=SPACING)
    cloud = cloud[~((cloud[:, 2] == 0.0) & (cloud[:, 0] > 3.48))]
    res = build_grid(cloud)
    assert res.grid.data.shape == (3, 3)
    assert res.grid.data[2, 0] == OCCUPIED
    assert np.count_nonzero(occupied(res)) == 1


# --- alignment ----------------------------------------------------------------------------------


@pytest.mark.parametrize("deg", [20.0, -33.0])
def test_alignment_follows_the_walls(paper_cloud, deg):
    res = build_grid(transform(paper_cloud, math.radians(deg), (2.0, -1.0)))
    assert math.degrees(res.yaw) == pytest.approx(deg, abs=0.05)
    np.testing.assert_array_equal(occupied(res), paper_like_expected())


def test_alignment_picks_the_rotation_closest_to_the_map_axes(paper_cloud):
    # Rotated by 70 degrees the walls are also at -20 degrees: that one is chosen, and the
    # grid is the room's grid turned by a quarter.
    res = build_grid(transform(paper_cloud, math.radians(70.0), (0.0, 0.0)))
    assert math.degrees(res.yaw) == pytest.approx(-20.0, abs=0.05)
    np.testing.assert_array_equal(occupied(res), np.rot90(paper_like_expected(), k=1))


def test_map_alignment_keeps_map_axes(paper_cloud):
    cloud = transform(paper_cloud, math.radians(10.0), (0.0, 0.0))
    res = build_grid(cloud, GridConfig(alignment="map"))
    assert res.yaw == 0.0 and res.grid.origin[2] == 0.0
    # Misaligned cells straddle the tables: never fewer occupied cells than the truth has.
    assert np.count_nonzero(occupied(res)) >= np.count_nonzero(paper_like_expected())


def test_wall_yaw_without_walls_is_none():
    flat = np.column_stack([np.random.default_rng(0).uniform(0, 3, (500, 2)), np.zeros(500)])
    assert wall_yaw(flat, GridConfig()) is None


# --- the fine map ----------------------------------------------------------------------------


def test_fine_map_is_in_map_axes_with_walls_floor_and_unknown(paper_cloud):
    cloud = transform(paper_cloud, math.radians(15.0), (1.0, 1.0))
    res = build_grid(cloud)
    fine = res.fine
    assert fine.origin[2] == 0.0 and fine.resolution == pytest.approx(0.05)
    # whole pixels, written as such: fine.yaml read -6.8500000000000005 (a pixel count times
    # 0.05; this room, as it is and shifted by 0.3 m, gave such origins too)
    for shift in (0.0, 0.3):
        origin = build_grid(paper_cloud + np.array([shift, -shift, 0.0])).fine.origin
        assert all(v == round(v, 9) for v in origin), origin
    vals = set(np.unique(fine.data).tolist())
    assert vals == {FREE, OCCUPIED, UNKNOWN}  # outside the rotated room is unknown
    # a table-top pixel is occupied, the middle of the room free
    for x, y, want in ((2.4, 3.0, OCCUPIED), (6.6, 1.8, FREE)):
        p = transform(np.array([[x, y, 0.0]]), math.radians(15.0), (1.0, 1.0))[0]
        r, c = fine.cell_of(p[0], p[1])
        assert fine.data[r, c] == want


# --- bad input ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("points", "cause"),
    [
        (np.empty((0, 3)), "empty"),
        (np.full((10, 3), np.nan), "empty"),
        (np.column_stack([np.zeros(100), np.zeros(100), np.full(100, 2.0)]), "all_above_band"),
        (np.column_stack([np.arange(100.0), np.zeros(100), np.full(100, 0.8)]), "no_floor"),
        (np.zeros((5, 2)), "bad_shape"),
    ],
)
def test_bad_maps_raise_grid_error(points, cause):
    with pytest.raises(GridError) as info:
        build_grid(points)
    assert info.value.cause == cause
    assert str(info.value)


def test_far_stray_points_change_nothing(paper_cloud):
    # A few wild returns hundreds of metres away: same grid, and no giant raster.
    stray = np.array([[400.0, -300.0, 0.9], [-250.0, 380.0, 0.0], [300.0, 300.0, 2.0]])
    res = build_grid(np.vstack([paper_cloud, stray]))
    np.testing.assert_array_equal(occupied(res), paper_like_expected())


def test_a_stray_point_beyond_the_float32_range_changes_nothing(paper_cloud):
    """One point 60 km out, or a scanner's FLT_MAX "no return" marker, made the whole room
    map refused ("re-centre the map"); in the grid node every later map too. A map whose
    bulk lies that far is still refused (its own test below)."""
    for far in ([6e4, 0.0, 0.5], [3.4e38, 3.4e38, 3.4e38]):
        res = build_grid(np.vstack([paper_cloud, [far]]))
        np.testing.assert_array_equal(occupied(res), paper_like_expected())


def test_a_floor_too_large_for_one_map_is_refused():
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(0, 300, (20000, 2)), np.zeros(20000)])
    posts = np.column_stack([rng.uniform(0, 300, (1000, 2)), np.ones(1000)])
    with pytest.raises(GridError) as info:
        build_grid(np.vstack([floor, posts]))
    assert info.value.cause == "too_large"


def test_a_map_of_floor_alone_is_refused_and_a_room_on_its_side_is_doubted():
    """Both once gave a grid of free cells: a map flattened to z = 0 (every point floor), and
    a room turned y-up (a wall at z = 0 read as the floor, the rest of the room above it)."""
    room = room_cloud(paper_like_boxes(), spacing=SPACING)
    flat = np.column_stack([room[:, :2], np.zeros(len(room))])
    with pytest.raises(GridError, match="only floor") as info:
        build_grid(flat)
    assert info.value.cause == "only_floor"
    on_its_side = build_grid(room[:, [0, 2, 1]])
    (doubt,) = on_its_side.stats["warnings"]
    assert "rises 9.6 m above its floor" in doubt and "z up" in doubt
    assert build_grid(room).stats["warnings"] == []  # the room as scanned: no doubt


def test_invalid_config_is_rejected():
    cloud = room_cloud([], size=(2.4, 2.4), spacing=SPACING)
    with pytest.raises(ValueError, match="whole number"):
        build_grid(cloud, GridConfig(cell_size=1.23))
    with pytest.raises(ValueError, match="alignment"):
        build_grid(cloud, GridConfig(alignment="diagonal"))
    # Each of these crashed (OverflowError, ZeroDivisionError, a 2.6 PiB allocation, an
    # IndexError) or, worse, made cells free that nobody saw.
    for kw, message in (
        ({"cell_size": math.inf}, "cell_size must be finite"),
        ({"pixel_size": 0.0}, "must be > 0"),
        ({"pixel_size": 0.001, "cell_size": 1.2}, "pixel_size must be >= 0.01"),
        ({"boundary_margin": math.nan}, "boundary_margin must be finite"),
        ({"fine_margin": math.inf}, "fine_margin must be finite"),
        ({"min_observed_fraction": 0.0}, "less than half observed"),
        ({"floor_fill": 60}, "invents 3 m of floor"),
        ({"min_floor_points": 0}, "min_floor_points must be >= 1"),
        ({"boundary_margin": 0.25}, "boundary_margin must be <= 0.2 m"),
        ({"guard_line_length": 0.1}, "guard_line_length must be 0"),
        ({"guard_line_length": 1.5}, "guard_line_length must be 0"),
        ({"guard_line_min_points": 0}, "guard_line_min_points must be >= 1"),
        ({"min_points_per_pixel": 12}, "the points a thin obstacle leaves in a pixel"),
        # the grid reaches half of it past the floor seen: 1.1 m left 22 cm of an unseen drop
        # in a free border cell where the floor ended with no wall (a review)
        ({"extent_tolerance": 1.1}, "extent_tolerance must be <= 0.25 m"),
    ):
        with pytest.raises(ValueError, match=message):
            build_grid(cloud, GridConfig(**kw))  # type: ignore[arg-type]


def test_the_ranges_the_grid_parameters_declare_hold_every_valid_value_and_no_other():
    """The grid node's parameters carry ranges (`ros2 param describe`, rqt's sliders, rclpy
    refusing a value before the node sees it), which nothing had. At the ends themselves the
    config's open ends refuse (drop_depth 0, density_threshold 1); pixel_size must also
    divide cell_size, which no range can say (cell_size is at least the chair's length: a
    free 0.6 m cell lay in a 70 cm gap, and a route led through it)."""
    from wheelgrid_common.map_io import CHAIR_SIZE_M
    from wheelgrid_common.testing import check_declared_bounds
    from wheelgrid_nav.grid import GridNodeConfig

    ranged = check_declared_bounds(
        GridNodeConfig, lambda c: c.validate(), outside_only=("pixel_size", "cell_size")
    )
    assert {"safe_height", "density_threshold", "min_observed_fraction", "max_rate_hz"} <= set(
        ranged
    )
    assert "cell_size" in ranged
    GridNodeConfig(cell_size=CHAIR_SIZE_M).validate()  # the chair's own size is a cell
    with pytest.raises(ValueError, match="smaller than the chair"):
        GridNodeConfig(cell_size=CHAIR_SIZE_M - 0.05).validate()


def test_the_most_points_a_pixel_may_need_keeps_every_obstacle_of_the_paper_room():
    """min_points_per_pixel had no upper bound: 12 on the paper room sampled at 3 cm (a map's
    voxels) lost three of its occupied cells, 20 four. It may be at most
    guard_line_min_points (5), and there every occupied cell stays."""
    cloud = room_cloud(paper_like_boxes(), spacing=0.03)
    highest = GridConfig().guard_line_min_points
    grid = build_grid(cloud, GridConfig(min_points_per_pixel=highest)).grid
    np.testing.assert_array_equal(grid.data == OCCUPIED, paper_like_expected())
    lost = build_grid(cloud, GridConfig(min_points_per_pixel=12, guard_line_min_points=12)).grid
    assert (paper_like_expected() & (lost.data != OCCUPIED)).any()  # why the bound is there


def test_a_map_far_from_its_origin_is_refused_not_gridded_as_unknown():
    """UTM-sized coordinates: the float32 pass lost half a metre and every cell came out
    unknown, exit 0. Safe, but useless without saying why."""
    cloud = room_cloud([], size=(2.4, 2.4), spacing=SPACING)
    with pytest.raises(GridError, match="re-centre the map") as info:
        build_grid(cloud + np.array([0.0, 5e6, 0.0]))
    assert info.value.cause == "too_large"


def test_a_raster_too_fine_for_the_floor_is_refused_before_it_is_allocated():
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(0, 90, (20000, 2)), np.zeros(20000)])
    posts = np.column_stack([rng.uniform(0, 90, (1000, 2)), np.ones(1000)])
    with pytest.raises(GridError, match="raise pixel_size") as info:  # 9000 x 9000 pixels
        # (1 cm pixels need guard_line_min_points 1: a rope leaves ~1.5 points in 3x3 of them)
        cfg = GridConfig(pixel_size=0.01, cell_size=1.2, guard_line_min_points=1)
        build_grid(np.vstack([floor, posts]), cfg)
    assert info.value.cause == "too_large"


def test_the_wall_search_needs_memory_for_its_points_not_for_the_floors_area():
    """The wall-direction search rasterised the map's whole extent at half a pixel, in five
    float64 images: 8.8 GB for the 90 m floor above at 1 cm pixels (killed for memory on a
    chair's 8 GB computer, before the size check could refuse it). It now keeps only the
    pixels that hold points (at most 80,000)."""
    import tracemalloc

    rng = np.random.default_rng(2)
    floor = np.column_stack([rng.uniform(0, 40, (20000, 2)), np.zeros(20000)])
    xy = rng.uniform(0, 40, (500, 2))
    posts = np.column_stack([np.repeat(xy, 10, axis=0), np.tile(np.linspace(0.1, 1.4, 10), 500)])
    points = np.vstack([floor, posts])
    tracemalloc.start()
    try:
        wall_yaw(points, GridConfig(pixel_size=0.01, cell_size=1.2, guard_line_min_points=1))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 100e6, f"{peak / 1e6:.0f} MB"  # was 2.5 GB (8000 x 8000 half-pixels)


# --- the guard's line rule: rods, ropes and cables one map point thick --------------------------


def rope(p0, p1, seed: int, spacing: float = 0.02, noise: float = 0.005) -> np.ndarray:
    """A rod or rope as the mapper leaves it: one line of points at the map's 2 cm voxel
    spacing, each jittered by ~5 mm."""
    a, b = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    t = np.linspace(0.0, 1.0, int(np.linalg.norm(b - a) / spacing) + 1)[:, None]
    return a + t * (b - a) + np.random.default_rng(seed).normal(0.0, noise, (t.size, 3))


ROOM_3x3 = room_cloud([], size=(3.6, 3.6), spacing=SPACING)
NO_LINES = GridConfig(guard_line_length=0.0)  # the guard before the line rule


@pytest.mark.parametrize(
    "p0, p1",
    [
        ((1.25, 1.77, 0.8), (2.35, 1.77, 0.8)),  # a rope across the middle cell at 80 cm
        ((1.5, 1.82, 1.2), (1.9, 1.82, 1.2)),  # a 40 cm rod at chest height
        ((1.25, 1.32, 0.3), (2.35, 1.32, 0.3)),  # a cable at 30 cm, near the cell's edge
    ],
)
def test_guard_catches_a_rope_or_rod_one_map_point_thick(p0, p1):
    res = build_grid(np.vstack([ROOM_3x3, rope(p0, p1, seed=1)]))
    assert res.density[1, 1] <= res.config.density_threshold  # eq 10 misses it
    assert res.grid.data[1, 1] == OCCUPIED and res.guard[1, 1]
    assert np.count_nonzero(occupied(res)) == 1
    # what the point rule alone said: free, a chair planned through the rope
    before = build_grid(np.vstack([ROOM_3x3, rope(p0, p1, seed=1)]), NO_LINES)
    assert before.grid.data[1, 1] == FREE


@pytest.mark.parametrize("pixel_size", [0.02, 0.03, 0.04, 0.05, 0.06])
def test_a_rope_is_caught_at_every_pixel_size_accepted_and_finer_ones_say_what_to_lower(
    pixel_size,
):
    """The line rule's counts are per 3x3 pixels: at 3 cm pixels a rope leaves about 4.5 points
    there, under guard_line_min_points 5, and the rope's cell read free with no word. Such a
    pixel size is refused, naming the guard_line_min_points that would catch it."""
    cloud = np.vstack([ROOM_3x3, rope((1.25, 1.77, 0.8), (2.35, 1.77, 0.8), seed=1)])
    cfg = GridConfig(pixel_size=pixel_size)
    try:
        cfg.validate()
    except ValueError as exc:
        assert pixel_size < 0.04, exc
        found = re.search(r"guard_line_min_points <= (\d+)$", str(exc))
        assert found and "ropes and cables would read free" in str(exc), exc
        cfg = GridConfig(pixel_size=pixel_size, guard_line_min_points=int(found.group(1)))
    res = build_grid(cloud, cfg)
    assert res.grid.data[1, 1] == OCCUPIED and res.guard[1, 1], pixel_size


def test_the_wall_strip_never_grows_past_its_cap_at_coarse_pixels():
    """The strip of obstacles taken for the walls is at most MAX_BOUNDARY_MARGIN (20 cm) deep;
    rounded to 24 cm pixels, a 16 cm strip became 24 cm and hid a 22 cm deep cabinet standing
    against the wall (its cell read free)."""
    from wheelgrid_nav.grid_synth import Box

    pts = room_cloud([Box(0.0, 0.22, 4.0, 5.0, 0.0, 0.8)], spacing=0.02)
    pts = pts[~((pts[:, 2] == 0.0) & (pts[:, 0] < 0.10))]  # the floor unseen by that wall
    for ps in (0.05, 0.24):
        cfg = GridConfig(pixel_size=ps, alignment="map", guard_line_length=max(0.3, 3 * ps))
        if ps > 0.2:  # a raster this coarse cannot look for holes (hidden_hole)
            cfg.floor_fill, cfg.unobserved_patch = 0, 0.0
        res = build_grid(pts, cfg)
        r, c = res.grid.cell_of(0.11, 4.5)
        assert res.grid.data[r, c] == OCCUPIED, ps


def test_guard_catches_a_2cm_pole():
    # Three lines of points around a 2 cm pole from floor to 1.5 m: its points stack in one
    # pixel, which the point rule already catches (this guards that it stays caught).
    pole = np.vstack(
        [
            rope(
                (1.8 + 0.01 * math.cos(a), 1.8 + 0.01 * math.sin(a), 0.0),
                (1.8 + 0.01 * math.cos(a), 1.8 + 0.01 * math.sin(a), 1.5),
                seed=i,
            )
            for i, a in enumerate((0.0, 2.1, 4.2))
        ]
    )
    res = build_grid(np.vstack([ROOM_3x3, pole]))
    assert res.grid.data[1, 1] == OCCUPIED and res.guard[1, 1]
    assert np.count_nonzero(occupied(res)) == 1


@pytest.mark.parametrize("seed", range(5))
def test_scattered_noise_does_not_make_a_line(seed):
    rng = np.random.default_rng(seed)
    line = rope((1.25, 1.77, 0.8), (2.35, 1.77, 0.8), seed=1)

    def noise(n: int, y0: float, y1: float) -> np.ndarray:
        """n points scattered over the middle cell's x span at band heights (flying pixels,
        speckles), their y within [y0, y1]."""
        return np.column_stack(
            [rng.uniform(1.25, 2.35, n), rng.uniform(y0, y1, n), rng.uniform(0.1, 1.4, n)]
        )

    # As many points as the rope (56): they blacken about twice as many pixels, so eq 10
    # occupies the cell as before, but the guard sees no line in them.
    res = build_grid(np.vstack([ROOM_3x3, noise(line.shape[0], 1.25, 2.35)]))
    assert res.density[1, 1] > res.config.density_threshold
    assert not res.guard.any()
    # As many black pixels as the rope (22, a density under δ): over the cell, or packed in a
    # 20 cm strip along the rope's line where it would chain if anywhere, the cell stays free.
    rope_pixels = round(build_grid(np.vstack([ROOM_3x3, line])).density[1, 1] * 24 * 24)
    for y0, y1 in ((1.25, 2.35), (1.67, 1.87)):
        res = build_grid(np.vstack([ROOM_3x3, noise(rope_pixels, y0, y1)]))
        assert res.density[1, 1] <= res.config.density_threshold
        assert not res.guard.any() and not occupied(res).any()


def test_line_rule_on_hand_made_image():
    obs = np.zeros((12, 12), dtype=bool)
    counts = np.zeros((12, 12), dtype=np.int64)
    obs[2, 1:8] = True  # a horizontal line of 7 pixels, 3 points each: links (9 per 3x3)
    counts[2, 1:8] = 3
    for i in range(5):  # a diagonal of 5 pixels (4 * sqrt 2 + 1 = 6.7 pixels along its axis)
        obs[6 + i, 1 + i] = True
        counts[6 + i, 1 + i] = 3
    obs[9, 8:11] = True  # a short line of 3 pixels: too short
    counts[9, 8:11] = 3
    obs[5, 5:11] = True  # a row of lone points, 1 a pixel: 3 per 3x3, not links
    counts[5, 5:11] = 1
    lines = linear_obstacles(obs, counts, min_points=5, min_length_px=6)
    assert lines[2, 1:8].all() and lines[6:11].sum() == 5
    assert not lines[9, 8:11].any() and not lines[5, 5:11].any()
    assert lines.sum() == 12
    # a 7-pixel threshold keeps the straight line, not the shorter diagonal
    assert linear_obstacles(obs, counts, 5, 7).sum() == 7
    guard = thin_obstacle_guard(obs, counts, 6, 6, 12, 5, 6)
    assert guard.tolist() == [[True, True], [True, False]]
    assert not thin_obstacle_guard(obs, counts, 6, 6, 12).any()  # the point rule alone


@pytest.mark.parametrize("seed", range(5))
def test_a_rod_fixed_to_a_wall_is_measured_from_the_wall(seed):
    """A 40 cm rod out of the east wall (a towel rail, a bracket) lost its first 15 cm to the
    wall strip, measured 25 cm, under guard_line_length, and its cell read free. The line is
    measured through the strip; only what lies beyond the strip marks its cell, so the walls'
    own sparse stretches occupy nothing (the bare room stays free)."""
    res = build_grid(np.vstack([ROOM_3x3, rope((3.6, 1.8, 0.8), (3.2, 1.8, 0.8), seed)]))
    assert res.grid.data[1, 2] == OCCUPIED and res.guard[1, 2], res.grid.data
    assert np.count_nonzero(res.grid.data == OCCUPIED) == 1
    assert (build_grid(ROOM_3x3).grid.data == FREE).all()


@pytest.mark.parametrize("spacing", [0.02, 0.04])
def test_a_rod_out_of_a_densely_scanned_wall_is_measured_from_the_wall(spacing):
    """Near a densely scanned wall the wall's points lift a rod's last pixels over the point
    rule's count, so they were no links of its line: a rod 35-38 cm out of a wall scanned at 2
    or 4 cm was measured from 10-15 cm out, under guard_line_length, and its cell read free
    (as did a 40 cm rod at 45 deg). The line is now followed along its axis through the black
    pixels that continue it to the wall strip; one along the wall is not, and a bracket under
    the 30 cm stays free, as one standing alone does."""
    room = room_cloud([], size=(3.6, 3.6), spacing=spacing)
    centre = np.array([1.8, 1.8])
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])

    def rod_out_of_wall(wall: int, length: float, slant_deg: float, seed: int) -> np.ndarray:
        """From the east wall's middle (turned a quarter ``wall`` times), ``slant_deg`` off
        its normal."""
        a = math.radians(slant_deg)
        p0 = np.array([3.6, 1.75 + 0.013 * seed])
        p1 = p0 + length * np.array([-math.cos(a), math.sin(a)])
        turn = np.linalg.matrix_power(quarter, wall)
        p0, p1 = centre + turn @ (p0 - centre), centre + turn @ (p1 - centre)
        return rope((*p0, 0.8), (*p1, 0.8), seed)

    assert (build_grid(room).grid.data == FREE).all()
    for wall in range(4):
        for length, slant in ((0.35, 0.0), (0.38, 0.0), (0.40, 45.0)):
            for seed in range(3):
                res = build_grid(np.vstack([room, rod_out_of_wall(wall, length, slant, seed)]))
                assert np.count_nonzero(res.grid.data == OCCUPIED) == 1, (wall, length, slant)
                assert res.stats["guard_only_cells"] == 1
        res = build_grid(np.vstack([room, rod_out_of_wall(wall, 0.2, 0.0, 0)]))
        assert (res.grid.data == FREE).all(), wall
    # along the wall 3 cm beyond the strip: its own length counts, nothing added
    along = rope((3.42, 1.0, 0.8), (3.42, 1.26, 0.8), seed=0)
    assert (build_grid(np.vstack([room, along])).grid.data == FREE).all()


def test_a_cell_with_an_unseen_hole_in_its_middle_is_not_free():
    """The observed fraction alone let a cell 84 % seen be free with a 68 x 68 cm hole in its
    middle, right under the chair (a stairwell or pit), its bottom seen as a few sparse points
    or not at all. A square of ``unobserved_patch`` (35 cm, after floor_fill) with neither
    floor nor an obstacle seen now keeps the cell from free: a hole of 50 cm or more."""
    from wheelgrid_nav.grid_synth import room_cloud

    room = room_cloud([], size=(3.6, 3.6), spacing=0.02)
    x, y, z = room.T
    middle = (1, 1)

    def hole(side: float) -> np.ndarray:
        return (z == 0.0) & (np.abs(x - 1.8) < side / 2) & (np.abs(y - 1.8) < side / 2)

    assert build_grid(room).grid.data[middle] == FREE
    for side, bottom in ((0.68, False), (0.68, True), (0.5, False)):
        pts = room[~hole(side)]
        if bottom:  # the pit's bottom, 25 sparse returns 0.6 m down
            g = np.mgrid[1.5:2.1:0.12, 1.5:2.1:0.12].reshape(2, -1).T
            pts = np.vstack([pts, np.column_stack([g, np.full(len(g), -0.6)])])
        res = build_grid(pts)
        assert res.observed[middle] >= GridConfig().min_observed_fraction, side  # as before
        assert res.grid.data[middle] != FREE, (side, bottom)
        if not bottom:  # free before: 84-85 % observed
            assert build_grid(pts, GridConfig(unobserved_patch=0)).grid.data[middle] == FREE
    # a hole loses floor_fill's pixel on each side to the filled floor: 45 cm (an unseen 35 cm
    # once filled) is as far as the rule lets a cell be free
    assert build_grid(room[~hole(0.45)]).grid.data[middle] == FREE
    for bad in (-0.35, 0.9, math.nan):
        with pytest.raises(ValueError, match="unobserved_patch must be"):
            build_grid(room, GridConfig(unobserved_patch=bad))


def test_a_coarser_raster_never_hides_a_hole_wider_than_it_says():
    """At 10 cm pixels (``--pixel-size 0.1``) floor_fill's pixel and the pixel a hole's edge
    cuts grew the floor seen 20 cm over each edge: a 55 cm pit in a cell's middle lay under a
    free cell, 70 cm at 20 cm pixels, exit 0 and no word (a review). Such a raster is refused;
    one that is taken keeps every hole wider than its ``hidden_hole`` from a free cell."""
    from wheelgrid_nav.grid_synth import room_cloud

    with pytest.raises(ValueError, match=r"unseen hole up to 0\.70 m"):
        GridConfig(pixel_size=0.1).validate()
    room = room_cloud([], size=(4.8, 4.8), spacing=0.02)
    x, y, z = room.T
    for kw in ({"pixel_size": 0.1, "floor_fill": 0}, {"pixel_size": 0.08, "floor_fill": 0}, {}):
        cfg = GridConfig(alignment="map", **kw)
        side = cfg.hidden_hole() + 0.01
        for cx, cy in ((1.8, 3.0), (1.84, 3.03), (1.87, 3.06), (1.81, 3.05)):
            hole = (z == 0.0) & (np.abs(x - cx) < side / 2) & (np.abs(y - cy) < side / 2)
            grid = build_grid(room[~hole], cfg).grid
            assert grid.data[grid.cell_of(cx, cy)] != FREE, (kw, side, cx, cy)


def test_a_lone_speck_in_the_band_over_an_unseen_hole_does_not_make_its_cell_free():
    """One point at 50 cm over a 68 cm unseen hole (a speck of noise, the tip of a cord
    hanging over a stairwell) blocked every 35 cm square the hole rule could fit, and the
    cell read free (a review: 5 of 5 draws). A band speck with no floor seen beside it counts
    for nothing against a hole now; an obstacle standing on seen floor still does."""
    from wheelgrid_nav.grid_synth import room_cloud

    room = room_cloud([], size=(3.6, 3.6), spacing=0.02)
    x, y, z = room.T
    middle = (1, 1)
    pit = room[~((z == 0.0) & (np.abs(x - 1.8) < 0.34) & (np.abs(y - 1.8) < 0.34))]
    assert build_grid(pit).grid.data[middle] != FREE
    for speck in ([[1.8, 1.8, 0.5]], [[1.8, 1.8, 0.5], [1.81, 1.8, 0.52], [1.8, 1.81, 0.9]]):
        res = build_grid(np.vstack([pit, speck]))
        assert res.grid.data[middle] != FREE, speck
    # a 2 cm post (a chair leg) on seen floor in that cell: still occupied or free, as before
    post = np.array([[1.2 + 0.01 * i, 1.2, h] for i in range(2) for h in np.arange(0.1, 0.8, 0.02)])
    with_post = build_grid(np.vstack([room, post])).grid.data[middle]
    assert (
        with_post
        == build_grid(np.vstack([room, post]), GridConfig(unobserved_patch=0)).grid.data[middle]
    )


def test_a_stray_floor_return_over_an_unseen_hole_does_not_make_its_cell_free():
    """One return at floor height in the middle of a 68 cm unseen hole (a stray point, a
    mixed pixel) blocked every 35 cm square the hole rule could fit, and the cell read free (a
    review: 5 of 5 draws at 55-65 cm). A patch of floor with fewer than PATCH_MIN_FLOOR pixels
    holding a return counts for nothing against a hole now; a wide patch of seen floor in the
    hole (a 20 cm square: no 35 cm square fits beside it) still does."""
    from wheelgrid_nav.grid import PATCH_MIN_FLOOR
    from wheelgrid_nav.grid_synth import room_cloud

    room = room_cloud([], size=(3.6, 3.6), spacing=0.02)
    x, y, z = room.T
    middle = (1, 1)
    in_hole = (z == 0.0) & (np.abs(x - 1.8) < 0.34) & (np.abs(y - 1.8) < 0.34)
    pit = room[~in_hole]
    assert build_grid(pit).grid.data[middle] != FREE
    # one return; two, 5 cm apart (two pixels, one patch once floor_fill grows them); one
    # with a point 30 cm above it, and a streak from the floor to 50 cm (a cord hanging to the
    # floor, flying pixels): each rule took the other's speck for seen, and the cell read free
    streak = [[1.8, 1.8, h] for h in np.arange(0.0, 0.51, 0.05)]
    for speck in (
        [[1.8, 1.8, -0.03]],
        [[1.8, 1.8, 0.0], [1.85, 1.8, 0.01]],
        [[1.8, 1.8, 0.0], [1.8, 1.8, 0.3]],
        streak,
    ):
        assert sum(1 for q in speck if q[2] <= 0.05) < PATCH_MIN_FLOOR
        res = build_grid(np.vstack([pit, speck]))
        assert res.grid.data[middle] != FREE, speck
        # the rule, not the observed share, keeps it from free
        assert res.observed[middle] >= GridConfig().min_observed_fraction
        with_rule_off = build_grid(np.vstack([pit, speck]), GridConfig(unobserved_patch=0))
        assert with_rule_off.grid.data[middle] == FREE
    # the floor seen in the hole's middle, 20 cm across, leaves no 35 cm square unseen
    island = room[in_hole & (np.abs(x - 1.8) < 0.1) & (np.abs(y - 1.8) < 0.1)]
    assert build_grid(np.vstack([pit, island])).grid.data[middle] == FREE
    # patches join within 5 cm whatever the pixel: at 1 cm pixels each return of a floor
    # sampled every 4 cm was a patch of its own, and no cell of an empty room was free
    sparse = room_cloud([], size=(3.6, 3.6), spacing=0.04)
    fine = GridConfig(pixel_size=0.01, min_observed_fraction=0.5, guard_line_min_points=1)
    assert (build_grid(sparse, fine).grid.data == FREE).sum() == 9


def test_a_step_down_just_past_drop_depth_is_not_floor_because_of_noise():
    """A lower level 11 cm down (drop_depth 10 cm) seen past a step's edge from a few metres:
    the edge hides 30 cm of it, and with 1 cm of noise ~16 % of its returns read above -10 cm,
    as floor. They grew floor over the hidden strip, which then looked like a trench too narrow
    for the hole rule, and the cell holding 15-25 cm of the step read free on 9-10 of 10 draws
    (a review). A floor return outnumbered by drop returns around it seeds no floor."""

    def plane(x0: float, x1: float, y0: float, y1: float, z: float, dx: float) -> np.ndarray:
        gx, gy = np.meshgrid(np.arange(x0, x1, dx), np.arange(y0, y1, 0.02), indexing="ij")
        return np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])

    def wall(fixed: float, along_x: bool, z0: float) -> np.ndarray:
        ga, gz = np.meshgrid(np.arange(0.0, 4.8, 0.02), np.arange(z0, 2.4, 0.02), indexing="ij")
        f = np.full(ga.size, fixed)
        cols = [ga.ravel(), f, gz.ravel()] if along_x else [f, ga.ravel(), gz.ravel()]
        return np.column_stack(cols)

    free = 0
    for seed in range(10):
        edge = 2.4 - 0.25  # the step's edge 25 cm inside the cells of column 1
        pts = np.vstack(
            [
                plane(0.0, edge, 0.0, 4.8, 0.0, 0.02),
                plane(edge + 0.30, 4.8, 0.0, 4.8, -0.11, 0.06),  # seen sparsely, 30 cm hidden
                wall(0.0, True, -0.11),
                wall(4.8, True, -0.11),
                wall(0.0, False, 0.0),
                wall(4.8, False, -0.11),
            ]
        )
        pts = pts + np.random.default_rng(seed).normal(0.0, 0.01, pts.shape)
        res = build_grid(pts, GridConfig(alignment="map"))
        free += int(res.grid.data[res.grid.cell_of(edge + 0.001, 1.8)] == FREE)
    assert free == 0, free


def test_an_unseen_hole_across_cell_borders_keeps_every_cell_it_reaches_from_free():
    """A 60 cm hole 10 cm off the corner of four cells: a 35 cm square fits in it, but its
    centres (where the square may sit) all lie in one cell. Only that cell was kept from free,
    and the three others, 15 cm of the hole in each, read free: on synthetic rooms with 1 cm of
    noise a 60 cm hole on a four-cell corner left a touching cell free on 3 of 5 draws, a 56 cm
    trench along a border on 3 of 5 (bench/grid_holes.py). Every cell the squares reach is now
    kept from free."""
    from wheelgrid_nav.grid_synth import room_cloud

    room = room_cloud([], size=(3.6, 3.6), spacing=0.02)
    x, y, z = room.T

    def without(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
        return room[~((z == 0.0) & (x > x0) & (x < x1) & (y > y0) & (y < y1))]

    grid = build_grid(without(1.0, 1.6, 1.0, 1.6)).grid  # the cells meet at (1.2, 1.2)
    corner = grid.data
    touched = {grid.cell_of(a, b) for a in (1.1, 1.3) for b in (1.1, 1.3)}
    assert len(touched) == 4 and all(corner[rc] != FREE for rc in touched), corner
    assert np.count_nonzero(corner != FREE) == 4, corner  # no other cell
    trench = build_grid(without(0.95, 1.45, -0.1, 3.7)).grid.data  # 50 cm across x = 1.2
    assert (trench[:, :2] != FREE).all() and (trench[:, 2] == FREE).all(), trench
    # a hole no 35 cm square fits in (45 cm, less floor_fill's 5 cm a side) reaches nothing
    small = build_grid(without(0.95, 1.4, 0.95, 1.4)).grid.data
    assert (small == FREE).all(), small


def test_a_floor_that_leans_is_warned_of():
    """Heights are read against one level z = 0: a room leaning 2 deg hid a 9 cm box on its
    low side in the floor's band, its cell free, with no word of why."""
    from wheelgrid_nav.grid_synth import Box, room_cloud

    room = room_cloud([Box(1.7, 1.9, 0.4, 0.6, 0.0, 0.09)], size=(3.6, 3.6), spacing=0.02)
    assert not any("leans" in w for w in build_grid(room).stats["warnings"])
    a = math.radians(2.0)
    tilt = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    said = [w for w in build_grid(room @ tilt.T).stats["warnings"] if "leans" in w]
    # the floor points' plane (those within floor_clearance of z = 0: a band across the lean)
    assert said and re.search(r"leans (1\.[6-9]|2\.[0-2]) deg", said[0]) and "--level" in said[0]


def test_a_small_lean_across_a_long_room_is_warned_of():
    """The warning read the angle alone: 0.45 deg across a 14.4 m room is 5.7 cm at its ends,
    and a 9 cm kerb on the low side read as floor, its cells free, with no word (a review). A
    lean that puts the map more than 2.6 cm off z = 0 anywhere is warned of too; the same
    lean across a 4.8 m room is not."""
    from wheelgrid_nav.grid_synth import Box, room_cloud

    a = math.tan(math.radians(0.45))
    for length, warned in ((14.4, True), (4.8, False)):
        room = room_cloud([Box(0.6, 1.8, 1.8, 3.0, 0.0, 0.09)], size=(length, 4.8), spacing=0.03)
        room[:, 2] += (room[:, 0] - length / 2) * a
        said = [w for w in build_grid(room, GridConfig(alignment="map")).stats["warnings"]
                if "leans" in w]  # fmt: skip
        assert bool(said) == warned, (length, said)
        if warned:
            assert re.search(
                r"leans 0\.[345] deg from level, (4\.[5-9]|5\.\d) cm off z = 0", said[0]
            )


def test_a_border_cell_holds_the_chair_between_walls():
    """A 4.55 m room got four 1.2 m cells (extent_tolerance 25 cm): the walls 12.4 cm inside
    the border cells, the chair centred in one facing a wall overlapped it, and a corner cell
    held 95 x 95 cm of room (a review). Between walls found, the grid overhangs each by at most
    the chair's 10 cm clearance in its cell; the room gets three cells."""
    grid = build_grid(room_cloud([], size=(4.552, 4.552), spacing=SPACING)).grid
    assert grid.data.shape == (3, 3), grid.data.shape
    assert (grid.data == FREE).all(), grid.data
    grid = build_grid(room_cloud([], size=(4.7, 4.7), spacing=SPACING)).grid
    assert grid.data.shape == (4, 4), grid.data.shape  # 5 cm past each wall: the chair fits


def test_a_cell_of_more_pixels_than_a_float_holds_is_a_value_error():
    """cell_size 1e308 made cell / pixel inf, and round(inf) an OverflowError: a traceback
    from `wheelgrid grid` (exit 1) and a grid node that died at a parameter change."""
    with pytest.raises(ValueError, match="more than 10000 pixels"):
        GridConfig(cell_size=1e308).validate()
    with pytest.raises(ValueError, match="more than 10000 pixels"):
        GridConfig(pixel_size=5e-324).validate()
