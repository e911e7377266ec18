"""Frame-to-map registration with failure detection (ROS-free).

KISS-ICP (``kiss-icp`` package) is used piece by piece (its voxel hash map, point-to-point
registration with a robust kernel, adaptive threshold) instead of ``KissICP.register_frame``,
because that call always integrates the frame into its map: a chair's map must not absorb a
frame that failed to register. Here a frame is integrated only after it passed every check:

* too few points (``min_points``) - nothing to register;
* low overlap (``min_fitness``: fraction of the frame's points that land in an occupied map
  cell after alignment);
* an implausible jump for a chair at <= 3 km/h (``max_speed``, ``max_turn_rate``; the default
  leaves margin for a hand-held capture) or a large disagreement with the pose prior.
* degenerate geometry without a prior: point-to-plane information (normals of the frame's
  points) leaves a motion direction unconstrained, e.g. a view of bare floor cannot fix sliding
  or yaw, so the ICP pose would be a guess (``reject_degenerate_ratio``). With a prior the
  unconstrained directions are taken from the prior instead (:func:`constrain_to_observable`).

A failed frame is reported loudly, integration pauses (state ``relocalising``), and each later
frame is aligned against the unchanged map from the last good pose (or the prior's guess) with
a wider search; the first one that passes resumes mapping. Every event is counted. A frame
more than ``max_gap`` after the frame before it is registered the same way: over a dropout
the speed rule allows metres, so nothing else would catch a prior that re-anchored meanwhile.
A relocalisation must convince on the map's structure, not its floor: each surface family of
the frame (its points grouped by normal, :func:`surface_families`) is checked on its own.

The Open3D point-to-plane ICP path (``method: open3d``) keeps the same checks and map; it is
the baseline the benchmarks compare against.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Any

import numpy as np

from wheelgrid_common.params import check_bounds, check_finite, field

from .evidence import INVALID_KEY, NEIGHBOUR_KEYS, contains_sorted, voxel_keys_or_invalid
from .preprocess import MIN_VOXEL, grid_knn, neighbourhood_normals, voxel_downsample
from .se3 import exp_se3, log_se3, rotation_angle_deg, transform

#: A scale measurement spans at least this much of the prior's travel (m): ICP's millimetres
#: of noise would be most of a shorter one. Consecutive shorter steps (a 60 Hz phone moves
#: millimetres a frame) are joined until their travel reaches it.
PRIOR_SCALE_MIN_STEP = 0.02


#: Upper bounds of the counts KISS-ICP's C++ takes as 32-bit ints (far above any use).
MAX_COUNT = 100_000
MAX_THREADS = 1024


@dataclass
class RegistrationConfig:
    """Registration and failure-detection parameters (YAML section ``registration``)."""

    method: str = field("kiss", "kiss (KISS-ICP) or open3d (point-to-plane ICP baseline)", "")
    voxel_size: float = field(
        0.1,
        "voxel of the registration map (KISS-ICP voxel_size)",
        "m",
        # 1e-6 started, then failed every frame ("cloud too large for cell")
        bounds=(MIN_VOXEL, math.inf),
    )
    max_range: float = field(6.0, "map points farther than this from the sensor are dropped", "m")
    initial_threshold: float = field(
        0.3, "initial correspondence threshold of the adaptive estimator", "m"
    )
    fixed_threshold: float = field(
        0.0, "if > 0, use this KISS-ICP kernel sigma instead of the adaptive one", "m"
    )
    prior_threshold: float = field(
        0.015,
        "kernel sigma when a pose prior seeds the frame (correspondences within 3 sigma); "
        "small because wide searches let floor-dominated frames slide",
        "m",
    )
    min_motion_th: float = field(0.02, "motion below this does not adapt the threshold", "m")
    max_points_per_voxel: int = field(
        40,
        "points kept per registration-map voxel (denser: point-to-point ICP sticks less)",
        "",
        bounds=(1, MAX_COUNT),
    )
    max_iterations: int = field(100, "ICP iterations at most", "", bounds=(1, MAX_COUNT))
    convergence: float = field(
        1e-3,
        "ICP stops once an iteration's update (KISS-ICP's convergence_criterion: the norm of the "
        "twist, metres and radians together) is below this. KISS-ICP's own 1e-4 registers a "
        "real keyframe in about twice the time; over fifty simulated runs it read Table I 9(a) "
        "under 1 % on 35 against 39 (with preprocess.map_mixed_pixels, also the default); on "
        "the real capture with its prior the loop-closed map, rigidly aligned, agrees with "
        "ARKit's as closely (99.4 against 99.5 % within 5 cm; docs/mapping-fidelity.md)",
        "",
    )
    min_points: int = field(150, "a frame with fewer points after filtering fails", "points")
    min_fitness: float = field(
        0.25, "fraction of frame points that must land on the map after alignment", ""
    )
    fitness_cell: float = field(
        0.05, "map occupancy cell of the overlap check (a match is within 1-2 cells)", "m"
    )
    max_speed: float = field(
        1.5, "faster apparent motion is a failure (chair <= 0.83 m/s + hand-held margin)", "m/s"
    )
    max_turn_rate: float = field(120.0, "faster apparent rotation is a failure", "deg/s")
    min_dt: float = field(0.2, "time floor for the jump check (bag stamps can bunch)", "s")
    max_accel: float = field(
        8.0,
        "a pose prior whose step changes from one frame to the next by more than this times "
        "the frame interval squared (plus 2 cm) has jumped, however slow the step: its world "
        "re-anchored. The bundled bag's prior changes its 0.2 s step by 5.4 m/s^2 at most, the "
        "real capture's its 1/60 s step by 4.5 mm (16 m/s^2 of noise, within the 2 cm). Catches "
        "a re-anchor of 2.5 cm at 60 Hz, 10 cm at 10 Hz, 34 cm at 5 Hz",
        "m/s^2",
    )
    max_angular_accel: float = field(
        500.0,
        "the same for the prior's turn per frame (plus 1 deg): the bundled bag's changes by "
        "386 deg/s^2 at most, the real capture's by 0.3 deg a frame",
        "deg/s^2",
    )
    prior_check_step: float = field(
        0.05,
        "a pose prior's step that changes from the step before by more than this, within "
        "max_accel, is checked against the map: the frame is also aligned from the step before "
        "continued, and where the map clearly prefers that (prior_check_gain), the frame fails "
        "as a jump of the prior's world, which is re-anchored (max_accel allows 34 cm at 5 Hz). "
        "The bundled bag's 5 Hz prior changes its step by more on 11 % of frames, the real "
        "capture's never (0 = no check)",
        "m",
    )
    prior_check_turn: float = field(
        3.0, "the same for the change of the prior's turn per frame (0 = no check)", "deg"
    )
    prior_check_gain: float = field(
        0.25,
        "the prior jumped where one of the frame's surface families lands in the map's own "
        "occupied cells (fitness_cell, no neighbour's) with this much more of its points from "
        "the step before continued than from the prior's step, and none with 0.15 less. "
        "Re-anchors of 10-30 cm and 1-5 deg at 5 Hz on the bundled bag gained 0.28-0.59, the "
        "prior's true steps on 11 simulated runs at most 0.14",
        "",
    )
    max_prior_deviation: float = field(
        0.1, "a result this far from the pose prior's guess fails", "m"
    )
    max_prior_deviation_deg: float = field(3.0, "same, for rotation", "deg")
    degeneracy_ratio: float = field(
        0.2,
        "with a prior, ICP corrections along directions constrained by less than this share of "
        "the points (e.g. sliding along a floor) are dropped and the prior kept",
        "",
    )
    prior_rotation_gain: float = field(
        0.5,
        "with a pose prior, the share of ICP's rotation correction applied per frame: the "
        "prior's frame-to-frame rotation (IMU) is more precise than one ICP solve on a narrow "
        "depth view, and half the correction still pulls slow drift back within a few frames "
        "(1 = take ICP's rotation as it is)",
        "",
    )
    prior_translation_gain: float = field(
        1.0, "same for the translation correction (the prior's scale drifts ~1 %)", ""
    )
    prior_tilt_gain: float = field(
        -1.0,
        "with a pose prior whose frame has z up along gravity (ARKit through wheelgrid's Stray "
        "adapter or bridge), the share of the part of ICP's rotation correction that tilts the "
        "sensor against gravity; the turn about the vertical keeps prior_rotation_gain. 0 holds "
        "the tilt to the prior's (an IMU's gravity): on the real capture the online map as a "
        "whole turned 0.05 instead of 0.25 deg from ARKit's, the same shape; with convergence "
        "1e-4, on 24 simulated runs 9(a) under 1 % on 18 against 15, but the worst run worse, "
        "1.80 against 1.53 %; with the default 1e-3 and map_mixed_pixels, 7 of 9 against 9, one "
        "at 2.43 % (docs/mapping-fidelity.md). < 0 = prior_rotation_gain",
        "",
    )
    reject_degenerate_ratio: float = field(
        0.02,
        "without a prior, a frame whose geometry constrains some motion direction with less "
        "than this share of its points is a failure: its pose would be a guess (0 = off)",
        "",
    )
    prior_scale: float = field(
        1.0,
        "the pose prior's horizontal steps (its frame's x, y: z up) are divided by this before "
        "they seed ICP (1.02: the prior measures 2 % too long); wheelgrid map's loop closure "
        "sets it from the run itself",
        "",
    )
    relocalise_scale: float = field(
        3.0, "correspondence distance multiplier while relocalising", ""
    )
    relocalise_min_fitness: float = field(
        0.5,
        "while relocalising, the overlap each surface orientation of the frame must reach: its "
        "points are grouped by normal into three perpendicular families (a floor and two wall "
        "directions, say), each checked on its own. min_fitness over all points let the floor "
        "alone place a frame metres off; on the bundled bag such frames read 0.10-0.22 in one "
        "family, right ones 0.8-1",
        "",
    )
    relocalise_prior_min_fitness: float = field(
        0.3,
        "the same where the pose was found from the pose prior's guess: the prior's own motion "
        "is a second witness, so the map need only not refute it. A right catch-up of a prior "
        "that froze read 0.41 in a family (a wall half new), the guesses of a prior that had "
        "re-anchored 1 m away 0.10-0.26; ICP alone from the last pose reached 0.47 1.5-2.4 m off",
        "",
    )
    relocalise_min_points: int = field(
        100,
        "while relocalising, a surface family of the frame counts with this many points (at "
        "half the map voxel): all three must for ICP alone, two from the prior's guess (with "
        "fewer the view leaves a direction unfixed)",
        "points",
    )
    relocalise_ambiguity: float = field(
        0.1,
        "after a gap, a frame's placing is aligned again from this far along each of the two "
        "directions its view constrains least; where one of those alignments stays 90 % as far "
        "away and passes the same checks, the view cannot tell the two apart and the frame "
        "fails (0 = off). A floor and one wall slide along the wall: the checks, with their "
        "cell or two of tolerance, passed placings 14-39 cm off on the bundled bag",
        "m",
    )
    max_gap: float = field(
        0.5,
        "a frame this long after the frame before it is registered as a relocalisation "
        "(wider search, relocalise_min_fitness): over a dropout the speed rule allows metres, "
        "so a pose prior that re-anchored meanwhile (ARKit) would be followed, the floor alone "
        "giving the overlap; it had mapped a frame 1.5 m and 16 deg off, and the rest of the "
        "run with it. 0.5 s: two frames lost at 5 Hz, 30 at the phone's 60 Hz",
        "s",
    )
    threads: int = field(
        2,
        "KISS-ICP threads (0 = all cores; KISS-ICP takes it from a process's first registrar "
        "and keeps it). Two threads meet their partial sums in varying order, so replays of "
        "one bag differ in the last bits (micrometres after loop closure); 1 replays a bag to "
        "the same online trajectory, bit for bit, at 1.65x the registration time (2 cores, "
        "real frames: 58 against 35 ms a frame)",
        "",
        bounds=(0, MAX_THREADS),
    )

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ValueError for settings that cannot work (checked again when a Registrar starts,
        because a caller may change a field after construction)."""
        check_finite(self, "registration ")  # a NaN passes every range test below
        # Lengths and times that must be positive: a voxel of -1 m failed every frame with
        # the same error, a fitness cell of 0 called every frame "low overlap".
        for name in (
            "voxel_size", "max_range", "initial_threshold", "prior_threshold", "fitness_cell",
            "max_speed", "max_turn_rate", "min_dt", "max_prior_deviation",
            "max_prior_deviation_deg", "relocalise_scale", "convergence", "max_gap",
            "max_accel", "max_angular_accel",
        ):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ValueError(f"registration {name} must be > 0, not {getattr(self, name)}")
        for name in (
            "fixed_threshold", "min_motion_th", "prior_check_step", "prior_check_turn",
            "relocalise_ambiguity",
        ):  # fmt: skip
            if getattr(self, name) < 0:
                raise ValueError(f"registration {name} must be >= 0, not {getattr(self, name)}")
        for name in (
            "min_fitness", "degeneracy_ratio", "reject_degenerate_ratio",
            "relocalise_min_fitness", "relocalise_prior_min_fitness", "prior_check_gain",
        ):  # fmt: skip
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"registration {name} must be in [0, 1], not {getattr(self, name)}"
                )
        if not self.prior_check_gain > 0:  # 0 would call every checked step a jump
            raise ValueError(
                f"registration prior_check_gain must be in (0, 1] (prior_check_step and "
                f"prior_check_turn 0 turn the check off), not {self.prior_check_gain}"
            )
        if (
            self.max_points_per_voxel < 1
            or self.max_iterations < 1
            or self.min_points < 3
            or self.relocalise_min_points < 1
        ):
            raise ValueError(
                "registration max_points_per_voxel, max_iterations and relocalise_min_points must "
                "be >= 1, min_points >= 3"
            )
        if self.threads < 0:
            raise ValueError(f"registration threads must be >= 0 (0 = all), not {self.threads}")
        if self.method not in ("kiss", "open3d"):
            raise ValueError(f"registration method must be kiss or open3d, not {self.method!r}")
        if not 0.5 <= self.prior_scale <= 2.0:
            raise ValueError(
                f"registration prior_scale must be in [0.5, 2] (1 = as given), not "
                f"{self.prior_scale}"
            )
        for name in ("prior_rotation_gain", "prior_translation_gain", "prior_tilt_gain"):
            if name == "prior_tilt_gain" and self.prior_tilt_gain < 0:
                continue  # the rotation gain's
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"registration {name} must be in [0, 1] (0 = the prior, 1 = ICP), "
                    f"not {getattr(self, name)}"
                )
        # KISS-ICP's C++ takes these as 32-bit ints: 3e9 threads ended in a TypeError traceback
        check_bounds(self, "registration ")


