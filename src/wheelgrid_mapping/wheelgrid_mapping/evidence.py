"""A voxel map that remembers how many frames saw each place.

Per-frame filters (eqs 1-4, PFC) cannot tell a flying pixel or a wild depth from a real surface
when it has neighbours in its own frame. Across frames they can: a real surface -- a wall, a
table leg, a 5 cm bar -- is seen again and again as the chair moves, while a flying pixel at a
depth edge or a ~1 % wild return lands somewhere new in every frame. So the map keeps, for
every coarse *evidence voxel*, the number of distinct frames that put a point in it, and only
voxels seen by ``min_frames`` frames reach the map. This is the hit-count half of an occupancy
map (OctoMap's). With the sensor origin given, :meth:`EvidenceMap.add` also casts each ray
(a bounded random subset of them) and counts a *miss* in every evidence voxel the ray crossed
before its hit: a place some frames saw through is free, whatever a few others returned there.
A voxel reaches the map when ``hits >= min_frames`` and ``hits >= hit_fraction * (hits +
misses)``, counting each frame at most once per voxel. A thin bar keeps a high hit share (rays
that miss it still pass its voxel, but so do the rays that hit it); a flying pixel gets one hit
and many misses.

The decision is per evidence voxel (10 cm), but a surface's own range noise (1-2 cm at 2-3 m)
spills across the voxel's boundary into the free space in front of it, where the rays that see
the surface pass: that spill would be dropped, the spill behind kept, and every surface near a
boundary pulled up to half its noise away from the sensor (0.5 % on a 1.2 m gap between table
legs, with perfect poses). So map voxels within ``margin`` of a kept one are kept too (grown
ring by ring over the map voxels, ``ceil(margin / voxel)`` rings): the surface keeps both sides
of its noise, and nothing more than those rings from a confirmed surface comes back. They grow
sideways only (within 30 deg of horizontal, ``up`` given): a floor's noise spills upwards, and
anything 5 cm above the floor is an obstacle to the grid, so that spill stays carved (with
vertical growth the far floor of the paper room put a phantom obstacle in a free cell); without
``up`` (before the floor is found) nothing grows.
"""

from __future__ import annotations

import math

import numpy as np

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
# The 26 neighbours of a voxel: their steps, and the packed-key offsets (keys are offset-coded,
# never negative per axis, so a neighbour's key is the voxel's key plus its offset).
_STEPS = np.array(
    [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if dx or dy or dz],
    dtype=np.int64,
)
NEIGHBOUR_KEYS = (_STEPS[:, 0] << (2 * _BITS)) + (_STEPS[:, 1] << _BITS) + _STEPS[:, 2]
_DIRECTIONS = _STEPS / np.linalg.norm(_STEPS, axis=1, keepdims=True)


INVALID_KEY = -(1 << 62)  # below every key and every key plus a NEIGHBOUR_KEYS step


