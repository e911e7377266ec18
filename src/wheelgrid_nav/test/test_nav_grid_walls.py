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
