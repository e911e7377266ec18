"""Level a map made elsewhere: the floor found, turned flat and put at z = 0.

`wheelgrid map` writes its maps levelled, but a map from another tool (a laser scanner's PCD, an
RTAB-Map or octomap export) is z-up with its origin anywhere: PCL's room scans have their floor
at z = -1.27 m, and the grid found no floor at z = 0. ``wheelgrid grid --level`` finds the floor
as the lowest large level surface, as the mapper does, and moves the map so that it lies at
z = 0. Numpy only: the grid must not need the mapping stack.

The rotation is the smallest that turns the floor's normal onto +z, so the map's x and y axes
(and the walls' yaw) stay where they were up to the tilt; what it was is written beside the
grid, since the grid's origin is then in the levelled frame, not the input's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wheelgrid_common.geometry import angle_deg, fit_plane

# A map whose floor leans more than this from its z axis is not z-up (a y-up mesh export, a
# scan with its scanner's axes): turned flat anyway, its walls would become its floor.
MAX_TILT_DEG = 15.0
_BIN_M = 0.02  # height bins of the floor search
_BAND_M = 0.05  # floor candidates: within this of the lowest peak
_EDGE_BINS = 5  # a floor's edge: the bins just under it that must be nearly empty
_WINDOW_BINS = 10  # the floor's peak: within this many bins over the lowest that holds enough
_GATE_M = 0.03  # plane refits: within this of the previous fit (feet and skirting drop out)
# A floor is at least about a metre wide: its points' spread across, as a standard deviation
# (a uniform 1 m strip: 0.29 m; the slab a 25 deg tilted room cut in its surfaces: 3 cm).
_MIN_WIDTH_STD_M = 0.25
_Z = np.array([0.0, 0.0, 1.0])


class LevelError(ValueError):
    """No floor to level the map on."""


@dataclass(frozen=True)
class Levelling:
    """``levelled = rotation @ p + translation`` for every input point ``p``."""

    rotation: np.ndarray
    translation: np.ndarray
    tilt_deg: float  # the floor's normal from the input's +z
    floor_z: float  # the floor's height in the input, below the map's centre
    floor_points: int
    rms_m: float  # the floor points' spread about the fitted plane

    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.translation
        return T

    def line(self) -> str:
        return (
            f"levelled: floor found at z = {self.floor_z:.3f} m, leaning {self.tilt_deg:.2f} deg "
            f"from z ({self.floor_points} floor points, {100 * self.rms_m:.1f} cm rms), moved to "
            "z = 0"
        )


def _rotation_onto_z(n: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit ``n`` (within 90 deg of +z) onto +z (Rodrigues)."""
    axis = np.cross(n, _Z)
    s, c = float(np.linalg.norm(axis)), float(n @ _Z)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def _lowest_peak(h: np.ndarray, need: float) -> float | None:
    """Centre of the lowest 2 cm height bin (3-bin smoothed) that holds ``need`` points and is
    a local peak: the floor, below every table top; a few stray returns under it do not count."""
    lo, hi = float(np.percentile(h, 0.1)) - _BIN_M, float(h.max()) + _BIN_M
    edges = np.arange(lo, hi + _BIN_M, _BIN_M)
    if edges.size < 3:
        return None
    hist, edges = np.histogram(h, edges)
    smooth = np.convolve(hist, np.ones(3), "same")
    for i in range(smooth.size):
        if (
            smooth[i] >= need
            and smooth[i] >= smooth[max(i - 1, 0)]
            and smooth[i] >= smooth[min(i + 1, smooth.size - 1)]
        ):
            return float(0.5 * (edges[i] + edges[i + 1]))
    return None


def _coarse_up(pts: np.ndarray, need_share: float, max_tilt_deg: float) -> np.ndarray:
    """The direction within ``max_tilt_deg`` of +z (1 deg apart) along which the lowest
    height peak holding ``need_share`` of the points is sharpest: a floor tilted 6 deg spreads
    over a metre of z across a 10 m room, and a fit to the strip of it in the lowest bin
    turned it only part of the way back."""
    rng = np.random.default_rng(0)
    # (drawn with replacement: without, numpy permutes all N indices of a 10 M-point map)
    sub = pts[rng.integers(0, pts.shape[0], 30000)] if pts.shape[0] > 30000 else pts
    need = need_share * sub.shape[0]
    step = math.radians(1.0)
    dirs = [_Z]
    for tilt in np.arange(step, math.radians(max_tilt_deg) + 1e-9, step):
        n_az = max(6, math.ceil(2 * math.pi * math.sin(tilt) / step))
        for az in np.arange(n_az) * (2 * math.pi / n_az):
            dirs.append(
                np.array(
                    [math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)]
                )
            )
    # (points under the floor, points in the 10 cm just under it, score, direction)
    found: list[tuple[float, float, float, np.ndarray]] = []
    for up in dirs:
        h = sub @ up
        counts = np.bincount(((h - h.min()) / _BIN_M).astype(np.int64))
        smooth = np.convolve(counts, np.ones(3), "same")
        enough = np.flatnonzero(smooth >= need)
        if enough.size:
            under = max(int(enough[0]) - 1, 0)
            # the highest bin within 20 cm over the lowest that holds enough (not further up:
            # the scanner's own height, where a laser's returns crowd, is no floor)
            score = float(smooth[enough[0] : enough[0] + _WINDOW_BINS].max())
            just_under = float(counts[max(under - _EDGE_BINS, 0) : under].sum())
            found.append((float(counts[:under].sum()), just_under, score, up))
    if not found:
        return dirs[0]
    # The floor is the bottom of the map: along its normal its points all fall in the lowest
    # bins that hold enough, and few lie under them. Along a wrong direction the floor smears
    # out under whatever surface it meets square (PCL's second room scan has a large one
    # 12 deg off level), so that surface has most of the floor under it. Returns under the
    # floor (a glossy floor's reflections, a mirror's) lie under it along every direction:
    # with more of them than ``need``, no direction was taken and a tilted floor was left
    # leaning. So more are let through over the fewest any direction has, where the floor
    # starts sharply (a smeared one thins out over many bins under where it holds enough).
    fewest = min(f[0] for f in found)
    ok = [f for f in found if f[0] <= need or (f[0] <= fewest + need and f[1] <= need / 5)]
    return max(ok, key=lambda f: f[2])[3] if ok else dirs[0]


