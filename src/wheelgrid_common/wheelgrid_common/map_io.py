"""Occupancy grids in Nav2 map_server format (YAML + PGM) and as nav_msgs/OccupancyGrid.

Convention used across wheelgrid: :class:`Grid.data` is ``(rows, cols)`` int8 in *image*
orientation -- row 0 is the top row of the picture (largest y), as in the paper's Table II,
where "down" is row + 1. Values: 0 free, 100 occupied, -1 unknown. ``origin`` is map_server's
``[x, y, yaw]``: the pose of the lower-left corner of the bottom-left cell in the map frame.

Writing follows nav2_map_server's map_saver (trinary: free 254, occupied 0, unknown 205);
reading follows its loader exactly (``occ = 1 - shade`` unless negated, then thresholds). We
write ``free_thresh: 0.196`` because with map_saver's default 0.25 an unknown pixel (205,
occ = 0.196) reloads as FREE -- unacceptable for a wheelchair.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .fileio import quat_yaw, write_together
from .params import read_yaml

FREE, OCCUPIED, UNKNOWN = 0, 100, -1
PIX_FREE, PIX_OCCUPIED, PIX_UNKNOWN = 254, 0, 205
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
#: The chair's longer side (its length; it is 80 cm wide), in metres. The grid, the planner and
#: the drive treat one cell as the chair's place: a free cell smaller than the chair can lie in
#: a gap the chair does not fit through (a review: 0.6 m cells, and the 5 cm fine map, planned
#: and drove through a 70 cm gap, exit 0 at every stage).
CHAIR_SIZE_M = 1.0


def chair_cell_problem(resolution: float) -> str | None:
    """Why cells of ``resolution`` metres cannot carry a route of the chair (None: they can);
    each caller adds what to do about it."""
    if resolution >= CHAIR_SIZE_M - 1e-9:
        return None
    return (
        f"cells of {resolution:g} m are smaller than the chair ({CHAIR_SIZE_M:g} m): a free cell "
        "may be a gap it does not fit through"
    )


#: What a planner or drive given such a grid should be given instead.
CHAIR_GRID_HINT = "plan on the safe grid (grid.yaml, /wheelgrid/safe_grid), not the fine map"


@dataclass
class Grid:
    """A 2D grid in image orientation (see module docstring)."""

    data: np.ndarray  # (rows, cols) int8: 0 free, 100 occupied, -1 unknown
    resolution: float  # metres per cell
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x, y (m), yaw (rad)
    frame_id: str = "map"
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def rows(self) -> int:
        return int(self.data.shape[0])

    @property
    def cols(self) -> int:
        return int(self.data.shape[1])

    def cell_center(self, row: int | np.ndarray, col: int | np.ndarray) -> np.ndarray:
        """Map-frame (x, y) of cell centres; works on arrays too (returns ``(..., 2)``)."""
        gx = (np.asarray(col, dtype=np.float64) + 0.5) * self.resolution
        gy = (self.rows - np.asarray(row, dtype=np.float64) - 0.5) * self.resolution
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        return np.stack([x0 + c * gx - s * gy, y0 + s * gx + c * gy], axis=-1)

    def cell_of(self, x: float | np.ndarray, y: float | np.ndarray) -> tuple[Any, Any]:
        """(row, col) containing map-frame point(s); may be outside the grid (check bounds)."""
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = np.asarray(x, dtype=np.float64) - x0, np.asarray(y, dtype=np.float64) - y0
        gx, gy = c * dx + s * dy, -s * dx + c * dy
        col = np.floor(gx / self.resolution).astype(int)
        row = self.rows - 1 - np.floor(gy / self.resolution).astype(int)
        if np.ndim(row) == 0:
            return int(row), int(col)
        return row, col

    def inside(self, row: int, col: int) -> bool:
        return 0 <= row < self.rows and 0 <= col < self.cols


def same_geometry(a: Any, b: Any) -> bool:
    """Whether two grids put their cells at the same places (shape, resolution, origin, frame):
    a cell index means a place only on the grid it was planned on."""
    return (
        b is not None
        and np.shape(a.data) == np.shape(b.data)
        and a.resolution == b.resolution
        and tuple(a.origin) == tuple(b.origin)
        and a.frame_id == b.frame_id
    )


def write_map(yaml_path: str | Path, grid: Grid, image_name: str | None = None) -> Path:
    """Write ``grid`` as map_server YAML + binary PGM (trinary); returns the YAML path."""
    yaml_path = Path(yaml_path)
    # the pair replaces the old pair together: a YAML whose origin or size no longer matches
    # its PGM would put a loading map_server's obstacles in the wrong place
    write_together(map_writers(yaml_path, grid, image_name))
    return yaml_path


def map_writers(
    yaml_path: str | Path, grid: Grid, image_name: str | None = None
) -> dict[Path, Callable[[Path], object]]:
    """The writers of ``grid``'s PGM and YAML for :func:`~wheelgrid_common.fileio.write_together`
    (PGM first), so that a caller can replace them together with other files of the same
    result: the grid stage's two maps and their picture are one set, not two pairs."""
    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    pix = np.full(grid.data.shape, PIX_UNKNOWN, dtype=np.uint8)
    pix[grid.data == FREE] = PIX_FREE
    pix[grid.data == OCCUPIED] = PIX_OCCUPIED
    doc = {
        "image": image_name,
        "mode": "trinary",
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": OCCUPIED_THRESH,
        "free_thresh": FREE_THRESH,
    }
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
    if grid.meta:
        meta = yaml.safe_dump(grid.meta, default_flow_style=True, width=float("inf")).strip()
        text += "# wheelgrid: " + meta.replace("\n", " ") + "\n"
    return {
        yaml_path.parent / image_name: lambda p: write_pgm(p, pix),
        yaml_path: lambda p: p.write_text(text),
    }


