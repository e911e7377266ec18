"""``wheelgrid measure MAP.ply``: distance between two surfaces of a map (the paper's Table I).

The paper measured obstacle-to-obstacle distances on its 3D map by hand in MATLAB. Here each
surface is chosen by an axis-aligned box (map frame, metres) around it; in each box the plane
most points agree with is found (RANSAC, 1.5 cm) and refitted by SVD on its inliers, so a
neighbouring surface the box clips does not tilt or shift it; then only its inliers whose own
surface normal (from their neighbours within ``--normal-radius``) faces the same way are kept,
so the sides of a leg or the underside of a top that run into the face do not pull it inwards.
The distance is that between two parallel planes: their offsets stand on the kept points,
their one common normal on both planes' inliers (which the facing test need not narrow: see
:func:`faces_distance`). With ``--true`` the deviation in % is printed, as in Table I.

Every reading comes with a standard error: the spread of the same measure over bootstrap
resamples of each face's points. A face of a thin table leg seen from the side can be ten
points of a registered map; its reading then moves by millimetres with which ten points the
sensor happened to return, and a user comparing two maps (or a map with a tape) needs to know
that before reading anything into a difference. It is the points' own scatter only: an error
all of one face's points share (a frame placed a centimetre off) is not in it. The error is the
resamples' median absolute deviation from their median, scaled to a standard deviation where
they are normal (up to half of them may be far off without moving it), and the
share of resamples more than :data:`UNSTABLE_SIGMAS` of it from their median is reported
apart: on a face of 16 points, one resample in six can tilt the faces' common normal by
several degrees and read up to 18 cm off; a standard deviation would then call every reading
of that map +- 4 cm, when the reading itself sits in the main mode, and hide why.

What no resample shows is a tilt all of a face's points share, and the edge faces of two
tables (two 5 cm legs each and the rim of the top, 1-2 voxels high) fix their normal only to
0.1-1 deg on a registered 2 cm map. The reading therefore also says how far apart
sideways the two faces' points sit, and what each 0.1 deg of tilt does to it across that
lever. Where the faces' direction is known better than their points fix it (both are
perpendicular to a wall; a simulated scene's truth), ``--normal`` reads the same faces along
it and says how far it is from their own common normal, and ``--normal-box`` takes that
direction from the map itself: the normal of a large surface in a third box (a wall the faces
are parallel to), which thousands of points fix to a tenth of a degree or better.

A box around two parallel surfaces a few centimetres apart (a wall and a picture on it, a box
drawn too deep) has no one reading: the fit takes the surface with more points, and the other
may be the face meant. Where the other lies nearer the other box the box is refused (exit 2)
with both surfaces' offsets, points and readings, and the advice to shrink it; where it lies
farther away, it is most often the back face of the thin object whose front was read (a table
leg behind its row's edge), facing away, and the line names it (:func:`second_surfaces` says
what counts as a surface, not the spread of one; :func:`second_reading` why the side decides).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from wheelgrid_common.fileio import read_cloud

#: Normals from neighbours within this radius (m): 1.5 voxels of a 2 cm map, so the 3x3
#: neighbourhood of a point on a face, diagonals included.
NORMAL_RADIUS = 0.03
#: A point belongs to the fitted face when its normal is within this angle of the plane's.
NORMAL_ANGLE_DEG = 30.0
#: RANSAC's band (m): a face's points and its range noise.
INLIER = 0.015
#: Fewer points than this facing the plane: the normal step is skipped (noted in the result).
MIN_FACING = 10
#: Bootstrap resamples for the standard error (seeded: the same map always reads the same).
BOOTSTRAP = 200
#: A larger face is resampled as this many of its points: its standard error is then an upper
#: bound (already well under a millimetre), and a wall of 10^5 points takes a second, not 50.
BOOTSTRAP_MAX_POINTS = 5000
#: Resamples farther than this many standard errors from the median are counted as unstable
#: (0.006 % of them where the resamples are normal).
UNSTABLE_SIGMAS = 4.0
UNSTABLE_MIN_M = 1e-3  # a resample this close to the median is never "unstable"
#: A box's points fix a plane only if they spread at least this far (m, RMS) across the line
#: that fits them best. One point repeated (a map's duplicates) or one row of points leaves the
#: plane free to turn about that line, and its normal would be whatever rounding made it. Far
#: below any surface's noise, above float32 rounding of map coordinates (2 um RMS at 100 m).
MIN_PLANE_SPREAD = 1e-5
#: A ``--normal-box`` surface needs this many points: it is there to fix a direction better
#: than the faces do (0.04 m2 of a 2 cm map; a wall's box holds thousands).
MIN_REFERENCE_POINTS = 100
#: A second surface parallel to a box's face is a peak of the box's points along the face's
#: normal, a band as thin as the face's own (its 2.5 robust sigmas), at least :data:`MIN_FACING`
#: points, and apart from the face by a valley at least one band wide whose points lie this
#: many times thinner than the peak's: one surface's noise thins out steadily away from it and
#: has no valley, a second surface stands out of it.
SECOND_SURFACE_VALLEY = 0.25
#: ... and at least this share of the face's own points.
SECOND_SURFACE_SHARE = 0.01


@dataclass
class Plane:
    normal: np.ndarray
    centroid: np.ndarray
    points: int
    rms: float
    support: np.ndarray  # the points the final fit stands on
    facing: bool = False  # those are only the inliers whose normals face its way
    # with ``facing``: all of the fit's inliers, the facing ones among them (what the faces'
    # common direction stands on, see :func:`measure`)
    inliers: np.ndarray | None = None
    # other surfaces parallel to it in the box (fit_face), the most-supported on each side:
    # ``+`` along ``normal``, ``-`` against it
    seconds: dict[str, Surface] = field(default_factory=dict)


@dataclass
class Surface:
    """A second surface parallel to a box's face (:func:`second_surfaces`)."""

    offset: float  # m along the face's normal, from the face
    points: int


