"""The grid's files: grid.yaml/pgm and fine.yaml/pgm (Nav2 map_server format) and grid.png, the
paper's Fig. 12 in one picture -- (a) the 2D map, (b) the grid overlaid on it, (c) the safe 2D
grid -- with a scale bar, drawn with Pillow (no matplotlib on the chair's PC).

Colours: obstacle pixels black, observed floor white, unobserved grey, pixels taken as the walls
(the boundary rule) dark blue; grid cells black (occupied), white (free), grey (unknown), with an
orange frame on cells that only the thin-obstacle guard made occupied (eq 10 alone says free).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from wheelgrid_common.fileio import write_together
from wheelgrid_common.map_io import FREE, OCCUPIED, map_writers
from wheelgrid_nav.grid import GridResult, classify_density

_WHITE = (255, 255, 255)
_BLACK = (0, 0, 0)
_GREY = (170, 170, 170)
_WALL = (30, 50, 140)
_LINE = (220, 30, 30)
_GUARD = (255, 140, 0)
_PANEL = 420  # target panel side, pixels
_PAD = 16
_TITLE = 22
# the legend under the panels: (fill, outline, label); what each colour means, on the picture
_LEGEND = (
    (_BLACK, _BLACK, "obstacle pixel / occupied cell"),
    (_WHITE, _BLACK, "floor seen / free cell"),
    (_GREY, _GREY, "never seen / unknown"),
    (_WALL, _WALL, "walls"),
    (_BLACK, _GUARD, "occupied by the thin-obstacle guard"),  # drawn black, framed
)


def _map_rgb(result: GridResult) -> np.ndarray:
    h, w = result.obstacles.shape
    rgb = np.empty((h, w, 3), dtype=np.uint8)
    rgb[:] = _GREY
    rgb[result.floor] = _WHITE
    rgb[result.boundary] = _WALL
    rgb[result.obstacles] = _BLACK
    return rgb


def _grid_rgb(result: GridResult, k: int) -> np.ndarray:
    data = result.grid.data
    rgb = np.empty((*data.shape, 3), dtype=np.uint8)
    rgb[:] = _GREY
    rgb[data == FREE] = _WHITE
    rgb[data == OCCUPIED] = _BLACK
    return np.repeat(np.repeat(rgb, k, axis=0), k, axis=1)


#: Pillow's default font's line height and the gap between two legend entries, pixels
_LINE_H = 14
_GAP = 16


def _text_width(text: str) -> int:
    return int(ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(text))


@dataclass
class Layout:
    """Where everything goes on the picture, computed before anything is drawn: the canvas
    was as wide as the three panels, and a narrow grid (a 2.4 m corridor) printed its panel
    titles over each other and cut the legend off after two of its five entries (a review)."""

    size: tuple[int, int]
    scale: int  # canvas pixels per raster pixel
    panels: list[int]  # x of each panel's left edge
    texts: list[tuple[int, int, str]]  # (x, y, text), y its top
    bar: int  # 1 m in canvas pixels
    bar_y: int
    legend: list[tuple[int, int, tuple[int, int, int], tuple[int, int, int]]]  # x, y, colours


def layout(result: GridResult) -> Layout:
    """Panels, titles, scale bars, the grid's yaw and the legend, every text inside the
    canvas and none over another."""
    cfg = result.config
    h, w = result.obstacles.shape
    scale = max(1, _PANEL // max(h, w))
    ph, pw = h * scale, w * scale
    rows, cols = result.grid.data.shape
    titles = (
        f"(a) 2D map, band {cfg.floor_clearance:g}-{cfg.safe_height:g} m",
        f"(b) {rows} x {cols} grid of {cfg.cell_size:g} m",
        f"(c) safe grid, density > {cfg.density_threshold:g}",
    )
    # 1 m at the picture's scale: rounded to whole raster pixels first, it read 0.81 m at a
    # 0.4 m pixel_size (round(2.5) = 2), labelled "1 m" all the same (a review)
    bar = round(scale / cfg.pixel_size)
    col = max(pw, *(_text_width(t) + _PAD for t in titles), bar + 6 + _text_width("1 m") + _PAD)
    panels = [_PAD + i * (col + _PAD) for i in range(3)]
    width = 3 * col + 4 * _PAD
    texts = [(x, 4, t) for x, t in zip(panels, titles, strict=True)]
    bar_y = _TITLE + ph + 12
    texts += [(x + bar + 6, bar_y - 3, "1 m") for x in panels]
    yaw = result.stats.get("yaw_deg", 0.0)
    yaw_text = f"grid yaw {yaw:.2f} deg in the map frame"
    width = max(width, _PAD + _text_width(yaw_text) + _PAD)
    texts.append((panels[0], bar_y + _LINE_H, yaw_text))
    x, y = panels[0], bar_y + 2 * _LINE_H + 4
    legend = []
    for fill, outline, label in _LEGEND:
        entry = 14 + _text_width(label)
        if x > panels[0] and x + entry > width - _PAD:  # the next row
            x, y = panels[0], y + _LINE_H + 4
        legend.append((x, y, fill, outline))
        texts.append((x + 14, y - 1, label))
        width = max(width, x + entry + _PAD)
        x += entry + _GAP
    height = y + _LINE_H + _PAD
    return Layout((width, height), scale, panels, texts, bar, bar_y, legend)


def render(result: GridResult) -> Image.Image:
    """The three panels side by side, titled, with a 1 m scale bar under each."""
    cfg = result.config
    k = cfg.cell_pixels()
    plan = layout(result)
    scale = plan.scale
    h, w = result.obstacles.shape
    ph, pw = h * scale, w * scale
    canvas = Image.new("RGB", plan.size, _WHITE)
    draw = ImageDraw.Draw(canvas)

    def up(rgb: np.ndarray) -> Image.Image:
        big = np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)
        return Image.fromarray(np.ascontiguousarray(big), "RGB")

    map_img = up(_map_rgb(result))
    grid_img = up(_grid_rgb(result, k))
    xs = plan.panels
    y0 = _TITLE
    canvas.paste(map_img, (xs[0], y0))
    canvas.paste(map_img, (xs[1], y0))
    canvas.paste(grid_img, (xs[2], y0))
    cell_px = k * scale
    rows, cols = result.grid.data.shape
    for x in xs[1:]:
        for c in range(cols + 1):
            gx = x + min(c * cell_px, pw - 1)
            draw.line([(gx, y0), (gx, y0 + ph - 1)], fill=_LINE, width=1)
        for r in range(rows + 1):
            gy = y0 + min(r * cell_px, ph - 1)
            draw.line([(x, gy), (x + pw - 1, gy)], fill=_LINE, width=1)
    guard_only = result.guard & ~classify_density(result.density, cfg.density_threshold)
    for r, c in zip(*np.nonzero(guard_only), strict=True):
        x, y = xs[2] + c * cell_px, y0 + r * cell_px
        draw.rectangle([x + 2, y + 2, x + cell_px - 3, y + cell_px - 3], outline=_GUARD, width=3)
    for x in xs:
        draw.rectangle([x, plan.bar_y, x + plan.bar, plan.bar_y + 5], fill=_BLACK)
    for x, y, fill, outline in plan.legend:
        draw.rectangle([x, y, x + 10, y + 10], fill=fill, outline=outline, width=2)
    for x, y, text in plan.texts:
        draw.text((x, y), text, fill=_BLACK)
    return canvas


# Files that `wheelgrid grid` writes beside the grid only for some maps.
EXTRA_FILES = ("levelling.yaml",)


def _write_text(path: Path, text: str) -> None:
    path.write_text(text)


def write_outputs(
    result: GridResult,
    out_dir: str | Path,
    png: bool = True,
    extra: dict[str, str] | None = None,
) -> dict[str, Path]:
    """Write DIR/grid.yaml + grid.pgm (cells), DIR/fine.yaml + fine.pgm (fine safe obstacle map)
    and DIR/grid.png; returns name -> path. The YAML/PGM pairs are what Nav2's map_server loads
    (trinary, unknown stays unknown on reload: see wheelgrid_common.map_io).

    The five files are one result and replace the old ones together or not at all. Written
    pair by pair, with grid.png in place, a full disk while writing fine.pgm (the largest)
    left the new grid.yaml beside the old fine.yaml (Nav2's /map of another scan), and one
    while writing grid.png a cut-off picture beside the new grid. Without ``png``, an older
    grid.png in DIR is removed once the new maps are in place. ``extra``: text files (name ->
    text) written with them, such as ``levelling.yaml``; one of those names from an earlier run
    that is not given now is removed, as it described another grid."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    writers = {
        **map_writers(out / "grid.yaml", result.grid),
        **map_writers(out / "fine.yaml", result.fine),
    }
    if png:
        picture = render(result)
        writers[out / "grid.png"] = lambda p: picture.save(p, format="PNG")
    extra = extra or {}
    for name, text in extra.items():
        writers[out / name] = functools.partial(_write_text, text=text)
    write_together(writers)
    # an earlier run's picture (or levelling) beside the new grid shows another grid's cells
    # to the person who checks it before the chair moves
    for name, written in (("grid.png", png), *((n, n in extra) for n in EXTRA_FILES)):
        stale = out / name
        if not written and (stale.is_file() or stale.is_symlink()):
            stale.unlink()
    files = {name: out / name for name in ("grid.yaml", "fine.yaml", "grid.pgm", "fine.pgm")}
    if png:
        files["grid.png"] = out / "grid.png"
    files.update({name: out / name for name in extra})
    return files
