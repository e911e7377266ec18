"""Scenes made of axis-aligned boxes, with exact ground truth (the expected safe grid).

Everything is in the simulator's ROOM frame: z up, the floor's top face at z = 0, the room's
interior spanning ``room = (xmin, ymin, xmax, ymax)``. Floor, ceiling and walls are boxes lying
OUTSIDE the interior (their inner faces are exactly on the interior's boundary), so a camera
inside the room always hits something and no grid cell is ever "occupied by a wall".

Boxes are deliberately the only primitive: a ray-box slab test is exact and vectorises over all
rays x all boxes, and the expected grid is then a closed-form rectangle-overlap test, so the
ground truth never depends on sampling or on the pipeline under test.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from wheelgrid_common.map_io import FREE, OCCUPIED, Grid

#: Box kinds that are part of the room shell rather than obstacles.
STRUCTURE_KINDS = frozenset({"floor", "ceiling", "wall"})

# The paper's measured values (Table I and Section C), in metres.
PAPER_ROOM = 9.6
PAPER_TABLE_GAP = 1.2012  # Fig. 9(a): distance between two tables
PAPER_ROWS_GAP = 1.6572  # Fig. 9(c): distance between two rows of tables
BARRIER1_TOP = 0.77  # Barrier 1: blocks the chair
BARRIER2_CLEARANCE = 1.5116  # Fig. 9(b): floor to Barrier 2, above the 1.5 m safe height
BAR_THICKNESS = 0.05
CEILING = 2.7
WALL = 0.2  # thickness of the shell boxes


@dataclass(frozen=True)
class Box:
    """An axis-aligned box ``[min, max]`` (metres, room frame) with a label and a kind."""

    label: str
    kind: str
    min: tuple[float, float, float]
    max: tuple[float, float, float]

    def __post_init__(self) -> None:
        if any(lo >= hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError(f"box {self.label!r} is empty: min {self.min} max {self.max}")

    @property
    def is_obstacle(self) -> bool:
        return self.kind not in STRUCTURE_KINDS

    def to_json(self) -> dict[str, Any]:
        return {
            "label": self.label,
            "kind": self.kind,
            "min": [float(v) for v in self.min],
            "max": [float(v) for v in self.max],
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> Box:
        return Box(
            str(d["label"]),
            str(d["kind"]),
            tuple(float(v) for v in d["min"]),  # type: ignore[arg-type]
            tuple(float(v) for v in d["max"]),  # type: ignore[arg-type]
        )


def _box(
    label: str, kind: str, x0: float, y0: float, z0: float, x1: float, y1: float, z1: float
) -> Box:
    return Box(label, kind, (x0, y0, z0), (x1, y1, z1))


@dataclass
class Scene:
    """A room: interior rectangle, boxes, and descriptive metadata (barrier heights, seed)."""

    room: tuple[float, float, float, float]
    boxes: list[Box]
    name: str = "custom"
    seed: int = 0
    barriers: dict[str, Any] = field(default_factory=dict)
    ceiling: float = CEILING

    # --- arrays for the ray caster -------------------------------------------------------
    def box_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(M, 3)`` mins and maxes, float64."""
        lo = np.array([b.min for b in self.boxes], dtype=np.float64).reshape(-1, 3)
        hi = np.array([b.max for b in self.boxes], dtype=np.float64).reshape(-1, 3)
        return lo, hi

    @property
    def obstacles(self) -> list[Box]:
        return [b for b in self.boxes if b.is_obstacle]

    # --- ground truth ----------------------------------------------------------------------
    def expected_grid(
        self,
        safe_height: float = 1.5,
        floor_clearance: float = 0.05,
        cell_size: float = 1.2,
        margin: float = 0.01,
    ) -> Grid:
        """The exact safe grid over the room interior, in the ROOM frame.

        A cell is OCCUPIED iff some box, clipped to the height band ``floor_clearance < z <=
        safe_height``, overlaps the cell's area by more than ``margin`` in both x and y (so a
        box merely touching a cell boundary does not mark it); FREE otherwise. Cells are
        ``cell_size`` squares from the interior's lower-left corner; when the room is not a
        multiple of the cell size the last row/column reaches into the walls and is therefore
        occupied (a cell the chair cannot fully use is not free).
        """
        xmin, ymin, xmax, ymax = self.room
        cols = max(1, math.ceil((xmax - xmin) / cell_size - 1e-9))
        rows = max(1, math.ceil((ymax - ymin) / cell_size - 1e-9))
        data = np.full((rows, cols), FREE, dtype=np.int8)
        lo, hi = self.box_arrays()
        in_band = (hi[:, 2] > floor_clearance) & (lo[:, 2] <= safe_height)
        for r in range(rows):
            cy0 = ymin + cell_size * (rows - 1 - r)
            cy1 = cy0 + cell_size
            for c in range(cols):
                cx0 = xmin + cell_size * c
                cx1 = cx0 + cell_size
                ox = np.minimum(hi[:, 0], cx1) - np.maximum(lo[:, 0], cx0)
                oy = np.minimum(hi[:, 1], cy1) - np.maximum(lo[:, 1], cy0)
                if np.any(in_band & (ox > margin) & (oy > margin)):
                    data[r, c] = OCCUPIED
        return Grid(
            data=data,
            resolution=float(cell_size),
            origin=(float(xmin), float(ymin), 0.0),
            frame_id="room",
            meta={
                "safe_height": float(safe_height),
                "floor_clearance": float(floor_clearance),
                "scene": self.name,
            },
        )

    def sample_surface_points(self, spacing: float, include_structure: bool = False) -> np.ndarray:
        """Dense exact points on the faces of the obstacle boxes, ``(N, 3)`` float64.

        Every face gets a regular lattice of at most ``spacing`` pitch including its edges, so
        thin parts (5 cm legs and bars) are never skipped. Handy for grid tests that need a
        perfect "map cloud" with known geometry.
        """
        if spacing <= 0:
            raise ValueError("spacing must be positive")
        boxes = self.boxes if include_structure else self.obstacles
        out: list[np.ndarray] = []
        for b in boxes:
            lo, hi = np.array(b.min), np.array(b.max)
            axes = [
                np.linspace(lo[k], hi[k], max(2, math.ceil((hi[k] - lo[k]) / spacing) + 1))
                for k in range(3)
            ]
            for k in range(3):
                i, j = [a for a in range(3) if a != k]
                u, v = np.meshgrid(axes[i], axes[j], indexing="ij")
                for w in (lo[k], hi[k]):
                    face = np.empty((u.size, 3))
                    face[:, i], face[:, j], face[:, k] = u.ravel(), v.ravel(), w
                    out.append(face)
        if not out:
            return np.empty((0, 3))
        return np.unique(np.concatenate(out), axis=0)

    def interior_surface_points(self, spacing: float) -> np.ndarray:
        """Exact surface points a scanner inside the room could see: obstacles, the floor's top,
        the walls' inner faces and the ceiling's underside (nothing under the floor or behind
        the walls) -- a perfect map cloud for grid tests and benchmarks."""
        pts = self.sample_surface_points(spacing, include_structure=True)
        x0, y0, x1, y1 = self.room
        e = 1e-9
        keep = (
            (pts[:, 0] >= x0 - e)
            & (pts[:, 0] <= x1 + e)
            & (pts[:, 1] >= y0 - e)
            & (pts[:, 1] <= y1 + e)
            & (pts[:, 2] >= -e)
            & (pts[:, 2] <= self.ceiling + e)
        )
        return pts[keep]

    def interior_box_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`box_arrays` clipped to the room's interior (``room`` x ``[0, ceiling]``).

        The floor, ceiling and walls are 20 cm thick boxes OUTSIDE the interior; clipped, each
        is the flat face a scanner in the room sees (its far faces, behind the walls and under
        the floor, are no surface anything in the room can return). Boxes wholly outside are
        dropped."""
        lo, hi = self.box_arrays()
        x0, y0, x1, y1 = self.room
        lo = np.maximum(lo, [x0, y0, 0.0])
        hi = np.minimum(hi, [x1, y1, self.ceiling])
        keep = (lo <= hi).all(axis=1)
        return lo[keep], hi[keep]

    def distance_to_surfaces(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance of each point to the nearest true SURFACE seen from inside the
        room, metres: any box's face within the interior (:meth:`interior_box_arrays`), so a
        point 20 cm behind a wall is 20 cm off, not on the wall box's far face."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        lo, hi = self.interior_box_arrays()
        best = np.full(p.shape[0], np.inf)
        for k in range(lo.shape[0]):
            d_out = np.maximum(np.maximum(lo[k] - p, p - hi[k]), 0.0)
            outside = np.linalg.norm(d_out, axis=1)
            inside = np.min(np.minimum(p - lo[k], hi[k] - p), axis=1)  # > 0 only inside
            dist = np.where(outside > 0, outside, np.abs(inside))
            best = np.minimum(best, dist)
        return best

    def is_free_at(self, x: float, y: float, clearance: float, max_z: float) -> bool:
        """True when a disc of ``clearance`` around (x, y) touches no box below ``max_z``."""
        xmin, ymin, xmax, ymax = self.room
        inside_x = xmin + clearance <= x <= xmax - clearance
        if not (inside_x and ymin + clearance <= y <= ymax - clearance):
            return False
        for b in self.obstacles:
            if b.min[2] >= max_z:
                continue
            dx = max(b.min[0] - x, 0.0, x - b.max[0])
            dy = max(b.min[1] - y, 0.0, y - b.max[1])
            if math.hypot(dx, dy) < clearance:
                return False
        return True

    # --- serialisation -----------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return {
            "scene": self.name,
            "seed": int(self.seed),
            "room": [float(v) for v in self.room],
            "ceiling": float(self.ceiling),
            "barriers": self.barriers,
            "boxes": [b.to_json() for b in self.boxes],
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> Scene:
        return Scene(
            room=tuple(float(v) for v in d["room"]),  # type: ignore[arg-type]
            boxes=[Box.from_json(b) for b in d["boxes"]],
            name=str(d.get("scene", "custom")),
            seed=int(d.get("seed", 0)),
            barriers=dict(d.get("barriers", {})),
            ceiling=float(d.get("ceiling", CEILING)),
        )

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=1)


def shell_boxes(room: tuple[float, float, float, float], ceiling: float = CEILING) -> list[Box]:
    """Floor, ceiling and four walls OUTSIDE the interior (inner faces on its boundary)."""
    x0, y0, x1, y1 = room
    t = WALL
    return [
        _box("floor", "floor", x0 - t, y0 - t, -t, x1 + t, y1 + t, 0.0),
        _box("ceiling", "ceiling", x0 - t, y0 - t, ceiling, x1 + t, y1 + t, ceiling + t),
        _box("wall_west", "wall", x0 - t, y0 - t, 0.0, x0, y1 + t, ceiling),
        _box("wall_east", "wall", x1, y0 - t, 0.0, x1 + t, y1 + t, ceiling),
        _box("wall_south", "wall", x0, y0 - t, 0.0, x1, y0, ceiling),
        _box("wall_north", "wall", x0, y1, 0.0, x1, y1 + t, ceiling),
    ]


def table_boxes(
    label: str,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    height: float = 0.75,
    top: float = 0.03,
    leg: float = 0.05,
) -> list[Box]:
    """A table: a top slab and four square legs flush with the top's corners."""
    zt = height - top
    out = [_box(f"{label}_top", "table", x0, y0, zt, x1, y1, height)]
    for i, (lx, ly) in enumerate(((x0, y0), (x1 - leg, y0), (x0, y1 - leg), (x1 - leg, y1 - leg))):
        out.append(_box(f"{label}_leg{i}", "leg", lx, ly, 0.0, lx + leg, ly + leg, zt))
    return out


