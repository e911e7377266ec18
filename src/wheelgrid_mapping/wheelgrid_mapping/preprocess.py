"""Preprocessing of iPhone-LiDAR clouds after the paper's section II.A (ROS-free).

Order used by :func:`preprocess`, and why:

1. :func:`valid_mask` drops NaN/inf points (no return), points outside ``[min_range,
   max_range]`` (the iPhone LiDAR is specified to ~5 m; beyond that depth is interpolated guess
   work) and, when ARKit confidence is given, points below ``min_confidence``.
2. :func:`voxel_downsample` - the paper's space subdivision (eq. 5): the bounding cube is cut
   into equal cells of edge ``L``; each occupied cell keeps the centroid of its points. With a
   target point count (the paper: ~7 M -> ~1.3 M) ``L`` starts from eq. 5 and is refined.
3. :func:`grid_knn` - the K-nearest-neighbour search of the text after eq. 5: candidates come
   from the point's own and adjacent cells; where fewer than K are found the search area grows.
4. :func:`statistical_outlier_mask` - eqs. 1-4 exactly (mean K-NN distance per point, global
   mean and standard deviation, threshold ``t = mu + m * sigma``, outlier when ``mu_i >= t``).
5. :func:`plane_fit_criterion` - the PFC: an SVD plane through each point's neighbours; a point
   far from the plane of its neighbours while those neighbours are themselves flat is noise.

Safety: every removal step is tuned so thin real obstacles survive (a 5 cm bar, a table leg, a
table edge: they are dense along their own length, so their points have close neighbours and a
PFC near 0.5); only isolated points and points floating off smooth surfaces are removed. The
PFC additionally needs an absolute offset (``pfc_min_offset``) before it removes anything,
because the paper notes it misfires around small features and folds. Settings that undo this
pass :meth:`PreprocessConfig.validate` (each number is sane alone), so :mod:`.thin_check` runs
them on a thin-obstacle room where they enter, and refuses them there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from wheelgrid_common.params import check_finite, field

from .depth import check_min_confidence

#: The finest map, evidence, registration and submap voxel (m): voxel keys hold +-2^20 voxels
#: a side, a kilometre at 1 mm.
MIN_VOXEL = 0.001


@dataclass
class PreprocessConfig:
    """Every preprocessing parameter, one place (YAML section ``preprocess`` / ROS params)."""

    min_range: float = field(0.2, "points closer to the sensor are dropped", "m")
    max_range: float = field(
        6.0, "points farther from the sensor are dropped (iPhone LiDAR: ~5 m spec, 6.3 m seen)", "m"
    )
    min_confidence: int = field(
        1, "ARKit confidence below this is dropped (0 low, 1 medium, 2 high)", ""
    )
    voxel_size: float = field(
        0.03, "cell edge L of the space subdivision used to downsample each frame", "m"
    )
    target_points: int = field(
        0, "if > 0, downsample to about this many points instead (eq. 5 start value)", "points"
    )
    sor_k: int = field(8, "K neighbours for the statistical outlier removal (eqs. 1-4)", "")
    sor_m: float = field(2.5, "correction factor m of eq. 3 (t = mu + m sigma)", "")
    pfc_k: int = field(10, "neighbours for the plane fitting criterion", "")
    pfc_threshold: float = field(
        0.85, "a point with PFC above this (and far enough off) is noise", ""
    )
    pfc_min_offset: float = field(
        0.03, "PFC removes nothing closer than this to its neighbours' plane", "m"
    )
    enable_sor: bool = field(True, "run the statistical outlier removal", "")
    enable_pfc: bool = field(True, "run the plane fitting criterion", "")
    mixed_pixels: bool = field(
        False,
        "in an organised cloud, drop a pixel whose range lies between two opposite "
        "neighbours' by more than mixed_jump on both sides (a mixed pixel: a depth edge's "
        "foreground and background light in one return). For sensors without a confidence "
        "channel; off: it clears false obstacles behind posts, but it changes what ICP aligns, "
        "and with an earlier test the simulated and the real maps came out less accurate "
        "(docs/mapping-fidelity.md)",
        "",
    )
    map_mixed_pixels: bool = field(
        True,
        "leave the mixed pixels (the mixed_pixels test) out of the map only: registration "
        "still sees every pixel, the map gets a point where most of its cell's pixels passed. "
        "A time-of-flight pixel across a depth edge piles up behind thin posts, where no ray "
        "carves it; with registration.convergence 1e-3 such a smear filled a free grid cell "
        "of the bundled bag. Organised frames only; ARKit's confidence drops most of them "
        "first (docs/mapping-fidelity.md)",
        "",
    )
    mixed_jump: float = field(
        0.08, "range gap to a nearer and to a farther neighbour that marks a mixed pixel", "m"
    )
    mixed_jump_pitches: float = field(
        6.0,
        "plus the range times this many pixel pitches (the angle between neighbouring pixels' "
        "rays, measured on each frame): a surface seen at a grazing angle steps by about "
        "range x pitch / tan(incidence) a pixel, 5x at 11 deg",
        "",
    )
    accept_thin_obstacle_loss: bool = field(
        False,
        "run settings that the start-up check finds erasing a thin obstacle (a 5 cm bar, a "
        "table leg, a table edge, in a room sampled as the iPhone sees it at 2 m) instead of "
        "refusing them, with a warning at every start. Only for a sensor very unlike the "
        "iPhone, whose density the check does not model: for a wheelchair a lost bar is free "
        "floor to drive into",
        "",
    )

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ValueError for settings that cannot work.

        A NaN passes every range test written as a failing comparison: ``sor_m: .nan`` made
        the threshold t of eq. 3 NaN, and eq. 4 then removed every point of every frame."""
        check_finite(self, "preprocess ")
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError(
                f"preprocess needs 0 <= min_range < max_range, not {self.min_range}, "
                f"{self.max_range}"
            )
        if self.voxel_size < 0 or self.target_points < 0:
            raise ValueError("preprocess voxel_size and target_points must be >= 0")
        if self.voxel_size > 0 and 2.0 * self.max_range / self.voxel_size >= (1 << 21) - 2:
            # The subdivision packs 21 bits a axis: a frame spans up to 2 max_range, and
            # voxel_size 1e-6 passed, then failed every frame ("cloud too large for cell").
            raise ValueError(
                f"preprocess voxel_size {self.voxel_size} m is too fine for max_range "
                f"{self.max_range} m (at most 2 max_range / 2^21 cells a axis: "
                f">= {2.0 * self.max_range / ((1 << 21) - 2):.2g} m)"
            )
        if self.sor_m < 0:
            # t = mu + m sigma below the mean: eq. 4 then drops most of every surface first
            # where its points are sparsest, at its edges (sor_m -1 kept 470 of 17798 points of
            # the thin-obstacle room and no point of the table's front edge). m = 0 keeps them.
            raise ValueError(f"preprocess sor_m must be >= 0, not {self.sor_m}")
        if self.sor_k < 1 or self.pfc_k < 3:
            raise ValueError(
                f"preprocess needs sor_k >= 1 and pfc_k >= 3, not {self.sor_k}, {self.pfc_k}"
            )
        if not (self.mixed_jump > 0 and self.mixed_jump_pitches >= 0):
            raise ValueError("mixed_jump must be > 0 and mixed_jump_pitches >= 0")
        if self.pfc_min_offset < 0:
            raise ValueError(f"preprocess pfc_min_offset must be >= 0, not {self.pfc_min_offset}")
        # ARKit's levels only: min_confidence 3 dropped every point of every frame (the map
        # came out empty, frame after frame "empty"), -1 meant 0.
        check_min_confidence(self.min_confidence, "preprocess min_confidence")


