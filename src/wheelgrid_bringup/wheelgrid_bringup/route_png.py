"""route.png: the safe grid with the planned route (blue) and the path the chair actually
drove (red), like the paper's Fig. 14(c, d) in one picture."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from wheelgrid_common.map_io import Grid

CELL_PX = 64
MARGIN = 28
LABEL_RGB = (90, 90, 90)  # a cell's "r,c"
OCCUPIED_LABEL_RGB = (200, 60, 60)
ROUTE_RGB = (40, 90, 220)  # the planned route's line and arrows


def _to_px(grid: Grid, x: float, y: float) -> tuple[float, float]:
    """Map-frame metres -> picture pixels (continuous cell coordinates, so rotation is exact)."""
    x0, y0, yaw = grid.origin
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = x - x0, y - y0
    gx, gy = c * dx + s * dy, -s * dx + c * dy
    col = gx / grid.resolution
    row = grid.rows - gy / grid.resolution
    return MARGIN + col * CELL_PX, MARGIN + row * CELL_PX


def caption(planned_cells: Sequence[tuple[int, int]]) -> str:
    """What the colours are: the goal's red square beside the driven path's red line read as
    one thing, so both are named, with the start, the goal and the number of moves."""
    if not planned_cells:
        return "no planned route; red line: path driven by the chair"
    (sr, sc), (gr, gc) = planned_cells[0], planned_cells[-1]
    moves = len(planned_cells) - 1
    return (
        f"green square: start ({sr}, {sc}), red square: goal ({gr}, {gc}); blue: planned route, "
        f"{moves} move{'' if moves == 1 else 's'} (Q-learning); red line: path driven by the chair"
    )


def _wrap(text: str, width: float) -> list[str]:
    """``text`` in lines no wider than ``width`` pixels, broken after its "; " (a small grid's
    picture cut the caption off mid-word); a part wider than ``width`` alone (a grid one to
    three cells wide) is broken between its words. Only a single word wider than ``width``
    stays wider (:func:`draw_route` widens the picture for it)."""
    font = ImageFont.load_default()
    lines: list[str] = []
    for part in text.split("; "):
        joined = f"{lines[-1]}; {part}" if lines else part
        if lines and font.getlength(joined) <= width:
            lines[-1] = joined
            continue
        line = ""
        for word in part.split(" "):
            longer = f"{line} {word}" if line else word
            if line and font.getlength(longer) > width:
                lines.append(line)
                line = word
            else:
                line = longer
        lines.append(line)
    return lines


def draw_route(
    grid: Grid,
    path: Path | str,
    planned_cells: Sequence[tuple[int, int]],
    driven_xy: Sequence[tuple[float, float]],
    title: str = "",
) -> Path:
    w = MARGIN * 2 + grid.cols * CELL_PX
    lines = _wrap(title or caption(planned_cells), w - 2 * MARGIN)
    font = ImageFont.load_default()
    w = max(w, 2 * MARGIN + math.ceil(max(font.getlength(ln) for ln in lines)))
    h = MARGIN * 2 + grid.rows * CELL_PX + 8 + 16 * len(lines)
    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    colours = {0: (255, 255, 255), 100: (20, 20, 20)}
    for r in range(grid.rows):
        for c in range(grid.cols):
            v = int(grid.data[r, c])
            fill = colours.get(v, (170, 170, 170))
            x0, y0 = MARGIN + c * CELL_PX, MARGIN + r * CELL_PX
            d.rectangle([x0, y0, x0 + CELL_PX, y0 + CELL_PX], fill=fill, outline=(120, 120, 120))
    if planned_cells:
        (sr, sc), (gr, gc) = planned_cells[0], planned_cells[-1]
        for (r, c), colour in (((sr, sc), (60, 180, 75)), ((gr, gc), (230, 60, 60))):
            x0, y0 = MARGIN + c * CELL_PX, MARGIN + r * CELL_PX
            d.rectangle([x0 + 4, y0 + 4, x0 + CELL_PX - 4, y0 + CELL_PX - 4], fill=colour)
    for r in range(grid.rows):  # the labels last: the start's and goal's squares hid theirs
        for c in range(grid.cols):
            x0, y0 = MARGIN + c * CELL_PX, MARGIN + r * CELL_PX
            occupied = int(grid.data[r, c]) == 100
            d.text((x0 + 3, y0 + 2), f"{r},{c}", fill=OCCUPIED_LABEL_RGB if occupied else LABEL_RGB)
    # the route once, over the squares and labels (it sat in the labels' row loop: drawn once
    # a row, and under the labels of the rows after each drawing)
    centres = [
        (MARGIN + (c + 0.5) * CELL_PX, MARGIN + (r + 0.5) * CELL_PX) for r, c in planned_cells
    ]
    for (ax, ay), (bx, by) in itertools.pairwise(centres):
        d.line([ax, ay, bx, by], fill=ROUTE_RGB, width=5)
        vx, vy = bx - ax, by - ay
        n = max(np.hypot(vx, vy), 1e-9)
        ux, uy = vx / n, vy / n
        tip = (ax + 0.6 * vx, ay + 0.6 * vy)
        left = (tip[0] - 10 * ux + 6 * uy, tip[1] - 10 * uy - 6 * ux)
        right = (tip[0] - 10 * ux - 6 * uy, tip[1] - 10 * uy + 6 * ux)
        d.polygon([tip, left, right], fill=ROUTE_RGB)
    if len(driven_xy) >= 2:
        pts = [_to_px(grid, x, y) for x, y in driven_xy]
        d.line(pts, fill=(220, 30, 30), width=3)
    for k, line in enumerate(lines):
        d.text((MARGIN, h - 6 - 16 * (len(lines) - k)), line, fill=(0, 0, 0))
    # scale bar: one cell
    d.line([MARGIN, MARGIN - 10, MARGIN + CELL_PX, MARGIN - 10], fill=(0, 0, 0), width=2)
    d.text((MARGIN + CELL_PX + 4, MARGIN - 18), f"{grid.resolution:.2f} m", fill=(0, 0, 0))
    out = Path(path)
    img.save(out)
    return out
