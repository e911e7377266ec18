"""Draw a grid with a planned route as a PNG, like the paper's Fig. 14(c) (Pillow only).

White cells are free, black occupied, grey unknown (never free to the planner); the route is
a chain of blue arrows from the start (green cell) to the goal (red cell). A picture is the
quickest way for a person to check, before the chair moves, that the route makes sense.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import numpy as np

FREE_RGB = (255, 255, 255)
OCCUPIED_RGB = (0, 0, 0)
UNKNOWN_RGB = (150, 150, 150)
START_RGB = (40, 180, 60)
GOAL_RGB = (220, 40, 40)
ARROW_RGB = (30, 80, 230)
LINE_RGB = (200, 200, 200)


def render_plan(
    data: np.ndarray,
    cells: Sequence[Sequence[int]] = (),
    start: Sequence[int] | None = None,
    goal: Sequence[int] | None = None,
    cell_px: int = 0,
    caption: str = "",
) -> object:
    """A PIL image of the grid (image orientation, row 0 on top) with the route drawn, and
    ``caption`` below it, a line per "; "-separated part.

    ``cell_px`` 0 picks a size that makes small grids readable and keeps big ones < ~2000 px.
    """
    from PIL import Image, ImageDraw

    grid = np.asarray(data)
    rows, cols = grid.shape
    if cell_px <= 0:
        cell_px = int(max(3, min(48, 2000 // max(rows, cols))))
    rgb = np.empty((rows, cols, 3), dtype=np.uint8)
    rgb[:] = UNKNOWN_RGB
    rgb[grid == 0] = FREE_RGB
    rgb[grid > 0] = OCCUPIED_RGB  # any occupancy probability > 0 is drawn as occupied
    if start is not None:
        rgb[int(start[0]), int(start[1])] = START_RGB
    if goal is not None:
        rgb[int(goal[0]), int(goal[1])] = GOAL_RGB
    big = np.repeat(np.repeat(rgb, cell_px, axis=0), cell_px, axis=1)
    img = Image.fromarray(big, "RGB")
    draw = ImageDraw.Draw(img)
    if cell_px >= 8:  # cell borders help count cells as in the paper's figure
        for r in range(rows + 1):
            draw.line([(0, r * cell_px), (cols * cell_px, r * cell_px)], fill=LINE_RGB)
        for c in range(cols + 1):
            draw.line([(c * cell_px, 0), (c * cell_px, rows * cell_px)], fill=LINE_RGB)
    width = max(1, cell_px // 8)
    for a, b in itertools.pairwise(cells):
        _arrow(draw, _centre(a, cell_px), _centre(b, cell_px), cell_px, width)
    if not caption:
        return img
    from PIL import ImageFont

    font = ImageFont.load_default()
    lines = caption.split("; ")
    line_h, pad = 14, 6
    text_w = max(int(font.getlength(line)) for line in lines) + 2 * pad
    out = Image.new(
        "RGB", (max(img.width, text_w), img.height + len(lines) * line_h + pad), "white"
    )
    out.paste(img, (0, 0))
    text = ImageDraw.Draw(out)
    for i, line in enumerate(lines):
        text.text((pad, img.height + pad // 2 + i * line_h), line, fill=(40, 40, 40), font=font)
    return out


def plan_caption(
    cells: Sequence[Sequence[int]], start: Sequence[int], goal: Sequence[int], reason: str
) -> str:
    """What the picture shows, in words: the colours, the start and goal, the moves, or why
    there is no route (the picture had no text at all; a review)."""
    head = (
        f"green: start ({start[0]}, {start[1]}); red: goal ({goal[0]}, {goal[1]}); "
        "white free, black occupied, grey unknown (never entered)"
    )
    if len(cells) < 2:
        return f"{head}; no route: {reason}" if reason != "ok" else f"{head}; already at the goal"
    moves = len(cells) - 1
    return f"{head}; blue arrows: the route, {moves} move{'' if moves == 1 else 's'}"


#: The PNG text chunk "Software" of the pictures `wheelgrid plan --png` writes.
PLAN_PNG_SOFTWARE = "wheelgrid plan"


def save_plan_png(
    path: str | Path,
    data: np.ndarray,
    cells: Sequence[Sequence[int]] = (),
    start: Sequence[int] | None = None,
    goal: Sequence[int] | None = None,
    cell_px: int = 0,
    caption: str = "",
) -> Path:
    """Render (see :func:`render_plan`) and write a PNG; returns the path."""
    from PIL.PngImagePlugin import PngInfo

    path = Path(path)
    img = render_plan(data, cells, start, goal, cell_px, caption)
    info = PngInfo()
    info.add_text("Software", PLAN_PNG_SOFTWARE)  # a refused plan removes only its own kind
    img.save(path, format="PNG", pnginfo=info)  # type: ignore[attr-defined]
    return path


def is_plan_png(path: str | Path) -> bool:
    """Whether ``path`` is a picture :func:`save_plan_png` wrote (its text chunk says so)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return bool(im.info.get("Software") == PLAN_PNG_SOFTWARE)
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError):
        return False


def _centre(cell: Sequence[int], px: int) -> tuple[float, float]:
    return ((int(cell[1]) + 0.5) * px, (int(cell[0]) + 0.5) * px)


def _arrow(
    draw: object, p: tuple[float, float], q: tuple[float, float], px: int, width: int
) -> None:
    """A shaft from ``p`` to near ``q`` with a triangular head pointing at ``q``."""
    (x0, y0), (x1, y1) = p, q
    dx, dy = x1 - x0, y1 - y0
    norm = max(1e-9, float(np.hypot(dx, dy)))
    ux, uy = dx / norm, dy / norm
    head = 0.3 * px
    tip = (x1 - ux * 0.15 * px, y1 - uy * 0.15 * px)
    base = (tip[0] - ux * head, tip[1] - uy * head)
    draw.line([(x0, y0), base], fill=ARROW_RGB, width=width)  # type: ignore[attr-defined]
    half = 0.5 * head
    poly = [
        tip,
        (base[0] - uy * half, base[1] + ux * half),
        (base[0] + uy * half, base[1] - ux * half),
    ]
    draw.polygon(poly, fill=ARROW_RGB)  # type: ignore[attr-defined]
