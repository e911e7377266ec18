"""The committed bags/paper_room: readable, consistent with its ground truth, whole room seen."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wheelgrid_common.bagio import BagReader
from wheelgrid_common.map_io import FREE
from wheelgrid_common.pointcloud2 import read_fields
from wheelgrid_sim import TOPIC, load_ground_truth, paper_scene


def test_bundled_bag_matches_its_ground_truth_and_covers_every_free_cell(
    bundled_bag: Path,
) -> None:
    gt = load_ground_truth(bundled_bag)
    assert gt.truth["frames"] == len(gt.stamps) == 210
    np.testing.assert_array_equal(gt.expected_grid.data, paper_scene().expected_grid().data)
    assert gt.scene.boxes == paper_scene().boxes
    pts = []
    with BagReader(gt.bag) as reader:
        for i, (_, _, msg) in enumerate(reader.messages([TOPIC])):
            p = read_fields(msg)
            p = p[np.isfinite(p).all(axis=1)]
            T = gt.poses[i]
            pts.append(p @ T[:3, :3].T + T[:3, 3])
    cloud = np.concatenate(pts)
    # Noisy, with outliers and flying pixels, yet most points are within 1-2 cm of a surface.
    dist = gt.scene.distance_to_surfaces(cloud[::10])
    assert np.median(dist) < 0.01 and np.mean(dist < 0.05) > 0.85
    # Every free cell's floor is observed over at least half of its area (10 cm bins).
    floor = cloud[np.abs(cloud[:, 2]) < 0.03]
    grid = gt.expected_grid
    seen = np.zeros((96, 96), bool)
    ix = np.clip((floor[:, 0] / 0.1).astype(int), 0, 95)
    iy = np.clip((floor[:, 1] / 0.1).astype(int), 0, 95)
    seen[iy, ix] = True
    for r in range(grid.rows):
        for c in range(grid.cols):
            if grid.data[r, c] != FREE:
                continue
            y = grid.rows - 1 - r
            coverage = seen[y * 12 : (y + 1) * 12, c * 12 : (c + 1) * 12].mean()
            assert coverage > 0.5, (r, c, coverage)
    # Both barriers were seen: Barrier 2's underside at 1.5116 m is in the data.
    b2 = cloud[(np.abs(cloud[:, 1] - 4.2) < 0.1) & (cloud[:, 0] > 5.0) & (cloud[:, 2] > 1.45)]
    assert len(b2) > 30
