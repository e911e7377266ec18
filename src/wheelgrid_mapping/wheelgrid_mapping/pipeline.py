"""The mapping pipeline shared by ``wheelgrid map`` and the mapper node (ROS-free).

``Mapper.add_frame`` = preprocess (valid/range/confidence, subdivision downsample, SOR, PFC)
-> register against the map (KISS-ICP, failure detection) -> integrate into the global map.
Registration and the global map live in "odom" (the first sensor frame); the levelled ``map``
frame (see :mod:`wheelgrid_mapping.levelling` for the convention) is found from the floor once
enough of it has been seen, or from ``mount_xyz_rpy``. Until it is known, nothing is published
as a map: a map in the wrong frame would put obstacles in the wrong place.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.fileio import write_ply, write_together, write_tum
from wheelgrid_common.params import check_bounds, check_finite, field, from_mapping, read_yaml

from .evidence import EvidenceMap
from .frame_clock import AHEAD_CONFIRM, AHEAD_WINDOW, FrameClock
from .levelling import (
    DOWN_HINT,
    FloorNotFoundError,
    convention_for_frame,
    find_floor,
    floor_of_map,
    height_along,
    lean_within,
    level_vertical,
    map_from_floor,
    map_from_mount,
    tilt_deg,
)
from .loop_closure import LoopClosureConfig, LoopClosureResult, close_loops, submap_groups
from .preprocess import (
    MIN_VOXEL,
    PreprocessConfig,
    PreprocessStats,
    preprocess_for_map,
    voxel_downsample,
)
from .registration import (
    FrameInputs,
    Registrar,
    RegistrationConfig,
    RegResult,
    frame_inputs,
    transform,
)
from .se3 import is_rigid


@dataclass
class MapperConfig:
    """Map building and levelling parameters (YAML section ``mapper``)."""

    map_voxel: float = field(
        0.02, "voxel of the saved/published map", "m", bounds=(MIN_VOXEL, math.inf)
    )
    max_published_points: int = field(
        300000, "the published map cloud is coarsened until it has at most this many", "points"
    )
    sensor_convention: str = field(
        "auto", "auto (REP-103: frame id ending in _optical_frame = optical), optical or body", ""
    )
    mount_xyz_rpy: list[float] = field(  # noqa: RUF009 (params.field copies list defaults)
        [], "sensor pose on a levelled base (z=0 floor): x y z roll pitch yaw; [] = from floor", ""
    )
    floor_max_tilt_deg: float = field(
        45.0,
        "the floor normal may differ this much from the sensor's up (pitched and rolled 30 deg "
        "at once: 41.4 deg)",
        "deg",
    )
    prior_gravity: bool = field(
        True,
        "a pose prior's frame has z up along gravity (REP-105 odom; ARKit through the Stray "
        "adapter and the iPhone bridge): the first floor fit takes its vertical from the prior "
        "and fits only the floor's height, and the report gives the map frame's angle to it; "
        "false: the floor's own plane alone",
        "",
    )
    level_min_frames: int = field(3, "frames integrated before the floor is looked for", "")
    min_frame_interval: float = field(
        0.0, "frames closer in time than this to the last processed one are skipped", "s"
    )
    prepare_ahead: bool = field(
        True,
        "filter each frame in a second process while the frame before registers (wheelgrid "
        "map and the mapper node; the same map, ~1.4x the keyframes per second on 2 cores); "
        "false: one process",
        "",
    )
    evidence_voxel: float = field(
        0.1,
        "voxel in which frame evidence (hits, ray misses) is counted",
        "m",
        bounds=(MIN_VOXEL, math.inf),
    )
    evidence_min_frames: int = field(
        2, "a place reaches the map only when this many frames put points there", "frames"
    )
    evidence_hit_fraction: float = field(
        0.5,
        "and only when at least this share of the frames that looked at it saw something there "
        "(rays of the others passed through: flying pixels, wild returns); 0 = no ray casting",
        "",
    )
    evidence_margin: float = field(
        0.04,
        "map voxels this close to a kept one (sideways, in whole map voxels rounded up) are kept "
        "too, though their evidence voxel failed: a surface's range noise spills into the free "
        "voxel in front of it (0 = off)",
        "m",
    )
    relevel: bool = field(
        True,
        "refine the floor plane from the whole map as it grows (the first floor fit sees only a "
        "few frames; 0.3 deg of tilt lifts a floor 5 cm across a 10 m room), and find the floor "
        "again on the whole map each time the map doubles (a first fit on another plane is "
        "replaced; the report's levelling says so)",
        "",
    )

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ValueError for settings that cannot work (a YAML typo must not end in a traceback
        half-way through a bag). The evidence map, the convention and the mount are checked by
        the code that uses them, run here once on the settings. Non-finite numbers first: a
        NaN passes a test written as a failing comparison (``min_frame_interval: .nan`` did)."""
        check_finite(self, "mapper ")
        if not self.floor_max_tilt_deg > 0:
            raise ValueError(f"floor_max_tilt_deg must be > 0, not {self.floor_max_tilt_deg}")
        for name in ("max_published_points", "level_min_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, not {getattr(self, name)}")
        if self.min_frame_interval < 0:
            raise ValueError(f"min_frame_interval must be >= 0, not {self.min_frame_interval}")
        self.evidence_map()
        # 1e-12 m passed, every frame then "too far from the origin" and the save a traceback
        check_bounds(self, "mapper ")
        convention_for_frame("", self.sensor_convention)
        if self.mount_xyz_rpy:
            map_from_mount(self.mount_xyz_rpy, "optical")

    def evidence_map(self) -> EvidenceMap:
        """An empty map with these settings (the mapper's, and the benchmark's true-pose run)."""
        return EvidenceMap(
            self.map_voxel,
            self.evidence_voxel,
            self.evidence_min_frames,
            self.evidence_hit_fraction,
            margin=self.evidence_margin,
        )


# A level plane this far below z = 0 (m), with 3 % of the map, is a floor the first search missed.
LOWER_FLOOR_GAP = 0.15
# A failed search below the floor is repeated once the points there have grown by this factor.
LOWER_FLOOR_RETRY = 1.25
# With a gravity-aligned prior, a first-floor candidate may lean this much from its vertical
# (a patch of floor seen by three frames: 3.3 deg on the real capture).
PRIOR_FLOOR_MAX_TILT_DEG = 10.0
# ... and the map's floor, refitted as the map grows, this much: on the real capture plane
# fits to the first 4 s of floor leaned 1.4-3.7 deg from ARKit's gravity (1.5-2.5 deg on the
# map fused from ARKit's own poses, whose floor along gravity stayed within 3 cm), and the
# whole maps' floors 0.6-1.1 deg (ICP's tilt drifts against ARKit's; z = 0 follows the map).
PRIOR_FLOOR_LEAN_DEG = 1.5
# The floor is checked on the whole map each time the map has grown by this factor (points).
FLOOR_CHECK_GROWTH = 2.0
# The floor found on the whole map holding this many times the map points within 3 cm that
# z = 0 holds: z = 0 misses part of the floor, and the map frame is taken from the floor found.
FLOOR_CHECK_GAIN = 1.1
# ... but not a floor this far ABOVE z = 0 (m) with this many level map cells (5 cm) this far
# below it: that "floor" is a large low table top or a platform, and the real floor, seen only
# in strips, held too few cells to be the whole map's peak (a review: z = 0 moved 54 cm up on
# to a 2.9 x 3 m table, every obstacle lower than it under the grid's floor band, silently).
FLOOR_CHECK_MAX_RISE = 0.10
FLOOR_CHECK_BELOW_CELLS = 50
# The slab find_floor's RANSAC planes are fitted in (m, its ``distance``), and the lowest level
# along the voted vertical holding this share of the slab's points (at least this many) is the
# floor's part of it (the slab tilted through a strip of floor also cuts a table top).
FLOOR_SLAB_M = 0.03
FLOOR_LEVEL_SHARE = 0.1
FLOOR_LEVEL_MIN_POINTS = 50
# The first fit is turned to the level surfaces' vote only where they disagree this much (deg),
# and only the surfaces this far below the sensor (m) vote.
FIRST_FIT_REFINE_DEG = 3.0
FIRST_FIT_VOTE_BELOW_M = 0.3
# A floor the first frames show this far from the one an explicit mount transform gives
# (deg between the normals, m along them under the first pose) makes a warning: the mount is
# then wrong (a mount measured 30 cm high and 8 deg pitched off put the map's floor 3.4 deg
# off level and the run said nothing), and the grid's floor band would cut through the floor.
MOUNT_FLOOR_TILT_DEG = 2.0
MOUNT_FLOOR_HEIGHT_M = 0.05
# ... unless the mount's floor holds this share of the points within 3 cm that the floor found
# holds: the search takes the lowest level plane, and a ramp ahead can be lower than the floor
MOUNT_FLOOR_SUPPORT = 0.5
# A frame stamped at most this long before the last keyframe (or at its very stamp) is a repeat
# or a late frame, skipped; farther back, a bad stamp or a clock jump (BEHIND_CONFIRM) (s).
LATE_FRAME_WINDOW = 1.0
# Frames in a row stamped LATE_FRAME_WINDOW or more back that make a clock that went back
# (the first of them held back: one alone is a bad stamp, a driver's 0)
BEHIND_CONFIRM = 2
# report.json's reason for a frame with no valid point (all NaN, out of range, filtered away)
EMPTY_REASON = "no valid points"
# report.json lists this many registration failures one by one (all are counted): a
# lost scan fails on hundreds of frames, and the list would bury the rest of the report
MAX_LISTED_FAILURES = 200