def paper_scene() -> Scene:
    """The paper's experiment (Section IV): a 9.6 x 9.6 m room whose safe grid is 8 x 8.

    Layout (grid rows from the top, cells of 1.2 m): row 3 holds tables A and B with the
    paper's 120.12 cm gap and Barrier 1 (top 0.77 m) -> cells (3,0)..(3,4) occupied, (3,5)
    free; row 5 holds a second row of tables 165.72 cm from the first; Barrier 2 (its underside
    1.5116 m above the floor, the paper's measured "floor to barrier" distance) hangs over row 4
    from a post in cell (4,4) to the east wall, so the chair passes under it at (4,5); a pillar
    stands in cell (0,6). The unique shortest route (2,0) -> (6,5) is then the paper's Table II
    route: right x5 along row 2, then down column 5.
    """
    room = (0.0, 0.0, PAPER_ROOM, PAPER_ROOM)
    boxes = shell_boxes(room)
    # Row 3 (y in [4.8, 6.0]): tables A and B with the paper's gap between them.
    ty0, ty1 = 5.0, 5.8
    boxes += table_boxes("table_A", 0.1, ty0, 1.1, ty1)
    boxes += table_boxes("table_B", 1.1 + PAPER_TABLE_GAP, ty0, 3.5, ty1)
    # Barrier 1: a bar whose top is at 0.77 m on two posts, x 3.5 .. 5.55, y ~ 5.4. Every
    # obstacle edge stays >= 0.2 m from a cell boundary it must not cross: a map that is good
    # to a few cm must not make the route cells (3,5), (4,3) or row 6 look occupied.
    b1y0, b1y1 = 5.375, 5.425
    boxes.append(
        _box(
            "barrier1_bar", "bar", 3.5, b1y0, BARRIER1_TOP - BAR_THICKNESS, 5.55, b1y1, BARRIER1_TOP
        )
    )
    boxes.append(
        _box("barrier1_post_w", "post", 3.5, b1y0, 0.0, 3.55, b1y1, BARRIER1_TOP - BAR_THICKNESS)
    )
    boxes.append(
        _box("barrier1_post_e", "post", 5.5, b1y0, 0.0, 5.55, b1y1, BARRIER1_TOP - BAR_THICKNESS)
    )
    # Row 5 (y in [2.4, 3.6]): four tables side by side, x 0.1 .. 4.7, 165.72 cm from row 3.
    r5y1 = ty0 - PAPER_ROWS_GAP  # 3.3428
    r5y0 = 2.64
    edges = np.linspace(0.1, 4.7, 5)
    for i in range(4):
        boxes += table_boxes(f"table_row5_{i}", float(edges[i]), r5y0, float(edges[i + 1]), r5y1)
    # Barrier 2: underside at 1.5116 m, y ~ 4.2, post at x 5.1 (cell (4,4)), anchored east.
    b2y0, b2y1 = 4.175, 4.225
    b2z0, b2z1 = BARRIER2_CLEARANCE, BARRIER2_CLEARANCE + BAR_THICKNESS
    boxes.append(_box("barrier2_bar", "bar", 5.1, b2y0, b2z0, PAPER_ROOM, b2y1, b2z1))
    boxes.append(_box("barrier2_post", "post", 5.1, b2y0, 0.0, 5.15, b2y1, b2z0))
    # A floor-to-ceiling pillar in cell (0,6), away from the route.
    boxes.append(_box("pillar", "pillar", 7.6, 8.8, 0.0, 8.0, 9.2, CEILING))
    return Scene(
        room=room,
        boxes=boxes,
        name="paper",
        seed=0,
        barriers={
            "barrier1": {
                "bottom": BARRIER1_TOP - BAR_THICKNESS,
                "top": BARRIER1_TOP,
                "blocks_chair": True,
            },
            "barrier2": {"bottom": b2z0, "top": b2z1, "blocks_chair": False},
            "table_gap": PAPER_TABLE_GAP,
            "rows_gap": PAPER_ROWS_GAP,
        },
    )