def valid_mask(
    points: np.ndarray,
    min_range: float = 0.0,
    max_range: float = math.inf,
    confidence: np.ndarray | None = None,
    min_confidence: int = 0,
) -> np.ndarray:
    """Boolean mask of finite points inside the range limits (and confident enough).

    ``points`` are in the sensor frame (range = distance from the origin). ``confidence`` is
    per point (same order; organised clouds flattened), or None when the sensor gives none.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    mask = np.isfinite(pts).all(axis=1)
    rng = np.full(pts.shape[0], np.inf)
    rng[mask] = np.linalg.norm(pts[mask], axis=1)
    mask &= (rng >= min_range) & (rng <= max_range)
    if confidence is not None:
        conf = np.asarray(confidence).reshape(-1)
        if conf.shape[0] != pts.shape[0]:
            raise ValueError(f"confidence has {conf.shape[0]} values for {pts.shape[0]} points")
        mask &= conf >= min_confidence
    return mask


def mixed_pixel_mask(points: np.ndarray, jump: float, pitches: float = 0.0) -> np.ndarray:
    """``(H, W)`` bool: the pixels of an organised ``(H, W, 3)`` sensor-frame cloud to drop as
    mixed (flying) pixels.

    A time-of-flight pixel across a depth edge returns a range between the foreground's and
    the background's. Such points fill the shadow behind a thin post or a table leg, a shadow
    no ray of that view crosses, so the evidence map cannot carve them and they pile up,
    frame after frame, into a false obstacle there.

    A mixed pixel lies between two opposite neighbours (across a row, a column or a
    diagonal: along a jagged edge the foreground is often only a diagonal step away), one
    nearer and one farther by more than ``jump + pitches * range * pitch`` (``pitch``: the
    median angle between neighbouring rays along that line, so the same setting suits a
    256-pixel frame and one strided to 86). A real surface pixel
    has a neighbour on its own surface: a 5 cm bar's edge pixel has the bar on one side and
    the background on the other, never a nearer neighbour. Opposite, not any two: a real
    pixel beside one of the sensor's wild returns has a nearer neighbour too, but rarely a
    farther one right across from it (such pixels are the 1-2 % of a thin obstacle's that
    go). A floor seen at a grazing angle steps by range x pitch / tan(incidence) a row, under
    the threshold, and by about as much on both sides of a pixel, where an edge has a surface
    on at least one side (the next step out is under half the jump). Invalid pixels (NaN) are
    never neighbours and never dropped here."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"an organised cloud is (H, W, 3), not {pts.shape}")
    r = np.sqrt(np.einsum("ijk,ijk->ij", pts, pts))
    h, w = r.shape
    padded = np.full((h + 4, w + 4), np.nan)  # NaN compares False: no neighbour there
    padded[2:-2, 2:-2] = r
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.full((h + 2, w + 2, 3), np.nan)
        unit[1:-1, 1:-1] = pts / r[..., None]
    r_or_0 = np.nan_to_num(r)

    def at(step: int, di: int, dj: int) -> np.ndarray:
        return padded[2 + step * di : 2 + step * di + h, 2 + step * dj : 2 + step * dj + w]

    mixed = np.zeros(r.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):  # the four lines through a pixel
            cos = np.einsum(
                "ijk,ijk->ij", unit[1:-1, 1:-1], unit[1 + di : 1 + di + h, 1 + dj : 1 + dj + w]
            )
            gap = jump + pitches * median_angle(cos.reshape(-1)) * r_or_0
            n1, p1 = at(1, di, dj), at(-1, di, dj)
            a, b = n1 - r, p1 - r
            between = ((a < -gap) & (b > gap)) | ((a > gap) & (b < -gap))
            # An edge has a surface on at least one side: the next step out is small there,
            # under half the smaller jump. A floor far off steps by about as much every row
            # (a coarse pixel grid at a grazing angle), on both sides alike: no edge. Tested
            # on the few pixels between their neighbours only (the whole frame took twice the
            # time, this mask being on by default for every organised frame).
            i, j = np.nonzero(between)
            half = 0.5 * np.minimum(np.abs(a[i, j]), np.abs(b[i, j]))
            flat = (np.abs(at(2, di, dj)[i, j] - n1[i, j]) < half) | (
                np.abs(at(-2, di, dj)[i, j] - p1[i, j]) < half
            )
            mixed[i[flat], j[flat]] = True
    return mixed