def floor_correction(
    pts: np.ndarray,
    band: float = 0.08,
    gate: float = 0.03,
    max_tilt_deg: float = 3.0,
    up: np.ndarray | None = None,
    max_lean_deg: float = PRIOR_FLOOR_LEAN_DEG,
) -> np.ndarray | None:
    """Small rigid correction making the map's floor exactly z = 0 (None if not confident).

    Least-squares plane through the points within ``band`` of z = 0, refit twice on the points
    within ``gate`` of it (table legs and wall feet drop out); rotated about the map origin so
    the origin stays below the first pose and x keeps its direction. ``up``: gravity in the
    map frame (a gravity-aligned pose prior's); the plane may lean at most ``max_lean_deg``
    from it, and its height is taken along the normal kept.
    """
    sel = np.abs(pts[:, 2]) < band
    if sel.sum() < 500:
        return None
    coef = np.zeros(3)
    for _ in range(3):
        a = np.c_[pts[sel, 0], pts[sel, 1], np.ones(int(sel.sum()))]
        coef, *_ = np.linalg.lstsq(a, pts[sel, 2], rcond=None)
        resid = pts[:, 2] - (coef[0] * pts[:, 0] + coef[1] * pts[:, 1] + coef[2])
        sel = (np.abs(resid) < gate) & (np.abs(pts[:, 2]) < band)
        if sel.sum() < 500:
            return None
    n = np.array([-coef[0], -coef[1], 1.0])
    n /= np.linalg.norm(n)
    if up is not None:
        n = lean_within(n, np.asarray(up, dtype=np.float64) / np.linalg.norm(up), max_lean_deg)
    tilt = float(np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0))))
    if tilt > max_tilt_deg:
        return None
    axis = np.cross(n, [0.0, 0.0, 1.0])
    s = float(np.linalg.norm(axis))
    rot = np.eye(3)
    if s > 1e-12:
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rot = np.eye(3) + k + k @ k * ((1.0 - n[2]) / s**2)
    corr = np.eye(4)
    corr[:3, :3] = rot
    corr[2, 3] = -float(np.median((pts[sel] @ rot.T)[:, 2]))
    return corr


