"""The mapper node: PointCloud2 in, levelled map cloud + odometry + status out.

Thin ROS layer over :class:`wheelgrid_mapping.pipeline.Mapper`. Frames are handed to one worker
thread through a bounded queue (``max_queue``, default 1): when it is full the oldest waiting
frame is dropped and counted (``frames_skipped_busy``), so the subscription never blocks and
nothing queues forever. A live sensor wants 1 (map the newest); a bag replay wants every frame.

Malformed clouds (missing x/y/z, a field defined twice, bad point_step, truncated or excess
data, empty, no frame_id while the sensor convention is ``auto``) are logged once per cause and
skipped. Big-endian clouds are valid PointCloud2: ``read_fields`` converts them, and the node
logs that once and uses them (the data is not wrong, only unusual).

The map cloud is published only once the levelled map frame is known (floor found or mount
given): a map in an unknown frame would place obstacles wrongly.

``~/close_loops`` ends a scan the way ``wheelgrid map`` ends a bag: the worker optimises the pose
graph over every frame mapped so far (``loop_closure.*`` parameters), rebuilds the map from the
corrected poses and republishes it; ``~/save_map`` then saves it. It runs in the background
(tens of seconds) while the node keeps publishing its status (``loop_closure`` key); the map is
then final, so later frames are counted (``frames_after_close``) and not mapped until
``~/reset``. For it the node keeps each mapped frame's filtered points (tens of kB a frame), up
to ``max_kept_frames``; beyond that they are released with a warning and the map goes on without
loop closure, so memory stays bounded on a scan that never ends, but for the trajectory (about
300 B a mapped frame, ~10 MB an hour at 10 frames/s).
"""

from __future__ import annotations

import math
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.fileio import (
    check_user_folder,
    matrix_to_quat,
    new_folder,
    pose_or_nan,
    user_folder,
)
from wheelgrid_common.frames import other_frame
from wheelgrid_common.params import check_no_undeclared, declare_dataclass, field
from wheelgrid_common.pointcloud2 import (
    CloudError,
    has_field,
    organised,
    read_fields,
    to_pointcloud2,
)
from wheelgrid_common.ros_env import (
    exit_logger,
    spin_node,
    steady_timer,
    tf2_available,
    tf2_problem,
)

from .loop_closure import LoopClosureConfig, closed_note
from .pipeline import DEFAULT_FRAME_ID, FrameOutcome, Mapper, MapperConfig
from .prefetch import FramePipeline
from .preprocess import PreprocessConfig
from .registration import RegistrationConfig
from .thin_check import check_thin_obstacles

try:
    from rclpy.node import Node
except ImportError:  # pragma: no cover - only without ROS
    Node = object  # type: ignore[assignment,misc]


@dataclass
class MapperNodeConfig:
    """The node's own parameters (the pipeline's are ``preprocess.*``, ``registration.*``,
    ``mapper.*``)."""

    topic: str = field("iphone/points", "sensor_msgs/PointCloud2 input (sensor-data QoS)")
    pose_prior_topic: str = field(
        "", "nav_msgs/Odometry pose prior (ARKit: /iphone/odometry); empty = register without"
    )
    output_dir: str = field(
        "wheelgrid_map",
        "where ~/save_map writes map.ply etc. (relative: to where the node started; ~ = home)",
    )
    save_on_exit: bool = field(
        True,
        "on Ctrl-C / SIGTERM a map not saved since it last changed is written to "
        "<output_dir>/on_exit (on_exit_<UTC time> where an earlier one lies; never over "
        "~/save_map's files; a new temporary folder, logged, if that cannot be written; one "
        "never levelled to <output_dir>/on_exit_unlevelled, in odom): a scan is not lost to a "
        "closed terminal",
    )
    map_frame: str = field("map", "frame id of the levelled map")
    publish_tf: bool = field(
        True,
        "publish each pose as /tf map_frame -> the cloud's frame (needs tf2_msgs, which "
        "scripts/setup.sh builds where the ROS install lacks it); off where that frame already "
        "has a parent (a URDF's base_link -> camera): tf allows a frame one parent only",
    )
    publish_period: float = field(2.0, "period of /wheelgrid/map_cloud and status updates", "s")
    max_queue: int = field(
        1,
        "frames waiting for the worker; when full the OLDEST is dropped and counted. 1 = live "
        "sensor (always map the newest frame); large (e.g. 1000) = bag replay (map every frame)",
        "frames",
    )
    max_kept_frames: int = field(
        6000,
        "frames kept for ~/close_loops (with loop_closure.enabled); beyond this they are "
        "released and loop closure is off until ~/reset (6000: ~10 min at 10 frames/s, "
        "0.3-0.6 GB; rebuilding the map after ~/close_loops holds the new map beside the old "
        "one and up to ~0.25 GB of frames waiting to be merged)",
        "frames",
    )


# A pose prior stamped this much before the newest one kept starts a new pose clock: the
# poses kept are dropped (ARKit's poses arrive in order; a bag replayed again does not).
PRIOR_CLOCK_BACK_S = 1.0
# /wheelgrid/odometry's covariances (row-major 6 x 6, x y z roll pitch yaw): the pose to 5 cm
# and 2 deg (the map-frame targets of issue #3; registration gives no covariance of its own),
# the twist not estimated at all (1e6: a fusing reader must not take its zeros as a stop).
_POSE_SIGMA = (0.05, 0.05, 0.05, *(math.radians(2.0),) * 3)
ODOM_POSE_COVARIANCE = [
    s * s if i == j else 0.0 for i, s in enumerate(_POSE_SIGMA) for j in range(6)
]
ODOM_TWIST_COVARIANCE = [1e6 if i == j else 0.0 for i in range(6) for j in range(6)]
PRIOR_CLOCK_BACK_POSES = 3

# Loop-closure states in which the worker holds (or is about to take) the map, and those after
# which the map is final until ~/reset.
_CLOSING = ("requested", "running")
_FINAL = (*_CLOSING, "closed")