def median_angle(cos: np.ndarray) -> float:
    """rad: ``np.median(np.arccos(np.clip(cos, -1, 1)))`` over the finite ``cos``, bit for bit,
    without an arccos per pixel: arccos falls monotonically, so the middle angle is the
    arccos of the middle cosine (for an even count the mean of the two middle angles, added
    in ascending order as ``np.median`` adds them: hence the reversal)."""
    cos = cos[np.isfinite(cos)]
    n = cos.size
    if n == 0:
        return 0.0
    k = (n - 1) // 2
    mid = np.partition(cos, k)[k : k + 1] if n % 2 else np.partition(cos, [k, k + 1])[k : k + 2]
    return float(np.mean(np.arccos(np.clip(mid, -1.0, 1.0))[::-1]))


def col_min(a: np.ndarray) -> np.ndarray:
    """``a.min(axis=0)`` of an ``(N, 3)`` array, column by column: numpy reduces a C-ordered
    (N, 3) array along axis 0 about 3x slower than it reduces its three columns one by one
    (7 M points: 177 against 63 ms; int64: 126 against 39 ms). Exact, as min is."""
    return np.array([a[:, i].min() for i in range(a.shape[1])], dtype=a.dtype)


def col_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=0)``, column by column (see :func:`col_min`)."""
    return np.array([a[:, i].max() for i in range(a.shape[1])], dtype=a.dtype)


def subdivision_cell(n_points: int, extent: np.ndarray, per_cell: float) -> float:
    """Eq. 5: ``L = cbrt(n / N_a * dX * dY * dZ)`` - the cell edge giving ``n`` points a cell.

    Degenerate (flat) extents are padded to 1 mm so a planar cloud still gets a finite cell.
    """
    if n_points <= 0:
        raise ValueError("no points to subdivide")
    ext = np.maximum(np.asarray(extent, dtype=np.float64), 1e-3)
    return float(np.cbrt(per_cell / n_points * float(np.prod(ext))))


def _cell_keys(points: np.ndarray, cell: float, origin: np.ndarray) -> np.ndarray:
    """Integer cell coordinates packed into one int64 (21 bits per axis)."""
    ijk = np.floor((points - origin) / cell).astype(np.int64)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def voxel_downsample(points: np.ndarray, cell: float) -> np.ndarray:
    """Centroid of the points in each occupied cell of edge ``cell`` (space subdivision).

    Centroids (not cell centres) keep surfaces where they were measured, so no bias of up to
    half a cell is introduced; a thin bar keeps at least one point per cell it touches.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        return pts.copy()
    return _centroids(pts, *_cell_groups(pts, cell))


