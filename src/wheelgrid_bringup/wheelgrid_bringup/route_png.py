"""route.png: the safe grid with the planned route (blue) and the path the chair actually
drove (red), like the paper's Fig. 14(c, d) in one picture."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from wheelgrid_common.map_io import Grid

CELL_PX = 64
MARGIN = 28


def _to_px(grid: Grid, x: float, y: float) -> tuple[float, float]:
    """Map-frame metres -> picture pixels (continuous cell coordinates, so rotation is exact)."""
    x0, y0, yaw = grid.origin
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = x - x0, y - y0
    gx, gy = c * dx + s * dy, -s * dx + c * dy
    col = gx / grid.resolution
    row = grid.rows - gy / grid.resolution
    return MARGIN + col * CELL_PX, MARGIN + row * CELL_PX


def draw_route(
    grid: Grid,
    path: Path | str,
    planned_cells: Sequence[tuple[int, int]],
    driven_xy: Sequence[tuple[float, float]],
    title: str = "",
) -> Path:
    w = MARGIN * 2 + grid.cols * CELL_PX
    h = MARGIN * 2 + grid.rows * CELL_PX + 24
    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    colours = {0: (255, 255, 255), 100: (20, 20, 20)}
    for r in range(grid.rows):
        for c in range(grid.cols):
            v = int(grid.data[r, c])
            fill = colours.get(v, (170, 170, 170))
            x0, y0 = MARGIN + c * CELL_PX, MARGIN + r * CELL_PX
            d.rectangle([x0, y0, x0 + CELL_PX, y0 + CELL_PX], fill=fill, outline=(120, 120, 120))
            d.text((x0 + 3, y0 + 2), f"{r},{c}", fill=(200, 60, 60) if v == 100 else (90, 90, 90))
    if planned_cells:
        (sr, sc), (gr, gc) = planned_cells[0], planned_cells[-1]
        for (r, c), colour in (((sr, sc), (60, 180, 75)), ((gr, gc), (230, 60, 60))):
            x0, y0 = MARGIN + c * CELL_PX, MARGIN + r * CELL_PX
            d.rectangle([x0 + 4, y0 + 4, x0 + CELL_PX - 4, y0 + CELL_PX - 4], fill=colour)
        centres = [
            (MARGIN + (c + 0.5) * CELL_PX, MARGIN + (r + 0.5) * CELL_PX) for r, c in planned_cells
        ]
        for (ax, ay), (bx, by) in itertools.pairwise(centres):
            d.line([ax, ay, bx, by], fill=(40, 90, 220), width=5)
            vx, vy = bx - ax, by - ay
            n = max(np.hypot(vx, vy), 1e-9)
            ux, uy = vx / n, vy / n
            tip = (ax + 0.6 * vx, ay + 0.6 * vy)
            left = (tip[0] - 10 * ux + 6 * uy, tip[1] - 10 * uy - 6 * ux)
            right = (tip[0] - 10 * ux - 6 * uy, tip[1] - 10 * uy + 6 * ux)
            d.polygon([tip, left, right], fill=(40, 90, 220))
    if len(driven_xy) >= 2:
        pts = [_to_px(grid, x, y) for x, y in driven_xy]
        d.line(pts, fill=(220, 30, 30), width=3)
    d.text(
        (MARGIN, h - 22),
        title or "blue: planned route (Q-learning), red: path driven by the chair",
        fill=(0, 0, 0),
    )
    # scale bar: one cell
    d.line([MARGIN, MARGIN - 10, MARGIN + CELL_PX, MARGIN - 10], fill=(0, 0, 0), width=2)
    d.text((MARGIN + CELL_PX + 4, MARGIN - 18), f"{grid.resolution:.2f} m", fill=(0, 0, 0))
    out = Path(path)
    img.save(out)
    return out