def _bulk(pts: np.ndarray) -> np.ndarray:
    """The points within the map's bulk: no further outside the box of its 0.5 to 99.5
    percentiles, on any axis, than that box is wide (plus a metre)."""
    if pts.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    lo, hi = np.percentile(pts[:: max(1, pts.shape[0] // 100_000)], [0.5, 99.5], axis=0)
    span = hi - lo + 1.0
    return np.all((pts >= lo - span) & (pts <= hi + span), axis=1)


def find_floor_plane(
    points: np.ndarray, max_tilt_deg: float = MAX_TILT_DEG, min_fraction: float = 0.02
) -> tuple[np.ndarray, float, np.ndarray]:
    """The floor ``n . p + d = 0`` (``n`` up) of a roughly z-up map and its points' mask.

    The lowest height peak holding ``min_fraction`` of the points is the floor; the plane is
    fitted to the points within 5 cm of it, then twice to those within 3 cm of the fit. Done
    again along the fitted normal, as a tilted floor spreads over many bins of z.
    """
    every = np.asarray(points, dtype=np.float64)
    # searched in the map's bulk only: the height histograms span the points searched, and
    # one stray point 1e9 m away (a tool's FLT_MAX for "no return") asked for 373 GiB
    bulk = _bulk(every)
    pts = every[bulk]
    need = max(200.0, min_fraction * pts.shape[0])
    if pts.shape[0] < need:
        raise LevelError(f"only {pts.shape[0]} points: too few to find a floor in")
    up = _coarse_up(pts, need / pts.shape[0], max_tilt_deg)
    n, d, mask = up, 0.0, np.zeros(pts.shape[0], dtype=bool)
    for _ in range(5):
        h = pts @ up
        peak = _lowest_peak(h, need)
        if peak is None:
            raise LevelError(
                f"no level surface holds {int(need)} points (the floor): is the map z-up?"
            )
        mask = np.abs(h - peak) < _BAND_M
        n, d = fit_plane(pts[mask], up)
        for _ in range(2):
            mask = np.abs(pts @ n + d) < _GATE_M
            if mask.sum() < 3:
                break
            n, d = fit_plane(pts[mask], n)
        if angle_deg(n, up) < 0.01:
            break
        up = n
    floor = pts[mask]
    spread = np.linalg.svd(floor - floor.mean(axis=0), full_matrices=False, compute_uv=False)
    narrow = float(spread[1]) / math.sqrt(floor.shape[0])
    if narrow < _MIN_WIDTH_STD_M:
        # a slab cut across a tilted room's surfaces holds enough points, but as a strip
        raise LevelError(
            f"the lowest level surface found is a strip ({100 * narrow:.0f} cm standard "
            "deviation across), not a floor: is the map z-up?"
        )
    tilt = angle_deg(n, _Z)
    if tilt > max_tilt_deg:
        raise LevelError(
            f"the lowest large level surface leans {tilt:.1f} deg from z (more than "
            f"{max_tilt_deg:g}): is the map z-up? (its floor cannot be told from a wall)"
        )
    found = np.zeros(every.shape[0], dtype=bool)
    found[bulk] = mask
    return n, d, found


def level_map(
    points: np.ndarray, max_tilt_deg: float = MAX_TILT_DEG
) -> tuple[np.ndarray, Levelling]:
    """``points`` (finite rows only) moved so that their floor is flat at z = 0."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.shape[0] == 0:
        raise LevelError("the map has no (finite) points")
    n, d, mask = find_floor_plane(pts, max_tilt_deg)
    R = _rotation_onto_z(n)
    floor = pts[mask]
    rms = float(np.sqrt(np.mean((floor @ n + d) ** 2)))
    t = np.array([0.0, 0.0, d])  # R n = z, so R p . z = n . p: the floor goes to z = -d
    centre = np.median(pts[:, :2], axis=0)  # (a stray far point moves a mean)
    floor_z = float((-d - n[0] * centre[0] - n[1] * centre[1]) / n[2])
    info = Levelling(
        rotation=R,
        translation=t,
        tilt_deg=angle_deg(n, _Z),
        floor_z=floor_z,
        floor_points=int(mask.sum()),
        rms_m=rms,
    )
    return pts @ R.T + t, info