class _CancelledError(Exception):
    """Raised from the loop closure's progress callback when ~/reset asks it to stop."""


#: While registration keeps failing, one warning per this many seconds (the first at once).
FAILURE_LOG_PERIOD_S = 10.0


def _stamp_seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


class MapperNode(Node):  # type: ignore[misc]
    def __init__(self, **kwargs: Any) -> None:  # context=, parameter_overrides= (tests)
        # the libraries the mapping imports where first needed, here at the start: without
        # open3d the node started, took frames, and died at the first floor search with a
        # traceback, the scan lost (a review); now one FATAL line, exit 2 (spin_node)
        import kiss_icp  # noqa: F401
        import open3d  # noqa: F401

        super().__init__("mapper", **kwargs)
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import PointCloud2
        from std_srvs.srv import Trigger

        from wheelgrid_common.qos import MAP_QOS, RELIABLE_QOS, SENSOR_QOS, TF_QOS

        try:
            node_cfg = declare_dataclass(self, MapperNodeConfig())
            self._check_node_config(node_cfg)
            pre = declare_dataclass(self, PreprocessConfig(), "preprocess.")
            reg = declare_dataclass(self, RegistrationConfig(), "registration.")
            cfg = declare_dataclass(self, MapperConfig(), "mapper.")
            self.loop_cfg = declare_dataclass(self, LoopClosureConfig(), "loop_closure.")
            check_no_undeclared(self)
            thin_note = check_thin_obstacles(pre)  # a filter that erases a bar: refused here
            self.mapper = Mapper(pre, reg, cfg, keep_frames=self.loop_cfg.enabled)
        except ValueError as exc:  # same as the other nodes: one FATAL line, exit 2
            self.get_logger().fatal(f"invalid parameters: {exc}")
            raise SystemExit(2) from exc
        if thin_note:
            self.get_logger().warning(thin_note)
        self.topic = node_cfg.topic
        self.prior_topic = node_cfg.pose_prior_topic
        self.output_dir = node_cfg.output_dir
        self.save_on_exit = node_cfg.save_on_exit
        self.map_frame = node_cfg.map_frame
        self.publish_period = node_cfg.publish_period
        self.max_queue = node_cfg.max_queue
        self.max_kept_frames = node_cfg.max_kept_frames
        # guards self.mapper and self._pipe; re-entrant: close() holds it for the last frame,
        # whose report may release the kept frames under it
        self._lock = threading.RLock()
        # each frame filtered in a second process while the one before registers (same map)
        self._pipe = FramePipeline(self.mapper, cfg.prepare_ahead)
        self._pipe_note = self._pipe.note  # a change is said once, in _report
        self._generation = 0  # bumped by ~/reset: a frame taken before it must not map after it
        self._slot_lock = threading.Condition()
        self._queue: deque[tuple[np.ndarray, float, str, np.ndarray | None, Any, float]] = deque()
        # the stamps of the frames dropped while busy since the worker last took one, and the
        # stamp of the frame it took last: a frame's predecessor is the last of those dropped,
        # else that one (what tells a dropout of the stream from frames this node dropped)
        self._dropped_busy: list[float] = []
        self._last_taken: float | None = None
        self._stop = False
        # (stamp, pose, child frame) of each prior received
        self._priors: deque[tuple[float, np.ndarray, str]] = deque(maxlen=2000)
        # poses stamped well before the newest kept, in a row: a new pose clock once there
        # are PRIOR_CLOCK_BACK_POSES of them (see _on_prior)
        self._priors_behind: list[tuple[float, np.ndarray, str]] = []
        self._floor_refound_seen: dict[str, Any] | None = None  # the one last warned of
        self._floor_refused_seen: str | None = None  # a floor check's refusal, warned of
        self._mount_check_seen: dict[str, Any] | None = None  # the mount check last warned of
        self._axes_lines_seen: set[str] = set()  # axes_lines already warned of
        self._logged: set[str] = set()
        # registration failures said one line each only where a run of them begins, then at
        # most every FAILURE_LOG_PERIOD_S with how many came between (see _say_failure)
        self._failing = False
        self._failure_said_t = -math.inf
        self._failures_unsaid = 0
        self._map_dirty = False
        self._saved: tuple[int, int, str, int] | None = None  # what ~/save_map last wrote
        # unmapped_at_exit: frames still queued when the node stopped (a bag replayed faster
        # than it maps, max_queue large): not mapped, and counted so that the report adds up
        self.counts = {
            "received": 0,
            "skipped_busy": 0,
            "malformed": 0,
            "after_close": 0,
            "unmapped_at_exit": 0,
        }
        # Loop closure: "off" | "ready" | "requested" | "running" | "closed" | "failed"; the
        # service sets "requested", the worker runs it, ~/reset cancels it.
        self._loop_state = "ready" if self.loop_cfg.enabled else "off"
        self._loop_note = ""
        self._loop_cancel = False
        # a ~/reset answered while a loop closure held the map: the worker clears the map as
        # soon as the closure lets go of it, before it maps any frame
        self._reset_pending = False
        self._sensor_frame = DEFAULT_FRAME_ID
        # (frame_id, header stamp) of each frame pushed, by its number in the mapper, until
        # its outcome (which carries that number) is reported: frames are filtered one ahead,
        # so the frame just taken may not be the one whose pose comes out next. The stamp goes
        # out as received: a float of epoch seconds is ~100 ns off. Not by stamp: a cloud
        # delivered twice took the first one's entry, and its pose went out with the repeat's
        # frame_id and a stamp rebuilt from the float.
        self._frame_ids: dict[int, tuple[str, Any]] = {}

        self.map_pub = self.create_publisher(PointCloud2, "wheelgrid/map_cloud", MAP_QOS)
        # A mapper started again (a crash, a relaunch) maps in a new frame under its own first
        # pose: the map cloud of the one before, and the grid made of it, stayed published
        # while its first poses went out, and a start in the new frame was planned on the old
        # grid (a review). An empty map cloud replaces it, as ~/reset does: the grid node
        # withdraws that grid until this mapper's first map.
        self._publish_empty_map()
        # reliable, keep last 10: best-effort readers (the planner) still match, and RViz's
        # and Nav2's default reliable readers do too (on sensor-data QoS they got nothing)
        self.odom_pub = self.create_publisher(Odometry, "wheelgrid/odometry", RELIABLE_QOS)
        self.status_pub = self.create_publisher(
            DiagnosticArray, "wheelgrid/mapper_status", RELIABLE_QOS
        )
        self.tf_pub = None
        if node_cfg.publish_tf and tf2_available():
            from tf2_msgs.msg import TFMessage

            # relative, as Nav2's multi-robot launch files remap it: /tf in the root
            # namespace, /chair1/tf under /chair1. Absolute, two chairs' mappers sent
            # different `map -> sensor` transforms on one /tf at the same stamps.
            try:
                self.tf_pub = self.create_publisher(TFMessage, "tf", TF_QOS)
            except Exception as exc:  # its C type support missing (a partial build)
                self.get_logger().warning(
                    f"publish_tf: tf2_msgs is importable but its type support does not load "
                    f"({exc}), so no /tf; the poses are on /wheelgrid/odometry"
                )
        elif node_cfg.publish_tf:
            self.get_logger().warning(
                f"publish_tf: {tf2_problem()}, so no /tf (scripts/setup.sh builds it into the "
                "venv where CMake and a compiler exist; log/tf2_msgs-build.log says why it did "
                "not); the poses are on /wheelgrid/odometry"
            )
        # Sensor-data QoS (best effort, volatile); its history grows with max_queue so that a
        # replay or a 60 Hz phone stream is not dropped by DDS while the worker holds the GIL.
        cloud_qos = QoSProfile(
            history=SENSOR_QOS.history,
            depth=min(max(SENSOR_QOS.depth, self.max_queue), 200),
            reliability=SENSOR_QOS.reliability,
            durability=SENSOR_QOS.durability,
        )
        self.create_subscription(PointCloud2, self.topic, self._on_cloud, cloud_qos)
        if self.prior_topic:
            # deep history too: a pose lost while the worker holds the GIL costs a whole frame
            prior_qos = QoSProfile(
                history=SENSOR_QOS.history,
                depth=max(cloud_qos.depth, 100),
                reliability=SENSOR_QOS.reliability,
                durability=SENSOR_QOS.durability,
            )
            self.create_subscription(Odometry, self.prior_topic, self._on_prior, prior_qos)
        self.create_service(Trigger, "~/save_map", self._on_save)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/close_loops", self._on_close_loops)
        steady_timer(self, self.publish_period, self._on_timer)
        self._worker = threading.Thread(target=self._work, name="mapper-worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"mapper: {self.resolve_topic_name(self.topic)} -> {self.map_pub.topic_name} "
            f"(prior: {self.resolve_topic_name(self.prior_topic) if self.prior_topic else 'none'}, "
            f"/tf {'on' if self.tf_pub is not None else 'off'}, "
            f"registration {reg.method} voxel {reg.voxel_size} m, loop closure "
            f"{'on ~/close_loops' if self.loop_cfg.enabled else 'off'}, frames filtered in "
            f"{'a second process' if self._pipe.ahead else 'this process'})"
        )
        if cfg.prepare_ahead and not self._pipe.ahead:
            self.get_logger().warning(f"frames filtered here, slower: {self._pipe.note}")

    # -- input -------------------------------------------------------------------------------
    def _check_node_config(self, c: MapperNodeConfig) -> None:
        """``ValueError`` for node parameters it cannot run with: rclpy raised its own
        tracebacks for a bad topic name or a negative timer period, a period of 0 spun a core,
        and a negative queue was clamped without a word."""
        from wheelgrid_common.ros_env import check_topic_params

        topics = {"topic": c.topic, "pose_prior_topic": c.pose_prior_topic}
        check_topic_params(self, topics, optional=("pose_prior_topic",))  # "": no prior
        if not 0.05 <= c.publish_period <= 3600.0:
            raise ValueError(f"publish_period must be in [0.05, 3600] s, not {c.publish_period}")
        if c.max_queue < 1 or c.max_kept_frames < 0:
            raise ValueError("max_queue must be >= 1 and max_kept_frames >= 0")
        if not c.map_frame:
            raise ValueError("map_frame must not be empty")
        check_user_folder(c.output_dir)  # `~maps` for `~/maps`

    def _say_failure(self, stamp: float, reason: str) -> None:
        """A registration failure, loudly where a run of them begins; while the mapper stays
        lost, one line every FAILURE_LOG_PERIOD_S saying how many failed since the last. A
        line per failed frame grew every log (the node's, ROS_LOG_DIR's, /rosout) ~7 MB an hour
        for as long as it stayed lost (a review); frames_failed counts every one."""
        now = time.monotonic()
        if self._failing and now - self._failure_said_t < FAILURE_LOG_PERIOD_S:
            self._failures_unsaid += 1
            return
        more = (
            f" ({self._failures_unsaid} more failed since the last such line)"
            if self._failures_unsaid
            else ""
        )
        self.get_logger().warning(
            f"registration failed at {stamp:.3f} s: {reason}; map integration paused, "
            f"relocalising{more}"
        )
        self._failing, self._failure_said_t, self._failures_unsaid = True, now, 0

    def _end_failures(self) -> None:
        if self._failures_unsaid:
            self.get_logger().info(
                f"{self._failures_unsaid} more frames failed before this one was mapped"
            )
        self._failing, self._failures_unsaid = False, 0

    def _log_once(self, key: str, text: str, warn: bool = True) -> None:
        if key not in self._logged:
            self._logged.add(key)
            # rclpy forbids one call site logging at two severities: two separate calls.
            if warn:
                self.get_logger().warning(text)
            else:
                self.get_logger().info(text)

    def _on_cloud(self, msg: Any) -> None:
        self.counts["received"] += 1
        if self._loop_state in _FINAL and not self._reset_pending:
            self.counts["after_close"] += 1
            self._log_once(
                "closed",
                "loops closed (or closing): the map is final, new frames are not "
                "mapped; ~/reset starts a new map",
                False,
            )
            return
        try:
            pts = organised(read_fields(msg), msg)  # the pixel grid, for the mixed-pixel test
            conf = read_fields(msg, ("confidence",))[:, 0] if has_field(msg, "confidence") else None
        except CloudError as exc:
            self.counts["malformed"] += 1
            self._log_once(exc.cause, f"skipping malformed PointCloud2 ({exc}); logged once")
            return
        if not msg.header.frame_id and self.mapper.cfg.sensor_convention == "auto":
            # The frame's name is what says optical or body (REP-103): guessed, a first frame
            # taken the wrong way levels the whole map on a wall.
            self.counts["malformed"] += 1
            self._log_once(
                "no_frame_id",
                "skipping PointCloud2 without a frame_id: its axes are unknown (set "
                "mapper.sensor_convention to optical or body to map such clouds); logged once",
            )
            return
        if msg.header.frame_id and msg.header.frame_id.lstrip("/") == self.map_frame.lstrip("/"):
            # A cloud in the map frame itself is no sensor's view: mapped, its pose went out
            # as /tf and odometry map -> map, a self-transform tf2 refuses, without a word.
            self.counts["malformed"] += 1
            self._log_once(
                "map_frame_cloud",
                f"skipping PointCloud2 in the map frame {self.map_frame!r} itself: the mapper "
                "registers a sensor's clouds (in its own frame); logged once",
            )
            return
        if msg.is_bigendian:
            self._log_once("bigendian", "big-endian PointCloud2 converted to host order", False)
        # when it arrived (the node's clock), for a stamp far ahead of it (:mod:`.frame_clock`)
        received = self.get_clock().now().nanoseconds * 1e-9
        stamp = _stamp_seconds(msg.header.stamp)
        frame = (pts, stamp, msg.header.frame_id, conf, msg.header.stamp, received)
        with self._slot_lock:
            if len(self._queue) >= self.max_queue:
                self._dropped_busy.append(self._queue.popleft()[1])
                self.counts["skipped_busy"] += 1
            self._queue.append(frame)
            self._slot_lock.notify()

    def _on_prior(self, msg: Any) -> None:
        p = msg.pose.pose
        T = pose_or_nan(p.position, p.orientation)  # a NaN pose is refused and counted later
        stamp = _stamp_seconds(msg.header.stamp)
        prior = (stamp, T, str(msg.child_frame_id))
        if self._priors and self._priors[-1][0] > stamp + PRIOR_CLOCK_BACK_S:
            # The pose clock went back (a bag replayed again, a simulator restarted): the
            # poses of before sat at the same stamps and seeded the new frames with another
            # session's world (11 of 12 frames then failed as a "prior jump"). Taken as a new
            # clock once PRIOR_CLOCK_BACK_POSES come in a row; one stray (a zero stamp) alone
            # wiped every pose the queued frames were waiting for.
            self._priors_behind.append(prior)
            if len(self._priors_behind) >= PRIOR_CLOCK_BACK_POSES:
                self._priors.clear()
                self._priors.extend(self._priors_behind)
                self._priors_behind.clear()
            return
        self._priors_behind.clear()  # strays: not a new clock
        self._priors.append(prior)

    def _no_prior_note(self, stamp: float) -> str:
        """Why a frame has no prior, with how far the nearest pose's stamp is: a pose topic on
        another clock (stamps 50 s apart) read like one that was merely late."""
        note = f"no pose on {self.prior_topic} within 0.1 s of a frame"
        if not self._priors:
            return note + " (none received yet); frames register without a prior"
        gap = min((s - stamp for s, _, _ in list(self._priors)), key=abs)
        return (
            f"{note}: the nearest is {gap:+.3f} s from the frame's stamp (a pose topic on "
            "another clock?); frames register without a prior until one has had it, and "
            "fail after that"
        )

    def _prior_for(self, stamp: float, frame_id: str) -> np.ndarray | bool | None:
        """The prior pose for a frame stamped ``stamp`` (within 0.1 s), None when there is
        none yet, or False when the nearest is the pose of another frame than the cloud's
        (``child_frame_id`` not the cloud's ``frame_id``, both named): a base_link pose read
        as the camera's was an initial guess off by the mount, and its vertical levelled the
        map by a wrong gravity. There is no tf here to chain them: it is not used."""
        if not self._priors:
            return None
        # newest first: of two poses as near, the one received last (min keeps the first)
        best = min(reversed(list(self._priors)), key=lambda sp: abs(sp[0] - stamp))
        if abs(best[0] - stamp) > 0.1:
            return None
        if other_frame(best[2], frame_id):
            self._log_once(
                "priorframe",
                f"the poses on {self.resolve_topic_name(self.prior_topic)} are of frame "
                f"{best[2]!r}, the clouds of {frame_id!r}: the prior is not used (frames "
                "register without it); publish the sensor's own pose as the prior",
            )
            return False
        return best[1]

    # -- worker ------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._slot_lock:
                while (
                    not self._queue
                    and not self._stop
                    and self._loop_state != "requested"
                    and not self._pipe.pending
                    and not self._reset_pending
                ):
                    self._slot_lock.wait(0.5)
                if self._stop:
                    return
                if self._reset_pending:
                    with self._lock:
                        self._clear_map()
                    continue
                # frames received before a ~/close_loops are mapped first, and the one in
                # preparation is finished
                frame = self._queue.popleft() if self._queue else None
                if frame is not None:
                    dropped, self._dropped_busy = self._dropped_busy, []
                    before = dropped[-1] if dropped else self._last_taken
                    self._last_taken = frame[1]
                closing = (
                    frame is None and not self._pipe.pending and self._loop_state == "requested"
                )
                if closing:
                    self._loop_state = "running"
                generation = self._generation
            if closing:
                self._close_loops()
                continue
            if frame is None:  # nothing new came: the frame in preparation is added now
                with self._lock:
                    done = self._pipe.flush() if generation == self._generation else []
                self._report(done, generation)
                continue
            pts, stamp, frame_id, conf, header_stamp, received = frame
            # Frames dropped while busy (max_queue) are no dropout: the stream went on. Where
            # the cloud received before this one is within max_gap of it, registration is told
            # so; else it judges from the frames it saw. Before, two frames skipped at 5 Hz
            # made a 0.6 s "gap" on the unedited bundled bag, and the next 30 frames (6 s of
            # map, odometry and /tf) failed the rule for a relocalisation after a dropout.
            no_gap = before is not None and 0.0 <= stamp - before <= self.mapper.reg_cfg.max_gap
            if frame_id:
                self._sensor_frame = frame_id
            found = self._prior_for(stamp, frame_id)
            if self.prior_topic and found is None:
                # The pose may arrive just after its cloud: wait a moment rather than register
                # without it (once frames have had one, a frame without it fails).
                deadline = time.monotonic() + 0.25
                while found is None and time.monotonic() < deadline and not self._stop:
                    time.sleep(0.01)
                    found = self._prior_for(stamp, frame_id)
                if found is None:
                    self._log_once("noprior", self._no_prior_note(stamp))
            prior = found if isinstance(found, np.ndarray) else None
            # and which of the frames dropped before it had a pose: registration measures a
            # pause of the prior up to the first of them, not from the frames it saw
            had = [
                s
                for s in dropped
                if s < stamp and isinstance(self._prior_for(s, frame_id), np.ndarray)
            ]
            dropped_priors = (stamp - min(had), stamp - max(had)) if no_gap and had else None
            with self._lock:
                if generation != self._generation:
                    # ~/reset came while it was in hand: dropped with the map, and not counted,
                    # as it was received before the reset cleared the counters (counted, the
                    # status read one skipped of none received)
                    continue
                # this frame goes to the second process; the one before it to the map
                number = self.mapper.frames_read  # the mapper's own count, as its report's
                self._frame_ids[number] = (frame_id or self._sensor_frame, header_stamp)
                done = self._pipe.push(
                    pts,
                    stamp,
                    frame_id,
                    conf,
                    prior,
                    received,
                    False if no_gap else None,
                    dropped_priors,
                    number,
                )
            self._report(done, generation)

    def _report(
        self, done: list[tuple[float, FrameOutcome]], generation: int | None = None
    ) -> None:
        """Logs, the pose and the map's state for frames just added (never raises: a bad frame
        must never kill the mapper). ``generation``: the map's when they were added; a pose
        is published only if no ~/reset came since (it bumps the generation under ``_lock``
        unless a loop closure holds the map, when the worker is not here)."""
        if self._pipe_note != self._pipe.note:
            # the second process died (killed, out of memory): nothing is lost, but frames are
            # filtered here from now on, slower; only the status key said so
            self._pipe_note = self._pipe.note
            self.get_logger().warning(
                "the second process that filtered frames is gone; frames are filtered in this "
                f"process from now on, slower, none lost: {self._pipe.note}"
            )
        for stamp, out in done:
            frame_id, header_stamp = self._frame_ids.pop(out.number, (self._sensor_frame, None))
            if out.status == "error":
                # throttled like the registration failures (frames_errored counts each)
                self.get_logger().error(
                    f"frame at {stamp:.3f} s failed: {out.reason}",
                    throttle_duration_sec=FAILURE_LOG_PERIOD_S,
                )
            elif out.status == "failed":
                self._say_failure(stamp, out.reason)
            elif out.status == "empty":
                self._log_once("no_valid_points", f"frame without valid points ({out.reason})")
            elif out.cause:
                self._log_once(
                    out.cause, f"skipping clouds like the one at {stamp:.3f} s: {out.reason}"
                )
            if out.status == "used":
                self._end_failures()
            if out.after_gap:
                self.get_logger().info(f"after a dropout, placed against the map at {stamp:.3f} s")
            elif out.relocalised:
                self.get_logger().info(f"relocalised at {stamp:.3f} s; mapping resumed")
            if out.status == "used":
                with self._lock:  # only _lock: _bound_kept_frames takes _slot_lock
                    if generation is not None and generation != self._generation:
                        continue  # the map it was added to is gone: its pose is of no frame
                    self._map_dirty = True
                    if out.pose_map is not None:
                        self._publish_pose(out.pose_map, stamp, frame_id, header_stamp)
                self._bound_kept_frames()

    def _bound_kept_frames(self) -> None:
        if self.mapper.keep_frames and len(self.mapper.poses_odom) > self.max_kept_frames:
            with self._slot_lock:
                # a ~/close_loops answered "closing" needs the kept frames: they stay until it
                # ran (set "off" under it, such a request was lost after its "success")
                if self._loop_state in ("requested", "running"):
                    return
                self._loop_state = "off"
                self._loop_note = f"frames released after {self.max_kept_frames} (max_kept_frames)"
            with self._lock:
                self.mapper.release_frames()
            self.get_logger().warning(
                f"loop closure OFF until ~/reset: more than max_kept_frames "
                f"({self.max_kept_frames}) mapped, their kept points released; the map goes on "
                "without it"
            )

    def _close_loops(self) -> None:
        """Runs in the worker: the pose graph over every frame so far, then the map rebuilt."""
        frames = len(self.mapper.poses_odom)
        self.get_logger().info(f"closing loops over {frames} frames ...")

        def progress(done: int, total: int) -> None:
            if self._loop_cancel:
                raise _CancelledError
            self._loop_note = f"{done}/{total} submaps"

        # The outcome is set while the map is still held: a ~/reset waiting for it then finds
        # it and overrides it, never the other way round.
        with self._lock:
            try:
                lc = self.mapper.close_loops(self.loop_cfg, progress)
            except _CancelledError:
                return  # ~/reset takes it from here
            except Exception as exc:  # the online map is kept as it was: nothing is lost
                self._loop_state = "failed"
                self._loop_note = repr(exc)
                self.get_logger().error(
                    f"loop closure failed ({exc!r}); the online map is kept, ~/save_map saves it"
                )
                return
            if self._loop_cancel:
                return  # finished just as a ~/reset came: it clears this map anyway
            self._loop_state = "closed"
            self._loop_note = closed_note(lc)
            self._map_dirty = True
        self.get_logger().info(f"loops closed: {self._loop_note}; map republished")

    def _publish(self, pub: Any, msg: Any) -> bool:
        """Publish, unless Ctrl-C or SIGTERM has shut the context down: the worker may finish a
        frame after that, and its ``RCLError`` ("publisher's context is invalid") killed the
        worker thread and, from ``close()``'s last flush, skipped the save on exit. False when
        nothing was published."""
        if not self.context.ok():
            return False
        try:
            pub.publish(msg)
        except Exception:
            if self.context.ok():
                raise
            return False  # shut down between the check and the publish
        return True

    def _publish_pose(
        self, T: np.ndarray, stamp: float, frame_id: str, header_stamp: Any = None
    ) -> None:
        """The pose of the frame stamped ``header_stamp`` (its cloud's own stamp, exactly:
        tf lookups and exact-time syncs at the cloud's stamp need it), else from ``stamp``."""
        from nav_msgs.msg import Odometry

        msg = Odometry()
        msg.header.frame_id = self.map_frame
        if header_stamp is not None:
            msg.header.stamp = header_stamp
        else:
            ns = round(stamp * 1e9)
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        msg.child_frame_id = frame_id
        qx, qy, qz, qw = matrix_to_quat(T[:3, :3])
        msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = (
            float(v) for v in T[:3, 3]
        )
        msg.pose.pose.orientation.x, msg.pose.pose.orientation.y = qx, qy
        msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = qz, qw
        # Zeros said "exactly known" to a fusing reader (robot_localization): the pose gets
        # a fixed, conservative covariance, and the twist, which the mapper does not
        # estimate, one that says so.
        msg.pose.covariance = ODOM_POSE_COVARIANCE
        msg.twist.covariance = ODOM_TWIST_COVARIANCE
        if not self._publish(self.odom_pub, msg):
            return
        if self.tf_pub is not None:
            from geometry_msgs.msg import TransformStamped
            from tf2_msgs.msg import TFMessage

            tf = TransformStamped()
            tf.header = msg.header
            tf.child_frame_id = msg.child_frame_id
            tf.transform.translation.x = msg.pose.pose.position.x
            tf.transform.translation.y = msg.pose.pose.position.y
            tf.transform.translation.z = msg.pose.pose.position.z
            tf.transform.rotation = msg.pose.pose.orientation
            self._publish(self.tf_pub, TFMessage(transforms=[tf]))

    # -- output ------------------------------------------------------------------------------
    def _on_timer(self) -> None:
        # A loop closure holds the map for tens of seconds and the status must go on meanwhile:
        # no waiting for it then. Only this (executor) thread moves the state from "ready" to
        # "requested", so a closure cannot start between this check and the lock.
        if self._map_dirty and self._loop_state not in _CLOSING:
            with self._lock:
                try:
                    pts = self.mapper.published_points()
                except RuntimeError as exc:
                    pts = None
                    self._log_once("nolevel", f"map not published yet: {exc}")
            if pts is not None:
                self._map_dirty = False
                self._warn_levelling()
                msg = to_pointcloud2(pts.astype(np.float32), self.map_frame)
                msg.header.stamp = self.get_clock().now().to_msg()
                self._publish(self.map_pub, msg)
        self._publish_status()

    def _publish_empty_map(self) -> None:
        """No map (yet, or any more): what the grid node takes for a map gone."""
        empty = to_pointcloud2(np.zeros((0, 3), dtype=np.float32), self.map_frame)
        empty.header.stamp = self.get_clock().now().to_msg()
        self.map_pub.publish(empty)

    def _warn_levelling(self) -> None:
        """Say so, once each, when the map frame jumped to the floor found on the whole map
        (the map, the poses and any grid made from an earlier map cloud move with it), and
        when the floor in view contradicts an explicit mount transform."""
        from .cli_map import axes_lines, floor_refound_line, mount_check_line

        got = self.mapper.level_info.get("floor_refound")
        refused = (self.mapper.level_info.get("floor_check") or {}).get("refused")
        if got and got is not self._floor_refound_seen:
            self._floor_refound_seen = got
            self.get_logger().warning(f"mapper: {floor_refound_line(self.mapper.level_info)}")
        elif not got and refused and refused != self._floor_refused_seen:
            # a large low table taken for the floor and not used: said once (not each check)
            self._floor_refused_seen = refused
            self.get_logger().warning(f"mapper: {floor_refound_line(self.mapper.level_info)}")
        check = self.mapper.level_info.get("mount_floor_check")
        if check and check is not self._mount_check_seen:
            self._mount_check_seen = check
            line = mount_check_line(self.mapper.level_info)
            if line:
                self.get_logger().warning(f"mapper: {line}")
        for line in axes_lines(self.mapper.levelling_report()):
            if line not in self._axes_lines_seen:
                self._axes_lines_seen.add(line)
                self.get_logger().warning(f"mapper: {line}")

    def _publish_status(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        c = self.mapper.registrar.counters
        state = self.mapper.state
        level = self.mapper.levelling_report()
        st = DiagnosticStatus()
        st.name = "wheelgrid mapper"
        st.hardware_id = self._sensor_frame
        st.level = DiagnosticStatus.OK if state == "ok" else DiagnosticStatus.WARN
        st.message = state if self.mapper.T_map_odom is not None else f"{state} (map frame unknown)"
        values = {
            "state": state,
            "frames_received": self.counts["received"],
            "frames_used": c.accepted,
            "frames_failed": c.failed,
            "frames_relocalised": c.relocalised,
            "frames_after_gap": c.gaps,
            "frames_after_prior_gap": c.prior_gaps,
            "frames_dropped_before_prior": self.mapper.dropped_before_prior,
            "frames_skipped_busy": self.counts["skipped_busy"],
            "frames_between_keyframes": self.mapper.frames_skipped,
            "clock_jumps": self.mapper.clock_jumps,
            "frames_out_of_order": self.mapper.out_of_order,  # repeats, late: skipped
            # stamped far ahead of their arrival: skipped (:mod:`.frame_clock`)
            "frames_stamped_ahead": self.mapper.stamped_ahead,
            "frames_stamped_behind": self.mapper.stamped_behind,
            "frames_other_frame": self.mapper.other_frame,  # the other axis convention: skipped
            "frames_malformed": self.counts["malformed"],
            "frames_empty": self.mapper.frames_empty,
            # raised while prepared or registered (logged): without it the outcomes did not add
            # up to frames_received, and such a frame vanished from the status
            "frames_errored": self.mapper.frames_errored,
            "priors_refused": self.mapper.priors_refused,
            "priors_frozen": c.prior_frozen,  # repeated to the bit: ICP alone where it could
            "levelled": self.mapper.T_map_odom is not None,
            # where the first floor fit's vertical came from, and the map frame's angle to the
            # pose prior's gravity (the one check of the frame a user can read live)
            "vertical": level.get("vertical", "unknown"),
            "prior_gravity_deg": level.get("prior_gravity_deg", "no prior"),
            "floor_refound_at_frames": (self.mapper.level_info.get("floor_refound") or {}).get(
                "at_frames", "no"
            ),
            "loop_closure": self._loop_state,
            "loop_closure_note": self._loop_note,
            "frames_after_close": self.counts["after_close"],
            "prepare": self._pipe.note,  # where frames are filtered: second process | one ...
            # how often this comes: a reader can tell a silent (frozen, hung) mapper from one
            # whose counts have not changed
            "status_period_s": self.publish_period,
        }
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self._publish(self.status_pub, arr)

    def _on_save(self, request: Any, response: Any) -> Any:
        if self._reset_pending:  # it said "save once ... closed", which never came
            response.success = False
            response.message = "a ~/reset is clearing the map: nothing to save"
            return response
        if self._loop_state in _CLOSING:
            # the worker holds the map; waiting here would stall every other callback
            response.success = False
            response.message = (
                f"loop closure running ({self._loop_note or 'starting'}); save once "
                "/wheelgrid/mapper_status says loop_closure: closed"
            )
            return response
        if self.mapper.registrar.counters.accepted == 0:
            response.success = False
            response.message = (
                f"nothing to save: no frame mapped yet ({self.counts['received']} received)"
            )
            return response
        try:
            out = user_folder(self.output_dir)
            with self._slot_lock:
                waiting = len(self._queue)
            with self._lock:
                # received, not mapped yet: the frame in preparation and those queued (a save
                # during a burst read 75 frames of 100 received, the rest said nowhere)
                waiting += int(self._pipe.pending)
                counts = {**self.counts, "unmapped_at_save": waiting}
                rep = self.mapper.save(out, {"node_counts": counts})
                self._saved = self._map_state()
            response.success = True
            response.message = (
                f"wrote {out}/map.ply ({rep['points']['map']} points), trajectory.tum, report.json"
            )
            if waiting:
                response.message += (
                    f"; {waiting} frame(s) received are not mapped yet (queued), not in it"
                )
            from .cli_map import lost_at_end

            lost = lost_at_end(rep["registration"])
            if lost:  # saved while relocalising: the map is consistent, but not all of the route
                response.message += f"; {lost}"
            self.get_logger().info(response.message)
        except (RuntimeError, OSError) as exc:
            response.success = False
            response.message = f"cannot save: {exc}"
        return response

    def _clear_intake(self) -> None:
        """~/reset's work on what came in, with ``_slot_lock`` held: done when it answers."""
        self.counts["skipped_busy"] += len(self._queue)
        if self._queue:  # received: the next frame's predecessor
            self._last_taken = self._queue[-1][1]
        self._queue.clear()
        self._dropped_busy.clear()
        self._generation += 1  # a frame the worker has in hand must not map after the reset
        self._priors.clear()  # the old session's poses: a new one may reuse their stamps
        self._priors_behind.clear()
        for key in self.counts:  # "counters cleared" means the node's own too
            self.counts[key] = 0
        self._map_dirty = False

    def _clear_map(self) -> None:
        """~/reset's work on the map, with ``_slot_lock`` and ``_lock`` held: done when it
        answers, or by the worker once a loop closure lets go of the map."""
        self._pipe.discard()  # the frame in preparation belonged to the old map
        self._frame_ids.clear()
        self.mapper.reset()  # kept frames go too; keep them again if max_kept_frames stopped it
        self.mapper.keep_frames = self.loop_cfg.enabled
        self._loop_state = "ready" if self.loop_cfg.enabled else "off"
        self._loop_note = ""
        self._loop_cancel = False
        self._reset_pending = False

    def _on_reset(self, request: Any, response: Any) -> Any:
        self._loop_cancel = True  # a running loop closure stops at its next submap
        with self._slot_lock:
            if self._loop_state == "running" or self._reset_pending:
                # The worker holds the map until the solve's next check, which the graph's
                # passes do not make: waiting for it here stalled every other callback (the
                # status, the map timer, clouds) for as long. The worker clears the map as
                # soon as it lets go, before it maps any frame that comes after this answer.
                self._clear_intake()
                self._reset_pending = True
                self._loop_note = "cancelled by ~/reset: the map is cleared once it lets go"
                self._slot_lock.notify()
                deferred = True
            else:
                deferred = False
                with self._lock:
                    self._clear_intake()
                    self._clear_map()
        # The map topic is transient-local: left alone it kept the cleared map for every
        # subscriber that starts later (a restarted grid node made a grid of it, placed in a
        # map frame the next frames no longer share). An empty map cloud replaces it.
        self._publish_empty_map()
        response.success = True
        response.message = (
            "loop closure cancelled; map, trajectory and counters cleared before the next "
            "frame is mapped"
            if deferred
            else "map, trajectory and counters cleared"
        )
        return response

    def _on_close_loops(self, request: Any, response: Any) -> Any:
        with self._slot_lock:
            state, frames = self._loop_state, len(self.mapper.poses_odom)
            if self._reset_pending:
                response.success = False
                response.message = "a ~/reset is clearing the map: nothing to close yet"
            elif state == "off":
                response.success = False
                response.message = (
                    "loop closure is off ("
                    + (self._loop_note or "loop_closure.enabled is false")
                    + "); the online map stands, ~/save_map saves it"
                )
            elif state in _FINAL:
                # Idempotent, as callers retry a request whose answer DDS dropped: what was
                # asked for is under way or done.
                response.success = True
                response.message = (
                    f"loop closure already {state}"
                    + (f" ({self._loop_note})" if self._loop_note else "")
                    + "; ~/reset starts a new map"
                )
            elif frames < 2:
                response.success = False
                response.message = f"{frames} frame(s) mapped: nothing to close yet"
            else:
                self._loop_state = "requested"
                self._loop_note = ""
                self._slot_lock.notify()
                response.success = True
                # the queued ones are mapped first (it said 75 over a closure of 100)
                queued = len(self._queue) + int(self._pipe.pending)
                over = f"{frames} frames" + (f" and the {queued} queued" if queued else "")
                response.message = (
                    f"closing loops over {over} in the background; the map is final "
                    "from now on (new frames are not mapped until ~/reset); "
                    "/wheelgrid/mapper_status says loop_closure: closed when the corrected map "
                    "is on /wheelgrid/map_cloud"
                )
        return response

    def _map_state(self) -> tuple[int, int, str, int]:
        """Changes whenever the map does: a frame mapped, loops closed, a ~/reset, the map
        begun again on the first frame with a pose prior (one frame for another)."""
        return (
            self._generation,
            len(self.mapper.poses_odom),
            self._loop_state,
            self.mapper.dropped_before_prior,
        )

    def close(self) -> None:
        # A loop closure in progress is cancelled (it is all or nothing: the online map stays)
        # so the worker lets go of the map in time for it to be saved.
        self._loop_cancel = True
        with self._slot_lock:
            self._stop = True
            self._slot_lock.notify()
        self._worker.join(timeout=10.0)
        with self._slot_lock:
            left = len(self._queue)
            self._queue.clear()
        if left:
            self.counts["unmapped_at_exit"] += left
            exit_logger(self).warning(
                f"{left} frame(s) still queued at exit were not mapped (node_counts "
                "unmapped_at_exit in the report saved on exit)"
            )
        try:
            if self._lock.acquire(timeout=5.0):
                try:  # the frame taken last is mapped, so that the map saved below has it
                    if not self._worker.is_alive():
                        if self._reset_pending:  # answered: the map it cleared is not saved
                            self._clear_map()  # (the worker is gone: no _slot_lock after _lock)
                        self._report(self._pipe.flush())
                finally:
                    self._lock.release()
            self._pipe.close()
        finally:  # whatever went wrong with the last frame, the map so far is saved
            if self.save_on_exit:
                self._save_on_exit()

    def _save_on_exit(self) -> None:
        log = exit_logger(self)
        if not self._lock.acquire(timeout=5.0):
            log.error("map NOT saved on exit: the mapper did not let go of it within 5 s")
            return
        try:
            frames = len(self.mapper.poses_odom)
            if frames == 0 or self._map_state() == self._saved:
                return  # nothing mapped, or ~/save_map already has exactly this map
            extra = {"node_counts": dict(self.counts), "saved_on_exit": True}
            # A floor never seen (no mount given either) left no map frame, and the scan was
            # lost with "map NOT saved on exit": it is kept in odom, under other names, in a
            # folder of its own (in on_exit, an earlier session's map.ply stayed beside it
            # under this scan's report.json).
            levelled = self.mapper.try_level()
            save = self.mapper.save if levelled else self.mapper.save_unlevelled
            name = "on_exit" if levelled else "on_exit_unlevelled"
            try:
                # on_exit, or on_exit_<UTC time> where an earlier session's rescue lies: a
                # second launch's scan replaced the first one's there
                out = new_folder(user_folder(self.output_dir) / name)
                rep = save(out, extra)
            except OSError as exc:
                # An unwritable output_dir (a read-only mount, a full disk, a typo) must not
                # lose the scan this save exists for: a fresh temporary folder is tried next.
                fallback = Path(tempfile.mkdtemp(prefix="wheelgrid_on_exit_"))
                log.error(
                    f"cannot save the map to {self.output_dir}/{name} ({exc}); trying {fallback}"
                )
                out = fallback
                rep = save(out, extra)
            if levelled:
                log.warning(
                    f"map saved on exit: {out}/map.ply ({rep['points']['map']} points, "
                    f"{frames} frames), trajectory.tum, report.json"
                )
            else:
                why = self.mapper.level_info.get("error", "map frame unknown")
                log.warning(
                    f"map saved on exit, NOT levelled ({why}): {out}/map_odom.ply "
                    f"({rep['points']['map']} points, {frames} frames, in the first frame's "
                    "sensor frame), trajectory_odom.tum, report.json"
                )
        except (RuntimeError, OSError) as exc:
            log.error(f"map NOT saved on exit: {exc}")
        finally:
            self._lock.release()


def main() -> None:
    import sys

    code = spin_node(MapperNode)
    sys.exit(code)


if __name__ == "__main__":
    main()