def prior_up_in_odom(pose_odom: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """The prior's world z (its up) in odom, as one frame's registered pose and prior relate
    the two: ``R_odom_sensor R_world_sensor^T e_z``, the prior's third rotation row turned."""
    return pose_odom[:3, :3] @ np.asarray(prior, dtype=np.float64)[2, :3]


def complete_priors(priors: list[np.ndarray | None]) -> list[np.ndarray] | None:
    """The frames' pose priors for the loop closure, or None unless every frame had one: the
    prior's drift is measured along the whole trajectory (ARKit gives one always), and a gap
    would make its steps span frames it never saw."""
    given = [p for p in priors if p is not None]
    return given if len(given) == len(priors) else None


def load_configs(
    path: str | Path | None,
) -> tuple[PreprocessConfig, RegistrationConfig, MapperConfig, LoopClosureConfig]:
    """Read ``preprocess:``, ``registration:``, ``mapper:``, ``loop_closure:`` from one YAML."""
    if path is None:
        return PreprocessConfig(), RegistrationConfig(), MapperConfig(), LoopClosureConfig()
    data = read_yaml(path)
    data = {} if data is None else data  # an empty file; `false` or `0` is no mapping
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping with preprocess/registration/mapper")
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise ValueError(f"{path}: unknown section(s) {unknown}; use {'/'.join(SECTIONS)}")
    sections: dict[str, dict] = {}
    for name in SECTIONS:
        # only an empty section (``mapper:``) is no settings: `loop_closure: false` read as
        # one, and the loop closure it meant to turn off ran
        body = data.get(name)
        if body is None:
            body = {}
        if not isinstance(body, dict):
            hint = " (to turn it off: `loop_closure: {enabled: false}`, or --no-loop-closure)"
            raise ValueError(
                f"{path}: section {name!r} must be a mapping of parameter: value, got {body!r}"
                + (hint if name == "loop_closure" and body is False else "")
            )
        sections[name] = body
    return (
        from_mapping(PreprocessConfig, sections["preprocess"]),
        from_mapping(RegistrationConfig, sections["registration"]),
        from_mapping(MapperConfig, sections["mapper"]),
        from_mapping(LoopClosureConfig, sections["loop_closure"]),
    )


def check_keyframe_interval(reg: RegistrationConfig, cfg: MapperConfig) -> None:
    """ValueError where keyframes are kept further apart than a dropout: every one would be
    registered as a relocalisation (``registration.max_gap``)."""
    if cfg.min_frame_interval >= reg.max_gap:
        raise ValueError(
            f"mapper min_frame_interval ({cfg.min_frame_interval:g} s) must be under "
            f"registration max_gap ({reg.max_gap:g} s): keyframes further apart would each be "
            "taken for a dropout"
        )


SECTIONS = ("preprocess", "registration", "mapper", "loop_closure")
DEFAULT_FRAME_ID = "iphone_depth_optical_frame"  # a frame without one: the phone's depth camera


@dataclass
class FrameOutcome:
    """What happened to one frame (for logs and the node's status)."""

    status: str  # used | failed | skipped | empty | error (an exception: ``reason``)
    reason: str = ""
    pose_map: np.ndarray | None = None  # sensor pose in map (None until levelled)
    relocalised: bool = False
    after_gap: bool = False  # came after a dropout (registration.max_gap), placed on the map
    # of a skipped frame that a user must hear of (not a keyframe interval): "other_frame"
    cause: str = ""
    # the frame's number in the input (:meth:`Mapper.admit`'s), for the warnings that name it:
    # outcomes come back one frame late and out of order from the prefetch pipeline, and
    # matched to their frames by stamp, two frames stamped alike swapped numbers (-1: unknown)
    number: int = -1


@dataclass
class PreparedFrame:
    """Everything done to a frame before the map is needed: filtered points, their stats, and
    registration's inputs. A pure function of the frame and the configs, so it can be computed
    in another process while the mapper registers the frame before (:mod:`.prefetch`)."""

    points: np.ndarray  # filtered, sensor frame, float64
    stats: PreprocessStats
    inputs: FrameInputs | None  # None where no point is valid
    seconds: float  # what it took
    map_keep: np.ndarray | None = None  # which points the map may keep (None: all)

    @property
    def map_points(self) -> np.ndarray:
        return self.points if self.map_keep is None else self.points[self.map_keep]


def prepare_frame(
    points: np.ndarray,
    confidence: np.ndarray | None,
    pre: PreprocessConfig,
    reg: RegistrationConfig,
) -> PreparedFrame:
    """:class:`PreparedFrame` of one sensor-frame cloud (``(N, 3)``, NaN allowed)."""
    t0 = time.perf_counter()
    st = PreprocessStats(has_confidence=confidence is not None)
    pts, map_keep = preprocess_for_map(points, pre, confidence, st)
    inputs = frame_inputs(pts, reg) if st.valid else None
    return PreparedFrame(pts, st, inputs, time.perf_counter() - t0, map_keep)


class Mapper:
    """Incremental map builder; one instance per mapping session.

    ``keep_frames`` keeps every accepted frame's filtered points (float32, ~12 bytes a point)
    so that :meth:`close_loops` can rebuild the map at the end of a run; a live node bounds
    that memory with :meth:`release_frames`.
    """

    def __init__(
        self,
        pre: PreprocessConfig | None = None,
        reg: RegistrationConfig | None = None,
        cfg: MapperConfig | None = None,
        keep_frames: bool = False,
        receipts_on_stamp_clock: bool = False,
    ) -> None:
        self.pre = pre or PreprocessConfig()
        self.reg_cfg = reg or RegistrationConfig()
        self.cfg = cfg or MapperConfig()
        self.keep_frames = keep_frames
        # the frames' receipt times are on their stamps' clock (:class:`.frame_clock.FrameClock`)
        self.receipts_on_stamp_clock = receipts_on_stamp_clock
        check_keyframe_interval(self.reg_cfg, self.cfg)
        self.reset()

    def reset(self) -> None:
        """Forget everything (the node's ~/reset)."""
        self.convention: str | None = None
        self._clear_map()
        self.frames_read = 0
        # frames mapped before a pose prior arrived and dropped when the map began again on
        # the first frame with one (:meth:`_begin_again_with_prior`)
        self.dropped_before_prior = 0
        self.frames_skipped = 0
        # frames on a new time base: stamped before the last keyframe (the clock went back) or
        # confirmed ahead (:mod:`.frame_clock`); the mapping time goes on across them
        self.clock_jumps = 0
        self.stamped_ahead = 0  # of frames_skipped: stamped ahead of their arrival
        self.stamped_behind = 0  # of frames_skipped: stamped back, held (clock not confirmed)
        self.out_of_order = 0  # of frames_skipped: repeats and late frames (LATE_FRAME_WINDOW)
        self.other_frame = 0  # of frames_skipped: a frame_id of another axis convention
        # the first frame whose name says optical (REP-103's suffix) read as body because
        # sensor_convention says so: levelled on a wall, exit 0, without a word (a review)
        self.body_named_optical: str | None = None
        self.frames_errored = 0  # raised while prepared or registered (FrameOutcome "error")
        self.failed_since_used = 0  # registration failures since the last frame mapped
        self.frames_empty = 0
        self.priors_refused = 0  # pose priors that were no rigid transform (NaN, scaled, ...)
        # frames with no confidence channel while min_confidence asked for one: ARKit's filter
        # was not applied to them (a Stray export without confidence/, a sensor without one)
        self.frames_without_confidence = 0
        self.frames_with_confidence = 0
        # the first MAX_LISTED_FAILURES registration failures, as report.json lists them, and
        # how many there were: all of them kept, a sensor covered for hours on a live node grew
        # the list by some 9 MB an hour
        self.failures: list[dict[str, Any]] = []
        self.failures_total = 0
        self.points = {
            "input": 0,
            "valid": 0,
            "downsampled": 0,
            "after_sor": 0,
            "after_pfc": 0,
            "mixed_out_of_map": 0,
            "sor_kept_on_lines": 0,
        }
        self.timings = {
            "preprocess_s": 0.0,
            "registration_s": 0.0,
            "evidence_s": 0.0,
            "levelling_s": 0.0,
        }
        self._last_processed: float | None = None
        # stamps of the frames in a row stamped LATE_FRAME_WINDOW or more before the last
        # keyframe, held back until BEHIND_CONFIRM of them agree that the clock went back
        self._behind: list[float] = []
        # (index, stamp, mapping time, bridged) admitted, not yet added. Frames skipped for
        # their stamps leave a hole in the stamps the registration sees, which it read as a
        # dropout of the stream: two bad stamps in a row at 5 Hz, and the next 56 of 120
        # frames failed (a review). Where every frame arrived within max_gap of the one
        # before, the stream never stopped: the frame after such a hole is ``bridged``.
        self._admitted: list[tuple[int, float, float, bool]] = []
        self.clock = FrameClock(self.receipts_on_stamp_clock)
        self._seen_received: float | None = None  # when the last frame seen arrived
        self._receipt_gap: float | None = 0.0  # the longest since the last admitted (None: unknown)
        self._stamp_hole = False  # a frame skipped for its stamp since the last admitted

    def _begin_again_with_prior(
        self, pts: np.ndarray, t_map: float, prior: np.ndarray, inputs: FrameInputs | None
    ) -> RegResult | None:
        """This frame, the first with a pose prior, registered as the first of a map begun
        again, where the map holds one frame mapped without one (a cloud before the first
        odometry message, a first prior refused); None (the map as it was) where this frame
        cannot begin a map either (too few points).

        Registration takes the prior's step from the last accepted frame's prior, and that
        frame had none: every later prior was ignored, and where ICP alone could not place a
        view (a chair's floor and one wall) no frame after the first was mapped (live: 1 used,
        29 failed, state relocalising for good). The frame dropped is counted."""
        fresh = Registrar(self.reg_cfg)
        res = fresh.register(pts, t_map, prior, inputs)
        if not res.accepted:
            return None
        counters = self.registrar.counters
        counters.frames += 1  # this one; "accepted" stays: one frame dropped, this one mapped
        self._clear_map(fresh)
        fresh.counters = counters
        self.dropped_before_prior += 1
        return res

    def _clear_map(self, registrar: Registrar | None = None) -> None:
        """Forget the map, its frames and its frame (not what was read, nor the axis
        convention the first frame's frame_id fixed); ``registrar``: the one to go on with."""
        self.registrar = registrar or Registrar(self.reg_cfg)
        self.T_map_odom: np.ndarray | None = None
        self.level_info: dict[str, Any] = {}
        self._evidence = self.cfg.evidence_map()
        self._map_odom = np.empty((0, 3))
        self._dirty = 0
        self._relevelled_at = -1
        self._lower_floor_tried = 0  # points below the floor at the last search that found none
        self._floor_checked_at = 0  # map points when the floor was last found or checked
        # without a gravity-aligned prior: the vertical the map's level surfaces vote for
        # (odom), found with the first floor and again at each floor check (_relevel's bound)
        self._voted_up_odom: np.ndarray | None = None
        self.stamps: list[float] = []
        self.poses_odom: list[np.ndarray] = []
        self._frames: list[np.ndarray] = []
        self._map_keep: list[np.ndarray | None] = []  # per kept frame: PreparedFrame.map_keep
        self._priors: list[np.ndarray | None] = []  # the pose prior of each kept frame
        # per kept frame: whether it came after a dropout (registered again, it must be told:
        # without the frames that failed before it, its stamp would make gaps of their time)
        self._after_gap: list[bool] = []
        # sum over the registered frames with a prior of the prior's up (its z) in odom
        self._prior_up_sum = np.zeros(3)
        # how far the priors' z lies from any up an upright sensor could have, once it was
        # found to (None: not found): no vertical from then on, and said in every levelling
        self._prior_not_gravity_deg: float | None = None
        self.loop_info: dict[str, Any] = {}  # the report's loop_closure, once close_loops ran
        self.loop_result: LoopClosureResult | None = None  # its graph, for benchmarks

    def release_frames(self) -> None:
        """Stop keeping frames and free those kept: the map goes on, :meth:`close_loops` cannot.

        All or nothing: a pose graph over only the later frames would move them against an
        earlier map it cannot correct.
        """
        self.keep_frames = False
        self._frames = []
        self._map_keep = []
        self._priors = []
        self._after_gap = []

    # -- per frame ----------------------------------------------------------------------------
    def add_frame(
        self,
        points: np.ndarray,
        stamp: float,
        frame_id: str = DEFAULT_FRAME_ID,
        confidence: np.ndarray | None = None,
        prior: np.ndarray | None = None,
        received: float | None = None,
        number: int | None = None,
    ) -> FrameOutcome:
        """Process one sensor-frame cloud (``(N, 3)``, NaN allowed) taken at ``stamp`` seconds;
        ``received``: when it arrived, on any clock that runs at the stamps' rate (a bag's log
        time, the node's clock), which lets a stamp far ahead be told from a pause;
        ``number``: as :meth:`admit`'s."""
        skipped = self.admit(stamp, frame_id, received, number)
        if skipped is not None:
            return skipped
        try:
            prep = prepare_frame(points, confidence, self.pre, self.reg_cfg)
        except Exception:
            self.drop_admitted()
            raise
        return self.add_prepared(prep, prior)

    def drop_admitted(self) -> None:
        """Forget the oldest admitted frame: its preparation failed (it stays counted as read)."""
        if self._admitted:
            self._admitted.pop(0)
            self.frames_errored += 1

    def admit(
        self,
        stamp: float,
        frame_id: str = DEFAULT_FRAME_ID,
        received: float | None = None,
        number: int | None = None,
    ) -> FrameOutcome | None:
        """The first half of :meth:`add_frame`, before any work on the points: counts the frame,
        and returns its outcome where it is not to be processed (between keyframes), else None,
        and the caller goes on with :meth:`add_prepared` for exactly this frame. Split out so
        that a frame can be admitted in order and prepared ahead (:mod:`.prefetch`).

        ``number``: the frame's number in the input, which the report's failures and clock
        jumps name (default: its count here). An input's unreadable frames never come here,
        and counted here the report named another frame than the warning (a review)."""
        skipped = self._admit(stamp, frame_id, received, number)
        if skipped is not None:
            skipped.number = self.frames_read - 1 if number is None else number
        return skipped

    @property
    def newest_admitted(self) -> int:
        """The input number of the frame :meth:`admit` let through last (-1: none waiting)."""
        return self._admitted[-1][0] if self._admitted else -1

    def _admit(
        self, stamp: float, frame_id: str, received: float | None, number: int | None
    ) -> FrameOutcome | None:
        if self.loop_info:  # close_loops has run
            # The registration map still holds the pre-graph poses: a new frame would register
            # against a map that no longer matches the trajectory it is appended to.
            raise RuntimeError("Mapper.add_frame after close_loops: start a new Mapper")
        self.frames_read += 1
        prev, self._seen_received = self._seen_received, received
        if received is None:
            self._receipt_gap = None
        elif prev is not None and self._receipt_gap is not None:
            self._receipt_gap = max(self._receipt_gap, received - prev)
        convention = convention_for_frame(frame_id, self.cfg.sensor_convention)
        if (
            convention == "body"
            and self.body_named_optical is None
            and convention_for_frame(frame_id) == "optical"
        ):
            self.body_named_optical = frame_id
        if self.convention is None:
            self.convention = convention
        elif convention != self.convention:
            # sensor_convention auto: the first frame's frame_id fixed the axes every frame is
            # read in (levelling, the map's x). A later cloud in a frame of the other
            # convention (a body frame after an optical one) was mapped in those axes all the
            # same, turned 90 deg; there is no tf here to bring it over. A renamed frame of the
            # same convention (a driver restarted) is mapped.
            self.frames_skipped += 1
            self.other_frame += 1
            return FrameOutcome(
                "skipped",
                f"frame_id {frame_id!r} names a {convention} frame (REP-103), and this map's "
                f"frames are {self.convention}, as its first frame's was: its axes would be "
                "read wrong (set sensor_convention to override)",
                cause="other_frame",
            )
        verdict = self.clock.check(stamp, received)
        if verdict.ahead_s > 0.0:
            # Mapped, its dt of hours would let any pose through the jump check, and the
            # trajectory would go back at the next frame (:mod:`.frame_clock`).
            self._stamp_hole = True
            self.frames_skipped += 1
            self.stamped_ahead += 1
            return FrameOutcome(
                "skipped",
                f"stamped {verdict.ahead_s:.2f} s ahead of the time its arrival says passed "
                "since the frames before (a bad stamp; a clock that jumped forward is taken "
                f"after {AHEAD_CONFIRM} such frames in a row)",
                cause="stamped_ahead",
            )
        jumped = verdict.jumped_forward
        if jumped:
            self.clock_jumps += 1
            self._last_processed = None
        if (
            self._last_processed is not None
            and 0.0 <= self._last_processed - stamp < LATE_FRAME_WINDOW
        ):
            # The frame before again (a message delivered twice, two clouds stamped alike) or
            # a late one: mapped, it gave trajectory.tum a stamp twice or going back (no TUM
            # reader takes that), and a repeat counted its own flying pixels as a second frame's
            # evidence. A step back of LATE_FRAME_WINDOW or more is a clock jump (below).
            self._stamp_hole = True
            self.frames_skipped += 1
            self.out_of_order += 1
            return FrameOutcome(
                "skipped",
                "stamped at or before the frame before it (delivered twice, or clouds stamped "
                "alike: a recorder or bridge that repeats or leaves the header stamp)",
                cause="out_of_order",
            )
        if self._last_processed is not None and stamp < self._last_processed:
            # A stamp before the last keyframe's: a publisher restarted, a clock was set, or
            # one frame came stamped 0 (a driver's unset stamp). Taken as a new time base at
            # once, one such frame left the next, back on the real clock, decades "later":
            # nothing had set the pace on the new base to hold it back, and it and the frames
            # after it were registered as after a dropout (a third of a bag lost). It is held
            # back until the next frame agrees (BEHIND_CONFIRM in a row, each after the one
            # before): a publisher restarted costs one frame, which at 5 Hz leaves no dropout.
            behind = self._last_processed - stamp
            window = AHEAD_WINDOW + self.clock.interval()
            if self._behind and not 0.0 < stamp - self._behind[-1] <= window:
                self._behind.clear()  # not one clock: another bad stamp
            self._behind.append(stamp)
            if len(self._behind) < BEHIND_CONFIRM:
                self._stamp_hole = True
                self.frames_skipped += 1
                self.stamped_behind += 1
                return FrameOutcome(
                    "skipped",
                    f"stamped {behind:.2f} s before the frame before it (a bad stamp; a clock "
                    f"that went back is taken after {BEHIND_CONFIRM} such frames in a row)",
                    cause="stamped_behind",
                )
            # The keyframe clock restarts here; kept on the old stamp, every frame after would
            # fall "between keyframes" and the map would stop without a word.
            self._behind.clear()
            self.clock_jumps += 1
            self._last_processed = None
            jumped = True
        else:
            self._behind.clear()
        if (
            self.cfg.min_frame_interval > 0
            and self._last_processed is not None
            and stamp - self._last_processed < self.cfg.min_frame_interval
        ):
            self.frames_skipped += 1
            return FrameOutcome("skipped", "keyframe interval")
        self._last_processed = stamp
        index = self.frames_read - 1 if number is None else number
        gap = self._receipt_gap
        bridged = self._stamp_hole and gap is not None and gap <= self.reg_cfg.max_gap
        self._stamp_hole, self._receipt_gap = False, 0.0 if received is not None else None
        t_map = self.clock.admit(index, stamp, received, jumped, self.cfg.min_frame_interval)
        self._admitted.append((index, float(stamp), t_map, bridged))
        return None

    def _note_failure(self, entry: dict[str, Any]) -> None:
        self.failures_total += 1
        if len(self.failures) < MAX_LISTED_FAILURES:
            self.failures.append(entry)

    def add_prepared(
        self,
        prep: PreparedFrame,
        prior: np.ndarray | None = None,
        after_gap: bool | None = None,
        dropped_priors: tuple[float, float] | None = None,
    ) -> FrameOutcome:
        """The second half of :meth:`add_frame`: register and integrate the oldest admitted frame,
        ``prep`` its :func:`prepare_frame`. ``after_gap``: whether the frame follows a dropout of
        the stream, where the caller knows better than the frames mapped (a live node's frames
        dropped while busy are none); None: registration reads it from their stamps.
        ``dropped_priors``: (first, last): seconds from the first and the last frame before this
        one that the caller dropped (while busy) and that had a pose prior; None: none."""
        number = self._admitted[0][0] if self._admitted else -1
        outcome = self._add_prepared(prep, prior, after_gap, dropped_priors)
        outcome.number = number
        return outcome

    def _add_prepared(
        self,
        prep: PreparedFrame,
        prior: np.ndarray | None,
        after_gap: bool | None,
        dropped_priors: tuple[float, float] | None,
    ) -> FrameOutcome:
        if not self._admitted:
            raise RuntimeError("Mapper.add_prepared without a frame admitted before it")
        index, stamp, t_map, bridged = self._admitted.pop(0)
        if bridged and after_gap is None:
            after_gap = False
        if prior is not None and not is_rigid(prior):
            # A NaN pose from a bridge or bag would abort KISS-ICP (Sophus) and poison the loop
            # closure's prior drift: the frame is registered without it (it fails where frames
            # before it had a prior: registration places no frame of such a run by ICP alone),
            # and it is counted.
            self.priors_refused += 1
            prior = None
        st = prep.stats
        pts = prep.points
        self.frames_with_confidence += int(st.has_confidence)
        self.frames_without_confidence += int(not st.has_confidence and self.pre.min_confidence > 0)
        for k in self.points:
            self.points[k] += int(getattr(st, k))
        self.timings["preprocess_s"] += prep.seconds
        t1 = time.perf_counter()
        if st.valid == 0:
            self.frames_empty += 1
            self._note_failure({"frame": index, "stamp": stamp, "reason": EMPTY_REASON})
            return FrameOutcome("empty", "no valid points (all NaN or out of range)")
        res = None
        if prior is not None and len(self.poses_odom) == 1 and self.registrar.last_prior is None:
            res = self._begin_again_with_prior(pts, t_map, prior, prep.inputs)
        if res is None:
            res = self.registrar.register(pts, t_map, prior, prep.inputs, after_gap, dropped_priors)
        self.timings["registration_s"] += time.perf_counter() - t1
        if not res.accepted:
            self._note_failure({"frame": index, "stamp": stamp, "reason": res.reason})
            self.failed_since_used += 1
            return FrameOutcome("failed", res.reason, self.pose_in_map(self.registrar.last_pose))
        self.failed_since_used = 0
        self.stamps.append(t_map)  # the mapping time: the stamp, continuous across clock jumps
        self.poses_odom.append(res.pose)
        # the prior as registration used it (None where the frame had none), its world
        # re-anchored at any jump (ARKit relocalising): gravity and the loop closure's prior
        # drift read it frame to frame
        prior = res.prior
        if prior is not None:
            self._prior_up_sum += prior_up_in_odom(res.pose, prior)
        if self.keep_frames:
            self._frames.append(pts.astype(np.float32))
            self._map_keep.append(prep.map_keep)
            self._priors.append(None if prior is None else np.asarray(prior, dtype=np.float64))
            self._after_gap.append(res.after_gap)
        t2 = time.perf_counter()
        self._evidence.add(transform(prep.map_points, res.pose), res.pose[:3, 3])
        self.timings["evidence_s"] += time.perf_counter() - t2
        self._dirty += pts.shape[0]
        used = len(self.poses_odom)
        # Look for the floor after level_min_frames, then every 5th frame until found (each
        # attempt consolidates the map, which costs more as it grows).
        if (
            self.T_map_odom is None
            and used >= self.cfg.level_min_frames
            and (used - self.cfg.level_min_frames) % 5 == 0
        ):
            self.try_level()
        return FrameOutcome(
            "used",
            pose_map=self.pose_in_map(res.pose),
            relocalised=res.relocalised,
            after_gap=res.after_gap,
        )

    def close_loops(
        self, cfg: LoopClosureConfig, progress: Callable[[int, int], None] | None = None
    ) -> dict[str, Any]:
        """Optimise the trajectory as a pose graph and rebuild the map from the kept frames.

        For the end of an offline run: the registration map is not rebuilt, so no frame can be
        added afterwards. Loop edges correct x, y and yaw of the levelled map only (see
        ``LoopClosureConfig.horizontal_only``) once the map frame is known. Returns the
        report's ``loop_closure``.
        """
        if not self.keep_frames:
            raise RuntimeError("close_loops needs a Mapper made with keep_frames=True")
        up = None
        if self.T_map_odom is not None and self.poses_odom:
            # The graph's vertical from the floor refined on every online frame, whoever asked
            # for the map before: the live node's publishing had refined it, `wheelgrid map`
            # had not (it asks only when saving), so one bag closed its loops about two
            # verticals and gave two maps (9(a) 0.01 against 0.60 % on one simulated run).
            self.map_points()
        if self.T_map_odom is not None:
            up = self.T_map_odom[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        priors = complete_priors(self._priors)
        online = self.poses_odom
        scale_info: dict[str, Any] = {}
        if priors is not None and cfg.prior_scale_sigmas > 0:
            online, scale_info = self._rescale_prior(cfg, progress)
        res = close_loops(self._frames, online, self.stamps, cfg, progress, up=up, priors=priors)
        # All or nothing: the new map is built aside and swapped in only once complete, so a
        # failure anywhere (the graph, memory while rebuilding) leaves the online map, poses
        # and frames exactly as they were, and the caller can still save or extend them.
        evidence = self.cfg.evidence_map()
        for pts, keep, pose in zip(self._frames, self._map_keep, res.poses, strict=True):
            map_pts = pts if keep is None else pts[keep]
            evidence.add(transform(map_pts.astype(np.float64), pose), pose[:3, 3])
        self.poses_odom = res.poses
        if priors is not None:
            self._prior_up_sum = sum(
                (prior_up_in_odom(p, q) for p, q in zip(res.poses, priors, strict=True)),
                np.zeros(3),
            )
        self._evidence = evidence
        self._dirty = 1
        self._relevelled_at = -1
        self.timings["loop_closure_s"] = res.seconds
        self.loop_info = res.summary()
        self.loop_result = res
        if scale_info:
            self.loop_info["prior_scale"] = scale_info
        return self.loop_info

    def _rescale_prior(
        self, cfg: LoopClosureConfig, progress: Callable[[int, int], None] | None = None
    ) -> tuple[list[np.ndarray], dict[str, Any]]:
        """The online poses, registered again from the kept frames with the prior's horizontal
        steps rescaled where online ICP measured its scale error (:class:`PriorScaleEstimate`) at
        least ``cfg.prior_scale_sigmas`` standard errors from 0; else as they are. And what was
        measured and done, for the report. ``progress`` is called as the graph's is, with no
        submap done yet, every 10 frames: the node's ~/reset and shutdown cancel through it.

        A second pass because the error is known only once the run is over: the stretches it
        spoils are those where the view fixed no forward motion, and the prior alone placed
        them. Nothing is lost: if a frame fails in the new pass (it passed the first), or the
        estimate is beyond ``cfg.max_drift_scale``, the online poses stay.
        """
        fit = self.registrar.prior_scale_fit
        given = self.reg_cfg.prior_scale
        measured, stderr = fit.percent()
        info: dict[str, Any] = {
            "measured_pct": measured,
            "stderr_pct": stderr,
            "steps": fit.steps,
            "applied": False,
        }
        if stderr is None:  # too few stretches for a spread to judge it by
            info["note"] = "too few stretches to measure it: kept"
            return self.poses_odom, info
        if not abs(fit.error) >= cfg.prior_scale_sigmas * fit.stderr:
            info["note"] = f"within {cfg.prior_scale_sigmas:g} standard errors of 0: kept"
            return self.poses_odom, info
        if abs(fit.error) > cfg.max_drift_scale:
            info["note"] = f"beyond max_drift_scale ({100 * cfg.max_drift_scale:g} %): not believed"
            return self.poses_odom, info
        t0 = time.perf_counter()
        scale = given * (1.0 + fit.error)
        # the priors kept are continuous already: any jump the map judged was re-anchored in
        # the first pass, so a second verdict could only be on the rescale's own few mm
        reg = Registrar(
            replace(self.reg_cfg, prior_scale=scale, prior_check_step=0.0, prior_check_turn=0.0)
        )
        poses = []
        submaps = len(submap_groups(self.stamps, cfg.submap_seconds))
        for k, (pts, stamp, prior, after_gap) in enumerate(
            zip(self._frames, self.stamps, self._priors, self._after_gap, strict=True)
        ):
            if progress is not None and k % 10 == 0:
                progress(0, submaps)
            res = reg.register(pts.astype(np.float64), stamp, prior, after_gap=after_gap)
            if not res.accepted:
                info["note"] = f"a frame failed when registered again ({res.reason}): kept"
                return self.poses_odom, info
            poses.append(res.pose)
        self.timings["prior_rescale_s"] = time.perf_counter() - t0
        residual, residual_stderr = reg.prior_scale_fit.percent()
        info.update(
            applied=True,
            prior_scale=round(scale, 6),
            residual_pct=residual,
            residual_stderr_pct=residual_stderr,
        )
        return poses, info

    # -- map -----------------------------------------------------------------------------------
    def map_odom(self) -> np.ndarray:
        """Global map in odom, voxelised at ``map_voxel`` (consolidated lazily)."""
        if self._dirty:
            # the evidence margin grows sideways only, so only once the vertical is known
            up = None if self.T_map_odom is None else self.T_map_odom[2, :3]
            self._map_odom = self._evidence.points(up=up)
            self._dirty = 0
        return self._map_odom

    def prior_up(self) -> np.ndarray | None:
        """Gravity's up in odom as the pose priors give it (their mean over the registered
        frames), or None without priors or with ``prior_gravity`` off.

        Why: a visual-inertial prior (ARKit) holds its vertical to the IMU's gravity to a
        fraction of a degree for the whole session, where a floor fitted to the first frames
        leans with whatever patch of floor they saw."""
        norm = float(np.linalg.norm(self._prior_up_sum))
        if not self.cfg.prior_gravity or self._prior_not_gravity_deg is not None or norm < 1e-9:
            return None
        return self._prior_up_sum / norm

    def _prior_up_in_map(self) -> np.ndarray | None:
        """:meth:`prior_up` in the map frame, for the floor's later fits; None (and said in
        the report, once) where it lies more than :data:`PRIOR_FLOOR_MAX_TILT_DEG` from the
        frame's z: a prior that began after the first fit and is not gravity-aligned must not
        turn the floor toward a wall."""
        up = self.prior_up()
        if up is None or self.T_map_odom is None:
            return None
        lean = tilt_deg(self.T_map_odom, -up)
        if lean > PRIOR_FLOOR_MAX_TILT_DEG:
            self._prior_not_gravity_deg = round(lean, 1)
            self.level_info["prior_not_gravity_deg"] = self._prior_not_gravity_deg
            return None
        return self.T_map_odom[:3, :3] @ up

    def _upright_prior_up(self, down: np.ndarray) -> tuple[np.ndarray | None, dict[str, float]]:
        """:meth:`prior_up` if this sensor could stand upright on it (within
        ``floor_max_tilt_deg`` of the sensor's own down hint), else None and the angle, for the
        report: a prior whose frame is not gravity-aligned (a y-up VIO) is no vertical, and the
        floor alone is used, as without a prior. The angle stays in the report of every later
        try (a first try short of floor points had dropped it from the levelling that came)."""
        up = self.prior_up()
        if up is not None:
            lean = math.degrees(math.acos(float(np.clip(-(up @ down), -1.0, 1.0))))
            if lean > self.cfg.floor_max_tilt_deg:
                self._prior_not_gravity_deg = round(lean, 1)
                up = None
        if self._prior_not_gravity_deg is None:
            return up, {}
        return None, {"prior_not_gravity_deg": self._prior_not_gravity_deg}

    def try_level(self) -> bool:
        """Find ``T_map_odom`` (mount parameter or floor); True once known."""
        if self.T_map_odom is not None:
            return True
        t0 = time.perf_counter()
        conv = self.convention or "optical"
        try:
            if self.cfg.mount_xyz_rpy:
                self.T_map_odom = map_from_mount(self.cfg.mount_xyz_rpy, conv)
                self._dirty = 1
                self.level_info = {"method": "mount", "mount_xyz_rpy": list(self.cfg.mount_xyz_rpy)}
                self.level_info["mount_floor_check"] = self._mount_floor_check(conv)
            else:
                pts = self.map_odom()
                first = self.poses_odom[0] if self.poses_odom else np.eye(4)
                down = first[:3, :3] @ DOWN_HINT[conv]
                up, not_gravity = self._upright_prior_up(down)
                refined: dict[str, Any] = {}
                if up is None:
                    n, d = find_floor(pts, down, first[:3, 3], self.cfg.floor_max_tilt_deg)
                    n, d, refined = self._refine_first_floor(pts, n, d, first[:3, 3])
                else:
                    n, d = find_floor(
                        pts,
                        -up,
                        first[:3, 3],
                        min(self.cfg.floor_max_tilt_deg, PRIOR_FLOOR_MAX_TILT_DEG),
                        vertical=True,
                    )
                self.T_map_odom = map_from_floor(n, d, conv, first)
                self._floor_checked_at = pts.shape[0]
                self._dirty = 1  # the map again, now with the vertical for the margin
                tilt = float(np.degrees(np.arccos(np.clip(-(n @ down), -1, 1))))
                self.level_info = {
                    "method": "floor",
                    "vertical": "floor plane" if up is None else "pose prior's gravity",
                    **not_gravity,
                    "sensor_height_m": float(n @ first[:3, 3] + d),
                    "first_view_tilt_deg": tilt,
                    **refined,
                }
        except FloorNotFoundError as exc:
            self.level_info = {"method": "none", "error": str(exc)}
        finally:
            self.timings["levelling_s"] += time.perf_counter() - t0
        return self.T_map_odom is not None

    def _refine_first_floor(
        self, pts: np.ndarray, n: np.ndarray, d: float, origin: np.ndarray
    ) -> tuple[np.ndarray, float, dict[str, Any]]:
        """The first frames' floor levelled along the vertical their level surfaces vote for
        (:func:`level_vertical`, about the plane RANSAC gave): the same floor, its points'
        median height along that vertical, as a gravity-aligned prior's vertical is used.
        RANSAC's 3 cm slab through a narrow strip of floor tilts with the strip: a floor seen
        only beside a large low table leaned 7-13 deg (9.4 after relevelling, z = 0 13 cm off
        under the first pose; the floor check then moved z = 0 on to the table top, 45 cm up;
        a review). As RANSAC gave it where the vote finds no vertical. Returns the plane and
        what the refinement turned and moved it by."""
        finite = pts[np.isfinite(pts).all(axis=1)]
        # only what lies well below the sensor votes: a ceiling sloping down ahead (an attic)
        # outvoted the floor and turned the frame 11 deg, z = 0 64 cm up (a review)
        below = finite[(origin - finite) @ n > FIRST_FIT_VOTE_BELOW_M]
        try:
            _, _, up = level_vertical(below, n)
        except FloorNotFoundError as exc:
            return n, d, {"first_fit_refined": {"error": str(exc)}}
        turn = float(np.degrees(np.arccos(np.clip(n @ up, -1.0, 1.0))))
        if turn < FIRST_FIT_REFINE_DEG:
            # RANSAC's plane kept where the vote nearly agrees: a ramp's normals lean the vote
            # too, and a vote taken for the frame pushed a 1:12 ramp's room past 2 deg (a
            # review); only a fit far off (7-13 deg beside a large low table) is turned
            return n, d, {"first_fit_refined": {"kept": round(turn, 3)}}
        self._voted_up_odom = up
        on = finite[np.abs(finite @ n + d) < FLOOR_SLAB_M]
        # the tilted slab also cuts what stands on the floor (a table top): its points along
        # the vertical fall into levels, and the floor is the lowest that holds a share of them
        heights = on @ up
        need = max(FLOOR_LEVEL_MIN_POINTS, FLOOR_LEVEL_SHARE * on.shape[0])
        lowest = None
        if on.shape[0] >= need:
            counts, edges = np.histogram(
                heights, np.arange(heights.min(), heights.max() + 0.04, 0.02)
            )
            smooth = np.convolve(counts, np.ones(3), "same")
            lowest = next((i for i, c in enumerate(smooth) if c >= need), None)
        if lowest is None:
            why = "no level of the floor plane holds a share of its points"
            return n, d, {"first_fit_refined": {"error": why}}
        level = 0.5 * (edges[lowest] + edges[lowest + 1])
        n2, d2 = height_along(finite, on[np.abs(heights - level) < FLOOR_SLAB_M], up, FLOOR_SLAB_M)
        moved = float((n2 @ origin + d2) - (n @ origin + d))
        refined = {"turn_deg": round(turn, 3), "moved_m": round(moved, 4)}
        return n2, d2, {"first_fit_refined": refined}

    def _mount_floor_check(self, conv: str) -> dict[str, Any]:
        """The floor the first frames show against the floor the mount transform puts at
        z = 0: the mount is taken as given (the floor may be hidden), but where a floor is
        plainly seen elsewhere, and the mount's own floor holds far fewer of the points, it is
        said, with a ``warning``.

        The floor is looked for about the mount's vertical, then (a mount off by more than
        ``floor_max_tilt_deg``: a sign, a convention) about the sensor's own axes. The lowest
        level plane wins that search, so a ramp going up ahead, extended back under the chair,
        can be it: the points each plane holds within 3 cm decide, and a mount whose floor
        holds MOUNT_FLOOR_SUPPORT of what the plane found holds is a mount on a real floor.
        """
        assert self.T_map_odom is not None
        up = self.T_map_odom[2, :3]  # the mount's floor, z = 0, in odom: up . p + d = 0
        d_mount = float(self.T_map_odom[2, 3])
        first = self.poses_odom[0] if self.poses_odom else np.eye(4)
        pts = self.map_odom()
        found = None
        for down in (-up, first[:3, :3] @ DOWN_HINT[conv]):
            try:
                found = find_floor(pts, down, first[:3, 3], self.cfg.floor_max_tilt_deg)
                break
            except FloorNotFoundError as exc:
                why = str(exc)
        if found is None:
            return {"floor_seen": False, "why": why}
        n, d = found
        tilt = math.degrees(math.acos(float(np.clip(n @ up, -1.0, 1.0))))
        # the first pose's height above each floor, along each floor's own normal
        off = float(n @ first[:3, 3] + d) - float(up @ first[:3, 3] + d_mount)
        on_mount = int(np.count_nonzero(np.abs(pts @ up + d_mount) < 0.03))
        on_found = int(np.count_nonzero(np.abs(pts @ n + d) < 0.03))
        out: dict[str, Any] = {
            "floor_seen": True,
            "tilt_deg": round(tilt, 2),
            "height_off_m": round(off, 3),
            "points_on_mount_floor": on_mount,
            "points_on_floor_found": on_found,
        }
        off_plane = tilt > MOUNT_FLOOR_TILT_DEG or abs(off) > MOUNT_FLOOR_HEIGHT_M
        if off_plane and on_mount < MOUNT_FLOOR_SUPPORT * on_found:
            out["warning"] = (
                f"the floor the first frames show is {tilt:.1f} deg and {100 * abs(off):.1f} cm "
                f"{'above' if off < 0 else 'below'} the floor mount_xyz_rpy gives, which holds "
                f"{on_mount} of the points against its {on_found} "
                f"({MOUNT_FLOOR_TILT_DEG:g} deg / {100 * MOUNT_FLOOR_HEIGHT_M:g} cm allowed): "
                "check the mount transform (and the sensor convention); the map frame follows "
                "the mount as given"
            )
        return out

    def pose_in_map(self, pose_odom: np.ndarray) -> np.ndarray | None:
        return None if self.T_map_odom is None else self.T_map_odom @ pose_odom

    def map_points(self) -> np.ndarray:
        """The map in the levelled map frame; RuntimeError if the floor was never found."""
        if not self.try_level():
            raise RuntimeError(self.level_info.get("error", "map frame unknown"))
        assert self.T_map_odom is not None
        pts = transform(self.map_odom(), self.T_map_odom)
        used = len(self.poses_odom)
        if (
            self.cfg.relevel
            and self.level_info.get("method") == "floor"
            and used != self._relevelled_at
        ):
            self._relevelled_at = used
            if self._refind_lower_floor(pts, used):
                pts = transform(self.map_odom(), self.T_map_odom)
            pts = self._relevel(pts, used)
            if self._check_floor(pts, used):
                pts = self._relevel(transform(self.map_odom(), self.T_map_odom), used)
        return pts

    def _relevel(self, pts: np.ndarray, used: int) -> np.ndarray:
        """``pts`` (the map in the map frame) after :func:`floor_correction`, if it made one."""
        assert self.T_map_odom is not None
        up = self._prior_up_in_map()
        if up is None and self._voted_up_odom is not None:
            # the floor's least-squares refit on a strip of floor beside a large low table
            # turned the map 0.45 deg further at each relevel (2.1 deg after 20 frames, the
            # first fit 0.09 deg off): it leans at most as far from the level surfaces' vote
            # as from a prior's gravity
            up = self.T_map_odom[:3, :3] @ self._voted_up_odom
        corr = floor_correction(pts, up=up)
        if corr is None:
            return pts
        # The refined floor (z = 0 after ``corr``), the convention applied afresh: the
        # correction alone turns about the origin, and repeated ones walked the first
        # pose millimetres off the z axis (and would turn x off the first view).
        floor = corr @ self.T_map_odom
        first = self.poses_odom[0] if self.poses_odom else np.eye(4)
        self.T_map_odom = map_from_floor(
            floor[2, :3], float(floor[2, 3]), self.convention or "optical", first
        )
        self.level_info["relevelled_tilt_deg"] = float(
            np.degrees(np.arccos(np.clip(corr[2, 2], -1.0, 1.0)))
        )
        self.level_info["relevelled_at_frames"] = used
        # the first pose's height over z = 0 as the map frame now has it (trajectory.tum's
        # first z): it stayed the first fit's, 3.8-7.2 cm off on the real capture
        self.level_info.setdefault(
            "first_fit_sensor_height_m", self.level_info.get("sensor_height_m")
        )
        self.level_info["sensor_height_m"] = float((self.T_map_odom @ first)[2, 3])
        return transform(self.map_odom(), self.T_map_odom)

    def _check_floor(self, pts: np.ndarray, used: int) -> bool:
        """Find the floor again on the whole map (:func:`floor_of_map`) each time the map has
        doubled, and take it as the map frame's where it holds :data:`FLOOR_CHECK_GAIN` times
        the map points within 3 cm that z = 0 holds. True if it did.

        Why: the first floor fit sees ``level_min_frames`` frames, and on the real capture
        those held too little floor to fit: three runs that differed by 0.1 % of their points
        put it 3.3-4.6 deg off ARKit's gravity, on planes 17-21 cm above or 20 cm below the
        floor. The relevelling refines the plane it is given, within a band of 8 cm, and the
        lower-floor search moves z = 0 down only: a z = 0 under the floor and tilted stayed
        there (3.5 deg off the whole map's floor). Points within 3 cm, the score RANSAC gives a
        plane, ask which plane is more of the floor; a first fit the whole map agrees with
        scores the same, and its frame is left exactly as it was.
        """
        assert self.T_map_odom is not None
        if pts.shape[0] < FLOOR_CHECK_GROWTH * self._floor_checked_at:
            return False
        self._floor_checked_at = pts.shape[0]
        info = self.level_info
        info["floor_checks"] = info.get("floor_checks", 0) + 1
        first_odom = self.poses_odom[0] if self.poses_odom else np.eye(4)
        first = self.T_map_odom @ first_odom
        g = self._prior_up_in_map()
        try:
            if g is None:
                z = np.array([0.0, 0.0, 1.0])
                vote = level_vertical(pts, z)
                if self._voted_up_odom is not None:
                    self._voted_up_odom = self.T_map_odom[:3, :3].T @ vote[2]
                n, d = floor_of_map(pts, z, first[:3, 3], vote=vote)
            else:
                n, d = floor_of_map(pts, g, first[:3, 3], max_lean_deg=PRIOR_FLOOR_LEAN_DEG)
        except FloorNotFoundError as exc:
            info["floor_check"] = {"at_frames": used, "error": str(exc)}
            return False
        held = int(np.count_nonzero(np.abs(pts[:, 2]) < 0.03))
        found = int(np.count_nonzero(np.abs(pts @ n + d) < 0.03))
        height = float(n @ first[:3, 3] + d)  # the first sensor pose above the floor found
        check: dict[str, Any] = {
            "at_frames": used,
            "turn_deg": round(float(np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0)))), 3),
            "moved_m": round(height - float(first[2, 3]), 4),
            "points_on_z0": held,
            "points_on_floor_found": found,
        }
        info["floor_check"] = check
        if found <= FLOOR_CHECK_GAIN * held:
            return False
        rise = float(first[2, 3]) - height  # how far above z = 0 the floor found lies
        if rise > FLOOR_CHECK_MAX_RISE:
            cells, level, _ = level_vertical(pts, n)
            under = int(np.count_nonzero(cells[level] @ n + d < -FLOOR_CHECK_MAX_RISE))
            if under >= FLOOR_CHECK_BELOW_CELLS:
                # A safe refusal, not a sure one: z = 0 on a small sunken spot, the floor 20 cm
                # above it, is refused alike (a review), and that floor then reads as an
                # obstacle, the grid with no free cell; lifted on to a table, every obstacle
                # lower than it would read free.
                check["refused"] = (
                    f"the floor found on the whole map lies {100 * rise:.0f} cm above z = 0 with "
                    f"{under} level map cells of 5 cm {100 * FLOOR_CHECK_MAX_RISE:.0f} cm or more "
                    "below it (a large low table or platform; or z = 0 on a small lower level): "
                    "z = 0 kept; give mapper.mount_xyz_rpy if z = 0 is not the floor"
                )
                return False
        self._level_on(n, d, first_odom)
        info["floor_refound"] = check
        info["sensor_height_m"] = height
        return True

    def _level_on(self, n: np.ndarray, d: float, first_odom: np.ndarray) -> None:
        """Make the plane ``n . p + d = 0`` (``p`` in the current map frame) the map frame's
        floor: the floor searches that replace z = 0 find their plane in the map frame."""
        assert self.T_map_odom is not None
        # the plane in odom: n . (R p + t) + d = 0
        R, t = self.T_map_odom[:3, :3], self.T_map_odom[:3, 3]
        self.T_map_odom = map_from_floor(
            R.T @ n, float(n @ t + d), self.convention or "optical", first_odom
        )
        self._dirty = 1

    def _refind_lower_floor(self, pts: np.ndarray, used: int) -> bool:
        """Move z = 0 down to a large level plane found below the floor; True if it did.

        The floor is first looked for after ``level_min_frames`` frames. If those frames saw no
        floor (a phone pointed at a sofa, a floor ARKit calls low confidence), the lowest level
        plane they saw (a seat) became z = 0, and the height band of the grid then started
        above real obstacles. Later frames that see the real floor fix it here: the same rule
        as the first search (the lowest plane with ``min_fraction`` of the map), on the map
        below the current floor.
        """
        assert self.T_map_odom is not None
        below = pts[pts[:, 2] < -LOWER_FLOOR_GAP]
        need = max(200, int(0.03 * pts.shape[0]))
        if below.shape[0] < need or below.shape[0] < LOWER_FLOOR_RETRY * self._lower_floor_tried:
            # What lies below is no plane (a stairwell, low-confidence returns): search again
            # only once there is markedly more of it, not on every republish of the live map.
            return False
        self.level_info["lower_floor_searches"] = self.level_info.get("lower_floor_searches", 0) + 1
        first_odom = self.poses_odom[0] if self.poses_odom else np.eye(4)
        first = self.T_map_odom @ first_odom
        g = self._prior_up_in_map()
        try:
            n, d = find_floor(
                below,
                np.array([0.0, 0.0, -1.0]) if g is None else -g,
                first[:3, 3],
                max_tilt_deg=10.0,
                min_fraction=0.0,
                min_points=need,
                vertical=g is not None,
            )
        except FloorNotFoundError:
            self._lower_floor_tried = below.shape[0]
            return False
        self._lower_floor_tried = 0
        height = float(n @ first[:3, 3] + d)  # the first sensor pose above the new floor
        self._level_on(n, d, first_odom)
        self.level_info["sensor_height_m"] = height
        self.level_info["floor_lowered_m"] = round(
            self.level_info.get("floor_lowered_m", 0.0) + height - float(first[2, 3]), 4
        )
        self.level_info["floor_lowered_at_frames"] = used
        return True

    def published_points(self) -> np.ndarray:
        """``map_points`` coarsened until it fits ``max_published_points``; RuntimeError before
        ``level_min_frames`` frames are mapped, where the map frame is not fixed yet: the live
        node publishes every second, and it fixed the frame from the first one or two frames
        whatever ``level_min_frames`` said (a review; ``wheelgrid map`` always honoured it)."""
        used = len(self.poses_odom)
        if (
            self.T_map_odom is None
            and not self.cfg.mount_xyz_rpy
            and used < self.cfg.level_min_frames
        ):
            raise RuntimeError(
                f"map frame unknown: the floor is looked for after {self.cfg.level_min_frames} "
                f"frames (level_min_frames), {used} mapped"
            )
        pts = self.map_points()
        cell = self.cfg.map_voxel
        while pts.shape[0] > self.cfg.max_published_points:
            cell *= 1.25
            pts = voxel_downsample(pts, cell)
        return pts

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, sensor poses in map) of every registered frame."""
        if not self.try_level():
            raise RuntimeError(self.level_info.get("error", "map frame unknown"))
        assert self.T_map_odom is not None
        poses = np.array([self.T_map_odom @ p for p in self.poses_odom]).reshape(-1, 4, 4)
        return np.asarray(self.stamps), poses

    @property
    def frames(self) -> list[np.ndarray]:
        """The kept frames' filtered sensor-frame points (``keep_frames``), one per pose of
        :meth:`trajectory`: what a caller needs to ask which frame saw what (empty otherwise)."""
        return self._frames

    @property
    def state(self) -> str:
        return self.registrar.state

    def report(self) -> dict[str, Any]:
        c = self.registrar.counters
        return {
            "frames": {
                "read": self.frames_read,
                "used": c.accepted,
                "failed": c.failed,
                "empty": self.frames_empty,
                "skipped": self.frames_skipped,
                "clock_jumps": self.clock_jumps,
                "stamped_ahead": self.stamped_ahead,
                "stamped_behind": self.stamped_behind,
                "out_of_order": self.out_of_order,
                "other_frame": self.other_frame,
                "relocalised": c.relocalised,
                # frames more than registration.max_gap after the frame before them (a
                # dropout): each registered as a relocalisation (relocalised where it passed)
                "after_gap": c.gaps,
                # frames whose pose prior came back more than max_gap after the last frame
                # that had one (frames between failed, "no pose prior"): as after a dropout
                "after_prior_gap": c.prior_gaps,
                "prior_frozen": c.prior_frozen,
                "priors_refused": self.priors_refused,
                # min_confidence not applied: the frame had no confidence channel
                "without_confidence": self.frames_without_confidence,
                "with_confidence": self.frames_with_confidence,
                # mapped before the first pose prior, dropped as the map began again with it
                "dropped_before_prior": self.dropped_before_prior,
                "errors": self.frames_errored,
            },
            # where registration stood when the report was made: "relocalising" means the
            # last failed_since_used frames are not in the map (it ends at the last one used)
            "registration": {
                "state": self.registrar.state,
                "failed_since_used": self.failed_since_used,
            },
            # trajectory.tum's stamps are the frames' own plus offset_s, which changes only at
            # a clock jump (a publisher restarted): each listed with the offset from then on
            "mapping_time": {
                "offset_s": round(self.clock.offset, 6),
                "jumps": self.clock.jumps[:MAX_LISTED_FAILURES],
            },
            # every failure by reason, as `failures` names them: registration's and the frames
            # with no valid point left (all NaN, out of range), which never reach it
            "failure_reasons": dict(
                c.failure_reasons,
                **({EMPTY_REASON: self.frames_empty} if self.frames_empty else {}),
            ),
            "failures": self.failures,
            # the list stops at MAX_LISTED_FAILURES; the count says it was cut, and by how much
            "failures_not_listed": self.failures_total - len(self.failures),
            "points": dict(self.points, map=int(self.map_odom().shape[0])),
            "timings": {k: round(v, 3) for k, v in self.timings.items()},
            "levelling": self.levelling_report(),
            "loop_closure": self.loop_info or {"run": False},
            "map_frame": "z up, z=0 floor, origin below first sensor pose, x = first view on floor",
            "config": {
                "preprocess": asdict(self.pre),
                "registration": asdict(self.reg_cfg),
                "mapper": asdict(self.cfg),
            },
        }

    def levelling_report(self) -> dict[str, Any]:
        """``level_info`` and, with a gravity-aligned prior, the map frame's vertical against
        the prior's: the one check of the map frame a user without ground truth can read."""
        rep = dict(self.level_info)
        if self.body_named_optical is not None:
            rep["body_named_optical"] = self.body_named_optical
        up = self.prior_up()
        if up is not None and self.T_map_odom is not None:
            rep["prior_gravity_deg"] = round(tilt_deg(self.T_map_odom, -up), 3)
        return rep

    def save(self, out_dir: str | Path, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write map.ply, trajectory.tum, report.json into ``out_dir``; returns the report.

        Each file is written under a temporary name first, and the three replace what the
        folder held only once all three are complete: a save that fails (a full disk, a
        levelling error) leaves the folder's previous map, trajectory and report as they were.
        It used to write map.ply in place, so a second run into the same ``--out`` that failed
        mid-write left a cut-off map.ply beside the first run's report, the first map gone."""
        Path(out_dir).mkdir(parents=True, exist_ok=True)  # before the levelling may refuse
        pts = self.map_points()
        stamps, poses = self.trajectory()
        comment = "wheelgrid map frame: z up, z=0 floor, metres"
        return self._write(out_dir, "", pts, stamps, poses, comment, extra)

    def save_unlevelled(
        self, out_dir: str | Path, extra: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """Write map_odom.ply, trajectory_odom.tum and report.json into ``out_dir``: the map
        and the sensor poses in odom (the first registered frame's sensor frame), for a live
        scan whose floor was never found that must not be lost as its node stops. Not
        map.ply: nothing may take these for the levelled map frame a grid stands on."""
        poses = np.array(self.poses_odom).reshape(-1, 4, 4)
        comment = "wheelgrid odom frame (the first sensor frame; not levelled), metres"
        extra = {"frame": "odom: the first registered frame's sensor frame, NOT levelled"} | (
            extra or {}
        )
        return self._write(
            out_dir, "_odom", self.map_odom(), np.asarray(self.stamps), poses, comment, extra
        )

    def _write(
        self,
        out_dir: str | Path,
        suffix: str,
        pts: np.ndarray,
        stamps: np.ndarray,
        poses: np.ndarray,
        comment: str,
        extra: dict[str, Any] | None,
    ) -> dict[str, Any]:
        """map{suffix}.ply, trajectory{suffix}.tum and report.json, written together."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)  # (save's is made already; the odom save's not)
        rep = self.report()
        if extra:
            rep.update(extra)
        write_together(
            {
                out / f"map{suffix}.ply": lambda p: write_ply(p, pts, comment=comment),
                out / f"trajectory{suffix}.tum": lambda p: write_tum(p, stamps, poses),
                out / "report.json": lambda p: p.write_text(
                    json.dumps(rep, indent=2, default=float)
                ),
            }
        )
        return rep
