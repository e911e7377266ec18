"""How large an unseen hole in the floor must be before the safe grid stops calling a cell free.

    python bench/grid_holes.py [--draws N]

A 4.8 x 4.8 m room (four walls, floor at 2 cm spacing, every coordinate jittered by Gaussian
noise of 0, 0.5 or 1 cm) with a square hole cut out of its floor, neither its bottom nor its
sides seen: a stairwell or an open hatch that the sensor never looked into. For each hole size,
the number of draws (the hole nudged by 2 cm a draw, the noise redrawn) on which a cell the hole
touches still reads FREE, with the default GridConfig (``alignment: map``):

* in a cell's middle (cell (2, 1), centred at (1.8, 1.8) m); and so with one point over it, in
  the band (50 cm up) or at floor height, or a cable lying across it (a line of points 1 cm
  up, 2 cm apart);
* on the corner of four cells (centred at (2.4, 2.4) m);
* as a trench across the room along the cell border x = 2.4 m;
* in cell (2, 1) and reaching a few centimetres past x = 2.4 m into cell (2, 2): whether that
  cell, the hole's edge inside it, reads free (55, 60 and 70 cm holes, draws summed).

The README's Safety section quotes these counts. Fidelity, not speed: nothing here is timed,
and it is no stage of `make bench` (bench/run_all.py runs the bench_*.py scripts).
"""

from __future__ import annotations

import argparse

import numpy as np

from wheelgrid_common.map_io import FREE
from wheelgrid_nav.grid import GridConfig, build_grid

SIDE = 4.8
SPACING = 0.02


def _grid(x0: float, x1: float, y0: float, y1: float, z: float) -> np.ndarray:
    xs = np.arange(x0, x1 + 1e-9, SPACING)
    ys = np.arange(y0, y1 + 1e-9, SPACING)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])


def _wall(fixed: float, along_x: bool) -> np.ndarray:
    a = np.arange(0.0, SIDE + 1e-9, SPACING)
    z = np.arange(0.0, 2.4 + 1e-9, SPACING)
    ga, gz = np.meshgrid(a, z, indexing="ij")
    f = np.full(ga.size, fixed)
    cols = [ga.ravel(), f, gz.ravel()] if along_x else [f, ga.ravel(), gz.ravel()]
    return np.column_stack(cols)


def room(hole: tuple[float, float, float, float], noise: float, seed: int) -> np.ndarray:
    """The room's points with the floor inside ``hole`` (x0, x1, y0, y1) never seen."""
    floor = _grid(0.0, SIDE, 0.0, SIDE, 0.0)
    x0, x1, y0, y1 = hole
    inside = (floor[:, 0] > x0) & (floor[:, 0] < x1) & (floor[:, 1] > y0) & (floor[:, 1] < y1)
    pts = np.vstack(
        [floor[~inside]] + [_wall(v, along_x) for v in (0.0, SIDE) for along_x in (True, False)]
    )
    return pts + np.random.default_rng(seed).normal(0.0, noise, pts.shape)


def free_draws(kind: str, size: float, noise: float, draws: int) -> int:
    """On how many draws a cell the hole touches reads free."""
    count = 0
    for seed in range(draws):
        shift = 0.02 * seed
        speck = None
        if kind.startswith("middle"):  # "middle+band|floor|cable": something over it
            c = 1.8 + shift
            hole, cells = (c - size / 2, c + size / 2, c - size / 2, c + size / 2), [(2, 1)]
            if kind.endswith("+band"):
                speck = [c, c, 0.5]  # a speck of noise, a cord's tip over a stairwell
            elif kind.endswith("+floor"):
                speck = [c, c, -0.03]  # a stray return at floor height
            elif kind.endswith("+cable"):  # a cable lying across it, one line of map points
                xs = np.arange(c - size / 2 - 0.1, c + size / 2 + 0.1, SPACING)
                speck = np.column_stack([xs, np.full(xs.size, c), np.full(xs.size, 0.01)])
        elif kind == "corner":
            c = 2.4 + shift
            hole = (c - size / 2, c + size / 2, c - size / 2, c + size / 2)
            cells = [(1, 1), (1, 2), (2, 1), (2, 2)]
        elif kind.startswith("edge"):  # ``size`` is how far past x = 2.4 it reaches
            side, yc = float(kind[4:]), 1.8 + shift
            hole = (2.4 + size - side, 2.4 + size, yc - side / 2, yc + side / 2)
            cells = [(2, 2)]
        else:  # a trench along the border x = 2.4 between columns 1 and 2
            c = 2.4 + shift
            hole = (c - size / 2, c + size / 2, -0.01, SIDE + 0.01)
            cells = [(r, col) for r in range(4) for col in (1, 2)]
        pts = room(hole, noise, seed)
        if speck is not None:
            pts = np.vstack([pts, np.atleast_2d(speck)])
        data = build_grid(pts, GridConfig(alignment="map")).grid.data
        count += int(any(data[rc] == FREE for rc in cells))
    return count


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=5, help="draws per hole size (default 5)")
    args = p.parse_args(argv)
    n = args.draws
    for noise in (0.0, 0.005, 0.01):
        sizes = " ".join(
            f"{s * 100:.0f} cm {free_draws('middle', s, noise, n)}/{n}"
            for s in (0.45, 0.50, 0.55, 0.60)
        )
        print(f"hole in a cell's middle, noise {noise * 100:.1f} cm: free on {sizes}")
    for kind, what in (
        ("middle+band", "a lone point at 50 cm over it"),
        ("middle+floor", "a stray point at floor height over it"),
        ("middle+cable", "a cable lying across it (a line of map points 1 cm up)"),
    ):
        sizes = " ".join(
            f"{s * 100:.0f} cm {free_draws(kind, s, 0.01, n)}/{n}" for s in (0.55, 0.65, 0.75)
        )
        print(f"hole in a cell's middle with {what}, noise 1.0 cm: free on {sizes}")
    reach = " ".join(
        f"{d * 100:.0f} cm {sum(free_draws(f'edge{s}', d, 0.01, n) for s in (0.55, 0.6, 0.7))}"
        f"/{3 * n}"
        for d in (0.06, 0.08, 0.10)
    )
    print(f"hole reaching into a cell past its border, noise 1.0 cm: the cell free on {reach}")
    for kind, sizes_m in (("corner", (0.5, 0.6, 0.7)), ("trench", (0.46, 0.56, 0.66))):
        row = " ".join(f"{s * 100:.0f} cm {free_draws(kind, s, 0.01, n)}/{n}" for s in sizes_m)
        print(
            f"hole on a four-cell {kind}, noise 1.0 cm: a touching cell free on {row}"
            if kind == "corner"
            else f"trench along a cell border, noise 1.0 cm: a touching cell free on {row}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
