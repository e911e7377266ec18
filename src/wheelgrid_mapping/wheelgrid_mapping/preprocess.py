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
because the paper notes it misfires around small features and folds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wheelgrid_common.params import field


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
    if cell <= 0:
        raise ValueError("cell size must be > 0")
    # Lattice anchored at 0 (not at the cloud's minimum) so grid_knn with the same cell sees
    # exactly one centroid per cell: a centroid never leaves its (convex) cell.
    origin = np.floor(pts.min(axis=0) / cell) * cell
    span = (pts.max(axis=0) - origin) / cell
    if (span >= (1 << 21) - 1).any():
        raise ValueError(f"cloud too large for cell {cell} m (span {span.max():.0f} cells)")
    ijk = np.floor((pts - origin) / cell).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    if int(dims.prod()) <= 256_000_000:
        # Dense lattice: cell index by a bitmap + cumulative sum instead of a sort.
        lin = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        occ = np.zeros(int(dims.prod()), dtype=bool)
        occ[lin] = True
        rank = np.cumsum(occ, dtype=np.int64) - 1
        inverse = rank[lin]
        counts = np.bincount(inverse)
    else:
        keys = _cell_keys(pts, cell, origin)
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.zeros((counts.shape[0], 3))
    for axis in range(3):
        out[:, axis] = np.bincount(inverse, weights=pts[:, axis], minlength=counts.shape[0])
    return out / counts[:, None]


