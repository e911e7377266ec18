"""Benchmark of the safe grid: levelled map -> 8 x 8 safe grid (+ fine map) on ~1.3 M points.

    python bench/bench_grid.py [--quick] [--json FILE] [--repeats N]

Input: the simulator's paper scene (exact surface points of obstacles, floor, inner wall faces
and ceiling, 5 mm Gaussian noise), put into the mapper's map frame (shifted by (-0.6, -6.6) m
and turned 2 degrees, so the wall alignment has work to do), ~1.3 M points like the paper's
downsampled map; --quick uses ~0.3 M. Falls back to wheelgrid_nav.grid_synth's hand-made copy
of the room when wheelgrid_sim is not installed.

Figures, timed in this process (median of N runs after one warm-up):

* ``build_grid``: the whole wheelgrid grid (height classes, wall-direction search, floor
  extent, rasterisation, eqs 9/10, guard, unknown cells, fine map in map axes);
* baseline: a straightforward Open3D + numpy version of the paper's steps only -- Open3D
  PointCloud + two AABB crops (band, floor), eq 8, ``np.histogram2d`` of the band points over
  the floor's bounding box, then a Python loop over the cells computing eq 9 and eq 10. It does
  less (no alignment, no guard, no unknown cells, no fine map), so the ratio understates the
  gap for equal work.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from wheelgrid_common.map_io import OCCUPIED
from wheelgrid_nav.grid import GridConfig, build_grid, grid_text


def make_cloud(target: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray | None, str]:
    """(points in a map frame, expected occupied mask or None, description)."""
    rng = np.random.default_rng(seed)
    spacing = 0.03 * math.sqrt(350_000 / target)
    try:
        from wheelgrid_sim.scene import paper_scene

        scene = paper_scene()
        pts = scene.interior_surface_points(spacing)
        expected = scene.expected_grid().data == OCCUPIED
        what = "wheelgrid_sim paper scene"
    except ImportError:
        from wheelgrid_nav.grid_synth import paper_like_boxes, paper_like_expected, room_cloud

        pts = room_cloud(paper_like_boxes(), spacing=spacing)
        expected = paper_like_expected()
        what = "grid_synth paper-like room"
    pts = pts + rng.normal(0.0, 0.005, pts.shape)
    yaw = math.radians(2.0)
    c, s = math.cos(yaw), math.sin(yaw)
    out = pts.copy()
    out[:, 0] = c * pts[:, 0] - s * pts[:, 1] - 0.6
    out[:, 1] = s * pts[:, 0] + c * pts[:, 1] - 6.6
    return out, expected, what


def baseline(points: np.ndarray, cfg: GridConfig) -> np.ndarray:
    """The paper's steps written plainly with Open3D and numpy (map axes, density only)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    big = 1e9
    band = pcd.crop(
        o3d.geometry.AxisAlignedBoundingBox(
            np.array([-big, -big, cfg.floor_clearance + 1e-6]),
            np.array([big, big, cfg.safe_height]),
        )
    )
    floor = pcd.crop(
        o3d.geometry.AxisAlignedBoundingBox(
            np.array([-big, -big, -cfg.drop_depth]), np.array([big, big, cfg.floor_clearance])
        )
    )
    fxy = np.asarray(floor.points)[:, :2]
    lo, hi = fxy.min(axis=0), fxy.max(axis=0)
    k = cfg.cell_pixels()
    cols = max(1, round((hi[0] - lo[0]) / cfg.cell_size))
    rows = max(1, round((hi[1] - lo[1]) / cfg.cell_size))
    xy = np.asarray(band.points)[:, :2]  # eq 8
    img, _, _ = np.histogram2d(
        xy[:, 0],
        xy[:, 1],
        bins=[cols * k, rows * k],
        range=[[lo[0], lo[0] + cols * cfg.cell_size], [lo[1], lo[1] + rows * cfg.cell_size]],
    )
    black = np.flipud(img.T > 0)
    grid = np.zeros((rows, cols), dtype=bool)
    for r in range(rows):
        for c in range(cols):
            sigma = black[r * k : (r + 1) * k, c * k : (c + 1) * k].sum() / (k * k)  # eq 9
            grid[r, c] = sigma > cfg.density_threshold  # eq 10
    return grid


def timed(fn, repeats: int) -> tuple[list[float], list[float]]:
    """Wall-clock and process CPU seconds of ``repeats`` calls after one warm-up call.

    CPU time is printed beside wall time because the 2 cores are shared: under load the wall
    time measures the neighbours as much as this code.
    """
    fn()  # warm-up (imports, allocator)
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="~0.3 M points, 3 runs")
    ap.add_argument("--json", type=Path, help="write the rows as JSON here")
    ap.add_argument("--repeats", type=int, default=0, help="timed runs (default 7, quick 3)")
    args = ap.parse_args(argv)
    target = 300_000 if args.quick else 1_300_000
    repeats = args.repeats or (3 if args.quick else 7)
    cfg = GridConfig()

    points, expected, what = make_cloud(target)
    n = points.shape[0]
    print(f"input: {what}, {n:,} points (map frame, 2 deg yaw, 5 mm noise)")

    result = build_grid(points, cfg)
    ok = expected is not None and bool(np.array_equal(result.grid.data == OCCUPIED, expected))
    print(grid_text(result.grid))
    print(
        f"grid {result.grid.rows} x {result.grid.cols}, yaw {result.stats['yaw_deg']:.2f} deg, "
        f"matches the scene's truth: {ok}"
    )

    load = os.getloadavg()[0]
    ours, ours_cpu = timed(lambda: build_grid(points, cfg), repeats)
    base, base_cpu = timed(lambda: baseline(points, cfg), max(1, repeats // 2))
    ours_med, base_med = statistics.median(ours), statistics.median(base)
    ratio = base_med / ours_med
    print(f"machine: {os.cpu_count()} cores, load average {load:.2f} at the start")
    print(
        f"build_grid: median {ours_med * 1000:.1f} ms wall "
        f"({statistics.median(ours_cpu) * 1000:.1f} ms CPU), "
        f"min {min(ours) * 1000:.1f} ms over {repeats} runs "
        f"({n / ours_med / 1e6:.1f} M points/s)"
    )
    print(
        f"baseline (Open3D crop + histogram2d + per-cell loop, density only): median "
        f"{base_med * 1000:.1f} ms wall ({statistics.median(base_cpu) * 1000:.1f} ms CPU) -> "
        f"ratio baseline/wheelgrid {ratio:.2f}"
    )
    rows = [
        {
            "figure": f"safe grid from {n / 1e6:.2f} M points (median of {repeats})",
            "value": round(ours_med * 1000, 1),
            "unit": "ms",
            "baseline": round(base_med * 1000, 1),
            "ratio": round(ratio, 2),
            "note": "baseline: Open3D crop + np.histogram2d + per-cell loop (eqs 8-10 only, "
            f"no alignment/guard/unknown/fine map); CPU {statistics.median(ours_cpu) * 1000:.0f}"
            f" ms; load avg {load:.1f}; target < 200 ms; grid matches truth: {ok}",
        },
        {
            "figure": "safe grid throughput",
            "value": round(n / ours_med / 1e6, 2),
            "unit": "M points/s",
            "baseline": round(n / base_med / 1e6, 2),
            "ratio": round(ratio, 2),
            "note": "",
        },
    ]
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