@dataclass
class Measurement:
    distance: float  # m
    angle_deg: float  # between the two planes (0 = parallel)
    points_a: int
    points_b: int
    rms_a: float
    rms_b: float
    facing_a: bool = False  # the normal step was applied (enough points faced the plane)
    facing_b: bool = False
    stderr: float = math.nan  # m, bootstrap over each surface's points (their scatter only)
    unstable_pct: float = 0.0  # % of resamples beyond UNSTABLE_SIGMAS standard errors
    # m, how far apart the two faces' kept points sit across the normal: a normal tilted by
    # t radians moves the reading by about sideways * t, which no resample of the points shows
    sideways: float = 0.0
    along: list[float] | None = None  # the given direction the distance was read along
    along_angle_deg: float = 0.0  # between it and the faces' fitted common normal
    normal_points: int = 0  # the points the faces' common normal stands on (both faces)
    normal: list[float] | None = None  # the faces' fitted common normal (map frame)
    # a second surface parallel to the face in box A / B, nearer the other box: {"offset": m,
    # toward the other box positive; "points"; "distance": the reading to it}; None where the
    # box holds none
    second_a: dict[str, float] | None = None
    second_b: dict[str, float] | None = None
    # the same, farther from the other box (most often the back face of a thin object)
    behind_a: dict[str, float] | None = None
    behind_b: dict[str, float] | None = None


def box_mask(points: np.ndarray, box: list[float] | np.ndarray, pad: float = 0.0) -> np.ndarray:
    """Which points lie in ``box`` (x0 y0 z0 x1 y1 z1, either corner first) widened by ``pad``."""
    b = np.asarray(box, dtype=float).reshape(2, 3)
    lo, hi = b.min(axis=0) - pad, b.max(axis=0) + pad
    return ((points >= lo) & (points <= hi)).all(axis=1)


def points_in_box(points: np.ndarray, box: list[float] | np.ndarray) -> np.ndarray:
    return points[box_mask(points, box)]


def _robust_band(r: np.ndarray, inlier: float) -> float:
    """2.5 robust sigmas (MAD) of a surface's own noise ``r`` (absolute offsets), 3 mm at the
    least (a noise-free surface keeps its points) and ``inlier`` at most."""
    return float(np.clip(2.5 * 1.4826 * np.median(r), 0.003, inlier))


def plane_defect(points: np.ndarray) -> str | None:
    """Why ``points`` fix no plane (fewer than 3 distinct ones, or all on one line), or None.

    Checked on a box's points before any fit, not left to the fits: SVD and np.unique take
    duplicates and lines without complaint and hand on a plane that turns freely, or too few
    rows for the faces' common normal (an IndexError deep in :func:`measure`).
    """
    n = points.shape[0]
    if n < 3:
        return f"a plane needs >= 3 points, the box holds {n}"
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if s[1] / math.sqrt(n) > MIN_PLANE_SPREAD:  # RMS distance from the best line
        return None
    distinct = np.unique(points, axis=0).shape[0]
    if distinct < 3:
        return f"a plane needs >= 3 distinct points, the box holds {n} but {distinct} distinct"
    return f"a plane needs points not all on one line, the box's {n} points lie on one"


