"""The cells are placed between the walls, even where the floor at a wall's foot went unseen."""

import numpy as np

from wheelgrid_nav.grid import GridConfig, build_grid, wall_near
from wheelgrid_sim import paper_scene


def test_unseen_floor_strip_does_not_shift_the_cells():
    scene = paper_scene()
    pts = scene.interior_surface_points(0.03)
    pts = pts[pts[:, 2] < 2.0]  # no ceiling
    floor = np.abs(pts[:, 2]) < 0.01
    unseen = floor & (pts[:, 0] < 0.6)  # 60 cm of floor along the west wall never observed
    res = build_grid(pts[~unseen], GridConfig())
    x0, y0, yaw = res.grid.origin
    assert abs(x0) < 0.02 and abs(y0) < 0.02 and abs(yaw) < 1e-3
    expected = scene.expected_grid()
    truth_occ = expected.data == 100
    assert res.grid.data.shape == (8, 8)
    assert (res.grid.data[truth_occ] == 100).all()
    assert ((res.grid.data == 100) == truth_occ).all()


def test_wall_near_finds_a_sharp_peak_and_ignores_clutter():
    rng = np.random.default_rng(3)
    coord = np.r_[rng.normal(9.6, 0.01, 2000), rng.uniform(8.0, 10.0, 300)]
    assert abs(wall_near(coord, 9.5) - 9.6) < 0.01
    assert np.isnan(wall_near(rng.uniform(8.0, 10.0, 300), 9.5))


def _plane(rng, x0, x1, y0, y1, z, sp=0.02):
    g = np.mgrid[x0 : x1 + 1e-9 : sp, y0 : y1 + 1e-9 : sp].reshape(2, -1).T
    return np.column_stack([g, np.full(len(g), z)]) + rng.normal(0.0, 0.01, (len(g), 3))


def _wall(rng, x, y0, y1, z0, z1, sp=0.02, along_y=True):
    g = np.mgrid[y0 : y1 + 1e-9 : sp, z0 : z1 + 1e-9 : sp].reshape(2, -1).T
    xs = np.full(len(g), x)
    pts = np.column_stack([xs, g]) if along_y else np.column_stack([g[:, 0], xs, g[:, 1]])
    return pts + rng.normal(0.0, 0.01, pts.shape)


def _stairwell_room(edge: float, bottom_seen: bool, bulkhead: float | None) -> np.ndarray:
    """A 4.8 m wide floor ending at x = ``edge`` over a 1 m drop with no wall beside it (walls
    on its other three sides), the drop's bottom and face scanned or not, and a ceiling
    bulkhead (2.1-2.4 m, above the safe height) at x = ``bulkhead`` over the drop."""
    rng = np.random.default_rng(0)
    parts = [
        _plane(rng, 0.0, edge, 0.0, 4.8, 0.0),
        _wall(rng, 0.0, 0.0, 4.8, 0.0, 2.4),
        _wall(rng, 0.0, 0.0, edge, 0.0, 2.4, along_y=False),
        _wall(rng, 4.8, 0.0, edge, 0.0, 2.4, along_y=False),
    ]
    if bottom_seen:
        parts += [
            _plane(rng, edge + 0.02, 6.0, 0.0, 4.8, -1.0),
            _wall(rng, edge + 0.01, 0.0, 4.8, -1.0, -0.02),
        ]
    if bulkhead is not None:
        parts.append(_wall(rng, bulkhead, 0.0, 4.8, 2.1, 2.4))
    return np.vstack(parts)


def test_a_drop_beyond_the_floors_edge_is_never_taken_for_the_wall():
    """The strip of obstacles taken for the walls took a stairwell's scanned bottom too, and a
    ceiling bulkhead over it (any face above the safe height: a lintel, a sign) was taken for
    the wall and stretched the grid over the drop: 18 cm of a scanned 1 m drop, or 28 cm of an
    unscanned one, lay in free border cells. A drop is never wall now, and a wall must stand on
    the floor."""
    for edge, bottom_seen in ((4.62, True), (4.52, False)):
        res = build_grid(_stairwell_room(edge, bottom_seen, bulkhead=4.8))
        g = res.grid
        x_end = g.origin[0] + g.cols * g.resolution
        free_last = (g.data[:, -1] == 0).any()
        # no free cell reaches more than the floor_fill past the floor's edge
        assert not (free_last and x_end > edge + 0.05), (edge, bottom_seen, x_end, g.data[:, -1])
    # the bulkhead alone: a wall seen only above the safe height is no wall
    rng = np.random.default_rng(1)
    coord = np.r_[rng.normal(4.8, 0.01, 2000), rng.uniform(4.3, 5.0, 200)]
    assert abs(wall_near(coord, 4.6) - 4.8) < 0.01
    assert np.isnan(wall_near(coord, 4.6, standing=np.zeros(coord.size, dtype=bool)))