def voxel_downsample_flagged(
    points: np.ndarray, cell: float, flags: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`voxel_downsample`, and for each centroid the share of its points that ``flags``
    marks: a cell is one map point, so a per-pixel verdict must become a per-cell one."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        return pts.copy(), np.empty(0)
    inverse, counts = _cell_groups(pts, cell)
    weights = np.asarray(flags, dtype=np.float64)
    flagged = np.bincount(inverse, weights=weights, minlength=counts.size)
    return _centroids(pts, inverse, counts), flagged / counts


def _centroids(pts: np.ndarray, inverse: np.ndarray, counts: np.ndarray) -> np.ndarray:
    out = np.zeros((counts.shape[0], 3))
    for axis in range(3):
        out[:, axis] = np.bincount(inverse, weights=pts[:, axis], minlength=counts.shape[0])
    return out / counts[:, None]


def _cell_groups(pts: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Each point's cell (0..cells-1, cells in key order) and each cell's point count."""
    if cell <= 0:
        raise ValueError("cell size must be > 0")
    # Lattice anchored at 0 (not at the cloud's minimum) so grid_knn with the same cell sees
    # exactly one centroid per cell: a centroid never leaves its (convex) cell.
    origin = np.floor(col_min(pts) / cell) * cell
    span = (col_max(pts) - origin) / cell
    if (span >= (1 << 21) - 1).any():
        raise ValueError(f"cloud too large for cell {cell} m (span {span.max():.0f} cells)")
    ijk = np.floor((pts - origin) / cell).astype(np.int64)
    dims = col_max(ijk) + 1
    if int(dims.prod()) <= min(256_000_000, max(8 * pts.shape[0], 1 << 16)):
        # Dense lattice: cell index by a bitmap + cumulative sum instead of a sort (a big
        # cloud). A frame's box is mostly empty (30 k points in 1.6 M cells): sorting its
        # points is 10x cheaper than summing that many cells, and orders the cells alike.
        lin = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        occ = np.zeros(int(dims.prod()), dtype=bool)
        occ[lin] = True
        rank = np.cumsum(occ, dtype=np.int64) - 1
        inverse = rank[lin]
        counts = np.bincount(inverse)
    else:
        keys = _cell_keys(pts, cell, origin)
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    return inverse, counts


def cell_for_target(points: np.ndarray, target: int, iterations: int = 8) -> float:
    """Cell edge whose :func:`voxel_downsample` leaves about ``target`` points.

    Starts from eq. 5 (``n = N_a / target`` points per cell); because scanned clouds are
    surfaces, not volumes, the count follows ``c * L^-a`` with ``a`` near 2, so a secant step
    in log-log space converges in a few iterations where the count is smooth. Where it is not
    (axis-aligned walls, whose count jumps as the lattice phase changes) the steps are kept
    inside the tightest bracket seen, and the cell returned is the one tried whose count came
    closest: the untried last step was returned, 90 % over a 100 k target (a review).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if target <= 0 or target >= pts.shape[0]:
        return 0.0
    lo = col_min(pts)
    extent = col_max(pts) - lo
    cell = subdivision_cell(pts.shape[0], extent, pts.shape[0] / target)
    # Offsets from the minimum once, in float32: the count only steers the search, so 1e-6 m
    # rounding at a cell border does not matter, and every pass then reads half the bytes.
    rel = (pts - lo).astype(np.float32)

    def count_full(c: float) -> int:
        # Occupied-cell count without sorting when the lattice fits a bitmap (O(N)); offsets
        # are >= 0, so truncation is floor. On voxel_downsample's lattice, anchored at 0: one
        # anchored at the cloud's minimum counted another phase, and on walls aligned with
        # the axes the two counts differed by up to 40 %, so the search missed its target
        shift = (lo - np.floor(lo / c) * c).astype(np.float32)
        ijk = ((rel + shift) * np.float32(1.0 / c)).astype(np.int32)
        dims = col_max(ijk).astype(np.int64) + 1
        if int(dims.prod()) <= 256_000_000:
            occ = np.zeros(int(dims.prod()), dtype=bool)
            occ[(ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]] = True
            return int(np.count_nonzero(occ))
        return int(np.unique(_cell_keys(pts, c, lo)).shape[0])

    prev: tuple[float, int] | None = None
    best = (math.inf, cell)
    small, big = 0.0, math.inf  # cells known to leave too many / too few points
    for _ in range(iterations):
        n = count_full(cell)
        best = min(best, (abs(n - target), cell))
        if abs(n - target) <= 0.02 * target:
            break
        if n > target:
            small = max(small, cell)
        else:
            big = min(big, cell)
        slope = 2.0
        if prev is not None and prev[1] != n and prev[0] != cell:
            slope = -math.log(n / prev[1]) / math.log(cell / prev[0])
            slope = min(max(slope, 0.5), 3.0)
        prev = (cell, n)
        step = cell * (n / target) ** (1.0 / slope)
        if not small < step < big:  # outside the bracket: its middle (geometric)
            step = math.sqrt(small * big) if small > 0 and big < math.inf else step
        cell = step
    return best[1]


def grid_knn(points: np.ndarray, k: int, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """K nearest neighbours (self excluded) through the space subdivision (text after eq. 5).

    Candidates are the points of the 3x3x3 cells around the point's cell; where that block
    holds fewer than ``k`` the point is searched in the whole 5x5x5 block (the paper's "expand
    the search area"). Neighbours closer than one cell are exact; farther ones are the nearest
    among the candidates searched (a bounded search: enough for SOR and PFC, which only need a
    local neighbourhood, and it is what keeps 1 M points to seconds without a k-d tree).
    Meant for :func:`voxel_downsample` output at the same cell (one point per cell, same
    lattice); a cell holding more points contributes its first 4. Returns ``(idx (N,k) int64,
    dist (N,k) float64)`` sorted by distance, equal distances in lattice-offset order; missing
    neighbours have index -1 and distance ``inf``.

    The candidates are gathered offset by offset over chunks of queries (one cache-sized
    gather a step, not an (N, 27, 3) temporary) and kept only where a cell is occupied, as
    (query, candidate) pairs that one flat sort of packed int64 keys orders. That, and counting
    the 3x3x3 block before searching it, made it a third faster than the dense (query,
    column) matrix it replaced (41 real frames at 3 cm, k = 10: 42.6 against 63.7 ms a frame;
    the same distances, ties apart), which was 1.5x faster than the first per-point version.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    idx_out = np.full((n, k), -1, dtype=np.int64)
    dist_out = np.full((n, k), np.inf)
    if n < 2 or k < 1:
        return idx_out, dist_out
    # Same lattice as voxel_downsample, padded by 2 cells so that keys +-2 cells never wrap.
    origin = (np.floor(col_min(pts) / cell) - 2.0) * cell
    ijk = np.floor((pts - origin) / cell).astype(np.int64)
    dims = col_max(ijk) + 3
    lin = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(lin, kind="stable")
    lin_sorted = lin[order]
    # Runs of equal keys in the sorted order = occupied cells (cheaper than np.unique).
    starts = np.flatnonzero(np.r_[True, lin_sorted[1:] != lin_sorted[:-1]])
    ucells = lin_sorted[starts]
    counts = np.diff(np.r_[starts, n])
    cap = int(min(4, counts.max()))
    # table[r, u] = r-th point of occupied cell u; column U (-1 lookups land there) is empty.
    table = np.full((cap, ucells.shape[0] + 1), -1, dtype=np.int32)
    for r in range(cap):
        has = np.flatnonzero(counts > r)
        table[r, has] = order[starts[has] + r]
    # Occupied-cell lookup: a dense table when the lattice is small enough (one gather per
    # query; with one point per cell it maps straight to the point), else a binary search.
    n_cells = int(dims.prod())
    dense: np.ndarray | None = None
    if n_cells <= 64_000_000:
        dense = np.full(n_cells, -1, dtype=np.int32)
        dense[ucells] = table[0, :-1] if cap == 1 else np.arange(ucells.shape[0], dtype=np.int32)
    # the dense table where it maps a cell straight to its one point (None elsewhere)
    direct = dense if cap == 1 else None

    def cell_rows(keys: np.ndarray) -> np.ndarray:
        if dense is not None:
            return dense[keys]
        pos = np.minimum(np.searchsorted(ucells, keys), ucells.shape[0] - 1)
        return np.where(ucells[pos] == keys, pos, -1).astype(np.int32)

    # float32 halves the memory traffic (cm-exact here).
    rel = (pts - origin).astype(np.float32)
    xs, ys, zs = (np.ascontiguousarray(rel[:, a]) for a in range(3))

    def offsets(inner: int, reach: int) -> list[int]:
        return [
            int((a * dims[1] + b) * dims[2] + c)
            for a in range(-reach, reach + 1)
            for b in range(-reach, reach + 1)
            for c in range(-reach, reach + 1)
            if max(abs(a), abs(b), abs(c)) >= inner
        ]

    def search(sel: np.ndarray, offs: list[int]) -> None:
        for s in range(0, sel.shape[0], 65_536):
            q = sel[s : s + 65_536]
            qkey = lin[q]
            # Only the candidates that exist become (query, candidate) pairs: in a frame ~15 %
            # of the 5x5x5 shell's cells are occupied, so a dense (query, column) matrix was
            # mostly padding to fill, transpose and partition.
            hits: list[np.ndarray] = []
            cands: list[np.ndarray] = []
            lens: list[int] = []
            col_off: list[int] = []
            col_slot: list[int] = []
            for off in offs:
                rows = cell_rows(qkey + off)
                if direct is not None:
                    slots = [(0, rows)] if off != 0 else []  # own cell: only the query itself
                else:
                    slots = [(r, table[r, rows]) for r in range(cap)]
                    if off == 0:
                        slots = [(r, np.where(c == q, -1, c)) for r, c in slots]
                for r, c in slots:
                    hit = np.flatnonzero(c >= 0)
                    hits.append(hit)
                    cands.append(c[hit])
                    lens.append(hit.shape[0])
                    col_off.append(off)
                    col_slot.append(r)
            qi = np.concatenate(hits)
            ci = np.concatenate(cands).astype(np.intp)
            qg = q[qi]
            dx = xs[ci] - xs[qg]
            dd = dx * dx
            dx = ys[ci] - ys[qg]
            dd += dx * dx
            dx = zs[ci] - zs[qg]
            dd += dx * dx
            # One sortable int64 a pair: query (16 bits) | float32 distance bits (monotonic for
            # d >= 0; 31 bits) | column (12 bits), so one flat sort orders every query's
            # candidates by distance, ties by lattice offset.
            key = (qi.astype(np.int64) << 43) | (dd.view(np.int32).astype(np.int64) << 12)
            key |= np.repeat(np.arange(len(lens), dtype=np.int64), lens)
            key.sort()
            qsort = key >> 43
            first = np.searchsorted(qsort, np.arange(q.shape[0]))
            rank = np.arange(key.shape[0]) - first[qsort]
            m = np.flatnonzero(rank < k)
            km = key[m]
            qm = q[qsort[m]]
            cm = (km & 4095).astype(np.intp)
            # The candidate of a kept pair, looked up again from its column rather than
            # carried through the sort (an argsort costs twice a sort).
            keys_m = lin[qm] + np.asarray(col_off, dtype=np.int64)[cm]
            if direct is not None:
                cand = direct[keys_m]
            else:
                cand = table[np.asarray(col_slot, dtype=np.intp)[cm], cell_rows(keys_m)]
            dist_out[qm, rank[m]] = np.sqrt(
                ((km >> 12) & 0x7FFFFFFF).astype(np.int32).view(np.float32)
            )
            idx_out[qm, rank[m]] = cand

    # How many candidates each point's 3x3x3 block holds, counted without their distances:
    # the points with fewer than k (on a voxelised surface nearly all of them) are searched
    # once over the whole 5x5x5 block instead of twice.
    inner = offsets(0, 1)
    found = np.zeros(n, dtype=np.int32)
    if direct is not None:
        for off in inner:
            if off != 0:
                found += direct[lin + off] >= 0
    else:
        per_row = np.r_[np.minimum(counts, cap), 0].astype(np.int32)
        for off in inner:
            found += per_row[cell_rows(lin + off)]
        found -= (table[:, cell_rows(lin)] == np.arange(n)).any(axis=0)
    short = found < k
    search(np.flatnonzero(~short), inner)
    if short.any():
        search(np.flatnonzero(short), offsets(2, 2) + inner)
    return idx_out, dist_out


def statistical_outlier_mask(
    dist: np.ndarray, m: float, missing_distance: float | None = None
) -> np.ndarray:
    """Eqs. 1-4 on K-NN distances ``dist (N, K)``: True = keep (inlier).

    mu_i is the mean distance of point i to its K neighbours; mu and sigma (eq. 2, N-1) are the
    mean and standard deviation of all mu_i; ``t = mu + m sigma`` (eq. 3); an outlier has
    ``mu_i >= t`` (eq. 4). A neighbour the bounded search did not find counts as
    ``missing_distance`` (default: the largest finite distance seen), so an isolated point
    among dense surfaces is an outlier rather than silently kept. It is a stand-in, not the
    distance: where the surfaces themselves are sampled about as sparsely as the search
    reaches, a point far from all of them reads as they do and is kept (README, the "No
    filter erases a thin obstacle" bullet).

    Where every mu_i is the same (a spread within rounding, 1e-9 of the largest), every point is
    kept: taken literally, eq. 4 then marks every point an outlier (``mu_i >= t = mu``), and
    with floating-point rounding sigma comes out ~1e-17 instead of 0, which removed every point
    of such a cloud (a regular lattice with K = 1, say), not one of them.
    """
    d = np.array(dist, dtype=np.float64)
    if d.shape[0] < 2:
        return np.ones(d.shape[0], dtype=bool)
    finite = np.isfinite(d)
    if missing_distance is None:
        missing_distance = float(d[finite].max()) if finite.any() else 1.0
    d[~finite] = missing_distance
    mu_i = d.mean(axis=1)  # eq. 1 per point
    mu = float(mu_i.mean())
    sigma = float(mu_i.std(ddof=1))  # eq. 2
    t = mu + m * sigma  # eq. 3
    if sigma == 0.0 or float(np.ptp(mu_i)) <= 1e-9 * float(np.abs(mu_i).max()):
        return np.ones(d.shape[0], dtype=bool)
    return mu_i < t  # eq. 4: outlier when mu_i >= t


def _neighbour_moments(
    points: np.ndarray, idx: np.ndarray
) -> tuple[list[np.ndarray], list[np.ndarray], dict[tuple[int, int], np.ndarray], np.ndarray]:
    """Per point: neighbour offsets, their mean and covariance (``idx`` -1 = no neighbour).

    Everything is relative to the point itself: cm-scale numbers, so no cancellation when the
    cloud sits metres from the origin, and the point-to-centroid vector is just ``-mean``.
    Returns ``(rel[axis] (N,k), mean[axis] (N,), cov[(i, j)] (N,), count (N,))``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    valid = idx >= 0
    cnt = valid.sum(axis=1)
    safe = np.where(valid, idx, np.arange(pts.shape[0])[:, None])  # missing -> self: offset 0
    n = np.maximum(cnt, 1).astype(np.float64)
    rel, mean = [], []
    for a in range(3):
        c = np.ascontiguousarray(pts[:, a])
        r = c[safe]
        r -= c[:, None]
        rel.append(r)
        mean.append(r.sum(axis=1) / n)
    cov = {
        (i, j): np.einsum("nk,nk->n", rel[i], rel[j]) / n - mean[i] * mean[j]
        for i in range(3)
        for j in range(i, 3)
    }
    return rel, mean, cov, cnt


def smallest_eigenvector(cov: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
    """Unit eigenvector of the smallest eigenvalue of many symmetric 3x3 matrices, (N, 3).

    Closed form (trigonometric eigenvalue, then the longest cross product of two rows of
    ``A - lambda I``), 2-3x faster than a batched ``eigh``. Where the smallest eigenvalue is
    not unique (a line or a single point) any vector of its eigenspace is as good; a zero
    matrix gets +z.
    """
    a00, a01, a02 = cov[0, 0], cov[0, 1], cov[0, 2]
    a11, a12, a22 = cov[1, 1], cov[1, 2], cov[2, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt(
        (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0
    )
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    ) / np.where(p > 0, p, 1.0) ** 3
    lam = q + 2.0 * p * np.cos(np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0 + 2.0 * np.pi / 3.0)
    d0, d1, d2 = a00 - lam, a11 - lam, a22 - lam
    best: list[np.ndarray] = []
    for (ux, uy, uz), (vx, vy, vz) in (
        ((d0, a01, a02), (a01, d1, a12)),
        ((d0, a01, a02), (a02, a12, d2)),
        ((a01, d1, a12), (a02, a12, d2)),
    ):
        cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        nn = cx * cx + cy * cy + cz * cz
        if not best:
            best = [cx, cy, cz, nn]
        else:
            longer = nn > best[3]
            best = [np.where(longer, v, b) for v, b in zip((cx, cy, cz, nn), best, strict=True)]
    cx, cy, cz, nn = best
    ok = nn > 1e-60
    inv = np.where(ok, 1.0 / np.sqrt(np.where(ok, nn, 1.0)), 0.0)
    return np.column_stack([cx * inv, cy * inv, np.where(ok, cz * inv, 1.0)])


def neighbourhood_normals(points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal (smallest-eigenvalue axis) and centroid of each point's neighbours."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    _, mean, cov, _ = _neighbour_moments(pts, idx)
    return smallest_eigenvector(cov), pts + np.column_stack(mean)


def plane_fit_criterion(points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PFC per point and its offset from the neighbours' plane.

    For each point a plane is fitted to its neighbours ``idx (N, k)`` (-1 = none) by the SVD of
    their centred coordinates, i.e. the smallest eigenvector of their 3x3 covariance (same
    thing, computed in closed form). ``d_p`` = distance of the point to that plane, ``d_avg`` =
    mean distance of the neighbours to it; ``PFC = d_p / (d_p + d_avg)``: it tends to 1 when
    the neighbourhood is flat and the point is off it, to 0 when the point lies on the plane.
    Points with fewer than 3 neighbours get PFC 0 (no evidence, keep).
    Returns ``(pfc (N,), d_p (N,))``.
    """
    rel, mean, cov, cnt = _neighbour_moments(points, idx)
    normal = smallest_eigenvector(cov)
    along = mean[0] * normal[:, 0] + mean[1] * normal[:, 1] + mean[2] * normal[:, 2]
    d_p = np.abs(along)
    proj = rel[0] * normal[:, :1]
    proj += rel[1] * normal[:, 1:2]
    proj += rel[2] * normal[:, 2:]
    proj -= along[:, None]
    np.abs(proj, out=proj)
    proj[idx < 0] = 0.0
    d_avg = proj.sum(axis=1) / np.maximum(cnt, 1)
    pfc = d_p / np.maximum(d_p + d_avg, 1e-12)
    pfc[cnt < 3] = 0.0
    return pfc, d_p


@dataclass
class PreprocessStats:
    """Point counts after each stage, for report.json and the status message."""

    input: int = 0
    valid: int = 0
    downsampled: int = 0
    after_sor: int = 0
    after_pfc: int = 0
    mixed_out_of_map: int = 0  # of after_pfc, left out of the map (map_mixed_pixels)
    sor_kept_on_lines: int = 0  # of after_sor, flagged by eq. 4 but inside a line of cells
    has_confidence: bool = False  # the frame had a confidence channel (min_confidence applies)


def filter_cloud(
    points: np.ndarray, cfg: PreprocessConfig, cell: float, stats: PreprocessStats
) -> np.ndarray:
    """SOR then PFC on an already downsampled cloud whose cell edge is ``cell``."""
    return points[filter_mask(points, cfg, cell, stats)]


# A point eq. 4 flags is kept where two of its neighbours within this many cells lie on
# opposite sides of it, or where it ends a line (see line_cells).
LINE_REACH_CELLS = 1.75  # a corner-adjacent cell is sqrt(3) = 1.73 cells away


def exact_knn(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`grid_knn`'s ``(idx, dist)`` by an exact search (Open3D's), for a cloud that was
    not downsampled: the grid search takes a cell's first 4 points, not its nearest, and with
    ``voxel_size 0`` eqs. 1-4 and the plane fits read 22 % of the true 8 nearest."""
    import open3d as o3d

    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    n = pts.shape[0]
    kk = min(k + 1, n)
    core: Any = o3d.core  # its stubs want a dtype and a device the numpy array carries
    tensor = core.Tensor(pts)
    nns = core.nns.NearestNeighborSearch(tensor)
    nns.knn_index()
    found, d2 = nns.knn_search(tensor, kk)
    idx = found.numpy().astype(np.int64)
    dist = np.sqrt(np.maximum(d2.numpy().astype(np.float64), 0.0))
    # self excluded: where a duplicate came first, self is further along the row
    rows = np.arange(n)
    is_self = idx == rows[:, None]
    drop = np.where(is_self.any(axis=1), is_self.argmax(axis=1), kk - 1)
    keep = np.ones_like(idx, dtype=bool)
    keep[rows, drop] = False
    idx = idx[keep].reshape(n, kk - 1)
    dist = dist[keep].reshape(n, kk - 1)
    if kk - 1 < k:  # fewer points than k + 1: the rest are missing, as grid_knn gives them
        pad = k - (kk - 1)
        idx = np.hstack([idx, np.full((n, pad), -1, dtype=np.int64)])
        dist = np.hstack([dist, np.full((n, pad), np.inf)])
    return idx, dist


def line_cells(
    points: np.ndarray, idx: np.ndarray, dist: np.ndarray, which: np.ndarray, cell: float
) -> np.ndarray:
    """For the points ``which`` of a downsampled cloud: does each lie on a line of cells? Inside
    one, two neighbours within :data:`LINE_REACH_CELLS` cells lie on opposite sides of it; at
    its end, one such neighbour and a second, farther one straight beyond it.

    Why: the paper removes outliers (eqs. 1-4) before it downsamples; done after, to keep a
    30 fps stream, a thin leg or a table's edge seen from chair height is one cell wide, so
    half its K = 8 neighbours are never within reach, its mean distance is 6 cm against 3.6 on
    a surface, and eq. 4 flagged the whole leg: a 3 cm leg at 1.5 m lost a 10 cm stretch on 6
    of 36 lattice phases (all of it on the worst), a table top seen from 0.70 m a third of its
    length. A wild return has no such neighbours, and eq. 4 still removes it."""
    if which.size == 0:
        return np.zeros(0, dtype=bool)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = dist[which]
    reach = LINE_REACH_CELLS * cell
    found = np.isfinite(d) & (d <= 2.0 * reach)
    safe = np.where(found, idx[which], which[:, None])
    vec = pts[safe] - pts[which][:, None, :]
    vec[~found] = 0.0
    dots = np.einsum("nkd,njd->nkj", vec, vec)
    near = found & (d <= reach)
    pair = near[:, :, None] & near[:, None, :]
    # opposite: an angle over ~105 deg between two one-cell steps
    inside = (pair & (dots < -0.25 * cell * cell)).any(axis=(1, 2))
    # the end: the farther neighbour k at least 1.5x as far as j, within 25 deg of its line
    dj, dk = d[:, :, None], d[:, None, :]
    beyond = near[:, :, None] & found[:, None, :] & (dk >= 1.5 * dj)
    straight = dots > 0.9 * np.where(np.isfinite(dj * dk), dj * dk, np.inf)
    end = (beyond & straight).any(axis=(1, 2))
    return np.asarray(inside | end)


def filter_mask(
    points: np.ndarray, cfg: PreprocessConfig, cell: float, stats: PreprocessStats
) -> np.ndarray:
    """Which points of :func:`filter_cloud`'s input it keeps; ``cell`` 0: not downsampled."""
    pts = points
    keep = np.ones(pts.shape[0], dtype=bool)
    need_k = max(cfg.sor_k if cfg.enable_sor else 0, cfg.pfc_k if cfg.enable_pfc else 0)
    stats.sor_kept_on_lines = 0
    if need_k > 0 and pts.shape[0] > need_k:
        idx, dist = exact_knn(pts, need_k) if cell <= 0 else grid_knn(pts, need_k, cell)
        if cfg.enable_sor:
            # A neighbour beyond the 5x5x5 block counts as 2.5 cells, not its distance: the
            # exact search for such points (44 % of a simulated frame's, 3 % of a real one's)
            # cost 26 ms a simulated frame and flagged 400x as many of its points (README)
            sor = statistical_outlier_mask(
                dist[:, : cfg.sor_k], cfg.sor_m, missing_distance=2.5 * (cell or 0.03)
            )
            if cell > 0:
                flagged = np.flatnonzero(~sor)
                lines = line_cells(pts, idx[:, : cfg.sor_k], dist[:, : cfg.sor_k], flagged, cell)
                sor[flagged[lines]] = True
                stats.sor_kept_on_lines = int(lines.sum())
            keep &= sor
        stats.after_sor = int(keep.sum())
        if cfg.enable_pfc:
            pfc, d_p = plane_fit_criterion(pts, idx[:, : cfg.pfc_k])
            keep &= ~((pfc > cfg.pfc_threshold) & (d_p > cfg.pfc_min_offset))
    else:
        stats.after_sor = pts.shape[0]
    stats.after_pfc = int(keep.sum())
    return keep


def preprocess(
    points: np.ndarray,
    cfg: PreprocessConfig,
    confidence: np.ndarray | None = None,
    stats: PreprocessStats | None = None,
) -> np.ndarray:
    """The whole chain on one sensor-frame cloud: valid -> downsample -> SOR -> PFC."""
    return preprocess_for_map(points, cfg, confidence, stats)[0]


def preprocess_for_map(
    points: np.ndarray,
    cfg: PreprocessConfig,
    confidence: np.ndarray | None = None,
    stats: PreprocessStats | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`preprocess`, and which of its points the map may keep (None: all of them).

    Registration and the map want different things from a depth edge: ICP holds on to the
    edge's pixels (dropping every mixed pixel redrew the simulated runs and read 9(a) worse),
    while the map must not keep the smear of mixed depths behind a post, which the grid reads
    as an obstacle. So ``map_mixed_pixels`` takes them out of the map only.
    """
    st = stats if stats is not None else PreprocessStats()
    organised = np.asarray(points, dtype=np.float64)
    if organised.size and organised.shape[-1] != 3:
        # (N, 4) (x y z intensity) reshaped to (-1, 3) whenever 4 N divides by 3, and every
        # point's coordinates came from two points: a map of garbage, and no word
        raise ValueError(f"points must be (N, 3) or (H, W, 3) x y z, not {organised.shape}")
    pts = organised.reshape(-1, 3)
    st.input = int(pts.shape[0])
    keep = valid_mask(pts, cfg.min_range, cfg.max_range, confidence, cfg.min_confidence)
    flagged = None
    if (cfg.mixed_pixels or cfg.map_mixed_pixels) and organised.ndim == 3:
        mixed = mixed_pixel_mask(organised, cfg.mixed_jump, cfg.mixed_jump_pitches).reshape(-1)
        if cfg.mixed_pixels:
            keep &= ~mixed
        else:
            flagged = mixed[keep]
    pts = pts[keep]
    st.valid = int(pts.shape[0])
    if pts.shape[0] == 0:
        st.downsampled = st.after_sor = st.after_pfc = 0
        return pts, None if flagged is None else np.zeros(0, dtype=bool)
    cell = cfg.voxel_size
    if cfg.target_points > 0:
        cell = cell_for_target(pts, cfg.target_points) or cfg.voxel_size
    share = None if flagged is None else flagged.astype(np.float64)
    if cell > 0:
        if flagged is None:
            pts = voxel_downsample(pts, cell)
        else:
            pts, share = voxel_downsample_flagged(pts, cell, flagged)
    st.downsampled = int(pts.shape[0])
    kept = filter_mask(pts, cfg, cell, st)
    if share is None:
        return pts[kept], None
    # a cell is left out of the map where most of its pixels were mixed
    map_keep = share[kept] <= 0.5
    st.mixed_out_of_map = int(map_keep.size - map_keep.sum())
    return pts[kept], map_keep