def write_pgm(path: str | Path, pixels: np.ndarray) -> None:
    """Binary (P5) 8-bit PGM, row 0 at the top."""
    pix = np.asarray(pixels, dtype=np.uint8)
    with open(path, "wb") as fh:
        fh.write(f"P5\n{pix.shape[1]} {pix.shape[0]}\n255\n".encode("ascii"))
        fh.write(np.ascontiguousarray(pix).tobytes())


def read_pgm(path: str | Path) -> np.ndarray:
    """Read a P5 or P2 PGM (8 or 16 bit) as a 2D array scaled to 0..255."""
    raw = Path(path).read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4 and pos < len(raw):
        while pos < len(raw) and raw[pos : pos + 1].isspace():
            pos += 1
        if raw[pos : pos + 1] == b"#":
            pos = raw.find(b"\n", pos) + 1 or len(raw)
            continue
        start = pos
        while pos < len(raw) and not raw[pos : pos + 1].isspace():
            pos += 1
        if pos > start:
            tokens.append(raw[start:pos])
    if len(tokens) < 4 or tokens[0] not in (b"P5", b"P2"):
        raise ValueError(f"{path}: not a PGM (P5 or P2) image")
    try:
        magic, width, height, maxval = tokens[0], *(int(t) for t in tokens[1:4])
    except ValueError:
        raise ValueError(f"{path}: bad PGM header (size and maxval are not numbers)") from None
    if width < 1 or height < 1 or not 1 <= maxval <= 65535:
        raise ValueError(f"{path}: bad PGM header ({width}x{height}, maxval {maxval})")
    if magic == b"P5":
        dtype = np.dtype(">u2" if maxval > 255 else "u1")
        data = raw[pos + 1 :]
        # frombuffer's own error for a short file was "buffer is smaller than requested size"
        body = np.frombuffer(
            data, dtype=dtype, count=min(width * height, len(data) // dtype.itemsize)
        )
    else:
        try:
            body = np.array([int(t) for t in raw[pos:].split()[: width * height]], dtype=np.int64)
        except ValueError:  # printed the raw bytes it choked on
            raise ValueError(f"{path}: P2 (text) PGM whose pixels are not numbers") from None
    if body.size != width * height:
        raise ValueError(f"{path}: truncated ({body.size} of {width * height} pixels)")
    if int(body.max()) > maxval:  # scaled past 255, an unknown gray read as free
        raise ValueError(f"{path}: a pixel of {int(body.max())} exceeds maxval {maxval}")
    img = body.reshape(height, width).astype(np.float64)
    return img * (255.0 / maxval)


def read_image(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """A non-PGM map image as nav2_map_server's GraphicsMagick sees it: the plain mean of R, G
    and B scaled to 0..255 whatever the bit depth, and the alpha (0..255, 255 = opaque) where
    the image has one, else None.

    PIL's ``convert("L")`` weighted the channels (a yellow pixel, unknown for map_server, read
    as free), clipped 16-bit samples at 255 (map_saver's unknown gray read as white: free) and
    dropped the alpha (map_saver's scale mode writes unknown cells transparent)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            if im.mode.startswith("I;16"):
                return np.asarray(im, dtype=np.float64) * (255.0 / 65535.0), None
            if im.mode in ("I", "F"):  # 32-bit samples: no scale map_server would agree on
                raise ValueError(f"{path}: {im.mode} (32-bit) images are not read as maps")
            has_alpha = im.has_transparency_data
            rgba = np.asarray(im.convert("RGBA"), dtype=np.float64)
    except UnidentifiedImageError as exc:
        raise ValueError(f"{path}: not an image ({exc})") from exc
    except Image.DecompressionBombError as exc:
        # a few KB of PNG that unpacks to gigabytes (over ~179 M pixels): a traceback, exit 1,
        # from `wheelgrid plan` and the drive's --grid (a review)
        raise ValueError(f"{path}: too large to read as a map ({exc})") from exc
    return rgba[..., :3].mean(axis=2), rgba[..., 3] if has_alpha else None


def _is_finite_number(value: Any) -> bool:
    """A YAML int or float that is finite (YAML's true/false are not numbers here)."""
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def _number(doc: dict[str, Any], key: str, default: float, path: Path) -> float:
    value = doc.get(key, default)
    if not _is_finite_number(value):
        raise ValueError(f"{path}: {key} must be a finite number, not {value!r}")
    return float(value)


def read_map(yaml_path: str | Path) -> Grid:
    """Load a map_server YAML the way nav2_map_server does (trinary / scale / raw).

    Every field is checked (a null origin, a zero resolution, a threshold above 1 are
    errors, not tracebacks or a mirrored map), and two readings that would make a cell free
    that is not are refused or corrected: ``free_thresh >= occupied_thresh`` (the free test
    overwrote occupied cells), and in trinary mode map_saver's unknown gray (205), which any
    ``free_thresh`` above 0.196 (Nav2 map_saver's default is 0.25) reads as free, stays
    unknown here (occupied where ``occupied_thresh`` makes it so, as in Nav2)."""
    yaml_path = Path(yaml_path)
    if yaml_path.is_file():
        with yaml_path.open("rb") as f:
            head = f.read(8)
        if head.startswith((b"P5", b"P2", b"\x89PNG")):  # read as YAML: "#x0000", "binary"
            raise ValueError(
                f"{yaml_path}: an image, not a map_server YAML: give the .yaml that names it "
                "(wheelgrid grid writes grid.yaml beside grid.pgm)"
            )
    doc = read_yaml(yaml_path)
    if not isinstance(doc, dict) or "image" not in doc or "resolution" not in doc:
        raise ValueError(f"{yaml_path}: not a map_server YAML (needs image and resolution)")
    if not isinstance(doc["image"], str) or not doc["image"]:
        raise ValueError(f"{yaml_path}: image must be a file name, not {doc['image']!r}")
    resolution = _number(doc, "resolution", 0.0, yaml_path)
    if resolution <= 0:
        raise ValueError(f"{yaml_path}: resolution must be > 0, not {resolution}")
    occ_t = _number(doc, "occupied_thresh", OCCUPIED_THRESH, yaml_path)
    free_t = _number(doc, "free_thresh", FREE_THRESH, yaml_path)
    if not 0.0 <= free_t < occ_t <= 1.0:
        raise ValueError(
            f"{yaml_path}: need 0 <= free_thresh < occupied_thresh <= 1, got {free_t} and {occ_t}"
        )
    mode = str(doc.get("mode", "trinary")).lower()
    if mode not in ("trinary", "scale", "raw"):
        raise ValueError(f"{yaml_path}: mode must be trinary, scale or raw, not {mode!r}")
    negate = doc.get("negate", 0)
    if negate not in (0, 1):  # True and False compare equal to 1 and 0
        raise ValueError(f"{yaml_path}: negate must be 0 or 1, not {negate!r}")
    origin = doc.get("origin", [0.0, 0.0, 0.0])
    if (
        not isinstance(origin, list)
        or len(origin) not in (2, 3)
        or not all(_is_finite_number(v) for v in origin)
    ):
        raise ValueError(
            f"{yaml_path}: origin must be [x, y, yaw] of finite numbers, not {origin!r}"
        )
    image_path = Path(doc["image"])
    if not image_path.is_absolute():
        image_path = yaml_path.parent / image_path
    alpha: np.ndarray | None = None
    if image_path.suffix.lower() == ".pgm":
        img = read_pgm(image_path)
    else:
        img, alpha = read_image(image_path)
    if mode == "raw":
        # map_server: round(shade * 255) is the cell's value; negate plays no part in raw mode
        value = np.rint(img)
        data = np.where((value >= 0) & (value <= 100), value, UNKNOWN).astype(np.int8)
    else:
        # map_server averages the alpha in with R, G and B in trinary mode (transparent darkens)
        shade = (img if alpha is None or mode != "trinary" else (3.0 * img + alpha) / 4.0) / 255.0
        occ = shade if negate else 1.0 - shade
        data = np.full(img.shape, UNKNOWN, dtype=np.int8)
        data[occ > occ_t] = OCCUPIED
        data[occ < free_t] = FREE
        if mode == "scale":
            mid = (occ >= free_t) & (occ <= occ_t)
            scaled = np.rint(100.0 * (occ[mid] - free_t) / (occ_t - free_t))
            # map_server rounds a shade just past free_thresh to 0, free: the unknown gray 205
            # (occ 0.19608 against 0.196) read free, and the planner routed through it. Between
            # the thresholds is never free here (1 at least: not free, to every reader).
            data[mid] = np.maximum(scaled, 1.0).astype(np.int8)
            if alpha is not None:  # map_saver's scale mode writes unknown as transparent
                data[alpha < 255.0] = UNKNOWN
        else:
            gray = 255.0 - PIX_UNKNOWN if negate else PIX_UNKNOWN
            # only where the thresholds do not make it occupied: with occupied_thresh at or
            # under 0.196 (the gray's occupancy is 0.19608) Nav2 reads it occupied, and an
            # unknown start cell is allowed (a plan started in a cell Nav2 calls occupied)
            data[(np.rint(img) == gray) & (data != OCCUPIED)] = UNKNOWN
    return Grid(
        data=data,
        resolution=resolution,
        origin=(float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) > 2 else 0.0),
    )


def to_occupancy_grid(grid: Grid, stamp: Any = None) -> Any:
    """Grid -> rclpy nav_msgs/OccupancyGrid (row-major from the bottom row, as ROS expects)."""
    from nav_msgs.msg import OccupancyGrid

    msg = OccupancyGrid()
    msg.header.frame_id = grid.frame_id
    if stamp is not None:
        msg.header.stamp = stamp
        msg.info.map_load_time = stamp
    msg.info.resolution = float(grid.resolution)
    msg.info.width = grid.cols
    msg.info.height = grid.rows
    x0, y0, yaw = grid.origin
    msg.info.origin.position.x = float(x0)
    msg.info.origin.position.y = float(y0)
    msg.info.origin.orientation.z = math.sin(yaw / 2.0)
    msg.info.origin.orientation.w = math.cos(yaw / 2.0)
    msg.data = np.flipud(grid.data).astype(np.int8).ravel().tolist()
    return msg


MAX_ORIGIN_TILT_DEG = 1.0  # rounding in another tool's quaternion, not a grid off the floor


def from_occupancy_grid(msg: Any) -> Grid:
    """nav_msgs/OccupancyGrid (rclpy or rosbags) -> Grid in image orientation."""
    rows, cols = int(msg.info.height), int(msg.info.width)
    flat = np.asarray(msg.data, dtype=np.int8)
    if flat.size != rows * cols:
        raise ValueError(f"OccupancyGrid has {flat.size} cells, info says {rows}x{cols}")
    q = msg.info.origin.orientation
    res = float(msg.info.resolution)
    position = (float(msg.info.origin.position.x), float(msg.info.origin.position.y))
    quat = (float(q.x), float(q.y), float(q.z), float(q.w))
    # A NaN or zero resolution or origin puts every cell nowhere: taken as valid, the drive
    # node checked a plan's cells against it and let the plan run to its end.
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"OccupancyGrid resolution {res} is not a finite size > 0")
    if not all(math.isfinite(v) for v in (*position, *quat)) or math.hypot(*quat) < 1e-6:
        raise ValueError(f"OccupancyGrid origin {position}, orientation {quat} is not a pose")
    # A grid lies on the floor: its origin turns about z only. A roll of 180 deg (the grid's
    # +y along the map's -y) was read as yaw 0, a mirror image, and routes went out that the
    # real origin put outside the grid (a review).
    tilt = 2.0 * math.degrees(math.asin(min(1.0, math.hypot(quat[0], quat[1]) / math.hypot(*quat))))
    if tilt > MAX_ORIGIN_TILT_DEG:
        raise ValueError(
            f"OccupancyGrid origin orientation {quat} tilts the grid {tilt:.1f} deg out of the "
            f"floor (more than {MAX_ORIGIN_TILT_DEG:g}): a grid's origin turns about z only"
        )
    # normalised first: the unit formula read a 90 deg origin at a third of unit length as
    # 5.6 deg, and put start and goal in other cells
    yaw = quat_yaw(*quat)
    return Grid(
        data=np.flipud(flat.reshape(rows, cols)).copy(),
        resolution=float(msg.info.resolution),
        origin=(float(msg.info.origin.position.x), float(msg.info.origin.position.y), yaw),
        frame_id=str(msg.header.frame_id) or "map",
    )


def grid_identity(grid: Any) -> dict[str, Any]:
    """What a plan's cell indices mean: the grid's shape, cell size, origin and a digest of
    its cells. A plan holds indices only, and one made on 1.2 m cells was driven on a grid of
    0.6 m cells (half of every step) with exit 0; `wheelgrid drive --grid` compares this."""
    import hashlib

    data = np.ascontiguousarray(grid.data, dtype=np.int8)
    return {
        "rows": int(data.shape[0]),
        "cols": int(data.shape[1]),
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "cells_sha256": hashlib.sha256(data.tobytes()).hexdigest(),
    }
