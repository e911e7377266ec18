"""Hand-made point clouds of boxes, for grid unit tests and the grid benchmark.

Independent of the simulator on purpose: the grid's own tests need clouds whose every obstacle
is known exactly (a bar at 77 cm, one at 151.16 cm, a 5 cm post), built in a few milliseconds.
A box is sampled on its surface on a regular lattice, like the simulator's exact surface points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [x0, x1] x [y0, y1] x [z0, z1] (metres)."""

    x0: float
    x1: float
    y0: float
    y1: float
    z0: float
    z1: float


def _face(a0: float, a1: float, b0: float, b1: float, spacing: float) -> np.ndarray:
    na = max(2, int(np.ceil((a1 - a0) / spacing)) + 1)
    nb = max(2, int(np.ceil((b1 - b0) / spacing)) + 1)
    a, b = np.meshgrid(np.linspace(a0, a1, na), np.linspace(b0, b1, nb), indexing="ij")
    return np.stack([a.ravel(), b.ravel()], axis=1)


def sample_box(box: Box, spacing: float) -> np.ndarray:
    """Points on the six faces of ``box`` on a lattice no coarser than ``spacing``."""
    out = []
    xy = _face(box.x0, box.x1, box.y0, box.y1, spacing)
    for z in (box.z0, box.z1):
        out.append(np.column_stack([xy, np.full(len(xy), z)]))
    xz = _face(box.x0, box.x1, box.z0, box.z1, spacing)
    for y in (box.y0, box.y1):
        out.append(np.column_stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]]))
    yz = _face(box.y0, box.y1, box.z0, box.z1, spacing)
    for x in (box.x0, box.x1):
        out.append(np.column_stack([np.full(len(yz), x), yz]))
    return np.concatenate(out)


def room_cloud(
    boxes: list[Box],
    size: tuple[float, float] = (9.6, 9.6),
    height: float = 2.6,
    spacing: float = 0.03,
    ceiling: bool = True,
) -> np.ndarray:
    """A room [0, sx] x [0, sy] with floor, four walls (inner faces on the boundary), optional
    ceiling, and the given boxes; ``(N, 3)`` float64."""
    sx, sy = size
    floor = _face(0.0, sx, 0.0, sy, spacing)
    parts = [np.column_stack([floor, np.zeros(len(floor))])]
    wall_x = _face(0.0, sx, 0.0, height, spacing)
    wall_y = _face(0.0, sy, 0.0, height, spacing)
    parts.append(np.column_stack([wall_x[:, 0], np.zeros(len(wall_x)), wall_x[:, 1]]))
    parts.append(np.column_stack([wall_x[:, 0], np.full(len(wall_x), sy), wall_x[:, 1]]))
    parts.append(np.column_stack([np.zeros(len(wall_y)), wall_y]))
    parts.append(np.column_stack([np.full(len(wall_y), sx), wall_y]))
    if ceiling:
        xy = _face(0.0, sx, 0.0, sy, spacing)
        parts.append(np.column_stack([xy, np.full(len(xy), height)]))
    parts += [sample_box(b, spacing) for b in boxes]
    return np.concatenate(parts)


def table(x0: float, x1: float, y0: float, y1: float, top: float = 0.75) -> list[Box]:
    """A table: a 4 cm top ending at ``top`` and four 5 cm legs."""
    leg = 0.05
    boxes = [Box(x0, x1, y0, y1, top - 0.04, top)]
    for lx in (x0, x1 - leg):
        for ly in (y0, y1 - leg):
            boxes.append(Box(lx, lx + leg, ly, ly + leg, 0.0, top - 0.04))
    return boxes


def paper_like_boxes() -> list[Box]:
    """A room laid out like the paper's (room frame, 9.6 m square): the grid tests' own
    hand-made stand-in for it, close to but not the simulator's scene
    (:func:`wheelgrid_sim.scene.paper_scene`, which the bundled bag is made from: there
    Barrier 1's bar is 0.72-0.77 m and ends at x 5.55, the pillar stands in cell (0, 6), and
    the second row's tables are split in four). Test against that scene where the bag's truth
    matters; this one is for the grid's rules on a layout of the same kind.

    Row 3 (y in [4.8, 6.0]): table A, table B, Barrier 1 (bar at 0.77 m) -> cells (3,0)..(3,4)
    occupied, (3,5) free. Row 5 (y in [2.4, 3.6]): tables x in [0.1, 4.7] -> (5,0)..(5,3).
    Barrier 2: bar at 1.5116 m over x 4.85..9.6 at y ~ 4.2 with one post in cell (4,4): removed
    by the safe height, so (4,5)..(4,7) stay free. A pillar in cell (1,6).
    """
    boxes: list[Box] = []
    boxes += table(0.1, 1.1, 5.0, 5.8)
    boxes += table(2.3012, 3.5, 5.0, 5.8)
    boxes.append(Box(3.5, 5.9, 5.375, 5.425, 0.745, 0.795))  # Barrier 1 bar (top 0.795)
    boxes.append(Box(5.85, 5.9, 5.375, 5.425, 0.0, 0.745))  # its post
    boxes += table(0.1, 4.7, 2.6, 3.4)
    boxes.append(Box(4.85, 9.6, 4.175, 4.225, 1.5116, 1.5616))  # Barrier 2 bar
    boxes.append(Box(4.85, 4.90, 4.175, 4.225, 0.0, 1.5116))  # its post
    boxes.append(Box(7.6, 7.9, 7.6, 7.9, 0.0, 2.6))  # pillar
    return boxes


def paper_like_expected() -> np.ndarray:
    """The 8 x 8 truth of :func:`paper_like_boxes` (image orientation): True = occupied."""
    occ = np.zeros((8, 8), dtype=bool)
    occ[3, 0:5] = True
    occ[5, 0:4] = True
    occ[4, 4] = True  # Barrier 2's post
    occ[1, 6] = True  # pillar
    return occ


def transform(points: np.ndarray, yaw: float, shift: tuple[float, float]) -> np.ndarray:
    """Rotate points by ``yaw`` about z, then shift in x, y (room -> some map frame)."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.asarray(points, dtype=np.float64).copy()
    x, y = out[:, 0].copy(), out[:, 1].copy()
    out[:, 0] = c * x - s * y + shift[0]
    out[:, 1] = s * x + c * y + shift[1]
    return out


def maze(n: int, rng: np.random.Generator) -> np.ndarray:
    """A perfect maze (recursive backtracker) as grid data (0 free, 100 occupied), n odd:
    passages on odd rows/cols, cells (1,1)..(n-2,n-2) all connected; for planner tests and bench."""
    g = np.full((n, n), 100, np.int8)
    m = (n - 1) // 2
    seen = np.zeros((m, m), bool)
    stack = [(0, 0)]
    seen[0, 0] = True
    g[1, 1] = 0
    while stack:
        r, c = stack[-1]
        nb = [
            (r + dr, c + dc)
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= r + dr < m and 0 <= c + dc < m and not seen[r + dr, c + dc]
        ]
        if not nb:
            stack.pop()
            continue
        rr, cc = nb[rng.integers(len(nb))]
        seen[rr, cc] = True
        g[2 * rr + 1, 2 * cc + 1] = 0
        g[r + rr + 1, c + cc + 1] = 0
        stack.append((rr, cc))
    return g
