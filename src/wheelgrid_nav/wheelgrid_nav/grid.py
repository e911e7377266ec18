"""The safe 2D grid map (the paper's section II.B), ROS-free: levelled 3D map -> wheelchair cells.

Pipeline, with the paper's equation numbers:

1. Height band: keep points with ``floor_clearance < z <= safe_height`` (the paper's safe height
   δ = 1.5 m: a bar at 1.5116 m is removed so the chair passes under it, one at 0.77 m stays).
2. Orthographic projection onto the floor (eq 8: drop z).
3. Rasterise to a fine obstacle image A of ``pixel_size`` pixels (black = obstacle).
4. Tile A into cells of m x n pixels (the chair's safe footprint, 1.2 m) and compute the black
   pixel density σ_i (eq 9); a cell is occupied when σ_i > ``density_threshold`` (eq 10).

What the paper leaves out and a wheelchair needs (a person's body rides on this map):

- **Unknown is not free.** A cell is free only where the floor was actually observed (points near
  z = 0) over ``min_observed_fraction`` of its area; otherwise it is unknown (-1).
- **Thin-obstacle guard.** A 5 cm post or a bar crossing a 1.2 m cell has a density far below any
  useful δ, yet the chair would hit it. Any black pixel that is part of a continuous obstacle
  (its 15 cm neighbourhood holds ``guard_min_points`` points: a bar, a rim, a pole whose points
  stack over its height) makes its cell occupied; lone noise speckles only count in σ_i.
  A rod, rope or cable under ~2 cm thick leaves one line of points at the map's 2 cm voxels
  (density 0.038, 7-8 points a neighbourhood: missed by both); the guard's line rule catches
  it when its pixels with ``guard_line_min_points`` in their neighbourhood chain over
  ``guard_line_length`` (30 cm). Measured: a 1.1 m rope at 80 cm, a 40 cm rod at 1.2 m and a
  cable at 30 cm occupy their cell; 22-40 noise points packed in a 20 cm strip along a cell
  made a guard-only cell in 0-1.5 % of 200 draws each, spread over the cell in none; on the
  bundled bag's map, the real iPhone room and the two PCL laser scans no 1.2 m cell changed.
  Still missed: a rod shorter than 30 cm, and a rope the map samples coarser than 3 cm (a
  1.1 m rope: caught 20 of 20 draws at 2.5 cm spacing, 18 at 3 cm, none at 3.5 cm).
- **Drops.** Points well below the floor (a step down, a hole) are obstacles too.
- **Alignment.** Cells are laid along the dominant wall direction (or the map axes) so that
  1.2 m cells line up with corridors; the 90-degree ambiguity is resolved by taking the rotation
  closest to the map axes (|yaw| <= 45 deg).
- **Extent and phase from the observed floor.** The grid covers the robust extent of the floor
  points, snapped to whole cells and centred on it, so cells coincide with the room interior.
- **Boundary rule.** Obstacle pixels within ``boundary_margin`` of the grid's outer edge are the
  room's walls (the boundary), not content of the border cells: the walls lie outside the cells,
  and a phase error of a pixel or two must not turn the whole border ring into obstacles. Side
  by side, where the grid reaches past the observed floor's end that strip is added to the
  margin, since the walls stand where the floor ends, and where the floor goes on past the
  grid's edge (the extent snapped down, no wall there) the strip shrinks by as much; no side's
  strip is ever deeper than ``MAX_BOUNDARY_MARGIN`` (:func:`boundary_widths`). Only obstacles
  lying *entirely* inside the strip are affected; anything reaching further in still occupies
  its cell, and a rod or rope reaching in from a wall is measured from the wall (through the
  black pixels that continue it into the strip, :func:`linear_obstacles`). The cost: an
  obstacle no deeper than the strip standing against a wall (a radiator, a shelf) is not seen.
  The chair (100 x 80 cm) in its safe cell (120 x 120 cm) clears it by 10 cm along its length
  and 20 cm along its width; the default margin, 15 cm (measured on the mapped bundled bag: a
  scanned wall's thickness plus the grid's phase error), is above the first, and no strip
  deeper than ``MAX_BOUNDARY_MARGIN`` (the second) is used, nor a margin over it accepted. The
  README says so too.

Everything is vectorised numpy (bincount rasterisation, reshaped cell sums) so a 1.3 M point
map becomes a grid in well under 0.2 s on two cores.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from wheelgrid_common.map_io import CHAIR_SIZE_M, FREE, OCCUPIED, UNKNOWN, Grid, chair_cell_problem
from wheelgrid_common.params import check_bounds, check_finite, field

ALIGNMENTS = ("walls", "map")

# A pixel whose points spread this much in height (standard deviation, m) is a vertical surface
# (a wall, a post, a table leg); table tops and the ceiling are flat and would bias the wall
# direction search towards 45 degrees, so only vertical pixels vote.
_VERTICAL_STD = 0.08
# Points used at most for the wall-direction search (a regular stride keeps it deterministic).
_ALIGN_MAX_POINTS = 80_000
_ALIGN_REFINE_POINTS = 12_000
_EXTENT_MAX_POINTS = 200_000
# Share of a wall peak's points in the obstacle band below which it does not stand on the floor
# (a room wall: ~60 %; one half behind furniture still ~30 %; a bulkhead over a drop: 0).
_WALL_MIN_STANDING = 0.1
# Largest grid side accepted (m): 200 m at 5 cm pixels is 16 M pixels. The build's peak is
# several times its rasters: `wheelgrid grid` on a 140 m square floor (7.8 M pixels) peaked at
# 0.82 GB with its floor sampled every 20 cm, 1.63 GB (build_grid alone) with a point in
# every pixel; before the floor patches were labelled in int32, 1.39 and 3.24 GB (a review
# measured 2.8 GB on a 200 m floor then).
_MAX_EXTENT = 200.0
_MAX_COORDINATE = 50_000.0  # m from the origin: beyond it the float32 pass loses millimetres
_MAX_PIXELS = 40_000_000  # the raster of one build: 200 m x 200 m at 3.2 cm pixels
# A room scan shows walls or furniture: with fewer of its points above the floor band than
# this, the map was flattened (z = 0) or is not levelled, and every cell would read free.
_MIN_ABOVE_FLOOR_FRACTION = 0.005
# A levelled scan has few points under its floor (noise, a step down); more than this share
# of the map there, and its floor is probably not at z = 0.
_MANY_DROPS = 0.1
# Indoor scans rise 2-4 m above their floor; higher, the map is probably not z-up.
_TALL_MAP_M = 5.0
MIN_PIXEL_SIZE = 0.01  # m
# m: the mapper's map_voxel, the spacing of the line of map points a rope or a cable leaves
LINE_MAP_SPACING = 0.02
GUARD_LINE_MIN_POINTS = 5  # guard_line_min_points' default: ~7.5 such points in 3 x 5 cm pixels
MIN_SAFE_HEIGHT = 0.9  # m: no wheelchair user sits lower (a child's chair seat ~45 cm + torso)
MAX_FLOOR_CLEARANCE = 0.15  # m: above it, a step is an obstacle to a wheelchair
# m: the deepest step down that may be read as floor. drop_depth 0 ("disables") or 0.7 m made
# the bottom of a 60 cm pit observed floor, and its cell free.
MAX_DROP_DEPTH = 0.15
# A floor leaning more than this is warned of: heights are read against one level z = 0, and
# at 0.5 deg the floor 3 m away is 2.6 cm off it (half of floor_clearance).
MAX_FLOOR_TILT_DEG = 0.5
# ... and so is a lean that puts any part of the map more than this (m) off z = 0, however
# small its angle: 0.45 deg across a 14 m room is 5.7 cm at its ends, and a 9 cm kerb on the
# low side read as floor, a 13 cm step down on the high side too, with no word (a review).
MAX_FLOOR_RISE = 0.026
MAX_UNOBSERVED_PATCH = 0.8  # the chair's width: a wider unseen square is no hole under it
_TILT_SAMPLE = 20_000  # floor points a plane fit needs (a regular subsample)
MAX_FLOOR_FILL_M = 0.2  # m of floor that gap-filling may invent
# m: how much wider than unobserved_patch an unseen hole may be and still lie under a free
# cell (GridConfig.hidden_hole), as at the defaults (5 cm pixels, floor_fill 1: a 35 cm patch,
# 55 cm holes), which bench/grid_holes.py and the README's Safety section measure
MAX_RASTER_LOSS = 0.2
MAX_EXTENT_TOLERANCE = 0.25  # m (the default): the grid reaches half of it past the floor seen
# m: the boundary rule's strip may hide an obstacle this deep against a wall; (120 - 80) / 2 cm,
# the chair's clearance along its width in its safe cell. "At most a cell" (1.2 m) emptied the
# obstacles of every border cell: the paper room's tables at (3, 0) and (5, 0) read free.
MAX_BOUNDARY_MARGIN = 0.2
MAX_CELL_PIXELS = 10_000  # pixels per cell side: 500 m cells of 5 cm pixels
# height_classes: number of thresholds (-drop_depth, floor_clearance, safe_height) below z ->
# class (drop 2, floor 0, band 1, above 3).
_CLASS_OF_LEVEL = np.array([2, 0, 1, 3], dtype=np.uint8)


class GridError(ValueError):
    """A map that cannot give a safe grid; ``cause`` is stable (for log-once), str() says why."""

    def __init__(self, cause: str, detail: str) -> None:
        super().__init__(detail)
        self.cause = cause
        self.detail = detail


@dataclass
class GridConfig:
    """Every parameter of the safe grid (CLI YAML keys and ROS parameters alike)."""

    safe_height: float = field(
        1.5,
        "safe height (the paper's height δ): points above it are removed so the chair may pass "
        f"under them; set it to at least the seated user's height (>= {MIN_SAFE_HEIGHT} m)",
        "m",
        bounds=(MIN_SAFE_HEIGHT, math.inf),
    )
    floor_clearance: float = field(
        0.05,
        "points at or below this height are floor (observed free space), not obstacles",
        "m",
        bounds=(0.0, MAX_FLOOR_CLEARANCE),
    )
    drop_depth: float = field(
        0.10,
        "points this far or more below the floor are a drop (a step down, a hole) and block like "
        f"obstacles; in (0, {MAX_DROP_DEPTH}]: anything shallower is read as floor",
        "m",
        bounds=(0.0, MAX_DROP_DEPTH),
    )
    pixel_size: float = field(
        0.05,
        "side of a fine obstacle-image pixel (and of /map)",
        "m",
        bounds=(MIN_PIXEL_SIZE, math.inf),
    )
    cell_size: float = field(
        1.2,
        f"side of a grid cell: the chair's safe footprint, at least the chair's {CHAIR_SIZE_M:g} m "
        "length; a whole number of pixels",
        "m",
        bounds=(CHAIR_SIZE_M, math.inf),
    )
    density_threshold: float = field(
        0.05,
        "the paper's density threshold δ (eq 10): a cell whose fraction of black pixels exceeds "
        "it is occupied",
        "fraction",
        bounds=(0.0, 1.0),
    )
    min_points_per_pixel: int = field(
        1,
        "points needed in a pixel to make it black (an obstacle pixel); at most "
        "guard_line_min_points, or thin obstacles vanish",
        "points",
        bounds=(1, math.inf),
    )
    thin_obstacle_guard: bool = field(
        True,
        "mark a cell occupied when a continuous obstacle (a post, a bar, a table edge) lies in "
        "it, whatever its density (off = the paper's eq 10 alone)",
    )
    guard_min_points: int = field(
        12,
        "guard: points within a black pixel's 3x3 neighbourhood (15 cm square at 5 cm pixels) "
        "that make it part of a continuous obstacle -- a bar, a table rim, or a pole whose points "
        "stack up over its height; scattered noise (one or two points) stays below it and only "
        "counts in the density. Assumes map voxels <= 3 cm; lower it for coarser maps",
        "points",
        bounds=(1, math.inf),
    )
    guard_line_min_points: int = field(
        GUARD_LINE_MIN_POINTS,
        "guard: points within a black pixel's 3x3 neighbourhood that make it a link of a line "
        "(a rod, rope or cable leaving one line of map points: about 7 at 2 cm map voxels; a "
        "row of lone noise points gives 3)",
        "points",
        bounds=(1, math.inf),
    )
    guard_line_length: float = field(
        0.3,
        "guard: links (see guard_line_min_points) 8-connected over at least this length along "
        "their longest axis are a linear obstacle and occupy every cell they touch; 0 disables",
        "m",
    )
    min_observed_fraction: float = field(
        0.8,
        "fraction of a cell's area where floor or obstacles were observed for it to be free; "
        "less makes it unknown",
        "fraction",
        bounds=(0.5, 1.0),
    )
    unobserved_patch: float = field(
        0.35,
        "a cell is not free where a square of this side (off the wall strip) with neither "
        "floor nor an obstacle seen reaches into it: a hole, a drop, or floor hidden behind "
        "something (0: off)",
        "m",
        bounds=(0.0, MAX_UNOBSERVED_PATCH),
    )
    floor_fill: int = field(
        1,
        "observed-floor pixels are grown by this many pixels to close sampling gaps between "
        "floor points (not real unobserved areas)",
        "pixels",
        bounds=(0, math.inf),
    )
    min_floor_points: int = field(
        50,
        "fewer floor points than this means no floor was found (bad input)",
        "points",
        bounds=(1, math.inf),
    )
    alignment: str = field(
        "walls",
        "grid axes: 'walls' (dominant wall direction, |yaw| <= 45 deg) or 'map' (map axes)",
    )
    extent_quantile: float = field(
        0.002,
        "the grid extent is the floor points' [q, 1-q] quantile range per axis (robust to "
        "stray points)",
        "fraction",
        bounds=(0.0, 0.25),
    )
    extent_tolerance: float = field(
        0.25,
        "a floor extent up to this much short of a whole number of cells still counts as that "
        f"many cells (floor points never reach the walls exactly); at most {MAX_EXTENT_TOLERANCE}",
        "m",
        bounds=(0.0, MAX_EXTENT_TOLERANCE),
    )
    boundary_margin: float = field(
        0.15,
        "obstacle pixels within this distance of the grid's outer edge (plus any strip where the "
        "grid reaches past the observed floor) are the walls (the boundary), not content of the "
        "border cells",
        "m",
        bounds=(0.0, MAX_BOUNDARY_MARGIN),
    )
    fine_margin: float = field(
        0.25,
        "the fine map (/map, fine.pgm) extends this far beyond the grid so the walls show",
        "m",
        bounds=(0.0, 5.0),
    )

    def hidden_hole(self) -> float:
        """The widest unseen square (m) that may lie in a free cell's middle, or 0 with
        ``unobserved_patch`` off: the patch as :func:`unobserved_patches` opens with it (an odd
        number of whole pixels), plus on each side the floor ``floor_fill`` grows over the
        hole's edge and the pixel that edge cuts, which holds floor returns and reads seen."""
        if self.unobserved_patch <= 0:
            return 0.0
        ps = self.pixel_size
        side = max(1, round(self.unobserved_patch / ps))
        opened = (2 * ((side - 1) // 2) + 1) * ps
        return opened + 2 * (self.floor_fill + 1) * ps

    def cell_pixels(self) -> int:
        """Pixels per cell side (m = n); ValueError unless cell_size is a whole number of them."""
        if not (math.isfinite(self.cell_size) and math.isfinite(self.pixel_size)):
            raise ValueError(
                f"cell_size and pixel_size must be finite, not {self.cell_size} and "
                f"{self.pixel_size}"
            )
        if self.pixel_size <= 0 or self.cell_size <= 0:
            raise ValueError(
                f"cell_size and pixel_size must be > 0, not {self.cell_size} and {self.pixel_size}"
            )
        k = self.cell_size / self.pixel_size
        # 1e308 / 0.05 is inf, and round(inf) an OverflowError no caller expects: the grid
        # node died at a parameter change, the CLI printed a traceback (a review)
        if not math.isfinite(k) or k > MAX_CELL_PIXELS:
            raise ValueError(
                f"cell_size {self.cell_size} m is more than {MAX_CELL_PIXELS} pixels of "
                f"pixel_size {self.pixel_size} m"
            )
        if abs(k - round(k)) > 1e-6 or k < 1:
            raise ValueError(
                f"cell_size {self.cell_size} m must be a whole number of pixel_size "
                f"{self.pixel_size} m"
            )
        return round(k)

    def validate(self) -> None:
        """Raise ValueError on values that would make the grid meaningless or unsafe.

        Besides the ranges each value needs, three bounds keep a cell from being called free
        on too little: a cell is free only when at least half its area was observed
        (``min_observed_fraction`` 0 made every unseen cell free), and neither ``floor_fill``
        (at most 20 cm of invented floor) nor ``boundary_margin`` (at most
        ``MAX_BOUNDARY_MARGIN``, 20 cm, of obstacles taken for the walls) may stretch what was
        seen. ``drop_depth`` is in (0, 15 cm]: what lies less deep below the floor is floor, so
        0 (which once disabled drops) or a deeper one read a pit's bottom as observed floor.
        ``pixel_size`` is at least 1 cm: a 1 mm raster of a room took 7 GB."""
        check_finite(self)
        self.cell_pixels()
        if problem := chair_cell_problem(self.cell_size):
            raise ValueError(
                f"cell_size must be at least the chair's {CHAIR_SIZE_M:g} m length: {problem}"
            )
        if self.pixel_size < MIN_PIXEL_SIZE:
            raise ValueError(f"pixel_size must be >= {MIN_PIXEL_SIZE} m, not {self.pixel_size}")
        if not 0.5 <= self.min_observed_fraction <= 1.0:
            raise ValueError(
                "min_observed_fraction must be in [0.5, 1]: a cell less than half observed is "
                f"not known to be free (got {self.min_observed_fraction})"
            )
        if self.floor_fill * self.pixel_size > MAX_FLOOR_FILL_M:
            raise ValueError(
                f"floor_fill {self.floor_fill} pixels invents "
                f"{self.floor_fill * self.pixel_size:g} m of floor; at most {MAX_FLOOR_FILL_M} m"
            )
        if self.min_floor_points < 1:
            raise ValueError(f"min_floor_points must be >= 1, not {self.min_floor_points}")
        if not 0.0 <= self.extent_tolerance < self.cell_size:
            raise ValueError("extent_tolerance must be in [0, cell_size)")
        if self.extent_tolerance > MAX_EXTENT_TOLERANCE:
            # the grid reaches half of it past the floor seen, into the wall strip: where no
            # wall stands (a floor that ends at a drop) 1.1 m left 22 cm of it unseen in a free
            # border cell (a review)
            raise ValueError(
                f"extent_tolerance must be <= {MAX_EXTENT_TOLERANCE} m: the grid reaches half "
                "of it past the floor seen, and where the floor ends at a drop, not a wall, "
                f"that edge of a border cell is unseen; not {self.extent_tolerance}"
            )
        if self.boundary_margin > min(MAX_BOUNDARY_MARGIN, self.cell_size):
            raise ValueError(
                f"boundary_margin must be <= {MAX_BOUNDARY_MARGIN} m (and the cell size): "
                f"obstacles within it of the grid's edge are taken for the walls, and "
                f"{self.boundary_margin:g} m hides what stands against them"
            )
        if not 0.0 <= self.fine_margin <= 5.0:
            raise ValueError("fine_margin must be in [0, 5] m")
        if not self.safe_height >= MIN_SAFE_HEIGHT:
            # 0.5 or 0.7 m removed a 75 cm counter top and freed the cells under it
            raise ValueError(
                f"safe_height must be >= {MIN_SAFE_HEIGHT} m (the top of the seated user in the "
                f"chair: what is lower than that is in the way), not {self.safe_height}"
            )
        if not self.safe_height > self.floor_clearance:
            raise ValueError("safe_height must be above floor_clearance")
        if not 0.0 <= self.floor_clearance <= MAX_FLOOR_CLEARANCE:
            # 1 m made the 75 cm tables floor, and their cells free
            raise ValueError(
                f"floor_clearance must be in [0, {MAX_FLOOR_CLEARANCE}] m (a kerb a chair "
                f"cannot climb is an obstacle), not {self.floor_clearance}"
            )
        if not 0.0 < self.drop_depth <= MAX_DROP_DEPTH:
            # less deep is floor: 0 (once "disables") or 0.7 m made the bottom of a 60 cm pit
            # observed floor, and the cell over it free
            raise ValueError(
                f"drop_depth must be in (0, {MAX_DROP_DEPTH}] m (a step down a chair cannot "
                f"take is an obstacle, not floor), not {self.drop_depth}"
            )
        if not 0.0 <= self.density_threshold < 1.0:
            raise ValueError("density_threshold must be in [0, 1)")
        if not (
            self.unobserved_patch == 0.0 or 0.0 < self.unobserved_patch <= MAX_UNOBSERVED_PATCH
        ):
            # -0.35 (a typo) turned the rule off as 0 does, silently; a patch wider than the
            # chair is no longer a hole under it
            raise ValueError(
                f"unobserved_patch must be 0 (off) or in (0, {MAX_UNOBSERVED_PATCH}] m, not "
                f"{self.unobserved_patch}"
            )
        looked_for = max(self.unobserved_patch, self.pixel_size)  # a pixel at the least
        if (hidden := self.hidden_hole()) > looked_for + MAX_RASTER_LOSS + 1e-9:
            # a coarser raster grows the floor seen over a hole's edge by floor_fill's pixels
            # and by the pixel its edge cuts: at 10 cm pixels a 55 cm pit, at 20 cm a 70 cm
            # one, lay under a free cell, with no word (a review)
            raise ValueError(
                f"pixel_size {self.pixel_size:g} m with floor_fill {self.floor_fill} lets an "
                f"unseen hole up to {hidden:.2f} m wide lie under a free cell, more than the "
                f"{looked_for:g} m square looked for (unobserved_patch) + {MAX_RASTER_LOSS} m: "
                "a smaller pixel_size or floor_fill (0 at 10 cm pixels)"
            )
        if self.alignment not in ALIGNMENTS:
            raise ValueError(f"alignment must be one of {ALIGNMENTS}, not {self.alignment!r}")
        if not 0.0 <= self.extent_quantile < 0.25:
            raise ValueError("extent_quantile must be in [0, 0.25)")
        if self.boundary_margin < 0 or self.fine_margin < 0 or self.floor_fill < 0:
            raise ValueError("boundary_margin, fine_margin and floor_fill must be >= 0")
        if self.min_points_per_pixel < 1 or self.guard_min_points < 1:
            raise ValueError("min_points_per_pixel and guard_min_points must be >= 1")
        if self.guard_line_min_points < 1:
            raise ValueError("guard_line_min_points must be >= 1")
        if self.min_points_per_pixel > self.guard_line_min_points:
            # A pixel that needs more points than a thin line leaves in it is no pixel of a
            # bar, a rope or a table edge, for the density and the guard alike: 12 (at 3 cm
            # map voxels) lost three occupied cells of the paper room, 20 four.
            raise ValueError(
                f"min_points_per_pixel ({self.min_points_per_pixel}) must be <= "
                f"guard_line_min_points ({self.guard_line_min_points}), the points a thin "
                "obstacle leaves in a pixel: more erases bars and table edges from the grid"
            )
        per_link = 3 * self.pixel_size / LINE_MAP_SPACING
        # (a count raised above the default is the user's own, for a finer map's spacing)
        needed = min(self.guard_line_min_points, GUARD_LINE_MIN_POINTS)
        if self.thin_obstacle_guard and self.guard_line_length != 0.0 and per_link < needed - 1e-9:
            # The counts are per 3x3 pixels: finer pixels leave a rope fewer points there, and
            # at 3 cm (4.5 against 5) ropes, rods and cables at chair height read free, silently.
            raise ValueError(
                f"pixel_size {self.pixel_size:g} m leaves a rope's line of map points "
                f"({LINE_MAP_SPACING * 100:g} cm apart) about {per_link:.1f} points in a link's "
                f"3x3 pixels, under guard_line_min_points ({self.guard_line_min_points}): ropes "
                "and cables would read free; use pixel_size >= "
                f"{needed * LINE_MAP_SPACING / 3:.3g} m or "
                f"guard_line_min_points <= {math.floor(per_link + 1e-9)}"
            )
        if self.guard_line_length != 0.0 and not (
            3 * self.pixel_size - 1e-9 <= self.guard_line_length <= self.cell_size
        ):
            # Shorter than a link's own 3x3 neighbourhood, one clump of points is a "line";
            # longer than a cell, a rope across a cell is not one.
            raise ValueError(
                f"guard_line_length must be 0 (off) or in [3 pixel_size, cell_size] = "
                f"[{3 * self.pixel_size:g}, {self.cell_size:g}] m, not {self.guard_line_length:g}"
            )
        check_bounds(self)  # the ranges the parameters declare; the explanations above first


@dataclass
class GridNodeConfig(GridConfig):
    """The grid node's parameters: the grid's own plus where ``~/save`` writes and how often the
    grid is recomputed. The CLI reads the same YAML (node-only keys are ignored there)."""

    output_dir: str = field(
        "out/grid",
        "folder where ~/save writes grid.yaml/pgm, fine.yaml/pgm and grid.png (~ = home)",
    )
    max_rate_hz: float = field(
        1.0,
        "the grid is recomputed at most this often while the map keeps changing (a 1 M point "
        "map costs about 0.1 s)",
        "Hz",
        bounds=(0.001, 100.0),
    )


@dataclass
class GridResult:
    """The safe grid and the intermediate images (grid frame, image orientation) behind it."""

    grid: Grid  # cells: 0 free, 100 occupied, -1 unknown; origin [x, y, yaw]
    fine: Grid  # fine safe obstacle map in MAP axes (yaw 0, what Nav2 costmaps expect)
    obstacles: np.ndarray  # (H, W) bool: black pixels A counted in the cells (boundary excluded)
    boundary: np.ndarray  # (H, W) bool: obstacle pixels taken as the walls (boundary rule)
    floor: np.ndarray  # (H, W) bool: observed floor (after floor_fill)
    density: np.ndarray  # (rows, cols) σ_i, eq 9
    observed: np.ndarray  # (rows, cols) observed fraction of each cell
    guard: np.ndarray  # (rows, cols) bool: cells the thin-obstacle guard made occupied
    yaw: float  # grid axes in the map frame, rad
    config: GridConfig
    stats: dict[str, Any]


# ---------------------------------------------------------------------------------------------
# The paper's steps as small functions (unit-tested on hand-made data)
# ---------------------------------------------------------------------------------------------


def height_classes(z: np.ndarray, cfg: GridConfig) -> np.ndarray:
    """Per-point class: 0 floor, 1 obstacle in the safe band, 2 drop, 3 above the band (ignored).

    The band is ``floor_clearance < z <= safe_height``: a point exactly at the safe height still
    blocks (the chair's user would touch it). Floor is ``-drop_depth < z <= floor_clearance``,
    a drop ``z <= -drop_depth`` (``drop_depth <= 0``, which :meth:`GridConfig.validate`
    refuses, makes everything low floor).
    Three comparisons summed and a lookup: 3x faster than masked assignments on 1 M points.
    """
    zz = np.asarray(z)
    low = -cfg.drop_depth if cfg.drop_depth > 0 else -np.inf
    level = (zz > low).view(np.uint8) + (zz > cfg.floor_clearance).view(np.uint8)
    level += (zz > cfg.safe_height).view(np.uint8)
    return _CLASS_OF_LEVEL[level]


def project(points: np.ndarray) -> np.ndarray:
    """Orthographic projection onto the floor plane (eq 8: P = diag(1, 1, 0)), ``(N, 2)``."""
    return np.asarray(points)[:, :2]


def cell_density(image: np.ndarray, m: int, n: int) -> np.ndarray:
    """σ_i of eq 9: fraction of black pixels in each m x n tile of a (rows*m, cols*n) image."""
    img = np.asarray(image)
    h, w = img.shape
    if h % m or w % n:
        raise ValueError(f"image {h}x{w} is not a whole number of {m}x{n} cells")
    sums = img.astype(np.float64).reshape(h // m, m, w // n, n).sum(axis=(1, 3))
    return sums / float(m * n)


def classify_density(density: np.ndarray, threshold: float) -> np.ndarray:
    """Eq 10: True (occupied) where σ_i > δ, False (free) where σ_i <= δ."""
    return np.asarray(density) > threshold


def _neighbour_count(img: np.ndarray) -> np.ndarray:
    """Sum over each 3x3 neighbourhood (itself included), zero padded (int32)."""
    p = np.pad(np.asarray(img).astype(np.int32), 1)
    rows = p[:-2] + p[1:-1] + p[2:]
    return rows[:, :-2] + rows[:, 1:-1] + rows[:, 2:]


def _dilate(img: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation with a (2r+1)^2 square, by repeated 3x3 neighbour counts."""
    out = img
    for _ in range(radius):
        out = _neighbour_count(out) > 0
    return out


def obstacle_support(obstacles: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(H, W) points in each pixel's 3x3 neighbourhood, black pixels' points only: what both
    of the guard's rules read (the guard computes it once for the two)."""
    return _neighbour_count(np.where(np.asarray(obstacles, dtype=bool), counts, 0))


def continuous_obstacles(
    obstacles: np.ndarray,
    counts: np.ndarray,
    min_points: int,
    support: np.ndarray | None = None,
) -> np.ndarray:
    """Black pixels that belong to a continuous obstacle (the guard's evidence).

    A black pixel counts when its 3x3 neighbourhood holds at least ``min_points`` points: a bar,
    a wall edge or a table rim crossing the cell has points along it, a thin pole has its points
    stacked over its height in one pixel. A lone speckle of one or two noise points does not:
    it still counts in the density of eq 9, but cannot occupy a cell by itself. ``support``:
    :func:`obstacle_support`, where the caller has it already.
    """
    obs = np.asarray(obstacles, dtype=bool)
    if support is None:
        support = obstacle_support(obs, counts)
    return obs & (support >= min_points)


def _components(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-connected components of a bool image: (rows, cols, component id) of its True pixels.

    Only the True pixels are touched (sorted flat indices and ``searchsorted`` find each one's
    neighbours), so the cost follows the black pixels, not the image. Labels are merged by
    hooking the larger root under the smaller one and compressing paths, until every
    neighbouring pair shares a root: a few rounds even for a line hundreds of pixels long.
    """
    h, w = mask.shape
    # int32 where it fits (the grid's rasters hold at most _MAX_PIXELS): int64 throughout
    # took ~2 GB on a 200 m floor's 16 M pixels (a review)
    index = np.int32 if mask.size < 2**31 - 2 * w - 2 else np.int64
    flat = np.flatnonzero(mask).astype(index)  # sorted
    rows, cols = flat // w, flat % w
    n = flat.size
    if n == 0:
        return rows, cols, np.zeros(0, dtype=np.int64)
    a_all, b_all = [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):  # half the neighbourhood: each pair once
        nr, nc = rows + dr, cols + dc
        inside = (nr < h) & (nc >= 0) & (nc < w)
        key = nr * w + nc
        del nr, nc
        at = np.minimum(np.searchsorted(flat, key), n - 1).astype(index)
        hit = inside & (flat[at] == key)
        a_all.append(np.flatnonzero(hit).astype(index))
        b_all.append(at[hit])
        del key, at, hit, inside
    a = np.concatenate(a_all)
    b = np.concatenate(b_all)
    del a_all, b_all
    lab = np.arange(n, dtype=index)
    while True:
        ra, rb = lab[a], lab[b]
        differ = ra != rb
        if not differ.any():
            break
        ra, rb = ra[differ], rb[differ]
        np.minimum.at(lab, np.maximum(ra, rb), np.minimum(ra, rb))
        while True:  # path compression: every label becomes its tree's root
            nxt = lab[lab]
            if np.array_equal(nxt, lab):
                break
            lab = nxt
    return rows, cols, np.unique(lab, return_inverse=True)[1]


def linear_obstacles(
    obstacles: np.ndarray,
    counts: np.ndarray,
    min_points: int,
    min_length_px: float,
    solid_points: int | None = None,
    support: np.ndarray | None = None,
    boundary: np.ndarray | None = None,
    wall_reach_px: int = 0,
) -> np.ndarray:
    """Black pixels that belong to a linear obstacle: a rod, a rope, a cable (the guard's
    second kind of evidence).

    A rod or a rope under about 2 cm thick leaves a single line of map points at the map's 2 cm
    voxel spacing: two or three points a 5 cm pixel, seven or eight per 3x3 neighbourhood, too
    few for :func:`continuous_obstacles` (12) and a density of about 0.04, under eq 10's δ, in
    the cell it crosses. What tells it from noise is not how many points it has but that they
    *chain*: a black pixel whose 3x3 neighbourhood holds ``min_points`` points is a link, and
    links 8-connected over at least ``min_length_px`` pixels along their principal axis are a
    line. Noise does not chain that way: a flying pixel or a speckle is one or two points with
    empty neighbours (a row of such lone points holds 3 per neighbourhood), and a chain of
    random links ``min_length_px`` long needs that many independent neighbours in a row. The
    extent is measured along the component's principal axis (its longest direction, so a
    diagonal rope counts its whole length and a round blob only its diameter), plus one pixel.

    With ``solid_points`` (the point rule's ``min_points``), pixels that rule already holds are
    no links: a line must be long on its own. Otherwise the thin fringe of a solid obstacle
    (a pixel or two of its scanned edge spilling over a cell border) joined it into one long
    component and occupied the neighbouring cell: on ``make demo``'s map that made truth-free
    cell (4, 3) occupied. A rope tied to a post still counts, from where the post's points end.
    ``support``: :func:`obstacle_support` of ``obstacles | boundary``, where the caller has it
    already.

    ``boundary``: the black pixels of the boundary strip (taken for the walls). A line is
    measured through them too, and kept where at least two of its links lie beyond them, where
    its cell is: a 40 cm rod fixed to a wall lost its first 15 cm to the strip, measured 25 cm,
    under ``guard_line_length``, and its cell read free. Only the pixels beyond the strip are
    marked, so a sparse stretch of the wall itself occupies nothing.

    ``wall_reach_px`` (> 0 with ``boundary``): a line that ends within that many pixels of the
    image's edge it points at is measured on, along its axis, through the black pixels that
    continue it, to where they reach the strip: the wall it is fixed to. Near a wall the wall's
    own points lift a rod's last pixels over ``solid_points``, so they are no links, and a rod
    35-38 cm out of a wall scanned at 2-4 cm read free (measured 25 cm from its first link). A
    line running along a wall points at another edge and is not extended.
    """
    obs = np.asarray(obstacles, dtype=bool)
    edge = np.zeros_like(obs) if boundary is None else np.asarray(boundary, dtype=bool)
    obs = obs | edge
    if support is None:
        support = obstacle_support(obs, counts)
    links = obs & (support >= min_points)
    if solid_points is not None:
        links &= support < solid_points
    out = np.zeros_like(obs)
    rows, cols, comp = _components(links)
    if comp.size == 0:
        return out
    k = int(comp.max()) + 1
    size = np.bincount(comp, minlength=k).astype(np.float64)
    r, c = rows.astype(np.float64), cols.astype(np.float64)
    mr = np.bincount(comp, r, k) / size
    mc = np.bincount(comp, c, k) / size
    dr, dc = r - mr[comp], c - mc[comp]
    srr = np.bincount(comp, dr * dr, k)
    scc = np.bincount(comp, dc * dc, k)
    src = np.bincount(comp, dr * dc, k)
    theta = 0.5 * np.arctan2(2.0 * src, scc - srr)  # principal axis, from the column axis
    proj = dc * np.cos(theta)[comp] + dr * np.sin(theta)[comp]
    order = np.argsort(comp, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(comp[order]) != 0])
    lo = np.minimum.reduceat(proj[order], starts)
    hi = np.maximum.reduceat(proj[order], starts)
    extent = hi - lo + 1.0
    long = extent >= min_length_px - 1e-9
    inner = ~edge[rows, cols]
    if boundary is not None:
        beyond = np.bincount(comp, inner, k) >= 2  # two links past the strip, where the cell is
        long &= beyond
        if wall_reach_px > 0:
            for i in np.flatnonzero(~long & beyond):
                axis = np.array([math.sin(theta[i]), math.cos(theta[i])])
                centre = np.array([mr[i], mc[i]])
                reach = sum(
                    _steps_to_wall(obs, edge, centre + t * axis, sign * axis, wall_reach_px)
                    for t, sign in ((lo[i], -1.0), (hi[i], 1.0))
                )
                long[i] = extent[i] + reach >= min_length_px - 1e-9
    keep = long[comp] & inner
    out[rows[keep], cols[keep]] = True
    return out


def _steps_to_wall(
    black: np.ndarray, edge: np.ndarray, end: np.ndarray, step: np.ndarray, max_steps: int
) -> int:
    """Whole pixel steps from a line's ``end`` (row, col) along ``step`` (a unit vector) through
    black pixels (3x3 around each step) to the last that touches the wall strip ``edge``; 0
    where the line does not point at an edge within ``max_steps`` or its black run ends first."""
    h, w = black.shape
    to_edge = min(
        (end[a] if step[a] < 0 else size - 1 - end[a]) / abs(step[a])
        for a, size in enumerate((h, w))
        if abs(step[a]) > 1e-9
    )
    if to_edge > max_steps:
        return 0  # along a wall, or into the room: not a line fixed to the wall ahead
    last = 0
    for j in range(1, max_steps + 1):
        r, c = (round(float(x)) for x in end + j * step)
        if not (0 <= r < h and 0 <= c < w):
            break
        window = (slice(max(r - 1, 0), r + 2), slice(max(c - 1, 0), c + 2))
        if not black[window].any():
            break
        if edge[window].any():
            last = j
    return last


def thin_obstacle_guard(
    obstacles: np.ndarray,
    counts: np.ndarray,
    m: int,
    n: int,
    min_points: int,
    line_min_points: int = 0,
    line_min_length_px: float = 0.0,
    boundary: np.ndarray | None = None,
    wall_reach_px: int = 0,
) -> np.ndarray:
    """(rows, cols) bool: cells holding any pixel of a continuous or (when
    ``line_min_length_px`` > 0) a linear obstacle; ``boundary``, ``wall_reach_px``: see
    :func:`linear_obstacles`."""
    support = obstacle_support(obstacles, counts)
    solid = continuous_obstacles(obstacles, counts, min_points, support)
    if line_min_length_px > 0:
        # a line is read through the wall strip too, so its support counts the strip's points
        line_support = (
            support
            if boundary is None
            else obstacle_support(np.asarray(obstacles, dtype=bool) | boundary, counts)
        )
        solid |= linear_obstacles(
            obstacles,
            counts,
            line_min_points,
            line_min_length_px,
            solid_points=min_points,
            support=line_support,
            boundary=boundary,
            wall_reach_px=wall_reach_px,
        )
    h, w = solid.shape
    return np.asarray(solid.reshape(h // m, m, w // n, n).any(axis=(1, 3)))


def boundary_ring(shape: tuple[int, int], sides: tuple[int, int, int, int]) -> np.ndarray:
    """(H, W) bool: the outer pixels of the image where the walls are, ``sides`` (top, bottom,
    left, right) pixels deep on each side."""
    ring = np.zeros(shape, dtype=bool)
    h, w = shape
    top, bottom, left, right = sides
    top, bottom = (min(max(x, 0), (h + 1) // 2) for x in (top, bottom))
    left, right = (min(max(x, 0), (w + 1) // 2) for x in (left, right))
    if top:
        ring[:top, :] = True
    if bottom:
        ring[-bottom:, :] = True
    if left:
        ring[:, :left] = True
    if right:
        ring[:, -right:] = True
    return ring


def boundary_widths(
    u0: float,
    v0: float,
    rows: int,
    cols: int,
    floor_u: tuple[float, float],
    floor_v: tuple[float, float],
    cfg: GridConfig,
) -> tuple[float, float, float, float]:
    """The boundary strip's width (m) on each side (top, bottom, left, right): the margin, plus
    how far the grid reaches past the observed floor's end on that side (the walls stand where
    the floor ends), minus how far the floor goes on beyond the grid's edge, within [0,
    ``MAX_BOUNDARY_MARGIN``].

    Per side and capped: taken as half the whole grid's overrun on both sides, a floor left
    unseen under a 25 cm bench along one wall widened the strip on both sides to 25 cm, and
    the bench and a 22 cm cabinet against the opposite wall read free; past 20 cm a strip
    reaches into a centred chair's side clearance. Where the grid stops short of the walls (its
    extent snapped down) the strip shrinks away: no wall stands at that edge, only floor, and a
    post there is content of its cell.
    """
    u1, v1 = u0 + cols * cfg.cell_size, v0 + rows * cfg.cell_size
    over = (v1 - floor_v[1], floor_v[0] - v0, floor_u[0] - u0, u1 - floor_u[1])
    widths = (min(max(cfg.boundary_margin + o, 0.0), MAX_BOUNDARY_MARGIN) for o in over)
    top, bottom, left, right = widths
    return top, bottom, left, right


def _rotate(xy: np.ndarray, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame (x, y) -> grid-frame (u, v), the grid's axes being at ``yaw`` in the map."""
    x, y = xy[:, 0], xy[:, 1]
    if yaw == 0.0:
        return x, y
    dt = xy.dtype.type
    c, s = dt(math.cos(yaw)), dt(math.sin(yaw))
    return c * x + s * y, -s * x + c * y


def _sharpness(px: np.ndarray, py: np.ndarray, angles: np.ndarray, bin_size: float) -> np.ndarray:
    """Σ h_u² + Σ h_v² of the projection histograms of points (px, py) for each angle.

    Walls aligned with an axis pile into a few bins, so the sum of squared bin counts peaks at
    the wall direction (periodic in 90 degrees).
    """
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    r = float(np.hypot(px, py).max()) + bin_size
    nb = int(2 * r / bin_size) + 2
    offs = (np.arange(angles.size) * nb)[:, None]
    u = np.floor((c * px + s * py + r) / bin_size).astype(np.int64) + offs
    v = np.floor((-s * px + c * py + r) / bin_size).astype(np.int64) + offs
    hu = np.bincount(u.ravel(), minlength=angles.size * nb).reshape(angles.size, nb)
    hv = np.bincount(v.ravel(), minlength=angles.size * nb).reshape(angles.size, nb)
    return (hu.astype(np.float64) ** 2).sum(axis=1) + (hv.astype(np.float64) ** 2).sum(axis=1)


def wall_yaw(points: np.ndarray, cfg: GridConfig) -> float | None:
    """Dominant wall direction in the map frame (rad, in (-pi/4, pi/4]); None without walls.

    Votes come from *vertical* pixels only (points spread over height: walls, posts, legs), so
    flat table tops and the ceiling do not pull the answer. Coarse 1.5-degree search over 90
    degrees, then 0.1 and 0.01-degree refinements.
    """
    pts = np.asarray(points)
    sub = pts[:: max(1, math.ceil(pts.shape[0] / _ALIGN_MAX_POINTS))]
    up = sub[:, 2] > cfg.floor_clearance
    sel = sub[up].astype(np.float64)
    # Only around the observed floor (+1 m): a few wild points far away must not blow the
    # raster below up to hundreds of megabytes.
    floor_xy = sub[~up & (sub[:, 2] > -cfg.drop_depth), :2]
    if floor_xy.shape[0] >= 10:
        lo = np.quantile(floor_xy, cfg.extent_quantile, axis=0) - 1.0
        hi = np.quantile(floor_xy, 1.0 - cfg.extent_quantile, axis=0) + 1.0
        x, y = sel[:, 0], sel[:, 1]
        inside = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])
        sel = sel.take(np.flatnonzero(inside), axis=0)
    if sel.shape[0] < 10 or (np.ptp(sel[:, :2], axis=0) > _MAX_EXTENT).any():
        return None
    ps = cfg.pixel_size / 2.0
    x0, y0 = sel[:, 0].min(), sel[:, 1].min()
    ix = np.floor((sel[:, 0] - x0) / ps).astype(np.int64)
    iy = np.floor((sel[:, 1] - y0) / ps).astype(np.int64)
    w = int(ix.max()) + 1
    # Only the pixels that hold points (at most _ALIGN_MAX_POINTS): five float64 images of the
    # whole extent at half a pixel took 8.8 GB for a 90 m floor at 1 cm pixels, before the size
    # checks could refuse it.
    pixels, flat = np.unique(iy * w + ix, return_inverse=True)
    n = np.bincount(flat).astype(np.float64)
    mean = np.bincount(flat, weights=sel[:, 2]) / n
    var = np.bincount(flat, weights=sel[:, 2] ** 2) / n - mean**2
    is_vertical = var > _VERTICAL_STD**2
    vertical = pixels[is_vertical]
    if vertical.size < 10:
        return None
    px = (vertical % w + 0.5) * ps
    py = (vertical // w + 0.5) * ps
    cx, cy = px.mean(), py.mean()
    px -= cx
    py -= cy
    coarse = np.deg2rad(np.arange(-45.0, 45.0, 1.5))
    best = float(coarse[int(np.argmax(_sharpness(px, py, coarse, ps)))])
    fine = best + np.deg2rad(np.arange(-1.5, 1.5001, 0.1))
    best = float(fine[int(np.argmax(_sharpness(px, py, fine, ps)))])
    # Last step on the points of the vertical pixels themselves (pixel centres are quantised to
    # ps, which limits the angle to ~0.1 degree; 0.1 degree is 2 cm over a 10 m room).
    wp = sel[is_vertical[flat]]
    if wp.shape[0] > _ALIGN_REFINE_POINTS:
        wp = wp[:: math.ceil(wp.shape[0] / _ALIGN_REFINE_POINTS)]
    wx = wp[:, 0] - x0 - cx
    wy = wp[:, 1] - y0 - cy
    finest = best + np.deg2rad(np.arange(-0.1, 0.1001, 0.01))
    yaw = float(finest[int(np.argmax(_sharpness(wx, wy, finest, ps / 2.5)))])
    # The answer is periodic in 90 degrees: bring it into (-45, 45] (closest to the map axes).
    quarter = math.pi / 2
    yaw = (yaw + math.pi / 4) % quarter - math.pi / 4
    if yaw <= -math.pi / 4 + 1e-12:
        yaw += quarter
    return yaw


def wall_near(
    coord: np.ndarray,
    end: float,
    reach: float = 0.3,
    bin_size: float = 0.02,
    standing: np.ndarray | None = None,
) -> float:
    """Position of the wall closest to ``end`` along one grid axis, or NaN if none stands out.

    ``coord`` holds that axis' coordinate of the points above the floor (all heights: upper
    walls carry no furniture). A wall is a sharp peak of their histogram; the floor's own
    extent stops short of it (the floor at a wall's foot is often unseen), so the walls place
    the cells more exactly than the floor does. ``standing`` (bool, per point): the points in
    the obstacle band; a peak with under :data:`_WALL_MIN_STANDING` of its points there does
    not stand on the floor (a bulkhead, a lintel or a sign over a stairwell) and is no wall:
    taken for one, it stretched the grid over the drop beyond the floor's edge, where the
    strip hid 18-28 cm of the drop in a free border cell.
    """
    inside = (coord > end - reach) & (coord < end + reach)
    sel = coord[inside]
    if sel.size < 50:
        return math.nan
    edges = np.arange(end - reach, end + reach + bin_size, bin_size)
    hist, _ = np.histogram(sel, bins=edges)
    i = int(np.argmax(hist))
    if hist[i] < max(25, 4.0 * float(np.median(hist)) + 1.0):
        return math.nan
    at_peak = np.abs(sel - (edges[i] + bin_size / 2)) <= 1.5 * bin_size
    if standing is not None and np.mean(standing[inside][at_peak]) < _WALL_MIN_STANDING:
        return math.nan
    return float(np.median(sel[at_peak]))


def floor_extent(
    u: np.ndarray,
    v: np.ndarray,
    cfg: GridConfig,
    walls_u: np.ndarray | None = None,
    walls_v: np.ndarray | None = None,
    walls_standing: np.ndarray | None = None,
) -> tuple[float, float, int, int, tuple[float, float], tuple[float, float]]:
    """Grid lower-left corner (u0, v0), size (rows, cols) and the floor's ends (m) along u, v.

    The robust extent of the floor points (quantiles, so stray points do not stretch it) is
    snapped to a whole number of cells (allowing ``extent_tolerance`` for floor points that stop
    short of the walls) and the grid is centred on it: with a 9.6 m room and 1.2 m cells the
    cells coincide with the room interior and the walls fall on the grid's outer edge.
    ``walls_standing``: which of the wall points lie in the obstacle band (:func:`wall_near`).
    """
    q = cfg.extent_quantile
    qs = [q, 1.0 - q]
    umin, umax = (float(a) for a in np.quantile(u, qs))
    vmin, vmax = (float(a) for a in np.quantile(v, qs))
    out = []
    for lo, hi, walls in ((umin, umax, walls_u), (vmin, vmax, walls_v)):
        tolerance = cfg.extent_tolerance
        if walls is not None and walls.size:
            # walls a little beyond the floor's ends (never inside by more than 10 cm) win
            wl = wall_near(walls, lo, standing=walls_standing)
            wh = wall_near(walls, hi, standing=walls_standing)
            if wl <= lo + 0.1 and wh >= hi - 0.1:
                lo, hi = wl, wh
                # Between walls a border cell holds at least the chair's length of room: the
                # grid, centred, overhangs each wall by at most the chair's clearance in its
                # cell. With the whole tolerance a 4.55 m room got four 1.2 m cells, the walls
                # 12.4 cm inside the border cells, and a free corner cell 95 cm square (a review).
                tolerance = min(tolerance, cfg.cell_size - CHAIR_SIZE_M)
        count = max(1, math.floor((hi - lo + tolerance) / cfg.cell_size + 1e-9))
        out.append(((lo + hi) / 2.0 - count * cfg.cell_size / 2.0, count))
    (u0, cols), (v0, rows) = out
    return u0, v0, rows, cols, (umin, umax), (vmin, vmax)


def _raster_classes(
    u: np.ndarray,
    v: np.ndarray,
    cls: np.ndarray,
    u0: float,
    v0: float,
    ps: float,
    h: int,
    w: int,
) -> np.ndarray:
    """(4, H, W) point counts per class (floor, obstacle, drop, above) in image orientation.

    One bincount over (pixel, class) pairs; points outside the image land in a one-pixel trash
    frame that is cut off afterwards (cheaper than masking 1 M points).
    """
    dt = u.dtype.type
    iu = ((u - dt(u0 - ps)) * dt(1.0 / ps)).astype(np.int32)
    iv = ((v - dt(v0 - ps)) * dt(1.0 / ps)).astype(np.int32)
    # Values below 0 truncate towards 0, i.e. into the trash column/row 0: still outside.
    np.clip(iu, 0, w + 1, out=iu)
    np.clip(iv, 0, h + 1, out=iv)
    flat = ((h + 1 - iv) * (w + 2) + iu) * 4 + cls
    counts = np.bincount(flat, minlength=(h + 2) * (w + 2) * 4).reshape(h + 2, w + 2, 4)
    return counts[1:-1, 1:-1].transpose(2, 0, 1)


def _check_input(points: np.ndarray, cfg: GridConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Finite float32 points and their height classes, or GridError for unusable maps.

    float32 keeps millimetres over kilometres and halves the memory traffic of every pass.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise GridError("bad_shape", f"points must be (N, 3), got {pts.shape}")
    pts = np.ascontiguousarray(pts[:, :3], dtype=np.float32)
    if not np.isfinite(pts).all():
        pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.shape[0] == 0:
        raise GridError("empty", "the map has no (finite) points")
    # float32 spacing beyond _MAX_COORDINATE is over 4 mm (0.5 m at UTM's 5e6 m). A map whose
    # bulk lies there is refused; a few points there are strays (a glitch, a scanner's FLT_MAX
    # "no return" marker) that lie off any indoor grid and are dropped: one of them made the
    # whole room map refused, and in the grid node every later map too.
    # (the per-point mask only where the farthest point calls for it: on 1.3 M points it
    # doubled this check's time, a fifth of the whole grid's)
    if float(np.abs(pts[:, :2]).max()) > _MAX_COORDINATE:
        far = (np.abs(pts[:, :2]) > _MAX_COORDINATE).any(axis=1)
        if 2 * int(np.count_nonzero(far)) > pts.shape[0]:
            dist = float(np.median(np.abs(pts[far, :2]).max(axis=1)))
            raise GridError(
                "too_large",
                f"points lie {dist / 1000:.0f} km from the map origin, where float32 keeps less "
                "than millimetres: re-centre the map (a wheelgrid map's origin is under the "
                "first pose)",
            )
        pts = pts[~far]
    cls = height_classes(pts[:, 2], cfg)
    class_counts = np.bincount(cls, minlength=4)
    if class_counts[3] == pts.shape[0]:
        raise GridError(
            "all_above_band",
            f"all {pts.shape[0]} points are above the safe height {cfg.safe_height} m: the map "
            "is not levelled with z = 0 on the floor, or shows only a ceiling",
        )
    n_floor = int(class_counts[0])
    if n_floor < cfg.min_floor_points:
        raise GridError(
            "no_floor",
            f"no floor found: {n_floor} points within [-{cfg.drop_depth}, {cfg.floor_clearance}] "
            f"m of z = 0 (need {cfg.min_floor_points}); is the map levelled with the floor at "
            "z = 0?",
        )
    n_rest = pts.shape[0] - n_floor
    if n_rest < _MIN_ABOVE_FLOOR_FRACTION * pts.shape[0]:
        raise GridError(
            "only_floor",
            f"only floor: {n_rest} of {pts.shape[0]} points lie outside [-{cfg.drop_depth}, "
            f"{cfg.floor_clearance}] m, where a room scan shows walls and furniture; every "
            "cell would read free. Is the map flattened to z = 0, or not levelled?",
        )
    return pts, cls, class_counts


def map_warnings(z: np.ndarray, drops: int, drop_depth: float) -> list[str]:
    """Doubts about a map that still gives a grid, for the log and the summary. ``drops``: how
    many of the points lie ``drop_depth`` or more under z = 0."""
    out = []
    if drops > _MANY_DROPS * z.size:
        # PCL's room scan, its floor at z = -1.27 m, gave a grid of 48 occupied cells and no
        # word of why: its whole floor read as a drop (safe, but useless)
        out.append(
            f"{100 * drops / z.size:.0f} % of the map lies {drop_depth:g} m or more under "
            "z = 0 and reads as drops (obstacles): is its floor at z = 0? (`wheelgrid grid "
            "--level` finds the floor of a map made elsewhere)"
        )
    high = float(np.quantile(z[:: max(1, z.size // _EXTENT_MAX_POINTS)], 0.99))
    if high > _TALL_MAP_M:
        out.append(
            f"the map rises {high:.1f} m above its floor (99th percentile), where a room scan "
            f"rarely passes 4 m: is it levelled with z up? (a wall read as the floor gives a "
            "grid of free cells)"
        )
    return out


def floor_lean(pts: np.ndarray, cls: np.ndarray) -> tuple[float, float] | None:
    """How far the floor points' plane leans from level (deg), and how far off z = 0 (m) it
    lies at the farthest point of the map below the safe height; None where the floor points
    span less than 2 m (too little to tell a lean from noise)."""
    idx = np.flatnonzero(cls == 0)
    floor = pts.take(idx[:: max(1, math.ceil(idx.size / _TILT_SAMPLE))], axis=0)
    if floor.shape[0] < 100 or np.ptp(floor[:, :2], axis=0).max() < 2.0:
        return None
    centre = floor[:, :2].mean(axis=0)
    a = np.column_stack([floor[:, :2] - centre, np.ones(len(floor))])
    (gx, gy, c0), *_ = np.linalg.lstsq(a, floor[:, 2], rcond=None)
    low = np.flatnonzero(cls != 3)  # the map the grid reads: floor, band, drops
    reach = pts.take(low[:: max(1, math.ceil(low.size / _TILT_SAMPLE))], axis=0)[:, :2] - centre
    rise = float(np.abs(c0 + reach @ np.array([gx, gy])).max())
    return math.degrees(math.atan(math.hypot(gx, gy))), rise


#: Band pixels (8-connected) a patch of them needs to count against an unseen hole: a lone
#: speck (at 5 cm pixels, 9 is a 15 x 15 cm block) does not.
PATCH_MIN_BAND = 9


def band_for_patches(band: np.ndarray, floor_points: np.ndarray) -> np.ndarray:
    """The band pixels :func:`unobserved_patches` takes for seen: not a speck of a few pixels
    with no floor seen beside it. One point in the band over an unseen stairwell (a speck of
    noise, the tip of a cord hanging over it) blocked every 35 cm square the rule could fit,
    and a 70 cm hole's cell read free (a review; 5 of 5 draws). Stricter only: a cell such a
    speck kept free is unknown now, never the reverse. Floor specks: :func:`floor_for_patches`."""
    rows, cols, comp = _components(band)
    if comp.size == 0:
        return band
    small = np.bincount(comp)[comp] < PATCH_MIN_BAND
    lone = small & ~_dilate(floor_points, 1)[rows, cols]
    out = band.copy()
    out[rows[lone], cols[lone]] = False
    return out


#: Pixels with a floor return a patch of seen floor needs to count against an unseen hole: a
#: stray return or two over a stairwell does not.
PATCH_MIN_FLOOR = 3
#: Floor returns this close (m) belong to one patch, whatever the pixel size: at 1 cm pixels
#: each return of a floor sampled every 4 cm was a patch of its own, and no floor counted.
PATCH_FLOOR_REACH = 0.05


def floor_for_patches(
    floor: np.ndarray, floor_points: np.ndarray, pixel_size: float
) -> tuple[np.ndarray, np.ndarray]:
    """The floor :func:`unobserved_patches` takes for seen, and its pixels with a floor return:
    ``floor`` (grown by floor_fill) without its specks, the patches (returns joined within
    PATCH_FLOOR_REACH) holding fewer than PATCH_MIN_FLOOR pixels with a return. One stray
    return at floor height over an unseen 55-65 cm hole blocked every square the rule could
    fit, and the cell read free (a review; 5 of 5 draws). Stricter only: a cell such a speck
    kept free is unknown now, never the reverse. A cable across the hole is a long patch and
    still blocks the squares (README, Safety)."""
    reach = max(1, math.ceil(PATCH_FLOOR_REACH / pixel_size - 1e-9))
    # joined across obstacle pixels too: a return inside one (a streak of flying pixels down
    # to the floor, a cord's end) belongs to the patch around it, and goes with it
    rows, cols, comp = _components(_dilate(floor_points, reach))
    out, returns = floor.copy(), floor_points.copy()
    if comp.size:
        raw = np.bincount(comp, weights=floor_points[rows, cols])[comp]
        speck = raw < PATCH_MIN_FLOOR
        out[rows[speck], cols[speck]] = False
        returns[rows[speck], cols[speck]] = False
    return out, returns


def unobserved_patches(
    floor: np.ndarray, band: np.ndarray, ring: np.ndarray, cfg: GridConfig, k: int
) -> np.ndarray:
    """(rows, cols): cells reached by a square of ``cfg.unobserved_patch`` side, off the wall
    strip, where neither floor nor an obstacle in the band was seen. The observed fraction
    alone let a cell 80 % seen be free with a 68 x 68 cm hole in its middle, right under the
    chair (a stairwell or pit; points seen below the floor count as not floor here, as they
    are: a few sparse returns off a pit's bottom had counted as observed). The strip counts as
    seen: it hides up to 25 cm of an unseen pit against a wall (a 60 x 50 cm pit left its
    border cell free, a review), but counted as seen only where the wall was, the floor along
    the bundled bag's north wall, which the camera does not see, took a free cell of its
    live demo's grid.

    Every cell such a square reaches, not only the one holding its centre: a hole across a
    cell border left the cells beside that one free with 15-25 cm of it inside (a 60 cm hole
    on a four-cell corner, a 56 cm trench along a border, on 3 of 5 noisy draws). A chair in a
    wheelchair-sized cell covers the whole cell, so the hole's edge is under it too. A hole
    reaching 10 cm or less into a cell still leaves it free (``floor_fill`` grows the floor
    seen 5 cm over its edge, and noise a few more; bench/grid_holes.py)."""
    if cfg.unobserved_patch <= 0:
        return np.zeros((floor.shape[0] // k, floor.shape[1] // k), dtype=bool)
    side = max(1, round(cfg.unobserved_patch / cfg.pixel_size))
    hole = ~(floor | band | ring)
    # erosion by a (2r+1)^2 square: a pixel stays where the whole square around it is a hole
    radius = max(0, (side - 1) // 2)
    inner = ~_dilate(~hole, radius) if radius else hole
    # and back out by the same square (an opening): the union of the squares that fit. Not
    # by floor_fill's pixels too, which grew the floor seen over the hole's edge: that caught
    # a hole reaching 8 cm into a cell (10 cm before), but the floor under the chair's start,
    # which the camera never sees, then reached the next cell of the bundled bag's route
    reached = _dilate(inner, radius) if radius else inner
    return cell_density(reached, k, k) > 0


def build_grid(
    points: np.ndarray, cfg: GridConfig | None = None, frame_id: str = "map"
) -> GridResult:
    """The safe 2D grid of a levelled map (``(N, 3)`` metres, z up, floor at z = 0).

    Raises :class:`GridError` (cause ``empty``, ``no_floor``, ``only_floor``, ``all_above_band``,
    ``bad_shape``, ``too_large``)
    for maps that cannot give a safe grid, and ValueError for an invalid config. Never returns a
    grid whose cells are free without observed floor.
    """
    cfg = cfg or GridConfig()
    cfg.validate()
    pts, cls, class_counts = _check_input(points, cfg)
    warnings = map_warnings(pts[:, 2], int(class_counts[2]), cfg.drop_depth)
    lean = floor_lean(pts, cls)
    if lean is not None and (lean[0] > MAX_FLOOR_TILT_DEG or lean[1] > MAX_FLOOR_RISE):
        # heights are read against one z = 0: a 2 deg lean lowered a 9 cm box's top by 4.5 cm
        # into the floor's band on the map's low side, and its cell read free, silently
        warnings.append(
            f"the floor leans {lean[0]:.1f} deg from level, {lean[1] * 100:.1f} cm off z = 0 "
            "at the map's far side: on its low side low obstacles can read as floor, on its "
            "high side floor as obstacles (`wheelgrid grid --level` levels a map made "
            "elsewhere; a live map: check the mapper's levelling)"
        )
    k = cfg.cell_pixels()
    ps = cfg.pixel_size

    yaw = 0.0
    if cfg.alignment == "walls":
        found = wall_yaw(pts, cfg)  # all heights: walls above the band help here
        yaw = 0.0 if found is None else found
    # Points above the floor, for placing the cells between the walls (a regular subsample).
    above = np.flatnonzero(cls % 2 == 1)  # classes 1 (band) and 3 (above the band)
    above = above[:: max(1, math.ceil(above.size / _EXTENT_MAX_POINTS))]
    wu, wv = _rotate(project(pts.take(above, axis=0)), yaw)
    standing = cls.take(above) == 1
    if class_counts[3]:
        # Points above the safe height play no further part (often 30-45 % of a room's map:
        # ceiling and upper walls); dropping them once saves more than it costs.
        keep = np.flatnonzero(cls != 3)  # take() is ~8x faster than boolean row indexing
        pts, cls = pts.take(keep, axis=0), cls.take(keep)
    u, v = _rotate(project(pts), yaw)
    # The extent's quantiles need no more than ~200k floor points: take a regular stride.
    step = max(1, math.ceil(int(class_counts[0]) / _EXTENT_MAX_POINTS))
    floor_pts = cls[::step] == 0
    u0, v0, rows, cols, floor_u, floor_v = floor_extent(
        u[::step][floor_pts], v[::step][floor_pts], cfg, wu, wv, standing
    )
    h, w = rows * k, cols * k
    if max(rows, cols) * cfg.cell_size > _MAX_EXTENT:
        raise GridError(
            "too_large",
            f"the floor spans {rows * cfg.cell_size:.0f} x {cols * cfg.cell_size:.0f} m, more "
            f"than {_MAX_EXTENT:.0f} m: not one indoor map (or not levelled)",
        )
    if h * w > _MAX_PIXELS:
        raise GridError(
            "too_large",
            f"{h} x {w} pixels of {ps} m for a {rows * cfg.cell_size:.0f} x "
            f"{cols * cfg.cell_size:.0f} m floor, more than {_MAX_PIXELS:,}: raise pixel_size",
        )

    counts = _raster_classes(u, v, cls, u0, v0, ps, h, w)
    obstacle_counts = counts[1] + counts[2]
    black = obstacle_counts >= cfg.min_points_per_pixel
    # The boundary rule: the walls are expected where the observed floor ends, side by side
    # (boundary_widths), never more than MAX_BOUNDARY_MARGIN deep.
    sides = boundary_widths(u0, v0, rows, cols, floor_u, floor_v, cfg)
    # rounded, but never past the cap: at 24 cm pixels a 16 cm strip rounded to 24 cm hid a
    # 22 cm deep cabinet against the wall
    cap = math.floor(MAX_BOUNDARY_MARGIN / ps + 1e-9)
    top, bottom, left, right = (min(round(x / ps), cap) for x in sides)
    ring = boundary_ring((h, w), (top, bottom, left, right))
    # A drop is never a wall: a pixel of the strip is taken for the wall only where its band
    # points alone blacken it. Below-floor points there (a stairwell's seen bottom, a dock's
    # edge) stay obstacles of the border cell: the strip, stretched to a bulkhead over the
    # drop, hid 18 cm of a seen 1 m drop in a free border cell.
    band_black = counts[1] >= cfg.min_points_per_pixel
    boundary = black & ring & band_black
    obstacles = black & ~boundary
    # Floor returns seed the floor only where no drop return shares their pixel: a lower
    # level 11 cm down (drop_depth 10) with 1 cm of noise put ~16 % of its returns above -10
    # cm, which grew floor over the unseen strip past a step's edge, and the cell holding
    # 15-25 cm of the step read free on 9-10 of 10 draws (a review)
    floor_seen = (counts[0] > 0) & (_neighbour_count(counts[2]) <= _neighbour_count(counts[0]))
    floor = _dilate(floor_seen, cfg.floor_fill) & ~black

    density = cell_density(obstacles, k, k)
    occupied = classify_density(density, cfg.density_threshold)
    if cfg.thin_obstacle_guard:
        guard = thin_obstacle_guard(
            obstacles,
            obstacle_counts,
            k,
            k,
            cfg.guard_min_points,
            cfg.guard_line_min_points,
            cfg.guard_line_length / ps,
            boundary,
            wall_reach_px=cap + 2,  # the deepest strip, and the wall's scanned thickness
        )
    else:
        guard = np.zeros_like(occupied)
    guard_only = guard & ~occupied
    occupied |= guard
    observed = cell_density(floor | black, k, k)
    # a band speck counts only beside floor that counts: a stray floor return with one point
    # above it (a cord hanging to the floor, a streak of flying pixels) kept each other's
    # speck seen, and the cell over a 60 cm hole read free (a review)
    seen_floor, seen_returns = floor_for_patches(floor, floor_seen, ps)
    patch = unobserved_patches(seen_floor, band_for_patches(band_black, seen_returns), ring, cfg, k)
    data = np.full((rows, cols), UNKNOWN, dtype=np.int8)
    data[(observed >= cfg.min_observed_fraction) & ~patch] = FREE
    data[occupied] = OCCUPIED

    c, s = math.cos(yaw), math.sin(yaw)
    origin = (c * u0 - s * v0, s * u0 + c * v0, yaw)
    # Kept short: map_io.write_map dumps meta as ONE comment line and PyYAML wraps flow mappings
    # at 80 columns, which would break the YAML (the continuation is not commented).
    meta = {
        "safe_height": cfg.safe_height,
        "density_threshold": cfg.density_threshold,
        "yaw_deg": round(math.degrees(yaw), 2),
    }
    grid = Grid(data=data, resolution=cfg.cell_size, origin=origin, frame_id=frame_id, meta=meta)
    fine = _fine_map(pts, cls, grid, cfg, frame_id)
    n_free = int(np.count_nonzero(data == FREE))
    if n_free == 0:
        warnings.append(
            f"no free cell: no route can be planned on this grid (no {cfg.cell_size:g} m square "
            "with obstacle pixels under the density threshold and floor seen; a room too small or "
            "crowded for such cells, or a floor the map leaves rough: see grid.png)"
        )
    stats = {
        "map_points": int(class_counts.sum()),
        "points": int(pts.shape[0]),
        "floor_points": int(class_counts[0]),
        "band_points": int(class_counts[1]),
        "drop_points": int(class_counts[2]),
        "above_points": int(class_counts[3]),
        "occupied": int(np.count_nonzero(data == OCCUPIED)),
        "free": n_free,
        "unknown": int(np.count_nonzero(data == UNKNOWN)),
        "guard_only_cells": int(np.count_nonzero(guard_only)),
        "yaw_deg": math.degrees(yaw),
        "walls_found": cfg.alignment == "walls" and yaw != 0.0,
        "warnings": warnings,
    }
    return GridResult(
        grid=grid,
        fine=fine,
        obstacles=obstacles,
        boundary=boundary,
        floor=floor,
        density=density,
        observed=observed,
        guard=guard,
        yaw=yaw,
        config=cfg,
        stats=stats,
    )


def _fine_map(pts: np.ndarray, cls: np.ndarray, grid: Grid, cfg: GridConfig, frame_id: str) -> Grid:
    """The fine safe obstacle map in map axes (yaw 0): Nav2's costmaps ignore a map's yaw.

    Obstacle pixels (band + drops, walls included) occupied, observed floor free, rest unknown.
    It covers the grid's footprint plus ``fine_margin`` so the walls are on it.
    """
    ps = cfg.pixel_size
    corners = grid.cell_center(
        np.array([-0.5, -0.5, grid.rows - 0.5, grid.rows - 0.5]),
        np.array([-0.5, grid.cols - 0.5, -0.5, grid.cols - 0.5]),
    )
    # whole pixels, to the nanometre: -137 * 0.05 is -6.8500000000000005, which fine.yaml wrote
    lo = np.round(np.floor((corners.min(axis=0) - cfg.fine_margin) / ps) * ps, 9)
    hi = np.round(np.ceil((corners.max(axis=0) + cfg.fine_margin) / ps) * ps, 9)
    w = round((hi[0] - lo[0]) / ps)
    h = round((hi[1] - lo[1]) / ps)
    if h * w > 2 * _MAX_PIXELS:  # a turned grid's footprint: up to twice its own area
        raise GridError("too_large", f"the fine map would be {h} x {w} pixels: raise pixel_size")
    counts = _raster_classes(pts[:, 0], pts[:, 1], cls, lo[0], lo[1], ps, h, w)
    black = (counts[1] + counts[2]) >= cfg.min_points_per_pixel
    # no floor seeded from a pixel a drop return shares (the grid weighs its 3 x 3 pixels)
    floor = _dilate((counts[0] > 0) & (counts[2] == 0), cfg.floor_fill) & ~black
    data = np.full((h, w), UNKNOWN, dtype=np.int8)
    data[floor] = FREE
    data[black] = OCCUPIED
    meta = {"safe_height": cfg.safe_height, "pixel_size": ps}
    return Grid(
        data=data,
        resolution=ps,
        origin=(float(lo[0]), float(lo[1]), 0.0),
        frame_id=frame_id,
        meta=meta,
    )


def grid_config(cfg: GridConfig) -> GridConfig:
    """The plain :class:`GridConfig` part of a (possibly node) config."""
    return GridConfig(**{f.name: getattr(cfg, f.name) for f in fields(GridConfig)})


def config_dict(cfg: GridConfig) -> dict[str, Any]:
    """The config as a plain mapping (for logs and the grid YAML's comment)."""
    return asdict(cfg)


def grid_text(grid: Grid) -> str:
    """The grid as text, row 0 on top: '#' occupied, '.' free, '?' unknown (for terminals)."""
    sym = {OCCUPIED: "#", FREE: ".", UNKNOWN: "?"}
    return "\n".join("".join(sym.get(int(c), "?") for c in row) for row in grid.data)