def fit_plane(points: np.ndarray, inlier: float = INLIER, trials: int = 300) -> Plane:
    """The plane most points of the box agree with (RANSAC), refitted by SVD on its inliers.

    A box drawn around a table's edge face also catches the rim of its top and the sides of
    its legs; a least-squares fit through all of them is tilted and pulled inwards by
    centimetres (the first version of this tool was: +1.3 % on a 1.66 m gap with perfect
    poses). The plane with the largest support within ``inlier`` metres is the surface the box
    was drawn for; refits on its inliers, narrowed to the surface's own noise, remove the
    sampling noise and what is left of the neighbour's rim. Seeded: the same map
    always measures the same.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    defect = plane_defect(pts)
    if defect is not None:
        raise ValueError(defect)
    rng = np.random.default_rng(0)
    best = np.ones(pts.shape[0], dtype=bool)
    if pts.shape[0] > 10:
        best_count = 0
        sample = pts if pts.shape[0] <= 20_000 else pts[rng.choice(pts.shape[0], 20_000, False)]
        tri = rng.integers(0, sample.shape[0], size=(trials, 3))
        a, b, c = sample[tri[:, 0]], sample[tri[:, 1]], sample[tri[:, 2]]
        normals = np.cross(b - a, c - a)
        norm = np.linalg.norm(normals, axis=1)
        for i in np.flatnonzero(norm > 1e-9):
            n = normals[i] / norm[i]
            inl = np.abs((pts - a[i]) @ n) <= inlier
            count = int(inl.sum())
            if count > best_count:
                best, best_count = inl, count
    # a sliver of a triangle can win on a box that is mostly one line: then all of its points
    sel = pts[best] if plane_defect(pts[best]) is None else pts
    for _ in range(5):
        # Refit, then re-select within 2.5 robust sigmas (MAD) of the surface's own noise: the
        # rim of a neighbouring surface inside the RANSAC band drops out step by step.
        c = sel.mean(axis=0)
        n = np.linalg.svd(sel - c, full_matrices=False)[2][2]
        inl = np.abs((pts - c) @ n) <= _robust_band(np.abs((sel - c) @ n), inlier)
        if plane_defect(pts[inl]) is not None:  # narrowed to a line or a point: keep the last
            break
        sel = pts[inl]
    c = sel.mean(axis=0)
    n = np.linalg.svd(sel - c, full_matrices=False)[2][2]
    rms = float(np.sqrt(np.mean(((sel - c) @ n) ** 2)))
    return Plane(n, c, int(sel.shape[0]), rms, sel)


def point_normals(points: np.ndarray, radius: float) -> np.ndarray:
    """Unit normal of each point from its neighbours within ``radius`` (at most 30; Open3D's
    PCA; sign arbitrary)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    return np.asarray(cloud.normals)


def fit_face(
    points: np.ndarray,
    box: list[float] | np.ndarray,
    radius: float = NORMAL_RADIUS,
    max_angle_deg: float = NORMAL_ANGLE_DEG,
) -> Plane:
    """The face inside ``box``: :func:`fit_plane`'s, standing on its points that face its way.

    A box drawn around a table leg's face also holds the first centimetres of the leg's sides
    and of the top's underside; their points lie within the fit's band, behind the face, and
    pull it inwards and tilt it. Their normals are at right angles to the face's, so the face
    is the points within the plane's band whose own normal (from their neighbours in the whole
    map: the box widened by ``radius``, so a point at the box's edge has all of its own) is
    within ``max_angle_deg`` of the plane's. Those points are the ``support``, on which
    :func:`measure` reads the faces' offsets; their common normal stands on the ``inliers``.
    """
    around = points[box_mask(points, box, max(radius, 0.0))]
    inside = box_mask(around, box)
    pts = around[inside]
    plane = fit_plane(pts)
    if pts.shape[0] < MIN_FACING:
        # 4 stray points in a box 1.2 m from a wall read as a face, 121.25 +- 1.11 cm, exit 0
        raise ValueError(
            f"the box holds {pts.shape[0]} points, too few to be a surface (at least "
            f"{MIN_FACING}): is it drawn around one?"
        )
    if radius <= 0:
        plane.seconds = second_surfaces(pts, plane)
        return plane
    normals = point_normals(around, radius)[inside]
    offset = (pts - plane.centroid) @ plane.normal
    parallel = np.abs(normals @ plane.normal) >= math.cos(math.radians(max_angle_deg))
    facing = parallel & (np.abs(offset) <= INLIER)
    if int(facing.sum()) < MIN_FACING:
        plane.seconds = second_surfaces(pts[parallel], plane)
        return plane
    sel = pts[facing]
    # The normal stays the fit's on all inliers: as few as 20 points of one leg may face the
    # plane on a real map, too few to fix its tilt (their own fit leaned 11-21 deg and the two
    # faces were called not parallel); the distance takes both faces' normal together.
    c = sel.mean(axis=0)
    rms = float(np.sqrt(np.mean(((sel - c) @ plane.normal) ** 2)))
    face = Plane(plane.normal, c, int(sel.shape[0]), rms, sel, facing=True, inliers=plane.support)
    face.seconds = second_surfaces(pts[parallel], face)
    return face


def second_surfaces(points: np.ndarray, face: Plane) -> dict[str, Surface]:
    """Other surfaces parallel to ``face`` among ``points`` (a box's, those whose normals
    face its way where known): the most-supported on each side of it, ``+`` along its normal
    and ``-`` against it.

    The fit takes the surface with the most points; a second one a few centimetres behind it
    is as much a face, and a reading to the wrong one is off by their distance with nothing
    said. What counts as a surface comes from the face itself: a band of the points' offsets
    along its normal as thin as the face's own (2.5 robust sigmas of its noise, as the fits
    trim to), at least :data:`MIN_FACING` points in it, and between the two a valley at least
    one band wide and :data:`SECOND_SURFACE_VALLEY` times thinner. One surface's noise and
    the first centimetres of a leg's sides thin out or stay level away from the face, with no
    valley; a few stray points fill no band. Which side matters is :func:`measure`'s to say.
    """
    own = np.abs((face.support - face.centroid) @ face.normal)
    band = _robust_band(own, INLIER)
    d = np.sort((np.asarray(points, np.float64) - face.centroid) @ face.normal)
    found: dict[str, Surface] = {}
    for side in (1.0, -1.0):
        o = np.sort(side * d[side * d > band])  # beyond the face's band, on this side
        if o.size < MIN_FACING:
            continue
        peak = np.searchsorted(o, o + band, "right") - np.searchsorted(o, o - band, "left")
        valley = np.searchsorted(o, o - band, "left")  # points between the face and the peak
        width = o - 2.0 * band
        # Beyond the fit's own inlier band (what lies within it is the face's, as the fit
        # reads it) and a share of the face's points: 13 of 300 uniform outliers 0.9 cm off a
        # 5000-point wall were "a second surface" on 2 of 10 draws (a review)
        least = max(MIN_FACING, SECOND_SURFACE_SHARE * face.support.shape[0])
        ok = (peak >= least) & (width >= band) & (o > INLIER)
        ok &= valley * 2.0 * band <= SECOND_SURFACE_VALLEY * peak * np.maximum(width, band)
        if not ok.any():
            continue
        k = int(np.argmax(np.where(ok, peak, -1)))
        sel = o[np.abs(o - o[k]) <= band]
        found["+" if side > 0 else "-"] = Surface(side * float(np.median(sel)), int(sel.size))
    return found