def random_scene(seed: int, cell_size: float = 1.2) -> Scene:
    """A random furnished room: size a multiple of ``cell_size`` in [6, 10] m.

    Obstacles (tables on legs, bars on posts at random heights -- some above and some below the
    1.5 m safe height -- and pillars) are kept at least one cell away from the walls, so the
    ring of cells along the walls stays free: that is where the trajectory drives, looking
    inwards. The expected grid follows from the boxes exactly, like the paper scene's.
    """
    rng = np.random.default_rng(seed)
    # Rounded so that e.g. 6 x 1.2 is 7.2, not 7.199999999999999 (it ends up in scene.json).
    sizes = [round(cell_size * k, 9) for k in range(1, 20) if 6.0 <= cell_size * k <= 10.0 + 1e-9]
    if not sizes:
        raise ValueError(f"no room size in [6, 10] m is a multiple of {cell_size} m")
    w, h = float(rng.choice(sizes)), float(rng.choice(sizes))
    room = (0.0, 0.0, w, h)
    boxes = shell_boxes(room)
    ix0, iy0, ix1, iy1 = cell_size, cell_size, w - cell_size, h - cell_size
    placed: list[tuple[float, float, float, float]] = []
    barriers: dict[str, Any] = {}

    def fits(x0: float, y0: float, x1: float, y1: float) -> bool:
        if x0 < ix0 or y0 < iy0 or x1 > ix1 or y1 > iy1:
            return False
        return all(
            x1 <= a0 - 0.3 or x0 >= a1 + 0.3 or y1 <= b0 - 0.3 or y0 >= b1 + 0.3
            for a0, b0, a1, b1 in placed
        )

    def spot(sx: float, sy: float) -> tuple[float, float, float, float] | None:
        for _ in range(50):
            x0 = float(rng.uniform(ix0, max(ix0, ix1 - sx)))
            y0 = float(rng.uniform(iy0, max(iy0, iy1 - sy)))
            if fits(x0, y0, x0 + sx, y0 + sy):
                placed.append((x0, y0, x0 + sx, y0 + sy))
                return x0, y0, x0 + sx, y0 + sy
        return None

    for i in range(int(rng.integers(2, 5))):
        sx, sy = float(rng.uniform(0.8, 1.8)), float(rng.uniform(0.6, 0.9))
        if rng.random() < 0.5:
            sx, sy = sy, sx
        s = spot(sx, sy)
        if s:
            boxes += table_boxes(f"table_{i}", *s, height=float(rng.uniform(0.65, 0.8)))
    for i in range(int(rng.integers(2, 4))):
        length = float(rng.uniform(1.0, 2.5))
        along_x = bool(rng.random() < 0.5)
        sx, sy = (length, 0.05) if along_x else (0.05, length)
        s = spot(sx, sy)
        if not s:
            continue
        above = i % 2 == 0  # alternate so both kinds appear
        bottom = float(rng.uniform(1.52, 1.9)) if above else float(rng.uniform(0.45, 1.3))
        top = bottom + BAR_THICKNESS
        x0, y0, x1, y1 = s
        boxes.append(_box(f"bar_{i}", "bar", x0, y0, bottom, x1, y1, top))
        p = 0.05
        boxes.append(_box(f"bar_{i}_post0", "post", x0, y0, 0.0, x0 + p, y0 + p, bottom))
        boxes.append(_box(f"bar_{i}_post1", "post", x1 - p, y1 - p, 0.0, x1, y1, bottom))
        barriers[f"bar_{i}"] = {"bottom": bottom, "top": top, "blocks_chair": not above}
    for i in range(int(rng.integers(1, 3))):
        s = spot(0.4, 0.4)
        if s:
            boxes.append(_box(f"pillar_{i}", "pillar", s[0], s[1], 0.0, s[2], s[3], CEILING))
    return Scene(room=room, boxes=boxes, name="random", seed=int(seed), barriers=barriers)