def _pack(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
    """One int64 key from offset-coded voxel indices (row-major: sorting keys sorts i, j, k)."""
    return (i << (2 * _BITS)) | (j << _BITS) | k


def voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
    """Pack the integer voxel coordinates of ``points`` into one int64 per point."""
    ijk = np.floor(np.asarray(points, dtype=np.float64) / size).astype(np.int64) + _OFFSET
    if ijk.size and (ijk.min() < 0 or ijk.max() > _MASK):
        raise ValueError(f"points too far from the origin for {size} m voxels")
    return _pack(ijk[:, 0], ijk[:, 1], ijk[:, 2])


def voxel_keys_or_invalid(points: np.ndarray, size: float) -> np.ndarray:
    """:func:`voxel_keys` for callers that must not fail on one far point (the registrar's
    overlap check, every frame): a point whose voxel or a neighbour of it lies outside the key
    space gets ``INVALID_KEY``, which no stored key and no neighbour step can equal, instead
    of a key that would alias a voxel on the other side of the space."""
    f = np.floor(np.asarray(points, dtype=np.float64) / size) + _OFFSET
    ok = np.all((f >= 1) & (f <= _MASK - 1), axis=1)  # NaN and inf fail too
    ijk = np.where(ok[:, None], f, 0.0).astype(np.int64)
    keys = _pack(ijk[:, 0], ijk[:, 1], ijk[:, 2])
    keys[~ok] = INVALID_KEY
    return keys


def contains_sorted(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Which ``keys`` are in the sorted array ``sorted_keys``."""
    if sorted_keys.size == 0:
        return np.zeros(keys.shape[0], dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), sorted_keys.size - 1)
    return sorted_keys[pos] == keys


def _unique_keys(
    columns: list[np.ndarray], size: float, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """``np.unique(voxel_keys(points, size))`` for points given as x, y, z columns whose voxel
    indices lie within ``lo..hi`` (inclusive, as ``floor(p / size)``): a bitmap over that box
    when it is small (a frame: up to ~2 M cells), 2-3x faster than hashing each sample."""
    lo, hi = lo.astype(np.int64), hi.astype(np.int64)
    dims = hi - lo + 1
    if columns[0].shape[0] == 0:
        return np.empty(0, np.int64)
    if int(dims.prod()) > 16 * columns[0].shape[0] + 2_000_000:
        return np.unique(voxel_keys(np.column_stack(columns), size))
    if (lo + _OFFSET < 0).any() or (hi + _OFFSET > _MASK).any():
        raise ValueError(f"points too far from the origin for {size} m voxels")
    ijk = [np.floor(c / size).astype(np.int64) for c in columns]
    lin = ijk[0] - lo[0]
    lin *= dims[1]
    lin += ijk[1] - lo[1]
    lin *= dims[2]
    lin += ijk[2] - lo[2]
    occ = np.zeros(int(dims.prod()), dtype=bool)
    occ[lin] = True
    # back to packed keys; row-major over (i, j, k) is the packed keys' sort order
    i, rest = np.divmod(np.flatnonzero(occ), dims[1] * dims[2])
    j, k = np.divmod(rest, dims[2])
    return _pack(i + lo[0] + _OFFSET, j + lo[1] + _OFFSET, k + lo[2] + _OFFSET)


#: Points added before they are merged into the map: bounds what waiting frames hold (their
#: points, voxel keys and ray misses; ~200 B a point) whoever adds them.
PENDING_POINTS = 1_000_000


class EvidenceMap:
    """Centroid voxel map (``voxel``) filtered by frame evidence (``evidence_voxel``)."""

    def __init__(
        self,
        voxel: float,
        evidence_voxel: float,
        min_frames: int,
        hit_fraction: float = 0.0,
        max_rays: int = 4000,
        seed: int = 0,
        margin: float = 0.0,
    ) -> None:
        # named as the mapper's parameters (MapperConfig.validate relies on these checks)
        if not voxel > 0:
            raise ValueError(f"map_voxel must be > 0, not {voxel}")
        if not evidence_voxel > 0:
            raise ValueError(f"evidence_voxel must be > 0, not {evidence_voxel}")
        if min_frames < 1:
            raise ValueError(f"evidence_min_frames must be >= 1, not {min_frames}")
        if not 0.0 <= hit_fraction <= 1.0:
            raise ValueError(f"evidence_hit_fraction must be in [0, 1], not {hit_fraction}")
        if not 0.0 <= margin <= evidence_voxel:
            raise ValueError(
                f"evidence_margin must be in [0, evidence_voxel = {evidence_voxel}], not {margin}"
            )
        self.voxel = voxel
        self.evidence_voxel = evidence_voxel
        self.min_frames = min_frames
        self.hit_fraction = hit_fraction
        self.max_rays = max_rays
        self.rings = math.ceil(margin / voxel - 1e-9)
        self._rng = np.random.default_rng(seed)
        self._miss_keys = np.empty(0, np.int64)
        self._miss_frames = np.empty(0, np.int64)
        self._pending_miss: list[np.ndarray] = []
        self.frames = 0
        self._keys = np.empty(0, np.int64)  # map voxels, sorted
        self._sums = np.empty((0, 3))
        self._counts = np.empty(0, np.int64)
        self._ev_keys = np.empty(0, np.int64)  # evidence voxels, sorted
        self._ev_frames = np.empty(0, np.int64)
        self._pending: list[np.ndarray] = []
        self._pending_ev: list[np.ndarray] = []
        self._pending_points = 0

    def add(self, points: np.ndarray, origin: np.ndarray | None = None) -> None:
        """Add one frame's points (already in the map's frame), seen from ``origin``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        self.frames += 1
        if pts.shape[0] == 0:
            return
        self._pending.append(pts)
        # one vote per frame and evidence voxel, however many points the frame put there
        hits = np.unique(voxel_keys(pts, self.evidence_voxel))
        self._pending_ev.append(hits)
        if origin is not None and self.hit_fraction > 0:
            misses = self._ray_misses(pts, np.asarray(origin, dtype=np.float64).reshape(3))
            self._pending_miss.append(np.setdiff1d(misses, hits, assume_unique=True))
        self._pending_points += pts.shape[0]
        if self._pending_points >= PENDING_POINTS:
            # merged as they come, not all at the end: loop closure's rebuild added every
            # kept frame before the first merge, ~0.9 MB a frame at its peak (471 MB over the
            # node's 461 for 588 frames, ~5 GB at max_kept_frames; a review), where the OOM
            # killer ends a mapper
            self._consolidate()

    def _ray_misses(self, pts: np.ndarray, origin: np.ndarray) -> np.ndarray:
        """Evidence voxels crossed by the rays before their last two voxels (unique keys)."""
        if pts.shape[0] > self.max_rays:
            pts = pts[self._rng.choice(pts.shape[0], self.max_rays, replace=False)]
        d = pts - origin
        length = np.linalg.norm(d, axis=1)
        step = 0.5 * self.evidence_voxel
        # stop two evidence voxels short of the hit: range noise must not carve the surface
        reach = length - 2.0 * self.evidence_voxel
        n_steps = int(np.ceil(max(float(reach.max(initial=0.0)), 0.0) / step))
        if n_steps == 0:
            return np.empty(0, np.int64)
        t = np.arange(1, n_steps + 1) * step
        unit = d / np.maximum(length, 1e-9)[:, None]
        # Only the samples short of each ray's reach (a ray's are a prefix of t), built
        # directly: the full (rays, steps, 3) block was 80 % discarded and cost half the time.
        per_ray = np.searchsorted(t, reach, side="left")
        first = np.cumsum(per_ray) - per_ray
        k = np.arange(int(per_ray.sum())) - np.repeat(first, per_ray)
        tk = t[k]
        # each ray's direction repeated along its samples (a repeat, not a gather by ray index)
        columns = [origin[a] + np.repeat(unit[:, a], per_ray) * tk for a in range(3)]
        # every sample lies between the origin and its point: their box bounds the voxels (one
        # voxel wider, so no rounding can put a sample outside it)
        box = np.vstack([pts.min(axis=0), pts.max(axis=0), origin])
        lo = np.floor(box.min(axis=0) / self.evidence_voxel) - 1
        hi = np.floor(box.max(axis=0) / self.evidence_voxel) + 1
        return _unique_keys(columns, self.evidence_voxel, lo, hi)

    def _consolidate(self) -> None:
        if not self._pending:
            return
        pts = np.vstack(self._pending)
        keys = np.concatenate([self._keys, voxel_keys(pts, self.voxel)])
        sums = np.vstack([self._sums, pts])
        counts = np.concatenate([self._counts, np.ones(pts.shape[0], np.int64)])
        order = np.argsort(keys, kind="stable")
        keys, sums, counts = keys[order], sums[order], counts[order]
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        self._keys = keys[starts]
        self._sums = np.add.reduceat(sums, starts, axis=0)
        self._counts = np.add.reduceat(counts, starts)
        self._ev_keys, self._ev_frames = _merge_counts(
            self._ev_keys, self._ev_frames, self._pending_ev
        )
        self._miss_keys, self._miss_frames = _merge_counts(
            self._miss_keys, self._miss_frames, self._pending_miss
        )
        self._pending, self._pending_ev, self._pending_miss = [], [], []
        self._pending_points = 0

    def points(self, min_frames: int | None = None, up: np.ndarray | None = None) -> np.ndarray:
        """Centroids of the map voxels whose evidence voxel was seen by enough frames, and of
        those within the margin of them sideways (``up``: the vertical in the points' frame)."""
        self._consolidate()
        if self._keys.size == 0:
            return np.empty((0, 3))
        need = self.min_frames if min_frames is None else min_frames
        centroids = self._sums / self._counts[:, None]
        ev_of = voxel_keys(centroids, self.evidence_voxel)
        pos = np.searchsorted(self._ev_keys, ev_of)
        pos = np.clip(pos, 0, self._ev_keys.size - 1)
        seen = np.where(self._ev_keys[pos] == ev_of, self._ev_frames[pos], 0)
        keep = seen >= need
        if self.hit_fraction > 0 and self._miss_keys.size and min_frames != 0:
            mpos = np.clip(np.searchsorted(self._miss_keys, ev_of), 0, self._miss_keys.size - 1)
            missed = np.where(self._miss_keys[mpos] == ev_of, self._miss_frames[mpos], 0)
            keep &= seen >= self.hit_fraction * (seen + missed)
        if min_frames != 0 and up is not None:
            keep = self._grow(keep, np.asarray(up, dtype=np.float64).reshape(3))
        return centroids[keep]

    def _grow(self, keep: np.ndarray, up: np.ndarray) -> np.ndarray:
        """``keep`` plus the map voxels up to ``rings`` sideways voxel steps away."""
        sideways = NEIGHBOUR_KEYS[np.abs(_DIRECTIONS @ (up / np.linalg.norm(up))) < 0.5]
        keep = keep.copy()
        for _ in range(self.rings):
            cand = np.flatnonzero(~keep)
            kept = self._keys[keep]  # sorted, as self._keys is
            if cand.size == 0 or kept.size == 0:
                break
            grow = np.zeros(cand.size, dtype=bool)
            cand_keys = self._keys[cand]
            for off in sideways:
                grow |= contains_sorted(kept, cand_keys + off)
            keep[cand[grow]] = True
        return keep

    def all_points(self) -> np.ndarray:
        """Every map voxel's centroid, evidence ignored (for diagnostics)."""
        return self.points(min_frames=0)


def _merge_counts(
    keys: np.ndarray, counts: np.ndarray, new: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique keys with counts, after adding one vote per key of each array in ``new``."""
    if not new:
        return keys, counts
    allk = np.concatenate([keys, *new])
    allc = np.concatenate([counts, np.ones(allk.shape[0] - keys.shape[0], np.int64)])
    order = np.argsort(allk, kind="stable")
    allk, allc = allk[order], allc[order]
    starts = np.flatnonzero(np.r_[True, allk[1:] != allk[:-1]])
    return allk[starts], np.add.reduceat(allc, starts)