def _common_normal(sets: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """One plane normal for point sets each centred on its own centroid, and the centroids."""
    cs = [s.mean(axis=0) for s in sets]
    stacked = np.vstack([s - c for s, c in zip(sets, cs, strict=True)])
    return np.linalg.svd(stacked, full_matrices=False)[2][2], cs


def parallel_distance(a: np.ndarray, b: np.ndarray, normal: np.ndarray | None = None) -> float:
    """Distance between two parallel planes fitted to point sets ``a`` and ``b`` together
    (or, with ``normal``, standing on that unit normal: only the offsets are fitted).

    Table I measures a gap between facing surfaces: one normal for both (the smallest singular
    vector of both sets, each centred on its own centroid) stands on both faces' points, so a
    face seen by only one leg's 20 points cannot tilt it, as its own fit can (on points lying
    exactly on the paper scene's surfaces, separate fits read the table gap 0.27 % long: the
    sides of the legs tilt them, and centroids 0.4 m apart sideways turn a tilt into length).
    """
    sets = [np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)]

    def common(sets: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
        if normal is None:
            return _common_normal(sets)
        return normal, [s.mean(axis=0) for s in sets]

    for _ in range(4):
        n, cs = common(sets)
        # as in fit_plane: each face within 2.5 robust sigmas of its own noise, so a corner
        # point whose normal still leans the face's way (its neighbours are mostly the face's)
        # drops out
        trimmed = []
        for s, c in zip(sets, cs, strict=True):
            r = np.abs((s - c) @ n)
            keep = r <= _robust_band(r, INLIER)
            trimmed.append(s[keep] if keep.sum() >= 3 else s)
        sets = trimmed
    n, cs = common(sets)
    return abs(float((cs[1] - cs[0]) @ n))


def sideways_offset(apart: np.ndarray, normal: np.ndarray) -> float:
    """How far apart two faces' points sit across ``normal`` (m), from ``apart``, the vector
    between their centroids.

    The lever of the reading: the edge faces of two tables fix their common normal only to
    a fraction of a degree. On a perfect map of the paper's tables (simulated seed 16 at its
    true poses) the kept faces were mostly one leg of each table, 0.6 m apart sideways, their
    points within 0.6 mm of the true surfaces; their common normal, fitted on those facing
    points alone, was 0.8 deg off the true one and the 120.12 cm gap read 1.1 cm short (0.2
    deg and 3 mm since the normal stands on the planes' inliers, the top's rim among them).
    """
    return float(np.linalg.norm(apart - (apart @ normal) * normal))


def reference_plane(points: np.ndarray, box: list[float] | np.ndarray) -> Plane:
    """The plane of the surface in ``box`` whose normal ``--normal-box`` reads a gap along.

    Two tables' edge faces fix their common normal to 0.1-1 deg, and across the half metre
    they sit apart sideways that is up to a centimetre of reading; a wall the faces are
    parallel to holds thousands of points, and on the simulated runs' TRUE-pose maps its
    fitted normal was within 0.15 deg of the true one. The plane is :func:`fit_plane`'s
    (RANSAC, then refits on its own band), so furniture the box clips does not tilt it.
    """
    pts = points_in_box(points, box)
    if pts.shape[0] < MIN_REFERENCE_POINTS:
        raise ValueError(
            f"--normal-box holds {pts.shape[0]} points; a reference surface needs "
            f">= {MIN_REFERENCE_POINTS} (draw it around a wall the faces are parallel to)"
        )
    try:
        return fit_plane(pts)
    except ValueError as exc:
        raise ValueError(f"--normal-box: {exc}") from exc


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle (deg) between two unit normals as lines: a plane's normal has no sign."""
    return math.degrees(math.acos(min(1.0, abs(float(np.asarray(u) @ np.asarray(v))))))


def unit_direction(v: list[float] | np.ndarray) -> np.ndarray:
    n = np.asarray(v, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(n))
    if not np.isfinite(n).all() or norm < 1e-9:
        raise ValueError(f"--normal must be a non-zero finite direction, not {n.tolist()}")
    return n / norm


# A reading longer than this (m) is no gap between two surfaces of a room or a building: the
# map is likely not in metres (a map in millimetres read 1000.01 m, exit 0, with no hint)
ROOM_SIZE_M = 100.0


def measure(
    points: np.ndarray,
    box_a: list[float],
    box_b: list[float],
    axis: int | None = None,
    normal_radius: float = NORMAL_RADIUS,
    along: list[float] | np.ndarray | None = None,
) -> Measurement:
    """Distance between the surfaces inside ``box_a`` and ``box_b`` (each x0 y0 z0 x1 y1 z1).

    ``axis`` (0/1/2) measures instead the difference of the two point sets' median coordinate
    along that axis: for thin objects (a bar seen from below) whose faces are too small for a
    plane fit. ``normal_radius`` 0 skips the facing-normals step (the previous measure).
    ``along`` (a direction) reads the distance between the same kept faces along it instead of
    along their fitted common normal: for faces a few centimetres wide whose direction is known
    better than their points fix it (both perpendicular to a wall, or a simulated scene's
    true normal). The faces' common normal is still fitted, to report how far it is off it.
    """
    if not normal_radius >= 0:
        raise ValueError(f"--normal-radius must be >= 0 (0 = off), not {normal_radius}")
    if axis is not None and along is not None:
        raise ValueError("--axis and --normal are two different readings: give one")
    given = None if along is None else unit_direction(along)
    shared = int(np.count_nonzero(box_mask(points, box_a) & box_mask(points, box_b)))
    if shared:
        # the same box twice (a copied --box-a) read "distance 0.00 +- 0.19 cm", exit 0
        raise ValueError(
            f"--box-a and --box-b share {shared} point(s) of the map: each box must hold one "
            "of the two surfaces, apart"
        )
    if axis is not None:
        a, b = points_in_box(points, box_a), points_in_box(points, box_b)
        # as many as a face needs (3 read a median and a bootstrap spread off three points)
        if a.shape[0] < MIN_FACING or b.shape[0] < MIN_FACING:
            raise ValueError(
                f"boxes hold {a.shape[0]} and {b.shape[0]} points, too few for a median and its "
                f"spread (at least {MIN_FACING} each): is each drawn around its surface?"
            )

        def on_axis(a: np.ndarray, b: np.ndarray) -> float:
            return abs(float(np.median(b[:, axis]) - np.median(a[:, axis])))

        spread_a, spread_b = float(a[:, axis].std()), float(b[:, axis].std())
        se, unstable = bootstrap_stderr(a, b, on_axis)
        return Measurement(
            on_axis(a, b), 0.0, a.shape[0], b.shape[0], spread_a, spread_b,
            stderr=se, unstable_pct=unstable,
        )  # fmt: skip
    faces = []
    for flag, box in (("--box-a", box_a), ("--box-b", box_b)):
        try:
            faces.append(fit_face(points, box, normal_radius))
        except ValueError as exc:  # say which box: "the box holds 0 points" alone does not
            raise ValueError(f"{flag}: {exc}") from exc
    pa, pb = faces
    angle = angle_deg(pa.normal, pb.normal)
    ta, tb = tag_face(pa), tag_face(pb)
    fitted = faces_normal(ta, tb)
    ca, cb = pa.support.mean(axis=0), pb.support.mean(axis=0)
    if given is not None:
        n = given

        def along_given(a: np.ndarray, b: np.ndarray) -> float:
            return parallel_distance(a, b, n)

        se, unstable = bootstrap_stderr(pa.support, pb.support, along_given)
        reading = along_given(pa.support, pb.support)
    else:
        n = fitted
        distance = faces_distance if normal_radius > 0 else tagged_centroid_distance
        se, unstable = bootstrap_stderr(ta, tb, distance)
        reading = distance(ta, tb)
    return Measurement(
        reading, angle, pa.points, pb.points, pa.rms, pb.rms,
        pa.facing, pb.facing, se, unstable, sideways_offset(cb - ca, n),
        None if given is None else given.tolist(),
        0.0 if given is None else angle_deg(given, fitted),
        int(ta[:, DIRECTION].sum() + tb[:, DIRECTION].sum()), fitted.tolist(),
        second_reading(pa, cb - ca, n, reading, True),
        second_reading(pb, ca - cb, n, reading, True),
        second_reading(pa, cb - ca, n, reading, False),
        second_reading(pb, ca - cb, n, reading, False),
    )  # fmt: skip


def second_reading(
    face: Plane, toward: np.ndarray, n: np.ndarray, reading: float, nearer: bool
) -> dict[str, float] | None:
    """What ``reading`` would be to ``face``'s second surface (:func:`second_surfaces`) on the
    side ``nearer`` the other face (``toward`` away from it) or farther from it, along the
    reading's normal ``n``: the surface's offset (toward the other face positive), its points,
    and the distance to it.

    Nearer, it is a face the reading may have been meant for (a box drawn too deep, a picture
    on the wall it was drawn for), or the measured one is a thin object's back face and this
    its front: :func:`main` refuses the box. Farther, it is most often the back face of the
    thin object whose front was measured (a table leg 5 cm deep, seen from behind too), which
    faces away from the other box and is no candidate: :func:`main` names it and reads on."""
    along = float(face.normal @ toward) >= 0  # the face's normal points to the other face
    second = face.seconds.get("+" if along == nearer else "-")
    if second is None:
        return None
    offset = second.offset if along else -second.offset
    shift = offset * abs(float(face.normal @ n))
    return {
        "offset": offset,
        "points": second.points,
        "distance": reading - shift,
    }


def two_surfaces(flag: str, kept: int, second: dict[str, float], distance: float) -> str:
    """The refusal of a box around two parallel surfaces: which box, both surfaces and what
    each reads, and what to do. A refusal, not a choice of one: Table I has one distance per
    pair of faces, and only the user knows which surface the box was drawn for."""
    return (
        f"{flag} holds two parallel surfaces: the one measured ({kept} points) and another "
        f"{abs(second['offset']) * 100:.1f} cm nearer the other box along its normal "
        f"({int(second['points'])} points); the distance reads {distance * 100:.2f} cm to the "
        f"first, {second['distance'] * 100:.2f} cm to the second. Shrink {flag} around the "
        "surface you mean"
    )


#: Columns of :func:`tag_face`'s rows after x, y, z: 1 where the faces' common direction
#: stands on the point, 1 where the face's offset does.
DIRECTION, OFFSET = 3, 4


def tag_face(plane: Plane) -> np.ndarray:
    """A face's points as rows x y z d o for :func:`faces_distance`: ``d`` marks the fit's
    inliers (the direction stands on them), ``o`` the facing points (the offset does).

    One array, so that a bootstrap resample moves the direction and the offset together with
    the points, as a different scan of the same face would.
    """
    direction = plane.support if plane.inliers is None else plane.inliers
    both = np.vstack([direction, plane.support])
    rows, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    flags = np.zeros((rows.shape[0], 2))
    flags[inverse[: direction.shape[0]], 0] = 1.0
    flags[inverse[direction.shape[0] :], 1] = 1.0
    return np.column_stack([rows, flags])


def _rows(tagged: np.ndarray, column: int) -> np.ndarray:
    """The points of ``tagged`` marked in ``column`` (all of them if a resample left < 3)."""
    sel = tagged[tagged[:, column] > 0, :3]
    return sel if sel.shape[0] >= 3 else tagged[:, :3]


def faces_normal(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The common normal of two faces' plane inliers (:func:`tag_face` rows)."""
    return _common_normal([_rows(a, DIRECTION), _rows(b, DIRECTION)])[0]


def faces_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two faces (:func:`tag_face` rows): along the common normal of both
    faces' plane inliers, between the offsets of their facing points.

    The offsets must stand on the facing points only: the first centimetres of a leg's sides
    lie within the plane's band, behind the face, and pull it inwards. The direction need not:
    those sides sit symmetrically about each leg and do not turn it, while the facing points
    of a table's edge are mostly its two 5 cm legs, whose common normal the points fix only to
    a degree or so; across the half metre two faces sit apart sideways that is a centimetre of
    reading, the whole 1 % target of a 1.2 m gap. The inliers add the rim of the table's top:
    a strip 80 cm long but one or two voxels high, whose points' own normals (a line of
    points has none) fail the facing test. On forty registered maps of the simulated runs
    (``bench_mapping.py --draws 4``) the common normal came out a median 0.42 deg off the true
    one (worst 1.01) instead of 0.64 (1.42), and 9(a) read under 1 % on 30 of them instead of
    20; on the ten TRUE-pose maps 0.42 deg instead of 0.68 (figures in docs/mapping-fidelity.md).
    """
    return parallel_distance(_rows(a, OFFSET), _rows(b, OFFSET), faces_normal(a, b))


def tagged_centroid_distance(a: np.ndarray, b: np.ndarray) -> float:
    """:func:`centroid_distance` on :func:`tag_face` rows (``--normal-radius 0``: the rows are
    the fit's inliers, both columns set)."""
    return centroid_distance(_rows(a, OFFSET), _rows(b, OFFSET))


def centroid_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The previous measure (``--normal-radius 0``): each plane's centroid to the other plane
    (SVD fits on the RANSAC inliers), both ways, averaged."""
    (ca, na), (cb, nb) = _svd_plane(a), _svd_plane(b)
    return 0.5 * (abs(float((cb - ca) @ na)) + abs(float((ca - cb) @ nb)))


def _svd_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(axis=0)
    return c, np.linalg.svd(points - c, full_matrices=False)[2][2]


def bootstrap_stderr(
    a: np.ndarray,
    b: np.ndarray,
    distance: Callable[[np.ndarray, np.ndarray], float],
    resamples: int = BOOTSTRAP,
) -> tuple[float, float]:
    """Standard error of ``distance`` over resamples (with replacement) of both point sets
    (each as at most :data:`BOOTSTRAP_MAX_POINTS` points), and the % of resamples farther than
    :data:`UNSTABLE_SIGMAS` of it from their median.

    Why a bootstrap rather than a formula: the distance goes through trimming and a common
    normal whose tilt, on a face a few centimetres wide, turns the faces' sideways offset into
    length; resampling carries all of that through without a model of it. Why the median
    absolute deviation rather than a standard deviation: see the module docstring (a few
    resamples that tilt the normal would dominate it).
    """
    rng = np.random.default_rng(0)
    ma, mb = min(a.shape[0], BOOTSTRAP_MAX_POINTS), min(b.shape[0], BOOTSTRAP_MAX_POINTS)
    vals = np.empty(resamples)
    for k in range(resamples):
        vals[k] = distance(a[rng.integers(0, a.shape[0], ma)], b[rng.integers(0, b.shape[0], mb)])
    mid = float(np.median(vals))
    se = 1.4826 * float(np.median(np.abs(vals - mid)))  # the MAD: up to half may be far off
    # at least a millimetre off: resamples microns apart on noise-free faces counted as
    # "4x away" and flagged them UNSTABLE (a review)
    far = max(UNSTABLE_SIGMAS * se, UNSTABLE_MIN_M)
    unstable = 100.0 * float(np.mean(np.abs(vals - mid) > far)) if se > 0 else 0.0
    return se, unstable


def not_parallel_reading(along_given: bool, normal_radius: float) -> str:
    """What the distance between two surfaces that are not parallel is, in each reading mode
    (``--axis`` fits no planes and never gets here): none of them is a gap between the two."""
    if along_given:
        # parallel_distance on the given normal: only the offsets are fitted
        return "the distance is their centroids' offset along the given direction"
    if normal_radius <= 0:
        return "the distance is each plane's centroid to the other plane, averaged"
    # faces_distance: one normal for both faces' inliers, which perpendicular faces lack
    return (
        "the distance is their centroids' offset along one normal fitted to both faces "
        "together, which they do not share"
    )


def non_finite(out: dict) -> list[str]:
    """The keys of ``out`` (one level into lists and dicts) holding a NaN or an infinity.

    Map coordinates near float64's range overflow the fits (a face's rms, how far apart
    sideways two faces sit); such a reading means nothing, and ``json.dumps`` would print NaN
    and Infinity, which no JSON parser takes.
    """

    def numbers(value: object) -> list[object]:
        if isinstance(value, dict):
            return list(value.values())
        return value if isinstance(value, list) else [value]

    return [
        key
        for key, value in out.items()
        if any(isinstance(v, float) and not math.isfinite(v) for v in numbers(value))
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="wheelgrid measure",
        description="Distance between two surfaces of a map, each selected by a box "
        "(x0 y0 z0 x1 y1 z1, map frame, metres), after the paper's Table I.",
    )
    p.add_argument(
        "map", type=Path, help="map.ply from `wheelgrid map`, or another PLY or a PCL .pcd file"
    )
    p.add_argument("--box-a", nargs=6, type=float, required=True, metavar="V")
    p.add_argument("--box-b", nargs=6, type=float, required=True, metavar="V")
    how = p.add_mutually_exclusive_group()
    how.add_argument(
        "--axis", choices=["x", "y", "z"], help="median-coordinate distance along this axis"
    )
    how.add_argument(
        "--normal",
        nargs=3,
        type=float,
        metavar=("NX", "NY", "NZ"),
        help="read the distance between the fitted faces along this direction (map frame) "
        "instead of their fitted normal: for faces a few cm wide whose direction is known",
    )
    how.add_argument(
        "--normal-box",
        nargs=6,
        type=float,
        metavar="V",
        help="as --normal, along the normal of the surface in this box (x0 y0 z0 x1 y1 z1): "
        "a wall the two faces are parallel to",
    )
    p.add_argument(
        "--normal-radius",
        type=float,
        default=NORMAL_RADIUS,
        metavar="M",
        help="neighbourhood (m) of the point normals that keep a fit to its face "
        f"(default {NORMAL_RADIUS}; 0 = off)",
    )
    p.add_argument("--true", type=float, help="the real distance (m): prints the deviation %%")
    p.add_argument("--json", action="store_true", help="print one JSON object instead")
    args = p.parse_args(argv)
    if args.true is not None and not (math.isfinite(args.true) and args.true > 0):
        # 0 would read as "not given"; a negative or NaN one makes a deviation of nonsense
        print(
            f"wheelgrid measure: --true must be a distance > 0 (m), not {args.true}",
            file=sys.stderr,
        )
        return 2
    for flag in ("box_a", "box_b", "normal", "normal_box"):
        values = getattr(args, flag)
        if values is not None and not all(math.isfinite(v) for v in values):
            # a NaN bound selects nothing: "the box holds 0 points" sent users looking for
            # the surface instead of at the typo
            print(
                f"wheelgrid measure: --{flag.replace('_', '-')} has a value that is not a "
                f"finite number: {' '.join(f'{v:g}' for v in values)}",
                file=sys.stderr,
            )
            return 2
    try:
        pts = read_cloud(args.map)
    except (OSError, ValueError) as exc:
        print(f"wheelgrid measure: {exc}", file=sys.stderr)
        return 2
    try:
        axis = None if args.axis is None else "xyz".index(args.axis)
        along, ref = args.normal, None
        # overflow is caught on the result (non_finite), not warned about line by line
        with np.errstate(all="ignore"):
            if args.normal_box is not None:
                ref = reference_plane(pts, args.normal_box)
                along = ref.normal
            m = measure(pts, args.box_a, args.box_b, axis, args.normal_radius, along)
    except ValueError as exc:
        print(f"wheelgrid measure: {exc}", file=sys.stderr)
        return 2
    refusals = [
        two_surfaces(flag, kept, second, m.distance)
        for flag, kept, second in (
            ("--box-a", m.points_a, m.second_a),
            ("--box-b", m.points_b, m.second_b),
        )
        if second is not None
    ]
    if refusals:
        for line in refusals:
            print(f"wheelgrid measure: {line}", file=sys.stderr)
        return 2
    out = asdict(m)
    # one surface per box: the keys are there only to say otherwise (the output is unchanged)
    del out["second_a"], out["second_b"], out["behind_a"], out["behind_b"]
    if axis is not None:  # no planes fitted: no angle between them (it read 0.0)
        out["angle_deg"] = None
    if ref is not None:
        out["normal_box"] = {"points": ref.points, "rms": ref.rms}
    if args.true is not None:
        out["true"] = args.true
        out["deviation_pct"] = 100.0 * abs(m.distance - args.true) / args.true
    bad = non_finite(out)
    if bad:
        print(
            f"wheelgrid measure: the reading overflowed ({', '.join(bad)} not finite): are the "
            "map's coordinates (and --true) in metres?",
            file=sys.stderr,
        )
        return 2
    # what makes the reading doubtful, said in the JSON too: it printed a 12 % "deviation"
    # between perpendicular faces with no word of them (a review)
    line_warnings = []  # the line's own (the normal's is said beside the normal)
    if m.angle_deg > 10.0:
        reading = not_parallel_reading(m.along is not None, args.normal_radius)
        line_warnings.append(f"surfaces {m.angle_deg:.0f} deg from parallel, {reading}")
    if m.distance > ROOM_SIZE_M:
        line_warnings.append(
            f"{m.distance:.0f} m is no gap within a room: are the map's coordinates in metres "
            "(a map in millimetres reads 1000x, its surfaces' points mostly outside the fits' "
            "centimetre gates)?"
        )
    if args.json:
        normal_off = m.along is not None and m.along_angle_deg > 10.0
        out["warnings"] = line_warnings + (
            ["the normal given does not stand on these faces"] if normal_off else []
        )
        print(json.dumps(out))
        return 0
    if axis is None:
        line = (
            f"distance {m.distance * 100:.2f} +- {m.stderr * 100:.2f} cm "
            f"(planes {m.angle_deg:.1f} deg apart; "
            f"{m.points_a} + {m.points_b} points, fit rms {m.rms_a * 1000:.1f} / "
            f"{m.rms_b * 1000:.1f} mm)"
        )
    else:  # no plane is fitted: no angle between planes, and the spread is along the axis
        line = (
            f"distance {m.distance * 100:.2f} +- {m.stderr * 100:.2f} cm along {args.axis} "
            f"(median coordinates; {m.points_a} + {m.points_b} points, spread along it "
            f"{m.rms_a * 1000:.1f} / {m.rms_b * 1000:.1f} mm)"
        )
    if args.true is not None:
        line += f"; true {args.true * 100:.2f} cm, deviation {out['deviation_pct']:.2f} %"
    if m.along is not None:
        given = "given normal" if ref is None else (
            f"--normal-box surface's normal ({ref.points} points, fit rms "
            f"{ref.rms * 1000:.1f} mm)"
        )  # fmt: skip
        line += f"; along the {given}, {m.along_angle_deg:.1f} deg from the faces' own"
        if m.along_angle_deg > 10.0:
            line += " (WARNING: it does not stand on these faces)"
    elif axis is None:
        # what the standard error cannot show: a tilt all of the normal's points share
        tilt_mm = 1000.0 * m.sideways * math.tan(math.radians(0.1))
        line += (
            f"; faces {m.sideways:.2f} m apart sideways: each 0.1 deg of normal tilt "
            f"moves it {tilt_mm:.1f} mm"
        )
    unfaced = [n for n, f in (("A", m.facing_a), ("B", m.facing_b)) if not f]
    if axis is None and args.normal_radius > 0 and unfaced:
        line += f"; box {' and '.join(unfaced)}: < {MIN_FACING} points face the plane, fit on all"
    if m.unstable_pct >= 1.0:
        why = "the faces' normal" if axis is None else "the medians"
        line += (
            f"; UNSTABLE: {m.unstable_pct:.0f} % of resamples of its points read it more than "
            f"{UNSTABLE_SIGMAS:.0f}x that away (too few points to fix {why})"
        )
    for warning in line_warnings:
        line += f"; WARNING: {warning}"
    for box, behind in (("A", m.behind_a), ("B", m.behind_b)):
        # "farther" has no sense between faces far from parallel (a table top's underside)
        if behind is not None and m.angle_deg <= 10.0:
            line += (
                f"; box {box} also holds a parallel surface {abs(behind['offset']) * 100:.1f} cm "
                f"farther from the other box ({int(behind['points'])} points: a back face? "
                f"{behind['distance'] * 100:.2f} cm to it), not read"
            )
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
