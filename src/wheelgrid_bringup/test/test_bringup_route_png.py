"""route.png (the demo's picture, like the paper's Fig. 14 c and d): what it shows can be read."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from wheelgrid_bringup.route_png import CELL_PX, LABEL_RGB, MARGIN, caption, draw_route
from wheelgrid_common.map_io import Grid


def _grid() -> Grid:
    data = np.zeros((4, 4), dtype=np.int8)
    data[1, 0:3] = 100
    return Grid(data=data, resolution=1.2, origin=(0.0, 0.0, 0.0), frame_id="map")


def test_start_and_goal_keep_their_cell_labels_and_the_caption_names_them(tmp_path: Path) -> None:
    """The start's and the goal's squares were drawn over their cells' "r,c" labels (the
    goal's was unreadable), and the caption's "red: path driven" said nothing of the red goal
    square beside it. The labels now stand on the squares, and the caption says which colour
    is what, with the start, the goal and the number of moves."""
    grid = _grid()
    cells = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 3), (2, 3)]
    path = draw_route(grid, tmp_path / "route.png", cells, [(0.6, 4.2), (4.2, 4.2), (4.2, 1.8)])
    img = np.asarray(Image.open(path).convert("RGB"))
    for r, c in (cells[0], cells[-1]):
        x0, y0 = MARGIN + c * CELL_PX, MARGIN + r * CELL_PX
        label = img[y0 + 2 : y0 + 14, x0 + 3 : x0 + 30].astype(int)
        ink = np.abs(label - np.array(LABEL_RGB)).sum(axis=2) < 30  # anti-aliased text
        assert ink.sum() > 5, (r, c)
    # the whole caption, in lines no wider than the picture (8 cells' width cut it off)
    from PIL import ImageFont

    from wheelgrid_bringup.route_png import _wrap

    said = caption(cells)
    lines = _wrap(said, 4 * CELL_PX)
    assert len(lines) > 1 and "; ".join(lines) == said
    assert all(ImageFont.load_default().getlength(ln) <= 4 * CELL_PX for ln in lines)
    assert "green square: start (0, 0)" in said and "red square: goal (2, 3)" in said
    assert "blue: planned route, 5 moves" in said and "red line: path driven" in said


def test_the_route_is_drawn_once_over_the_labels(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The route's line sat in the labels' row loop: drawn once per grid row (4 times here),
    and the labels of the rows after each drawing went over it."""
    from PIL import ImageDraw

    calls: list[str] = []
    line, text = ImageDraw.ImageDraw.line, ImageDraw.ImageDraw.text

    def spy_line(
        self: ImageDraw.ImageDraw, xy: Any, fill: Any = None, width: int = 0, *a: Any, **k: Any
    ) -> None:
        if fill == (40, 90, 220):  # the route's blue
            calls.append("route")
        return line(self, xy, fill, width, *a, **k)

    def spy_text(self: ImageDraw.ImageDraw, xy: Any, s: str, *a: Any, **k: Any) -> None:
        calls.append("label" if "," in s and len(s) <= 5 else "other")
        return text(self, xy, s, *a, **k)

    monkeypatch.setattr(ImageDraw.ImageDraw, "line", spy_line)
    monkeypatch.setattr(ImageDraw.ImageDraw, "text", spy_text)
    cells = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 3), (2, 3)]
    draw_route(_grid(), tmp_path / "route.png", cells, [])
    assert calls.count("route") == len(cells) - 1
    assert calls.index("route") > max(i for i, c in enumerate(calls) if c == "label")


@pytest.mark.parametrize("cols", [1, 2, 3])
def test_a_narrow_grid_s_caption_is_wrapped_to_its_width(tmp_path: Path, cols: int) -> None:
    """A grid one to three cells wide: each "; "-part of the caption was one line, wider than
    the picture, and cut off."""
    from PIL import ImageFont

    from wheelgrid_bringup.route_png import _wrap

    grid = Grid(np.zeros((3, cols), np.int8), 1.2, (0.0, 0.0, 0.0), "map")
    cells = [(0, 0), (1, 0), (2, 0)]
    said = caption(cells)
    width = cols * CELL_PX
    lines = _wrap(said, width)
    font = ImageFont.load_default()
    assert all(font.getlength(ln) <= width for ln in lines), lines
    assert " ".join(ln.replace("; ", " ") for ln in lines) == said.replace("; ", " ")
    img = Image.open(draw_route(grid, tmp_path / "route.png", cells, []))
    assert img.width >= 2 * MARGIN + max(font.getlength(ln) for ln in lines)


def test_one_move_is_one_move() -> None:
    assert "1 move (Q-learning)" in caption([(0, 0), (0, 1)])
    assert "0 moves" in caption([(0, 0)]) and "2 moves" in caption([(0, 0), (0, 1), (0, 2)])