def cell_for_target(points: np.ndarray, target: int, iterations: int = 4) -> float:
    """Cell edge whose :func:`voxel_downsample` leaves about ``target`` points.

    Starts from eq. 5 (``n = N_a / target`` points per cell); because scanned clouds are
    surfaces, not volumes, the count follows ``c * L^-a`` with ``a`` near 2, so a secant step
    in log-log space converges in a few iterations.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if target <= 0 or target >= pts.shape[0]:
        return 0.0
    extent = pts.max(axis=0) - pts.min(axis=0)
    cell = subdivision_cell(pts.shape[0], extent, pts.shape[0] / target)
    origin = pts.min(axis=0)

    def count_full(c: float) -> int:
        # Occupied-cell count without sorting when the lattice fits a bitmap (O(N)).
        ijk = np.floor((pts - origin) / c).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        if int(dims.prod()) <= 256_000_000:
            occ = np.zeros(int(dims.prod()), dtype=bool)
            occ[(ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]] = True
            return int(np.count_nonzero(occ))
        return int(np.unique(_cell_keys(pts, c, origin)).shape[0])

    prev: tuple[float, int] | None = None
    for _ in range(iterations):
        n = count_full(cell)
        if abs(n - target) <= 0.02 * target:
            break
        slope = 2.0
        if prev is not None and prev[1] != n and prev[0] != cell:
            slope = -math.log(n / prev[1]) / math.log(cell / prev[0])
            slope = min(max(slope, 0.5), 3.0)
        prev = (cell, n)
        cell *= (n / target) ** (1.0 / slope)
    return cell


def grid_knn(points: np.ndarray, k: int, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """K nearest neighbours (self excluded) through the space subdivision (text after eq. 5).

    Candidates are the points of the 3x3x3 cells around the point's cell; where fewer than
    ``k`` are found the point is searched again in the 5x5x5 block (the paper's "expand the
    search area"). Neighbours closer than one cell are exact; farther ones are the nearest
    among the candidates searched (a bounded search: enough for SOR and PFC, which only need a
    local neighbourhood, and it is what keeps 1 M points to seconds without a k-d tree). Meant
    for :func:`voxel_downsample` output at the same cell (one point per cell, same lattice); a
    cell holding more points contributes its first 4. Returns ``(idx (N,k) int64,
    dist (N,k) float64)`` sorted by distance; missing neighbours have index -1 and distance ``inf``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    idx_out = np.full((n, k), -1, dtype=np.int64)
    dist_out = np.full((n, k), np.inf)
    if n < 2 or k < 1:
        return idx_out, dist_out
    origin = (np.floor(pts.min(axis=0) / cell) - 2.0) * cell  # same lattice as voxel_downsample
    ijk = np.floor((pts - origin) / cell).astype(np.int64)
    dims = ijk.max(axis=0) + 3
    lin = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(lin, kind="stable")
    lin_sorted = lin[order]
    # Runs of equal keys in the sorted order = occupied cells (cheaper than np.unique).
    starts = np.flatnonzero(np.r_[True, lin_sorted[1:] != lin_sorted[:-1]])
    ucells = lin_sorted[starts]
    counts = np.diff(np.r_[starts, n])
    cap = int(min(4, counts.max()))
    # Row U is a sentinel (-1) so that "empty cell" (-1) indexes it directly.
    table = np.full((ucells.shape[0] + 1, cap), -1, dtype=np.int32)  # int32: half the traffic
    for r in range(cap):
        has = np.flatnonzero(counts > r)
        table[has, r] = order[starts[has] + r]
    cell_of_point = np.empty(n, dtype=np.int64)
    cell_of_point[order] = np.repeat(np.arange(ucells.shape[0]), counts)
    # Occupied-cell lookup: a dense table when the lattice is small enough (one gather per
    # query), else a binary search in the sorted cell list.
    n_cells = int(dims.prod())
    dense: np.ndarray | None = None
    if n_cells <= 64_000_000:
        dense = np.full(n_cells, -1, dtype=np.int32)
        dense[ucells] = np.arange(ucells.shape[0], dtype=np.int32)

    def lookup(keys: np.ndarray) -> np.ndarray:
        if dense is not None:
            inside = (keys >= 0) & (keys < n_cells)
            return np.where(inside, dense[np.clip(keys, 0, n_cells - 1)], -1)
        pos = np.minimum(np.searchsorted(ucells, keys), ucells.shape[0] - 1)
        return np.where(ucells[pos] == keys, pos, -1)

    # float32 halves the memory traffic (cm-exact here); the sentinel last row is far away.
    pts32 = np.vstack([(pts - origin), np.full((1, 3), 1e9)]).astype(np.float32)

    def search(sel: np.ndarray, reach: int) -> None:
        offs = np.array(
            [
                (a * dims[1] + b) * dims[2] + c
                for a in range(-reach, reach + 1)
                for b in range(-reach, reach + 1)
                for c in range(-reach, reach + 1)
            ],
            dtype=np.int64,
        )
        # Look neighbours up once per occupied cell, not per point.
        my_cells = (
            np.arange(ucells.shape[0]) if sel.shape[0] == n else np.unique(cell_of_point[sel])
        )
        neigh = ucells[my_cells][:, None] + offs[None, :]
        cand_cells = lookup(neigh)  # (C, len(offs)), -1 = empty
        local = (
            cell_of_point[sel]
            if sel.shape[0] == n
            else np.searchsorted(my_cells, cell_of_point[sel])
        )
        chunk = max(1, 2_000_000 // (len(offs) * cap))
        for s in range(0, sel.shape[0], chunk):
            q = sel[s : s + chunk]
            cc = cand_cells[local[s : s + chunk]]
            cand = table[cc].reshape(len(q), -1)  # cc = -1 -> sentinel row -> -1
            cand[cand == q[:, None]] = -1
            diff = pts32[cand] - pts32[q][:, None, :]  # cand = -1 -> sentinel point, far away
            d = np.einsum("nci,nci->nc", diff, diff)
            d[cand < 0] = np.inf
            kk = min(k, d.shape[1])
            part = np.argpartition(d, kk - 1, axis=1)[:, :kk]
            dd = np.take_along_axis(d, part, axis=1)
            ii = np.take_along_axis(cand, part, axis=1)
            srt = np.argsort(dd, axis=1)
            dd = np.take_along_axis(dd, srt, axis=1)
            ii = np.take_along_axis(ii, srt, axis=1)
            ii[~np.isfinite(dd)] = -1
            dist_out[q, :kk] = np.sqrt(dd)
            idx_out[q, :kk] = ii

    search(np.arange(n), 1)
    short = np.flatnonzero(~np.isfinite(dist_out[:, -1]))
    if short.size:
        search(short, 2)
    return idx_out, dist_out


def statistical_outlier_mask(
    dist: np.ndarray, m: float, missing_distance: float | None = None
) -> np.ndarray:
    """Eqs. 1-4 on K-NN distances ``dist (N, K)``: True = keep (inlier).

    mu_i is the mean distance of point i to its K neighbours; mu and sigma (eq. 2, N-1) are the
    mean and standard deviation of all mu_i; ``t = mu + m sigma`` (eq. 3); an outlier has
    ``mu_i >= t`` (eq. 4). A neighbour the bounded search did not find counts as
    ``missing_distance`` (default: the largest finite distance seen), so an isolated point is
    an outlier rather than silently kept.
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
    if sigma == 0.0:
        return np.ones(d.shape[0], dtype=bool)
    return mu_i < t  # eq. 4: outlier when mu_i >= t


def neighbourhood_normals(points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal (smallest-eigenvalue axis) and centroid of each point's neighbours."""
    pts = np.asarray(points, dtype=np.float64)
    valid = idx >= 0
    nb = pts[np.maximum(idx, 0)]
    w = valid[:, :, None].astype(np.float64)
    cnt = np.maximum(valid.sum(axis=1), 1)[:, None]
    centroid = (nb * w).sum(axis=1) / cnt
    cen = (nb - centroid[:, None, :]) * w
    cov = np.einsum("nki,nkj->nij", cen, cen) / cnt[:, :, None]
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0], centroid


def plane_fit_criterion(points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PFC per point and its offset from the neighbours' plane.

    For each point an SVD (eigen-decomposition of the 3x3 covariance, the same thing) fits a
    plane to its neighbours ``idx (N, k)`` (-1 = none). ``d_p`` = distance of the point to that
    plane, ``d_avg`` = mean distance of the neighbours to it; ``PFC = d_p / (d_p + d_avg)``: it
    tends to 1 when the neighbourhood is flat and the point is off it, to 0 when the point lies on
    the plane. Points with fewer than 3 neighbours get PFC 0 (no evidence, keep).
    Returns ``(pfc (N,), d_p (N,))``.
    """
    pts = np.asarray(points, dtype=np.float64)
    valid = idx >= 0
    nvalid = valid.sum(axis=1)
    nb = pts[np.maximum(idx, 0)]  # (N, k, 3)
    w = valid[:, :, None].astype(np.float64)
    cnt = np.maximum(nvalid, 1)[:, None]
    centroid = (nb * w).sum(axis=1) / cnt
    cen = (nb - centroid[:, None, :]) * w
    cov = np.einsum("nki,nkj->nij", cen, cen) / cnt[:, :, None]
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[:, :, 0]  # smallest eigenvalue = plane normal
    d_p = np.abs(np.einsum("ni,ni->n", pts - centroid, normal))
    d_nb = np.abs(np.einsum("nki,ni->nk", cen, normal))
    d_avg = (d_nb * valid).sum(axis=1) / np.maximum(nvalid, 1)
    pfc = d_p / np.maximum(d_p + d_avg, 1e-12)
    pfc[nvalid < 3] = 0.0
    return pfc, d_p


@dataclass
class PreprocessStats:
    """Point counts after each stage, for report.json and the status message."""

    input: int = 0
    valid: int = 0
    downsampled: int = 0
    after_sor: int = 0
    after_pfc: int = 0


def filter_cloud(
    points: np.ndarray, cfg: PreprocessConfig, cell: float, stats: PreprocessStats
) -> np.ndarray:
    """SOR then PFC on an already downsampled cloud whose cell edge is ``cell``."""
    pts = points
    need_k = max(cfg.sor_k if cfg.enable_sor else 0, cfg.pfc_k if cfg.enable_pfc else 0)
    if need_k > 0 and pts.shape[0] > need_k:
        idx, dist = grid_knn(pts, need_k, cell)
        keep = np.ones(pts.shape[0], dtype=bool)
        if cfg.enable_sor:
            keep &= statistical_outlier_mask(
                dist[:, : cfg.sor_k], cfg.sor_m, missing_distance=2.5 * cell
            )
        stats.after_sor = int(keep.sum())
        if cfg.enable_pfc:
            pfc, d_p = plane_fit_criterion(pts, idx[:, : cfg.pfc_k])
            keep &= ~((pfc > cfg.pfc_threshold) & (d_p > cfg.pfc_min_offset))
        pts = pts[keep]
    else:
        stats.after_sor = pts.shape[0]
    stats.after_pfc = int(pts.shape[0])
    return pts


def preprocess(
    points: np.ndarray,
    cfg: PreprocessConfig,
    confidence: np.ndarray | None = None,
    stats: PreprocessStats | None = None,
) -> np.ndarray:
    """The whole chain on one sensor-frame cloud: valid -> downsample -> SOR -> PFC."""
    st = stats if stats is not None else PreprocessStats()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    st.input = int(pts.shape[0])
    pts = pts[valid_mask(pts, cfg.min_range, cfg.max_range, confidence, cfg.min_confidence)]
    st.valid = int(pts.shape[0])
    if pts.shape[0] == 0:
        st.downsampled = st.after_sor = st.after_pfc = 0
        return pts
    cell = cfg.voxel_size
    if cfg.target_points > 0:
        cell = cell_for_target(pts, cfg.target_points) or cfg.voxel_size
    if cell > 0:
        pts = voxel_downsample(pts, cell)
    st.downsampled = int(pts.shape[0])
    return filter_cloud(pts, cfg, cell if cell > 0 else 0.03, st)