def _insert_sorted(sorted_keys: np.ndarray, new: np.ndarray) -> np.ndarray:
    """``sorted_keys`` with the sorted, unique, absent ``new`` merged in (one O(N) copy)."""
    return np.insert(sorted_keys, np.searchsorted(sorted_keys, new), new)


def _frame_normals(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of a frame's points from their 8 nearest neighbours within ``cell``, and
    which points have one (3 neighbours or more)."""
    idx, _ = grid_knn(points, 8, cell)
    normals, _ = neighbourhood_normals(points, idx)
    return normals, (idx >= 0).sum(axis=1) >= 3


def _information(points: np.ndarray, normals: np.ndarray, ok: np.ndarray) -> np.ndarray:
    n, p = normals[ok], points[ok]
    J = np.hstack([n, np.cross(p, n)])
    return (J.T @ J) / max(int(ok.sum()), 1)


def point_to_plane_information(points: np.ndarray, cell: float) -> np.ndarray | None:
    """Point-to-plane information ``H = sum J^T J / N`` with ``J = [n, p x n]`` (normals of the
    frame's own points, twist order translation then rotation), per point: ``u^T H u`` is the
    share of the points that constrain motion along ``u``. None below 10 points."""
    if points.shape[0] < 10:
        return None
    return _information(points, *_frame_normals(points, cell))


def surface_families(normals: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Each point's surface family: 0, 1, 2 along the principal axes of the frame's normals
    (0 the most common orientation: in a room the floor or the wall in view), -1 without a
    normal.

    Why: overlap over all points is mostly the floor's, and a floor matches wherever the frame
    slides or turns on it; the families that constrain the other directions each have to land
    on the map too before a relocalisation is believed (``relocalise_min_fitness``).
    """
    fam = np.full(normals.shape[0], -1, dtype=np.int8)
    if not ok.any():
        return fam
    n = normals[ok]
    _, axes = np.linalg.eigh(n.T @ n)  # ascending: the last axis is the most common normal
    fam[ok] = 2 - np.argmax(np.abs(n @ axes), axis=1)
    return fam


@dataclass(frozen=True)
class FrameInputs:
    """What registration reads from a frame's own points alone, before it knows any pose.

    Split out so that it can be computed ahead, in another process, while the frame before is
    registered (:mod:`.prefetch`): the point-to-plane information is a third of registration's
    time on a 256x192 frame, and the same numbers come out wherever it is computed.
    """

    down: np.ndarray  # the frame at half the map voxel: overlap, degeneracy, the map update
    source: np.ndarray  # at 1.5 map voxels: what ICP aligns
    info: np.ndarray | None  # point_to_plane_information(down); None where not needed
    families: np.ndarray  # surface_families of down's points (int8, -1 = no normal)


def frame_inputs(points: np.ndarray, cfg: RegistrationConfig) -> FrameInputs:
    """:class:`FrameInputs` of filtered sensor-frame ``points`` under ``cfg``."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    down = voxel_downsample(pts, 0.5 * cfg.voxel_size) if pts.size else pts
    source = voxel_downsample(down, 1.5 * cfg.voxel_size) if down.size else down
    info = None
    families = np.full(down.shape[0], -1, dtype=np.int8)
    if down.shape[0] >= 10:
        normals, ok = _frame_normals(down, 0.5 * cfg.voxel_size)
        families = surface_families(normals, ok)
        if cfg.degeneracy_ratio > 0 or cfg.reject_degenerate_ratio > 0:
            info = _information(down, normals, ok)
    return FrameInputs(down, source, info, families)


def constrain_to_observable(
    points: np.ndarray,
    cell: float,
    correction: np.ndarray,
    ratio: float,
    information: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """Keep only the part of an ICP ``correction`` (4x4, sensor frame) the geometry observes.

    Point-to-plane information (:func:`point_to_plane_information`, or ``information`` when the
    caller has it already) says which of the 6 motion directions the scene constrains. A
    floor-dominated view constrains height, roll and pitch but not sliding or yaw; ICP
    "corrections" along such directions are bias (points pulled back to where they were), so
    with a pose prior they are dropped and the prior kept. Returns the filtered correction and
    the number of degenerate directions.
    """
    H = point_to_plane_information(points, cell) if information is None else information
    if H is None:
        return correction, 0
    vals, vecs = np.linalg.eigh(H)
    keep = vals >= ratio
    x = log_se3(correction)
    x_kept = vecs @ (keep * (vecs.T @ x))
    return exp_se3(x_kept), int((~keep).sum())


@dataclass
class PriorScaleEstimate:
    """How much longer the pose prior's steps are than the ones ICP measures (ROS-free sums).

    A visual-inertial prior (ARKit) gets its scale from the IMU and is 1-2 % off on a room scan
    (:mod:`wheelgrid_sim.odometry` draws it from 1 %). Where the view constrains the direction of
    travel, ICP corrects each step, and its correction along the step is that step's scale error
    (plus ICP's noise); where it does not (driving along a row with nothing ahead), the
    degeneracy gate keeps the prior's step as it is, and its scale error with it: on the
    simulated seed 19 (prior 1.9 % short) the first leg came out 1.1 % short, and 11 % of the
    map more than 5 cm from a true surface. The loops cannot see it (a route that retraces
    itself observes no scale). So every accepted step whose direction the view constrains (or
    run of such steps, joined to :data:`PRIOR_SCALE_MIN_STEP`) is a measurement
    ``y = -(s - 1) x`` (``x`` the prior's travel, ``y`` ICP's correction along it), and ``s``
    is their least-squares fit; its standard error comes from their scatter.
    """

    sxy: float = 0.0
    sxx: float = 0.0
    syy: float = 0.0
    steps: int = 0

    def add(self, step: float, correction_along: float) -> None:
        self.sxy += step * correction_along
        self.sxx += step * step
        self.syy += correction_along * correction_along
        self.steps += 1

    @property
    def error(self) -> float:
        """The prior's scale error relative to the steps it was given (0.01 = 1 % too long)."""
        return -self.sxy / self.sxx if self.sxx > 0 else 0.0

    @property
    def stderr(self) -> float:
        if self.steps < 3 or self.sxx <= 0:
            return float("inf")
        rss = max(self.syy - self.sxy * self.sxy / self.sxx, 0.0)
        return float(np.sqrt(rss / (self.steps - 1) / self.sxx))

    def percent(self) -> tuple[float, float | None]:
        """``(error, stderr)`` in %, rounded for a report; the standard error None (JSON has no
        infinity) where too few steps fix it."""
        se = self.stderr
        return round(100.0 * self.error, 3), round(100.0 * se, 3) if np.isfinite(se) else None


def blend_correction(
    correction: np.ndarray,
    gain_t: float,
    gain_r: float,
    gain_tilt: float | None = None,
    up: np.ndarray | None = None,
) -> np.ndarray:
    """Scale an ICP correction of the prior's guess: ``gain`` 1 = ICP, 0 = the prior.

    A fixed-gain fusion (a complementary filter): the prior is precise from frame to frame but
    drifts, a single ICP solve is absolute but noisy; on the simulated room full ICP rotation
    corrections random-walked the yaw by 1.5 deg, half of them kept it within 0.5 deg.
    ``up`` (gravity in the correction's frame) splits the rotation: the turn about it takes
    ``gain_r``, the tilt against it ``gain_tilt``.
    """
    if gain_tilt is None or up is None:
        gain_tilt = gain_r
    if gain_t == 1.0 and gain_r == 1.0 and gain_tilt == 1.0:
        return correction
    x = log_se3(correction)
    x[:3] *= gain_t
    if gain_tilt == gain_r:
        x[3:] *= gain_r
    else:
        assert up is not None
        u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        turn = float(x[3:] @ u) * u
        x[3:] = gain_r * turn + gain_tilt * (x[3:] - turn)
    return exp_se3(x)


@dataclass
class RegResult:
    """Outcome of one frame; ``pose`` is the sensor pose in odom (the first sensor frame)."""

    pose: np.ndarray
    accepted: bool
    reason: str = ""
    fitness: float = 0.0
    relocalised: bool = False
    seconds: float = 0.0
    # the pose prior as registration used it: its world re-anchored at every jump, so that
    # what the mapper keeps of it (gravity, the loop closure's prior drift) is continuous too
    prior: np.ndarray | None = None
    # the frame came more than max_gap after the one before it (a dropout): registered as a
    # relocalisation, though mapping had not stopped
    after_gap: bool = False


@dataclass
class _Attempt:
    """One alignment of a frame from one guess, checked (:meth:`Registrar._attempt`)."""

    pose: np.ndarray
    fitness: float
    reason: str  # "" where every check passed
    guess: np.ndarray
    corr: np.ndarray  # ICP's correction of the guess, the part the view observes
    info: np.ndarray | None
    prior_step: np.ndarray | None
    step: np.ndarray  # from the last accepted pose
    prior: np.ndarray | None  # the prior as used (continuous world)


# A pose prior that repeats itself to the bit for longer than this has stopped estimating
# (:meth:`Registrar._repeat`); a repeat within it is one pose message serving the frames either
# side of it, each within the 0.1 s the frames take their prior from (s).
PRIOR_FROZEN_AFTER_S = 0.25


# What a pose prior's step may change by from one frame to the next beyond max_accel and
# max_angular_accel: its own noise (the real capture's ARKit: 4.5 mm and 0.3 deg at 60 Hz) (m, deg)
PRIOR_STEP_SLACK_M, PRIOR_STEP_SLACK_DEG = 0.02, 1.0


# What a surface family's share in the map's own cells may lose where the step before,
# continued, is preferred to the prior's own step (:meth:`Registrar._map_prefers`): the floor's
# lost 0.04-0.10 at the bundled bag's re-anchors, where a wall gained 0.28-0.59
PRIOR_CHECK_LOSS = 0.15


# ICP alone's step that says the sensor moved while its frozen prior stood still (m, deg)
STILL_M, STILL_DEG = 0.02, 1.0


def _reanchor(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """The re-anchoring of a prior's world that takes its pose ``current`` to ``target``:
    ``fix @ current`` is ``target`` in position, and in rotation too, but where the turn is
    within 10 deg of one about the world's z (a gravity-aligned prior keeps its gravity through
    a relocalisation) it is that turn about z alone."""
    fix = target @ np.linalg.inv(current)
    R = fix[:3, :3]
    if np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))) <= 10.0:
        yaw = np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1])
        c, s_ = np.cos(yaw), np.sin(yaw)
        fix[:3, :3] = [[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]
        fix[:3, 3] = target[:3, 3] - fix[:3, :3] @ current[:3, 3]
    return fix


def _continued(
    step: tuple[np.ndarray, float], interval: float, max_gap: float
) -> np.ndarray | None:
    """The prior's ``step`` (over its interval, s) continued over ``interval``: what a steady
    motion would have moved since, the guess where the prior's own step is in doubt. None where
    the two intervals are too unlike to carry one over to the other (bunched stamps would blow
    a 5 ms step up 40 times; a step over a dropout says little of the motion at its end)."""
    prev, prev_interval = step
    if not 0.0 < prev_interval <= max_gap:
        return None
    ratio = interval / prev_interval
    if not 0.5 <= ratio <= 2.0:
        return None
    return prev if abs(ratio - 1.0) <= 1e-3 else exp_se3(log_se3(prev) * ratio)


def _motion(step: np.ndarray | None) -> str:
    """What motion ``step`` is, for a failure reason; empty where it is none (within
    :data:`STILL_M` and :data:`STILL_DEG`)."""
    if step is None:
        return ""
    dist, turn = float(np.linalg.norm(step[:3, 3])), rotation_angle_deg(step)
    if dist <= STILL_M and turn <= STILL_DEG:
        return ""
    return f"the view moved {100 * dist:.0f} cm, {turn:.0f} deg"


@dataclass
class RegCounters:
    frames: int = 0
    accepted: int = 0
    failed: int = 0
    relocalised: int = 0
    # frames whose pose prior had repeated itself to the bit for longer than
    # PRIOR_FROZEN_AFTER_S (tracking lost, a pose source that stalled)
    prior_frozen: int = 0
    # frames that came more than max_gap after the frame before them (a dropout, a stalled
    # stream): each was registered as a relocalisation, and counts as relocalised if it passed
    gaps: int = 0
    # frames whose pose prior came back more than max_gap after the last frame that had one
    # (frames between came without): each was registered as after a dropout
    prior_gaps: int = 0
    failure_reasons: dict[str, int] = dc_field(default_factory=dict)


class Registrar:
    """Frame-to-map registration state machine: ``ok`` <-> ``relocalising``."""

    def __init__(self, cfg: RegistrationConfig) -> None:
        cfg.validate()
        from kiss_icp.config import load_config
        from kiss_icp.mapping import get_voxel_hash_map
        from kiss_icp.registration import get_registration
        from kiss_icp.threshold import get_threshold_estimator

        self.cfg = cfg
        kcfg = load_config(None)
        kcfg.data.max_range = cfg.max_range
        kcfg.data.min_range = 0.0
        kcfg.data.deskew = False
        kcfg.mapping.voxel_size = cfg.voxel_size
        kcfg.mapping.max_points_per_voxel = cfg.max_points_per_voxel
        kcfg.registration.max_num_iterations = cfg.max_iterations
        kcfg.registration.convergence_criterion = cfg.convergence
        kcfg.registration.max_num_threads = cfg.threads
        kcfg.adaptive_threshold.initial_threshold = cfg.initial_threshold
        kcfg.adaptive_threshold.min_motion_th = cfg.min_motion_th
        self._kcfg = kcfg
        self._map = get_voxel_hash_map(kcfg)
        self._reg = get_registration(kcfg)
        self._threshold = get_threshold_estimator(kcfg)
        self._occupied = np.empty(0, dtype=np.int64)  # fitness cells with map points, sorted
        self._near = np.empty(0, dtype=np.int64)  # those and their 26 neighbours, sorted
        self.state = "ok"
        self.last_pose = np.eye(4)
        self.last_delta = np.eye(4)
        self.last_stamp: float | None = None
        # the stamp of the frame before this one that had points to register, accepted or not:
        # a dropout is a gap between two such frames (max_gap)
        self._seen_stamp: float | None = None
        self.last_prior: np.ndarray | None = None  # the last accepted frame's, continuous
        # the pose of the frame last_prior came with: the last accepted one, but where the
        # frames since were registered by ICP alone while the prior stood still (frozen); the
        # prior's step when it moves again is taken from there, across the whole freeze
        self._prior_pose = np.eye(4)
        # The prior's world re-anchored at its jumps (:meth:`_continuous_prior`): the fix
        # applied to every raw prior now, the one as of the last accepted frame, and the
        # previous frame's continuous prior and stamp, which a jump is measured against.
        self._prior_fix = np.eye(4)
        self._fix_at_accept = np.eye(4)
        self._prev_prior: np.ndarray | None = None
        self._prev_prior_stamp: float | None = None
        # the prior's step into the previous frame and its interval (s), where that frame's
        # prior was neither a repeat nor a jump: what the next step is compared with
        self._prev_step: tuple[np.ndarray, float] | None = None
        # the previous frame's prior as given, and the stamp of the first frame it came with
        self._raw_prior: np.ndarray | None = None
        self._raw_since = 0.0
        # Relocalising since a gap (max_gap): the prior's world may have re-anchored across it
        # unseen, so its guesses are held to ICP alone's standard until a frame is accepted.
        self._after_gap = False
        # The stamp of the last frame that came with a pose prior (None: none has yet), and
        # whether frames have come without one since. A run with a prior places no frame by
        # ICP alone where the prior is missing, and a prior back after a pause longer than
        # max_gap is judged as after a dropout (its world may have re-anchored meanwhile).
        self._prior_seen: float | None = None
        self._prior_missing = False
        # whether registration was "ok" when the prior went missing, and only its absence
        # failed frames since: a prior back within max_gap then goes on as if those frames
        # had been dropped (its step since the last accepted frame spans them)
        self._paused_ok = False
        self.counters = RegCounters()
        self.prior_scale_fit = PriorScaleEstimate()
        # the steps joined so far into one scale measurement: the chain of the prior's steps
        # and the chain of those steps with ICP's corrections, since the last measurement
        self._scale_window: tuple[np.ndarray, np.ndarray] | None = None

    # -- map occupancy for the overlap check -------------------------------------------------
    def _keys(self, pts: np.ndarray) -> np.ndarray:
        # evidence's layout (so its NEIGHBOUR_KEYS step between cells); a point beyond the key
        # space (about 100 km at 5 cm: only a pose gone wild) matches nothing and is not stored
        return voxel_keys_or_invalid(pts, self.cfg.fitness_cell)

    def _hits(self, pts_odom: np.ndarray, own_cells: bool = False) -> np.ndarray:
        """Which points land on the map. A point matches when its cell or one of the 26 around
        it is occupied: the tolerance is one to two cells, independent of where cell borders
        fall. ``_near`` holds exactly those cells, so that is one lookup per point, not 27.
        ``own_cells``: in the map's occupied cells themselves (``_occupied``), no tolerance."""
        cells = self._occupied if own_cells else self._near
        if cells.size == 0:
            return np.zeros(pts_odom.shape[0], dtype=bool)
        return contains_sorted(cells, self._keys(pts_odom))

    @staticmethod
    def _share(hits: np.ndarray) -> float:
        return float(np.mean(hits)) if hits.size else 0.0

    def _fitness(self, pts_odom: np.ndarray) -> float:
        return self._share(self._hits(pts_odom))

    def _families(self, inputs: FrameInputs) -> tuple[np.ndarray, list[int]]:
        """The frame's surface-family sizes, and the families that count (of
        ``relocalise_min_points`` or more): smaller ones fix no direction to be checked."""
        fam = inputs.families
        counts = np.bincount(fam[fam >= 0], minlength=3)
        return counts, [f for f in range(3) if counts[f] >= self.cfg.relocalise_min_points]

    def _unconfirmed(self, inputs: FrameInputs, hits: np.ndarray, with_prior: bool) -> str:
        """Why a relocalised pose is not believed, or "" (``hits``: :meth:`_hits` of the
        frame's ``inputs.down`` at that pose).

        The frame's surface families (:func:`surface_families`) of ``relocalise_min_points`` or
        more must each land on the map with ``relocalise_min_fitness`` of their points (from
        the prior's guess, ``relocalise_prior_min_fitness``), and all three must be there for
        ICP alone, two for a guess from the prior: a family too small leaves a direction
        unfixed (floor and one wall slide along the wall), which the prior's motion fills in
        where there is one. Not after a gap, where the prior may have re-anchored unseen: a
        guess 2.4 m off read 0.30 in the wall family 12 s after one (the right catch-up of a
        prior that froze, with no gap, read 0.41). A view of floor alone never relocalises: on
        the bundled bag one with 93 and 48 points beside the floor had relocalised 2.4 m off,
        every family matching.
        """
        cfg = self.cfg
        least = cfg.relocalise_prior_min_fitness if with_prior else cfg.relocalise_min_fitness
        needed = 2 if with_prior else 3
        counts, big = self._families(inputs)
        if len(big) < needed:
            small = ", ".join(str(int(counts[f])) for f in range(3) if f not in big)
            return (
                f"relocalisation unconfirmed (too little structure to fix the pose: surface "
                f"families of {small} points < {cfg.relocalise_min_points})"
            )
        for family in big:
            share = float(hits[inputs.families == family].mean())
            if share < least:
                return (
                    f"relocalisation unconfirmed (surface family {family}: {share:.2f} of "
                    f"{int(counts[family])} points on the map < {least:.2f})"
                )
        return ""

    def _ambiguous(self, inputs: FrameInputs, pose: np.ndarray) -> str:
        """Why the view cannot tell ``pose`` from another placing, or "" (after a gap only).

        The frame is aligned again from ``relocalise_ambiguity`` away along each of the two
        directions its view constrains least (the weakest of its point-to-plane information's
        translation axes), with the search a relocalisation from the prior uses. Where the map
        pulls such an alignment back toward ``pose``, the view holds it there; where one stays
        as far away (90 % or more) and passes the checks of ICP alone (:meth:`_unconfirmed`),
        either placing is a guess, and after a gap the prior that chose this one may have
        re-anchored its world unseen. The checks alone, with their cell or two of tolerance
        and the map's clutter, had passed placings 14-39 cm off (the bundled bag with three
        frames dropped and the prior re-anchored across them, 15 to 30 cm).
        """
        cfg = self.cfg
        if cfg.relocalise_ambiguity <= 0:
            return ""
        info = inputs.info
        if info is None:
            info = point_to_plane_information(inputs.down, 0.5 * cfg.voxel_size)
            if info is None:
                return ""
        _, axes = np.linalg.eigh(info[:3, :3])  # ascending: the least constrained first
        kernel = cfg.prior_threshold * cfg.relocalise_scale
        for axis in axes[:, :2].T:
            for sign in (1.0, -1.0):
                seed = pose.copy()
                seed[:3, 3] += sign * cfg.relocalise_ambiguity * (pose[:3, :3] @ axis)
                other = np.asarray(self._align(inputs.source, seed, 3.0 * kernel, kernel))
                off = np.linalg.inv(pose) @ other
                apart = float(np.linalg.norm(off[:3, 3]))
                if apart < 0.9 * cfg.relocalise_ambiguity:
                    continue
                hits = self._hits(transform(inputs.down, other))
                if not self._unconfirmed(inputs, hits, with_prior=False):
                    return (
                        f"relocalisation ambiguous (a placing {apart:.2f} m, "
                        f"{rotation_angle_deg(off):.1f} deg away fits the map as well)"
                    )
        return ""

    def _integrate(self, pts_sensor: np.ndarray, pose: np.ndarray) -> None:
        # KISS-ICP's update() transforms the sensor-frame points by ``pose`` itself.
        self._map.update(pts_sensor, pose)
        keys = np.unique(self._keys(transform(pts_sensor, pose)))
        keys = keys[keys != INVALID_KEY]
        # Only a frame's new cells are merged (into sorted arrays, in place of a union that
        # re-sorted the whole map every frame: a cost that grew with the session).
        fresh = keys[~contains_sorted(self._occupied, keys)]
        if fresh.size:
            self._occupied = _insert_sorted(self._occupied, fresh)
            around = (fresh[:, None] + NEIGHBOUR_KEYS[None, :]).ravel()
            near = np.unique(np.concatenate([fresh, around]))
            self._near = _insert_sorted(self._near, near[~contains_sorted(self._near, near)])

    # -- alignment -----------------------------------------------------------------------------
    def _align(self, source: np.ndarray, guess: np.ndarray, max_corr: float, kernel: float) -> Any:
        if self.cfg.method == "kiss":
            return self._reg.align_points_to_map(
                points=source,
                voxel_map=self._map,
                initial_guess=guess,
                max_correspondance_distance=max_corr,
                kernel=kernel,
            )
        import open3d as o3d

        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self._map.point_cloud()))
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(3 * self.cfg.voxel_size, 20))
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
        res = o3d.pipelines.registration.registration_icp(
            src,
            target,
            max_corr,
            guess,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(
                max_iteration=self.cfg.max_iterations
            ),
        )
        return np.asarray(res.transformation)

    def register(
        self,
        points: np.ndarray,
        stamp: float,
        prior: np.ndarray | None = None,
        inputs: FrameInputs | None = None,
        after_gap: bool | None = None,
        dropped_priors: tuple[float, float] | None = None,
    ) -> RegResult:
        """Register one filtered sensor-frame cloud; integrate it only if it passes the checks.

        ``prior`` is an optional pose of the sensor in ANY fixed frame (e.g. ARKit world); only
        its motion since the last accepted frame is used, as the initial guess. ``inputs``:
        :func:`frame_inputs` of ``points`` under this registrar's config, where computed ahead.
        ``after_gap``: whether the frame follows a dropout (``max_gap``), where the stamps no
        longer tell (frames registered again without the ones that failed between them); by
        default read from the stamps. ``dropped_priors``: (first, last): seconds from the first and
        the last frame before this one that the caller dropped (a live node's, while busy) and
        that had a pose prior, since the frame it registered before: the prior went on there,
        or came back there after a pause.
        """
        t0 = time.perf_counter()
        cfg = self.cfg
        self.counters.frames += 1
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if inputs is None:
            inputs = frame_inputs(pts, cfg)
        frame_down = inputs.down
        if frame_down.shape[0] < cfg.min_points // 4 or pts.shape[0] < cfg.min_points:
            return self._fail(f"too few points ({pts.shape[0]})", t0)
        relocalising = self.state == "relocalising"
        gap = ""
        if self._seen_stamp is not None and self.last_stamp is not None:
            waited = float(stamp - self._seen_stamp)
            if after_gap if after_gap is not None else waited > cfg.max_gap:
                # Over a dropout the speed and turn rules allow metres and any heading, and a
                # prior that re-anchored meanwhile cannot be told from a drive: the map decides.
                # Measured from the frame before, failed or not: frames that fail one after
                # another make no gap, as each had its prior checked against the one before.
                relocalising = True
                self._after_gap = True
                self.counters.gaps += 1
                gap = f" ({waited:.1f} s after the frame before)"
        self._seen_stamp = float(stamp)
        # The prior's world as of the last accepted frame: a discontinuity since then
        # (:meth:`_continuous_prior`) is either the prior's world jumping (ARKit relocalising:
        # its raw step would put the frame metres off) or the prior catching up after it froze
        # (its raw step is right). Only the map can tell: while relocalising, both are tried.
        raw_fix = self._fix_at_accept
        # A prior that repeats the previous frame's says nothing of the motion since (a pose
        # topic slower than the clouds), and one that has repeated itself for longer has stopped
        # estimating (ARKit's tracking lost, a pose source stalled). Followed, its zero steps
        # were corrected by half ICP's turn each frame and the lag went into the map: after a
        # 2 s freeze the map ran 4.8 deg off for good; a chair driving at 0.8 m/s stayed on the
        # spot, 1.45 m off after 1.6 s, and the map doubled. ICP alone first; the prior where ICP
        # alone cannot place the frame, but not once it is frozen and ICP saw the view move.
        # A frozen prior's continuity is not updated: its catch-up is measured from where it
        # froze, and its step is taken from the pose of the last frame that followed it.
        repeat, frozen = self._repeat(prior, stamp)
        if dropped_priors is not None and self._prior_seen is not None and not self._prior_missing:
            # frames dropped while busy had their prior: the prior did not pause there
            self._prior_seen = max(self._prior_seen, float(stamp - dropped_priors[1]))
        if prior is None and self._prior_seen is not None and self.last_stamp is not None:
            # A run with a prior whose prior is missing for this frame (the pose topic paused,
            # a message lost or refused): the frame fails rather than being placed by ICP
            # alone. The views a prior is needed for are the views ICP alone cannot place:
            # the bundled bag with two odometry messages lost (0.4 s) mapped 1.06 m off, with
            # ten (2 s) 3.2 m off, no failure but the first frame's, and the map followed.
            paused_ok = self.state == "ok" if not self._prior_missing else self._paused_ok
            self._prior_missing = True
            since = float(stamp - self._prior_seen)
            failed = self._fail(f"no pose prior ({since:.1f} s since the last){gap}", t0)
            self._paused_ok = paused_ok and not gap
            return failed
        if prior is not None:
            # The prior came back with this frame or, where frames before it were dropped while
            # busy with their prior, with the first of those: the node waits up to 0.25 s for
            # a missing pose, and the frames after it were then often dropped (measured from
            # this one, a lost odometry message made a 0.6 s "pause", and 22 frames failed).
            # From the first, not the last: a pause that ended there was read as over (a
            # review: a re-anchor across a 2 s pause went on 31 cm off).
            back = float(stamp - (dropped_priors[0] if dropped_priors is not None else 0.0))
            paused = back - self._prior_seen if self._prior_seen is not None else 0.0
            if self._prior_missing and not gap:
                if paused > cfg.max_gap and not self._after_gap:
                    # The prior paused for longer than a dropout while the clouds went on: its
                    # world may have re-anchored meanwhile (ARKit relocalising is one reason it
                    # pauses), which the speed rules cannot tell from the motion over it. (Where
                    # a dropout of the clouds came first, it is judged so already, and counted.)
                    relocalising = True
                    self._after_gap = True
                    self.counters.prior_gaps += 1
                    gap = f" (the pose prior back after {paused:.1f} s)"
                elif paused <= cfg.max_gap and self._paused_ok:
                    # A short pause in a run registered "ok": the frames without a prior are
                    # as if dropped, and the prior's step spans them. Registered as a
                    # relocalisation, two odometry messages lost cost 24 frames of the
                    # bundled bag (22 of them "relocalisation unconfirmed").
                    relocalising = False
            self._prior_seen, self._prior_missing, self._paused_ok = float(stamp), False, False
        virtual: np.ndarray | None
        # where the prior's step changed enough for the map to judge it: the step before,
        # continued (:meth:`_continuous_prior`)
        suspect: np.ndarray | None = None
        if frozen:
            self.counters.prior_frozen += 1
            virtual, jumped = self._prior_fix @ np.asarray(prior, dtype=np.float64), ""
        elif prior is None:
            virtual, jumped = None, ""
        else:
            virtual, jumped, suspect = self._continuous_prior(prior, stamp, repeat)
        if self.last_stamp is None:  # the first frame: the map begins with it
            self._integrate(frame_down, np.eye(4))
            self._accepted_prior(stamp, virtual)
            self.counters.accepted += 1
            return RegResult(
                np.eye(4), True, fitness=1.0, seconds=time.perf_counter() - t0, prior=virtual
            )
        if jumped:
            return self._fail(jumped + gap, t0)
        hypotheses = [None, virtual] if repeat else [virtual]
        fallback = None  # the attempt of ICP alone where every guess of the prior failed
        raw = None
        if (
            relocalising
            and not repeat
            and prior is not None
            and not np.array_equal(raw_fix, self._prior_fix)
        ):
            raw = len(hypotheses)
            hypotheses.append(raw_fix @ np.asarray(prior, dtype=np.float64))
        # a repeated prior as the guess starts from the last pose, as it did before
        tries = [
            self._attempt(inputs, stamp, h, relocalising, self.last_pose if repeat else None)
            for h in hypotheses
        ]
        passed = [t for t in tries if not t.reason]
        if (
            suspect is not None
            and not relocalising
            and not repeat
            and passed
            and tries[0].prior_step is not None  # the prior's step was followed
        ):
            assert virtual is not None  # (a suspect is a prior's step; for mypy)
            judged = self._map_prefers(inputs, stamp, tries[0], suspect)
            if judged:
                # The map holds the prior's step to be a re-anchor of its world that max_accel
                # allows at this frame rate (34 cm at 5 Hz): followed, ICP's narrow search
                # around the prior's guess could not correct it, the floor gave the overlap,
                # and the map went on 0.1-0.7 m off with no failure counted.
                self._prev_prior = self._move_prior_world(suspect, virtual)
                # and the world it jumped to is not tried again while relocalising (the "raw"
                # guess, for a prior that froze and caught up): the map has refuted it, and the
                # overlap that picks between guesses cannot tell a wall 10 cm off (at a 10 cm
                # re-anchor it took the refuted world back, and the map went on 10.5 cm off)
                self._fix_at_accept = self._prior_fix.copy()
                return self._fail(f"pose prior jumped ({judged})", t0)
        if (
            relocalising
            and virtual is not None
            and not repeat
            and not passed
            and (gap or not self._after_gap)
        ):
            # The map refutes every guess the prior gives (a 2 m jump, say): ICP alone from
            # the last pose, under the same checks. Taken only where the prior's guesses fail,
            # because a right prior is the better guess; its pose then re-anchors the prior's
            # steps, which go on from the frame it places. After a gap, on the gap's first
            # frame only: ICP alone's guess (the last pose, one frame's motion on) knows nothing
            # of the motion over the gap, and every frame that fails after it makes it staler.
            # On the bundled bag with clouds 130-132 lost and the prior re-anchored 28 cm, it
            # placed the gap's first frame 51 cm off (which :meth:`_ambiguous` now refuses),
            # the prior was re-anchored to it, and the map ran on to 2.2 m off, none failed;
            # with the gap at 170, a later frame's placing 1.7 m off.
            alone = self._attempt(inputs, stamp, None, True)
            if not alone.reason:
                tries.append(replace(alone, prior=virtual))
                passed = tries[-1:]
                fallback = tries[-1]
        moved = ""  # what ICP alone saw of the motion, where the prior repeated itself
        if repeat:
            alone, followed = tries
            moved = _motion(alone.step)
            if not alone.reason:
                best = alone
            elif frozen and (moved or followed.reason):
                # ICP alone cannot place the frame (a view that leaves a direction free), and
                # the view moved where the prior stood, or the prior's guess fails too
                why = moved or alone.reason
                return self._fail(
                    f"pose prior stands still ({why}); its tracking lost?{gap}", t0, alone.fitness
                )
            else:
                best = followed  # at rest, as ICP alone saw too, or not frozen: as before
        else:
            best = max(passed or tries, key=lambda t: t.fitness)
        if passed and raw is not None and best is tries[raw]:
            # the map agrees with the prior's raw step since the last accepted frame (it froze
            # and caught up): its world is the one from before the discontinuity
            self._prior_fix = raw_fix
            self._prev_prior = best.prior
            self._prev_step = None
        pose, fitness, reason, guess = best.pose, best.fitness, best.reason, best.guess
        if reason:
            return self._fail(reason + gap, t0, fitness, pose)
        if best is fallback and self.last_prior is not None and virtual is not None:
            # The map placed the frame where the prior's guess was refuted: the prior's world
            # is re-anchored to agree with it, so that what is kept of the prior (gravity, the
            # loop closure's prior drift, a second registration pass) holds no refuted jump.
            expected = self.last_prior @ np.linalg.inv(self._prior_pose) @ pose
            virtual = self._move_prior_world(expected, virtual)
            best = replace(best, prior=virtual)
            self._prev_prior = virtual

        if relocalising or best.prior_step is None or best.info is None:
            self._scale_window = None  # a scale measurement spans registered steps only
        else:
            self._measure_prior_scale(best.prior_step, best.corr, best.info)
        if not relocalising:
            self._threshold.update_model_deviation(np.linalg.inv(guess) @ pose)
        self._integrate(frame_down, pose)
        self.last_delta = best.step if not relocalising else np.eye(4)
        self.last_pose = pose
        icp_alone = repeat and best.prior is None
        self._accepted_prior(stamp, best.prior, pose, icp_alone=icp_alone)
        # The prior the frame is said to have had (gravity, the loop closure's prior drift): a
        # repeat ICP alone registered is still the prior's word for the frame, one message late
        # (a slow pose topic), or right (a frozen prior at rest); a frozen one the view moved
        # away from is no word at all, and the loop closure then does without the prior.
        said = virtual if icp_alone and not (frozen and moved) else best.prior
        self.counters.accepted += 1
        self._after_gap = False
        if relocalising:
            self.counters.relocalised += 1
        self.state = "ok"  # (also after frames that failed only for a missing prior)
        return RegResult(
            pose,
            True,
            fitness=fitness,
            relocalised=relocalising,
            seconds=time.perf_counter() - t0,
            prior=said,
            after_gap=bool(gap),
        )

    def _repeat(self, prior: np.ndarray | None, stamp: float) -> tuple[bool, bool]:
        """Whether ``prior`` repeats the previous frame's to the bit, and whether it has done so
        for longer than :data:`PRIOR_FROZEN_AFTER_S` (frozen). No estimator of a pose in motion
        or at rest repeats itself (its noise moves the last digits): one that has stopped
        estimating does. A shorter repeat is one pose message given to the frames either side
        of it (a pose topic slower than the clouds: the mapper and ``wheelgrid map`` take the
        nearest within 0.1 s)."""
        if prior is None:
            # The prior given before is kept: a frozen prior whose messages are lost now and
            # then is still frozen (reset here, each repeat after a frame without one read as
            # fresh, and a prior frozen 1.6 s with every other message lost put the bundled
            # bag's map 1.28 m off, exit 0)
            return False, False
        if self._raw_prior is None or not np.array_equal(self._raw_prior, prior):
            self._raw_prior, self._raw_since = np.array(prior), float(stamp)
            return False, False
        if self.last_stamp is None:
            return False, False
        return True, float(stamp) - self._raw_since > PRIOR_FROZEN_AFTER_S

    def _accepted_prior(
        self,
        stamp: float,
        prior: np.ndarray | None,
        pose: np.ndarray | None = None,
        icp_alone: bool = False,
    ) -> None:
        """Remember an accepted frame's stamp and (continuous) prior: the next guess starts
        from them, and the prior's world as of now is the "raw" hypothesis of a later
        relocalisation. A frame ICP alone registered while the prior was frozen leaves the
        prior and its pose as they were: its catch-up is a step from there."""
        self.last_stamp = stamp
        self._fix_at_accept = self._prior_fix.copy()
        if icp_alone:
            return
        self.last_prior = prior
        self._prior_pose = np.eye(4) if pose is None else pose

    def _move_prior_world(self, target: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Re-anchor the prior's world so that its pose ``current`` (continuous) becomes
        ``target`` (:func:`_reanchor`), and return it re-anchored. The step into it is no step
        of the prior's, so the next one is not compared with it (:meth:`_jerk`)."""
        fix = _reanchor(target, current)
        self._prior_fix = fix @ self._prior_fix
        self._prev_step = None
        return fix @ current

    def _continuous_prior(
        self, prior: np.ndarray, stamp: float, repeat: bool = False
    ) -> tuple[np.ndarray, str, np.ndarray | None]:
        """``prior`` in a world continuous from frame to frame, a failure reason where the
        prior jumped since the previous frame that had one (a step no chair makes, by the same
        ``max_speed`` / ``max_turn_rate`` rule as the registered pose), and where its step
        changed enough for the map to judge it, the step before, continued (else None).

        Why: a visual-inertial prior re-anchors its world now and then (ARKit relocalising
        against its own map moves it by metres) or freezes and then catches up. Its step since
        the last accepted frame then holds the jump, and every later guess with it: the frame
        after an ARKit jump of 2 m failed, and once enough time had passed for 2 m to be a
        plausible drive, a frame registered 1.9 m off (the floor alone gave it the overlap) and
        mapping "resumed" there, the map doubled. At a jump the prior's world is re-anchored so
        that this frame's prior continues the step before it (a steady motion); where that step
        is not known, so that it is the previous frame's, a frame's motion lost for
        relocalisation's wider search to absorb. At 5 Hz that lost step was up to 16 cm, and a
        relocalisation then settled 18 cm and 2.2 deg off for good. The turn of the re-anchor
        is kept about the prior's z where it is within 10 deg of a turn about it (a
        gravity-aligned prior keeps gravity through a relocalisation), else taken whole.

        A step that fits those rules can still be a jump: a re-anchor of 30 cm is a walk at 5 Hz
        and a sprint at 60 Hz. So a step is also compared with the step before it
        (:meth:`_jerk`), where neither is a repeat (a pose topic slower than the clouds gives
        steps of 0 and 2x in turn) and no gap lies between (relocalisation checks those). A
        change within ``max_accel`` but over ``prior_check_step`` / ``prior_check_turn`` is
        returned with the step before, continued, for the map to judge (:meth:`_map_prefers`).
        """
        cfg = self.cfg
        virtual = self._prior_fix @ prior
        reason = ""
        judge: np.ndarray | None = None
        if self._prev_prior is not None and self._prev_prior_stamp is not None:
            jump = np.linalg.inv(self._prev_prior) @ virtual
            interval = float(stamp - self._prev_prior_stamp)
            dt = max(interval, cfg.min_dt)
            dist, turn = float(np.linalg.norm(jump[:3, 3])), rotation_angle_deg(jump)
            jerk, suspect = "", False
            # where the prior jumped, its world is re-anchored on the step before, continued
            # (where not known, on the prior standing still: a frame's motion lost)
            continued = self._prev_prior
            if self._prev_step is not None and not repeat and 0.0 < interval <= cfg.max_gap:
                jerk, suspect = self._jerk(self._prev_step, jump, interval)
                steady = _continued(self._prev_step, interval, cfg.max_gap)
                if steady is not None:
                    continued = self._prev_prior @ steady
                else:
                    suspect = False  # no steady motion to weigh the prior's step against
            self._prev_step = None if repeat else (jump, interval)
            if self._implausible(jump, dt) or jerk:
                virtual = self._move_prior_world(continued, virtual)
                reason = f"pose prior jumped ({dist:.2f} m, {turn:.0f} deg in {dt:.2f} s{jerk})"
            elif suspect:
                judge = continued
        self._prev_prior, self._prev_prior_stamp = virtual, float(stamp)
        return virtual, reason, judge

    def _attempt(
        self,
        inputs: FrameInputs,
        stamp: float,
        prior: np.ndarray | None,
        relocalising: bool,
        base: np.ndarray | None = None,
    ) -> _Attempt:
        """Align one frame from the guess ``prior`` (continuous, or None) gives and run every
        check on the result; changes nothing, so that two guesses can be tried. The prior's
        step is applied to ``base``, by default the pose of the frame ``last_prior`` came with."""
        cfg = self.cfg
        assert self.last_stamp is not None
        frame_down = inputs.down
        prior_step = None
        with_prior = prior is not None and self.last_prior is not None
        if with_prior:
            assert prior is not None and self.last_prior is not None
            target = prior
            if cfg.prior_scale != 1.0:
                # Horizontal only, in the prior's own frame (z up: REP-105's odom, ARKit's
                # world as the bridge publishes it): the floor fixes height, and on the real
                # capture rescaling a hand-held phone's climbs too moved its floor against
                # the surface first levelled on, by centimetres.
                target = prior.copy()
                target[:2, 3] = (
                    self.last_prior[:2, 3]
                    + (prior[:2, 3] - self.last_prior[:2, 3]) / cfg.prior_scale
                )
            prior_step = np.linalg.inv(self.last_prior) @ target
            guess = (self._prior_pose if base is None else base) @ prior_step
        else:
            guess = self.last_pose @ self.last_delta
        source = inputs.source
        if with_prior:
            sigma = cfg.prior_threshold
        elif cfg.fixed_threshold > 0:
            sigma = cfg.fixed_threshold
        else:
            sigma = float(self._threshold.get_threshold())
        scale = cfg.relocalise_scale if relocalising else 1.0
        pose = self._align(source, guess, 3.0 * sigma * scale, sigma * scale)
        corr = np.linalg.inv(guess) @ pose  # ICP's correction of the guess (sensor frame)
        degenerate = 0
        info = None
        ratio = cfg.degeneracy_ratio if with_prior else cfg.reject_degenerate_ratio
        if ratio > 0:
            info = inputs.info
            observed, degenerate = constrain_to_observable(
                frame_down, 0.5 * cfg.voxel_size, corr, ratio, info
            )
            if with_prior:
                corr = observed
        if with_prior:
            assert prior is not None  # (with_prior says so; for mypy)
            pose = guess @ blend_correction(
                corr,
                cfg.prior_translation_gain,
                cfg.prior_rotation_gain,
                None if cfg.prior_tilt_gain < 0 else cfg.prior_tilt_gain,
                prior[2, :3],  # its world's z in this sensor frame
            )
        hits = self._hits(transform(frame_down, pose))  # the overlap, and each family's
        fitness = self._share(hits)

        reason = ""
        dt = max(float(stamp - self.last_stamp), cfg.min_dt)
        step = np.linalg.inv(self.last_pose) @ pose
        if degenerate and not with_prior:
            dirs = "direction" if degenerate == 1 else "directions"
            reason = f"degenerate geometry ({degenerate} unconstrained motion {dirs}, no prior)"
        elif fitness < cfg.min_fitness:
            reason = f"low overlap (fitness {fitness:.2f} < {cfg.min_fitness:.2f})"
        elif implausible := self._implausible(step, dt):
            reason = implausible
        elif with_prior:
            dev = np.linalg.inv(guess) @ pose
            if np.linalg.norm(dev[:3, 3]) > cfg.max_prior_deviation:
                reason = f"disagrees with pose prior by {np.linalg.norm(dev[:3, 3]):.2f} m"
            elif rotation_angle_deg(dev) > cfg.max_prior_deviation_deg:
                reason = f"disagrees with pose prior by {rotation_angle_deg(dev):.0f} deg"
        if relocalising and not reason:
            reason = self._unconfirmed(inputs, hits, with_prior and not self._after_gap)
            if not reason and self._after_gap:
                reason = self._ambiguous(inputs, pose)
        return _Attempt(pose, fitness, reason, guess, corr, info, prior_step, step, prior)

    def _map_prefers(
        self, inputs: FrameInputs, stamp: float, followed: _Attempt, continued: np.ndarray
    ) -> str:
        """Why the map holds the prior's step into this frame to be a jump of its world, or "".

        The frame is aligned again from ``continued`` (the prior's step before, continued) as a
        relocalisation would be. The prior jumped where that placing passes every check and
        lands one of the frame's surface families (of ``relocalise_min_points`` or more) in
        the map's own occupied cells with ``prior_check_gain`` more of its points than
        ``followed`` (the prior's own step) does, and none with :data:`PRIOR_CHECK_LOSS` less.
        The map's own cells, not the overlap check's 1-2 cells around them: a wall 10 cm off
        still lands within those (0.94 against 0.98 of it at a 10 cm re-anchor, where the
        chair's own steps read up to 0.10 apart). A chair's true acceleration puts the step
        before, continued, off instead, and the map never prefers it by much (0.14 at most on
        11 simulated runs); a re-anchor of the prior's world leaves a wall or a table off by
        its size, which the step before, continued, puts back (0.28-0.59).
        """
        cfg = self.cfg
        other = self._attempt(inputs, stamp, continued, True)
        if other.reason:
            return ""
        counts, big = self._families(inputs)
        was_in, now_in = (
            self._hits(transform(inputs.down, pose), own_cells=True)
            for pose in (followed.pose, other.pose)
        )
        best, gain, was, now = -1, -np.inf, 0.0, 0.0
        for family in big:
            mine = inputs.families == family
            before, after = float(was_in[mine].mean()), float(now_in[mine].mean())
            if after - before < -PRIOR_CHECK_LOSS:
                return ""
            if after - before > gain:
                best, gain, was, now = family, after - before, before, after
        if best < 0 or gain < cfg.prior_check_gain:
            return ""
        off = np.linalg.inv(followed.pose) @ other.pose
        return (
            f"the map places the frame {np.linalg.norm(off[:3, 3]):.2f} m, "
            f"{rotation_angle_deg(off):.0f} deg from its guess: surface family {best} "
            f"{was:.2f} -> {now:.2f} of {int(counts[best])} points in the map's cells with the "
            f"step before continued"
        )

    def _jerk(
        self, before: tuple[np.ndarray, float], step: np.ndarray, interval: float
    ) -> tuple[str, bool]:
        """Why the prior's ``step`` (over ``interval`` s) is no continuation of the step
        ``before`` it, or "": it changed by more than ``max_accel`` / ``max_angular_accel``
        allow over the longer of the two intervals (a bunched stamp must not shrink the
        allowance), plus the slack of a prior's own noise. And whether, within that, it
        changed by more than ``prior_check_step`` / ``prior_check_turn``: enough for the map
        to be asked (:meth:`_map_prefers`)."""
        cfg = self.cfg
        prev, prev_interval = before
        dt = max(interval, prev_interval)
        # steps over unequal intervals differ at a steady speed too, by the speed times the
        # difference (the node skips frames while busy; a frame without points is not seen)
        uneven = abs(interval - prev_interval) / prev_interval if prev_interval > 0 else 0.0
        change = np.linalg.inv(prev) @ step
        moved = float(np.linalg.norm(step[:3, 3] - prev[:3, 3]))
        turned = rotation_angle_deg(change)
        slack_m = uneven * float(np.linalg.norm(prev[:3, 3]))
        slack_deg = uneven * rotation_angle_deg(prev)
        if moved > cfg.max_accel * dt * dt + PRIOR_STEP_SLACK_M + slack_m:
            return f"; its step changed by {moved:.2f} m from the one before", False
        if turned > cfg.max_angular_accel * dt * dt + PRIOR_STEP_SLACK_DEG + slack_deg:
            return f"; its turn changed by {turned:.1f} deg from the one before", False
        suspect = (0.0 < cfg.prior_check_step < moved - slack_m) or (
            0.0 < cfg.prior_check_turn < turned - slack_deg
        )
        return "", suspect

    def _implausible(self, step: np.ndarray, dt: float) -> str:
        """Why ``step`` (a relative pose over ``dt`` seconds) is no motion a chair makes, or
        "": the one rule for registered steps and for the pose prior's own jumps."""
        cfg = self.cfg
        dist = float(np.linalg.norm(step[:3, 3]))
        if dist > cfg.max_speed * dt + cfg.voxel_size:
            return f"implausible jump ({dist:.2f} m in {dt:.2f} s)"
        turn = rotation_angle_deg(step)
        if turn > cfg.max_turn_rate * dt + 5.0:
            return f"implausible turn ({turn:.0f} deg in {dt:.2f} s)"
        return ""

    def _measure_prior_scale(
        self, prior_step: np.ndarray, correction: np.ndarray, info: np.ndarray
    ) -> None:
        """One :class:`PriorScaleEstimate` measurement per :data:`PRIOR_SCALE_MIN_STEP` of the
        prior's travel, over accepted steps whose view constrains the direction travelled as
        the degeneracy gate would (else ICP kept the prior's step along it, and its correction
        there says nothing; such a step ends the measurement unmade).

        A step that long on its own is one measurement: ICP's correction along it. Shorter
        ones are joined first: a 60 Hz phone moves a centimetre a frame or less, and with
        every frame registered (``wheelgrid map``'s default) no single step would count.
        """
        G, C = self._scale_window or (np.eye(4), np.eye(4))
        G = G @ prior_step  # the prior's travel since the window began (in its first frame)
        C = C @ prior_step @ correction  # the same with ICP's corrections
        t = G[:3, 3]
        length = float(np.linalg.norm(t))
        if length < 1e-9:
            self._scale_window = (G, C)
            return
        u = np.zeros(6)
        u[:3] = G[:3, :3].T @ t / length  # the way travelled, in this frame's coordinates
        if float(u @ info @ u) < self.cfg.degeneracy_ratio:
            self._scale_window = None
            return
        if length < PRIOR_SCALE_MIN_STEP:
            self._scale_window = (G, C)
            return
        self._scale_window = None
        # for a single step: ICP's correction along it, in the step's own frame
        self.prior_scale_fit.add(length, float((C[:3, 3] - t) @ t) / length)

    def _fail(
        self, reason: str, t0: float, fitness: float = 0.0, pose: np.ndarray | None = None
    ) -> RegResult:
        self.counters.failed += 1
        self._scale_window = None
        self._paused_ok = False  # a frame failed for another reason than a missing prior
        key = reason.split(" (")[0].split(" by ")[0]
        self.counters.failure_reasons[key] = self.counters.failure_reasons.get(key, 0) + 1
        if self.last_stamp is not None:
            self.state = "relocalising"
        return RegResult(
            self.last_pose if pose is None else pose,
            False,
            reason=reason,
            fitness=fitness,
            seconds=time.perf_counter() - t0,
        )
