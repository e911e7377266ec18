"""The ``drive`` node: plans and velocity commands in, serial motor commands out.

Thin on purpose: the Table II rule (actions.py), the wire protocol (protocol.py), the link
(link.py) and the per-step execution with its free-cell check (runner.py) are ROS-free and
tested on their own. This module translates messages and parameters and owns the threads:

* the executor thread runs callbacks (plan, grid, cmd_vel, timers);
* the e-stop has a node (``drive_estop``) and an executor thread of its own, so that it never
  waits behind another callback: reading a 10,000-pose plan held the executor 0.4 s, during
  which the chair drove on (rclpy's MultiThreadedExecutor would do it with one node, but spins
  a core while two callbacks of one group are ready). The /cmd_vel watchdog's stop runs
  there too;
* one worker thread at a time drives a plan or a /cmd_vel step (a new job aborts the old one);
* the link's heartbeat thread feeds the controller watchdog and publishes /wheelgrid/chair_pose.

Safety: an e-stop sends STOP from its callback at once (it does not wait for the worker) and is
latched until a ``false`` arrives; every step is checked against the latest safe grid (only
FREE cells); a stale /cmd_vel (0.5 s) stops the chair; any link trouble stops the chair.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, Twist
from nav_msgs.msg import OccupancyGrid, Path
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, String

from wheelgrid_common.fileio import quat_yaw
from wheelgrid_common.map_io import CHAIR_GRID_HINT, Grid, chair_cell_problem, from_occupancy_grid
from wheelgrid_common.params import (
    check_bounds,
    check_finite,
    check_no_undeclared,
    declare_dataclass,
    field,
)
from wheelgrid_common.qos import MAP_QOS, RELIABLE_QOS, SENSOR_QOS, volatile_writers_expected
from wheelgrid_common.ros_env import (
    SideSpinner,
    exit_logger,
    received_ns,
    sample_key,
    side_node,
    spin_node,
    steady_timer,
    with_message_info,
)
from wheelgrid_drive import actions
from wheelgrid_drive import protocol as proto
from wheelgrid_drive.link import HEARTBEAT_PERIOD_S, RECONNECT_PERIOD_S, LinkError, MotorLink
from wheelgrid_drive.runner import (
    RunResult,
    cells_from_points,
    controller_step_length,
    dumps_record,
    grid_cell_check,
    off_centre_problem,
    planned_grid_check,
    run_steps,
    same_geometry,
    step_to_centre,
)

# DiagnosticStatus levels are ``byte`` fields: rclpy holds them as one-byte ``bytes``.
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
# The state says ERROR once the controller has not reported for this many heartbeat periods
# (and one heartbeat's tries): it no longer answers, and its last pose is not the chair's.
SILENT_HEARTBEATS = 3
HEARTBEAT_LOG_PERIOD_S = 10.0  # a failing heartbeat is logged at most this often


# The grid node's heartbeat (DiagnosticArray, 2 Hz): see DriveConfig.grid_state_timeout.
GRID_STATE_TOPIC = "wheelgrid/grid_state"
# One grid (or ~/save) taking longer than this is a node stuck in it: 200 m floors, the grid's
# largest, took 2-3 s on two cores.
GRID_BUSY_MAX_S = 30.0

# Reliable like the plan's publisher, but never the plan kept for late joiners (see __init__).
PLAN_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

MAX_PATH_POSES = 10_000  # a plan's poses: a route across a building is a few hundred cells
# /cmd_vel drives only once it has been zero, or silent this long since the node started: a
# joystick held forward while the drive (re)started, its e-stop latch gone with the old
# process, drove the chair at once. A wheelchair controller refuses a deflected stick at
# power-on for the same reason. 2 s covers DDS discovery on loopback, so a stream that is
# already running is heard within it.
STARTUP_QUIET_S = 2.0
# The /cmd_vel tick runs every 50 ms; a gap this long between two of them is the executor held
# up (a long plan read, a job joined), with Twists waiting unread behind it. Silence counts as
# a let-go stick only once the ticks have run on time for a whole watchdog timeout since: the
# last Twist before a hold-up looked stale, /cmd_vel was armed, and the Twists queued behind it
# drove a stick held through an e-stop, never released.
TICK_LATE_S = 0.2
# A plan parked until the safe grid comes (they arrive in any order at start-up) is kept this
# long: kept for ever, a plan parked while the grid was withdrawn drove, with no new command,
# whenever a grid came back, however much later.
PARKED_PLAN_MAX_S = 5.0


@dataclass(frozen=True)
class Arrival:
    """When a plan reached this process, to tell whether an e-stop came after it.

    Both are needed: rclpy reads (deserialises) a message before its callback runs, 0.3-0.5 s
    for 10,000 poses, so an e-stop in that time is seen only by the receive times; one during
    the callback only by the count (the system clock may step).
    """

    received_ns: int  # the middleware's receive time (system clock), or the callback's
    estops: int  # the node's e-stop count when the callback began


@dataclass
class DriveConfig:
    """Parameters of the drive node (also readable from a params YAML)."""

    port: str = field("", "serial device of the motor controller (or a simulator pty)")
    baud: int = field(115200, "serial baud rate", "baud")
    speed: float = field(
        3.0,
        "driving speed, hard-capped at 3 km/h; at least 0.1",
        "km/h",
        bounds=(proto.MIN_SPEED_KMH, math.inf),
    )
    cell_size: float = field(
        1.2,
        "not used: a /cmd_vel step needs the safe grid and drives to its next cell's centre, and "
        "a plan's steps are the grid's cells (kept so that a params file that sets it loads)",
        "m",
        bounds=(0.001, proto.MAX_DISTANCE_MM / 1000),
    )
    reply_timeout: float = field(0.1, "wait for each controller reply before a retry", "s")
    retries: int = field(3, "resends of an unanswered frame before giving up (and STOP)")
    heartbeat_period: float = field(HEARTBEAT_PERIOD_S, "heartbeat (and pose report) period", "s")
    reconnect_period: float = field(
        RECONNECT_PERIOD_S, "retry period to reopen a vanished port", "s"
    )
    cmd_vel_timeout: float = field(
        0.5, "no /cmd_vel Twist for this long -> STOP", "s", bounds=(0.0, 5.0)
    )
    initial_heading: str = field(
        "auto",
        "chair heading at the plan start: up/down/left/right, or auto = the plan's "
        "first pose orientation",
    )
    check_start_pose: bool = field(
        True,
        "refuse a plan unless the controller's pose is in its first cell, facing its start heading",
    )
    pose_tolerance: float = field(
        0.25,
        "every step (of a plan, with check_start_pose, and of /cmd_vel) drives from where the "
        "controller says the chair stands, in the step's first cell, to the next cell's "
        "centre, and its line as the controller drives it must pass within this much of that "
        "centre; a plan's end must be within this much of its goal's centre",
        "cells",
        bounds=(0.0, 0.5),
    )
    set_pose_on_plan: bool = field(
        False, "tell the controller it stands on the plan's start cell (simulator/demo only)"
    )
    linear_deadband: float = field(
        0.05, "|linear.x| below this is no motion", "m/s", bounds=(0.0, math.inf)
    )
    angular_deadband: float = field(
        0.3, "|angular.z| above this is a turn", "rad/s", bounds=(0.0, math.inf)
    )
    state_rate: float = field(5.0, "drive_state publishing rate", "Hz", bounds=(0.0, 100.0))
    grid_state_timeout: float = field(
        2.0,
        "once the grid node's state (wheelgrid/grid_state, 2 Hz) has been heard, a silence "
        "this long, or its executor reported stalled this long outside a grid, stops a running "
        "move and refuses steps: a hung grid node leaves its last grid published while newer "
        "maps go ungridded; 0 = off (a static grid: map_server)",
        "s",
        bounds=(0.0, 60.0),
    )


def check_config(c: DriveConfig) -> None:
    """``ValueError`` for settings the node cannot drive safely with (the link's own are
    :func:`~wheelgrid_drive.link.check_link_settings`'): a NaN ``cmd_vel_timeout`` let one
    Twist drive on for ever, and a negative deadband turned a zero Twist into a move."""
    check_finite(c)
    if not c.speed >= proto.MIN_SPEED_KMH:
        # 0 and below were replaced by the 3 km/h cap, with a warning: a user who set 0 to
        # keep the chair still got full speed (over the cap is capped, as documented)
        raise ValueError(
            f"speed must be >= {proto.MIN_SPEED_KMH:g} km/h (it is capped at "
            f"{proto.MAX_SPEED_KMH:g}), not {c.speed}"
        )
    if not 0.0 < c.cmd_vel_timeout <= 5.0:
        raise ValueError(f"cmd_vel_timeout must be in (0, 5] s, not {c.cmd_vel_timeout}")
    if c.linear_deadband < 0 or c.angular_deadband < 0:
        raise ValueError("linear_deadband and angular_deadband must be >= 0")
    if c.grid_state_timeout != 0.0 and not 1.0 <= c.grid_state_timeout <= 60.0:
        raise ValueError(
            f"grid_state_timeout must be 0 (off) or in [1, 60] s (the grid node reports every "
            f"0.5 s), not {c.grid_state_timeout}"
        )
    if not 0.0 < c.state_rate <= 100.0:
        raise ValueError(f"state_rate must be in (0, 100] Hz, not {c.state_rate}")
    if problem := proto.move_length_problem(c.cell_size, "cell_size"):
        raise ValueError(problem)
    if not 0.0 < c.pose_tolerance <= 0.5:
        raise ValueError(f"pose_tolerance must be in (0, 0.5] cells, not {c.pose_tolerance}")
    if c.initial_heading.strip().lower() not in ("auto", *actions.DELTA):
        raise ValueError(
            f"initial_heading must be auto, up, down, left or right, not {c.initial_heading!r}"
        )
    check_bounds(c)  # the ranges the parameters declare; the explanations above first


class DriveNode(Node):
    def __init__(self, cfg: DriveConfig | None = None, **kwargs: Any) -> None:
        # pyserial at the start: imported at the port's opening, its absence was a port that
        # "cannot open", retried for ever (a review); now one FATAL line, exit 2 (spin_node)
        import serial  # noqa: F401

        super().__init__("drive", **kwargs)
        try:
            self.cfg = declare_dataclass(self, cfg or DriveConfig())
        except ValueError as exc:  # a value of the wrong type: one FATAL line, exit 2, too
            self.get_logger().fatal(f"invalid parameters: {exc}")
            raise SystemExit(2) from exc
        c = self.cfg
        self.speed = min(c.speed, proto.MAX_SPEED_KMH)  # check_config refuses too slow
        if c.speed > proto.MAX_SPEED_KMH:
            self.get_logger().warning(f"speed {c.speed} km/h capped at {self.speed} km/h")
        self._started_ns = time.time_ns()  # plans published before it are not driven
        self._lock = threading.Lock()
        self._grid: Grid | None = None
        self._pending_plan: tuple[Path, Arrival] | None = None  # a plan that came before any grid
        self._estop = False
        # The e-stop runs beside the other callbacks: latching it, parking a plan and starting
        # a job each happen under this lock. A plan that an e-stop came after (even one cleared
        # since) is dropped: see Arrival.
        self._gate = threading.Lock()
        self._estops = 0
        self._estop_received_ns = 0  # when the last e-stop reached this process (system clock)
        self._estop_failed = False  # the e-stop thread died: nothing can clear the latch
        self._grid_state_heard: float | None = None  # the grid node's last state (monotonic)
        self._grid_state = (0.0, 0.0)  # what it said: stalled_s, busy_s
        # the last samples the reliable e-stop subscription served (see _on_estop_best_effort)
        self._estop_samples: deque[tuple[int, int]] = deque(maxlen=64)
        self._abort = threading.Event()
        # Who ended the last plan, for the planner (drive_state's plan_end): "done", "planner"
        # (its empty path, a newer plan, its grid changed under the move), "user" (the stick,
        # an e-stop) or "fault" (a refusal, a failed step, a silent grid node or controller).
        # A plan the user or a fault ended must not be sent again by the planner's next
        # replan: the chair set off 4.8 m to a goal its user had stopped (a review).
        self._plan_end = ""
        self._abort_by = ""  # what aborted the running job (see _plan_end); "" a newer job
        self._worker: threading.Thread | None = None
        self._job = "idle"
        self._progress = (0, 0)
        self._level = OK
        self._message = "waiting for a plan or /cmd_vel"
        self._last_twist: Twist | None = None
        self._last_twist_t = 0.0
        # the last Twist was a non-finite one, taken as a stop: a stop, but no release of the
        # stick (a glitch in a stream held through an e-stop armed /cmd_vel, and it drove)
        self._twist_glitch = False
        # the /cmd_vel move last refused, the grid it was refused on and whether the grid
        # node was heard then (see _cmd_vel_tick)
        self._twist_refused: tuple[str, Grid | None, bool] | None = None
        # a move has been sent (ACKed) since this node started: from then on, set_pose_on_plan
        # may not move the controller's pose out of the cell it reports
        self._moved = False
        self._link_note = ""
        self._entering: tuple[int, int] | None = None  # destination of the running command
        self._job_grid: Grid | None = None  # the grid the running job's cells were read on
        # the action of the /cmd_vel step last started; None once /cmd_vel went stale
        self._twist_running: str | None = None
        # False from an e-stop until /cmd_vel has been zero or silent: a stream that went on
        # through the e-stop drove the chair the moment it was cleared. False at start too,
        # until a zero Twist or STARTUP_QUIET_S without one (see there).
        self._twist_armed = False
        self._disarmed_why = "it was already moving when the drive started"  # for the warning
        self._started_mono = time.monotonic()
        self._last_tick_mono = self._ticks_on_time_since = self._started_mono

        pub = self.create_publisher
        self.pub_state = pub(DiagnosticArray, "wheelgrid/drive_state", RELIABLE_QOS)
        self.pub_cmds = pub(String, "wheelgrid/drive_commands", RELIABLE_QOS)
        self.pub_pose = pub(PoseStamped, "wheelgrid/chair_pose", RELIABLE_QOS)
        self.create_subscription(OccupancyGrid, "wheelgrid/safe_grid", self._on_grid, MAP_QOS)
        # Volatile, not the topic's transient-local: the plan the topic keeps for late joiners
        # (RViz, the monitor) is one made before this node started, and a restarted drive
        # node, its e-stop latch gone with it, drove it where the chair still stood at its
        # start. The publication-time check in _on_plan alone failed when the wall clock had
        # stepped back since (NTP): a volatile reader is never sent a plan of before.
        self._plan_sub = self.create_subscription(
            Path, "wheelgrid/plan", with_message_info(self._on_plan), PLAN_QOS
        )
        self.create_subscription(Twist, "cmd_vel", with_message_info(self._on_twist), RELIABLE_QOS)

        try:
            check_no_undeclared(self)
            check_config(c)
            self.link = MotorLink(
                c.port,
                c.baud,
                reply_timeout=c.reply_timeout,
                retries=c.retries,
                heartbeat_period=c.heartbeat_period,
                reconnect_period=c.reconnect_period,
                on_status=self._on_status,
                on_event=self._on_link_event,
            )
        except ValueError as exc:  # as the other nodes: one FATAL line, exit 2
            self.get_logger().fatal(f"invalid parameters: {exc}")
            raise SystemExit(2) from exc
        if not c.port:
            self._set_state(ERROR, "no port parameter: cannot reach the motor controller")
        else:
            try:
                self.link.open()
            except LinkError as exc:
                self._set_state(ERROR, f"{exc}; retrying")
            self.link.start_heartbeat()  # also reconnects a port that is not there yet
        # The /cmd_vel watchdog measures staleness on the monotonic clock, and its timers run
        # on steady time too: on the node's clock, use_sim_time (a Nav2 simulation's ``/**``)
        # stopped them whenever /clock paused, and a step drove on with no /cmd_vel. The
        # state too: with no /clock it was never published, and no launcher saw the drive.
        steady_timer(self, 0.05, self._cmd_vel_tick)
        steady_timer(self, 1.0 / max(c.state_rate, 0.1), self._publish_state)

        estop = side_node(self, "estop")  # a remapped e-stop topic still applies to it
        estop.create_subscription(
            Bool, "wheelgrid/estop", with_message_info(self._on_estop_message), RELIABLE_QOS
        )
        # A best-effort e-stop publisher (a joystick, a safety bridge on sensor-data QoS)
        # matches no reliable subscription: it was never heard. This one hears it, and may
        # only latch: a clear must come reliably (a lost clear keeps the chair stopped, a lost
        # e-stop would not). A reliable publisher reaches both; the second copy is a no-op.
        estop.create_subscription(
            Bool, "wheelgrid/estop", with_message_info(self._on_estop_best_effort), SENSOR_QOS
        )
        # A latched e-stop source (reliable + transient-local, as a safety bridge or a button
        # keeps its state): the two above are volatile and never hear the state it kept from
        # before this node started, and an e-stop held through a (re)start was ignored while
        # the chair drove. This third copy hears it on matching; it may only latch.
        estop.create_subscription(
            Bool,
            "wheelgrid/estop",
            with_message_info(self._on_estop_latched),
            MAP_QOS,
            event_callbacks=volatile_writers_expected(),
        )
        # The grid node's heartbeat, on this thread too: a silence stops the chair even while
        # the node's executor is held up.
        estop.create_subscription(
            DiagnosticArray, GRID_STATE_TOPIC, self._on_grid_state, RELIABLE_QOS
        )
        steady_timer(estop, 0.05, self._cmd_vel_guard)
        steady_timer(estop, 0.1, self._grid_state_guard)
        self._estop_side: SideSpinner | None = SideSpinner(estop, "drive-estop", self._spin_estop)

    def _spin_estop(self, executor: Any) -> None:
        """The e-stop thread. Should its executor ever fail, nothing could stop the chair from
        ROS any more: it stops it and latches the e-stop for good."""
        try:
            executor.spin()
        except ExternalShutdownException:
            pass  # Ctrl-C or rclpy.shutdown(): close() stops the chair
        except Exception as exc:
            if not self.context.ok():
                # the same shutdown, caught as the executor built its wait set (RCLError
                # "context is not valid"): a clean Ctrl-C logged "e-stop thread failed" on 1
                # of 10 runs (a review); close() stops the chair
                return
            self._estop_failed = True
            self._latch_estop()
            self._set_state(ERROR, f"e-stop thread failed ({exc!r}): chair stopped for good")

    # ---- state reporting ----------------------------------------------------------------------

    def _set_state(self, level: bytes, message: str) -> None:
        with self._lock:
            self._level, self._message = level, message
        # One call site per severity: rclpy refuses a call site that changes severity. The
        # state changes as the node stops too (a plan aborted by shutdown): not to /rosout then.
        logger = exit_logger(self)
        if level == OK:
            logger.info(message)
        elif level == WARN:
            logger.warning(message)
        else:
            logger.error(message)
        self._publish_state(level, message)

    def _publish_state(self, level: bytes | None = None, message: str | None = None) -> None:
        """Publish the state; a caller's own (level, message) wins over a newer one, so no
        event is lost when another thread sets the next state in between."""
        with self._lock:
            job, (done, total) = self._job, self._progress
            if level is None or message is None:
                level, message = self._level, self._message
        st = self.link.last_status
        s = self.link.stats
        values = {
            "connected": str(self.link.connected).lower(),
            "estop": str(self._estop).lower(),
            "job": job,
            "plan_end": self._plan_end,
            "step": str(done),
            "steps": str(total),
            "speed_kmh": f"{self.speed:g}",
            "link_note": self._link_note,
            "sent": str(s.sent),
            "retries": str(s.retries),
            "timeouts": str(s.timeouts),
            "garbled": str(s.garbled),
            "unexpected": str(s.unexpected),
            "disconnects": str(s.disconnects),
            "reconnects": str(s.reconnects),
            # planners this node's plan reader has matched: read volatile, a plan published
            # before the match is never received, so whoever sends the goal (the demo) waits
            # for this rather than for the reader to appear in its own graph (a loaded machine
            # matched the planner later than that, and the demo's route was never driven)
            "plan_publishers": str(self._plan_sub.get_publisher_count()),
        }
        silent = self.link.silent_for() if self.link.connected else 0.0
        # heartbeats go every heartbeat_period, each tried twice: silent longer than three
        # periods and one heartbeat's two tries (0.5 s: about two heartbeats lost in a row) is
        # a controller that no longer answers (a dead firmware, a cut RX wire), whose last
        # pose is no longer the chair's
        deaf = silent > SILENT_HEARTBEATS * self.cfg.heartbeat_period + 2 * self.cfg.reply_timeout
        if self.link.connected:
            values["status_age_s"] = f"{silent:.2f}"
        if st is not None and not deaf:
            values.update(
                x=f"{st.x:.3f}",
                y=f"{st.y:.3f}",
                yaw=f"{st.yaw:.3f}",
                state=st.state.name,
                result=st.result.name,
            )
        # "<job>: <last event>", e.g. "idle: plan done: 9/9 steps" -- the job first, so a
        # monitor can tell at a glance whether the chair is being driven.
        message = f"{job}: {message}"
        if not self.link.connected and self.cfg.port:
            level, message = ERROR, f"motor controller port {self.cfg.port} not connected"
        elif self.link.stop_owed:
            level, message = (
                ERROR,
                "a STOP went unacknowledged: the link is silent so that the controller's "
                "watchdog stops the motors",
            )
        elif deaf:
            # an open port said OK with 19 heartbeats unanswered, and the last pose as current
            level, message = (
                ERROR,
                f"motor controller not answering for {silent:.1f} s on {self.cfg.port}",
            )
        elif self._estop_failed:
            level, message = (
                ERROR,
                "e-stop thread failed: chair stopped for good (restart the node)",
            )
        elif self._estop:
            level, message = (
                ERROR,
                f"e-stop latched (publish false on {self.resolve_topic_name('wheelgrid/estop')} to "
                "clear)",
            )
        status = DiagnosticStatus(
            level=level,
            name="wheelgrid/drive",
            message=message,
            hardware_id=self.cfg.port or "none",
            values=[KeyValue(key=k, value=v) for k, v in values.items()],
        )
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [status]
        self._publish(self.pub_state, msg)

    def _on_status(self, st: proto.Status) -> None:
        """The controller's pose, in the frame of the grid it is a place on: the plan's cells
        set and check it there (a fixed "map" was ignored by the planner, and misplaced in
        RViz, whenever the map frame has another name)."""
        grid = self._job_grid or self._grid
        msg = PoseStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = grid.frame_id if grid is not None else "map"
        msg.pose.position.x, msg.pose.position.y = float(st.x), float(st.y)
        msg.pose.orientation.z = math.sin(st.yaw / 2.0)
        msg.pose.orientation.w = math.cos(st.yaw / 2.0)
        self._publish(self.pub_pose, msg)

    def _on_link_event(self, kind: str, message: str) -> None:
        if kind == "timeout":
            return
        if kind in ("vanished", "reconnected"):
            # A controller that comes back is one powering on: nothing under way resumes
            # (serial-protocol.md, host duty 5). A joystick held through the unplug drove the
            # chair 1.5 m off the reopened port, 50 ms after its STOP; it must go zero (or
            # silent) first, as after an e-stop.
            self._disarm_cmd_vel("it went on through a loss of the controller's link")
        self._link_note = f"{kind}: {message}"
        logger = exit_logger(self)  # close() stops the chair after the context is shut down
        if kind in ("vanished", "stop", "nak", "garbled", "unexpected"):
            logger.warning(self._link_note)
        elif kind == "heartbeat":  # ten a second from a controller that does not answer
            logger.warning(self._link_note, throttle_duration_sec=HEARTBEAT_LOG_PERIOD_S)
        elif kind == "reconnected":
            logger.info(self._link_note)

    def _publish_record(self, rec: dict[str, Any]) -> None:
        if "seq" in rec:  # a move the controller took: the chair has moved
            self._moved = True
        self._publish(self.pub_cmds, String(data=dumps_record(rec)))

    def _publish(self, pub: Any, msg: Any) -> None:
        """Publish from any thread; after shutdown the threads' last words are only logged."""
        if not self.context.ok():
            return
        try:
            pub.publish(msg)
        except Exception as exc:  # context shut down between the check and the call
            exit_logger(self).debug(f"publish after shutdown dropped: {exc}")

    # ---- inputs -------------------------------------------------------------------------------

    def _on_grid(self, msg: OccupancyGrid) -> None:
        try:
            grid = from_occupancy_grid(msg)
            if problem := chair_cell_problem(grid.resolution):
                raise ValueError(f"{problem}; {CHAIR_GRID_HINT}")
            # a cell the controller cannot cross in one move: every step failed in pack_move
            if problem := proto.move_length_problem(grid.resolution, "the grid's cell size"):
                raise ValueError(problem)
        except ValueError as exc:
            self._grid = None  # a broken grid is no grid: every cell check now refuses
            self._set_state(ERROR, f"bad safe grid: {exc}")
            self._abort_if_moving("no valid safe grid")
            return
        self._grid = grid
        job_grid = self._job_grid
        if self._busy() and job_grid is not None and not same_geometry(grid, job_grid):
            # the running move's cells are other places on this grid: stop, never re-read them
            self._abort_if_moving(
                "the safe grid's size, resolution, origin or frame changed", by="planner"
            )
        with self._gate:
            pending, self._pending_plan = self._pending_plan, None
        if pending is not None:
            waited = (time.time_ns() - pending[1].received_ns) / 1e9
            if waited > PARKED_PLAN_MAX_S:
                self._set_state(
                    WARN,
                    f"plan dropped: it waited {waited:.0f} s for the safe grid (more than "
                    f"{PARKED_PLAN_MAX_S:g} s); send the goal again",
                )
            elif not self._busy():
                self._plan_arrived(*pending)
            else:  # the move a bad grid stopped is still ending: never queued behind it
                self._set_state(
                    WARN,
                    "plan dropped: the chair was still stopping when the safe grid came; "
                    "send the goal again",
                )
        dst = self._entering
        if dst is not None and self._busy():
            reason = grid_cell_check(lambda: grid)(dst)
            if reason:
                # The map changed under a running move (someone stepped in): stop now.
                # (the planner withdraws a route through it and plans another)
                self._abort_if_moving(f"the cell being entered changed: {reason}", by="planner")

    def _abort_if_moving(self, why: str, by: str = "fault") -> None:
        """Stop the running job for ``why``; ``by``: who ended it, as _plan_end says."""
        if self._busy():
            self._abort_by = by
            self._abort.set()
            self.link.stop()
            self._set_state(ERROR, f"chair stopped: {why}")

    def _on_estop_message(self, msg: Bool, info: dict[str, Any] | None) -> None:
        """The reliable e-stop subscription's callback. (``info`` has no default: rclpy passes
        it only to callbacks that need two arguments.)"""
        key = sample_key(info)
        if key is not None:
            if key in self._estop_samples:  # the latched copy latched it first
                return
            self._estop_samples.append(key)
        self._handle_estop(msg, info)

    def _handle_estop(self, msg: Bool, info: dict[str, Any] | None) -> None:
        """Both e-stop subscriptions end here: whatever goes wrong, it must not end the e-stop
        thread."""
        try:
            self._on_estop(msg, received_ns(info))
        except Exception as exc:
            if msg.data:  # latch it and stop the chair, whatever else failed
                self._latch_estop(received_ns(info))
            self.get_logger().error(f"e-stop handling failed: {exc!r}; chair stopped")

    def _on_estop_best_effort(self, msg: Bool, info: dict[str, Any] | None) -> None:
        # The copy of a sample the reliable subscription has served is not a new e-stop: the
        # executor may serve it after the clear that followed it, which it undid (the chair
        # stayed stopped behind an e-stop the user had cleared).
        if msg.data and not self._estop and sample_key(info) not in self._estop_samples:
            self._handle_estop(msg, info)

    def _on_estop_latched(self, msg: Bool, info: dict[str, Any] | None) -> None:
        # The kept state of a transient-local source, or a live sample's third copy: it may
        # latch, never clear (a clear reaches the reliable subscription), and a sample either
        # reliable subscription served is not handled again.
        key = sample_key(info)
        if msg.data and not self._estop and key not in self._estop_samples:
            if key is not None:
                self._estop_samples.append(key)
            self._handle_estop(msg, info)

    def _latch_estop(self, received: int = 0) -> None:
        """Latch the e-stop, drop what it must not let run, and send STOP now (never queued
        behind the worker). ``received``: when the e-stop reached this process, if known."""
        with self._gate:
            self._estop = True
            self._twist_armed = False
            self._disarmed_why = "it went on through the e-stop"
            self._estops += 1
            stamp = received or time.time_ns()
            self._estop_received_ns = max(self._estop_received_ns, stamp)
            self._pending_plan = None  # a plan parked for the grid must not drive after it
            self._abort_by = "user"
            self._abort.set()
        self.link.stop()

    def _on_estop(self, msg: Bool, received: int = 0) -> None:
        if msg.data:
            self._latch_estop(received)
            self._set_state(ERROR, "e-stop: chair stopped")
        elif self._estop:
            with self._gate:
                self._estop = False
            self._set_state(OK, "e-stop cleared (nothing resumes by itself)")

    def _on_plan(self, msg: Path, info: dict[str, Any] | None) -> None:
        published = received_ns(info, "source_timestamp")
        if msg.poses and 0 < published < self._started_ns:
            # A second guard behind the volatile subscription (an RMW that sent a volatile
            # reader the kept plan all the same): nothing made before this node is driven.
            self._set_state(
                WARN,
                f"plan refused: published {(self._started_ns - published) / 1e9:.1f} s before "
                "this drive started (the topic's kept plan); send the goal again",
            )
            return
        self._plan_arrived(msg, Arrival(received_ns(info) or time.time_ns(), self._estops))

    def _estop_since(self, arrival: Arrival) -> bool:
        """Whether an e-stop came after ``arrival`` (call with the gate held)."""
        return self._estops != arrival.estops or self._estop_received_ns >= arrival.received_ns

    def _plan_arrived(self, msg: Path, arrival: Arrival) -> None:
        if self._estop and msg.poses:  # not even parked: nothing resumes after a clear
            with self._gate:
                self._pending_plan = None
            self._set_state(ERROR, "plan refused: e-stop latched")
            return
        if len(msg.poses) > MAX_PATH_POSES:
            # a route across a building is a few hundred cells; more is a broken publisher, and
            # reading it would hold this executor (and an e-stop behind it) for seconds. As
            # every newer plan does, it voids one parked for the grid (that one drove once the
            # grid came).
            with self._gate:
                self._pending_plan = None
            self._stop_job()
            self._set_state(
                ERROR, f"plan refused: {len(msg.poses)} poses, more than {MAX_PATH_POSES}"
            )
            return
        if self._grid is None and msg.poses:
            # A plan and the latched grid arrive in any order at start-up: keep the plan until
            # the grid is here (it is checked against it then), never run it unchecked.
            with self._gate:
                parked = not self._estop_since(arrival)
                if parked:
                    self._pending_plan = (msg, arrival)
            if parked:
                self._set_state(OK, "plan waiting for the safe grid")
            else:
                self._set_state(ERROR, "plan refused: an e-stop came while it was read")
            return
        with self._gate:
            self._pending_plan = None
        if not msg.poses:
            # The planner's "no route" (a goal refused or unreachable, a pose in no known
            # frame): the chair stops, as ordered; no fault of the drive's, so not an ERROR.
            self._stop_job()
            if not self._estop:  # a latched e-stop stays what the state says
                self._set_state(WARN, "no route: chair stopped (the planner's log says why)")
            return
        try:
            steps, cells, grid = self._steps_from_path(msg)
        except ValueError as exc:
            self._stop_job()
            self._set_state(ERROR, f"plan refused: {exc}")
            return
        if self._estop:
            self._set_state(ERROR, "plan refused: e-stop latched")
            return
        if not steps:
            self._stop_job()
            self._set_state(OK, "plan has no moves: nothing to do")
            return
        if not self._start_job(
            "plan", lambda abort: self._run_plan(steps, cells, grid, abort), arrival
        ):
            self._set_state(ERROR, "plan refused: an e-stop came while it was read")

    def _steps_from_path(self, msg: Path) -> tuple[list[actions.Step], list[tuple[int, int]], Grid]:
        """The plan's steps and cells, and the grid they were read on (the run is checked
        against that grid's geometry). ``msg`` has poses: _plan_arrived takes an empty path
        as the planner's "no route" before it gets here."""
        grid = self._grid
        if grid is None:
            raise ValueError("no safe grid received yet")
        frame = msg.header.frame_id or msg.poses[0].header.frame_id
        if frame and frame != grid.frame_id:
            raise ValueError(f"path frame {frame!r} is not the grid frame {grid.frame_id!r}")
        for i, p in enumerate(msg.poses):  # each pose may name its own frame (no tf here)
            if p.header.frame_id and p.header.frame_id != grid.frame_id:
                raise ValueError(
                    f"path pose {i} is in frame {p.header.frame_id!r}, not the grid's "
                    f"{grid.frame_id!r}"
                )
        pts = [(p.pose.position.x, p.pose.position.y) for p in msg.poses]
        cells = cells_from_points(grid, pts)
        heading = self.cfg.initial_heading.strip().lower()
        if heading == "auto":
            q = msg.poses[0].pose.orientation
            # normalised first (a scaled quaternion read as another yaw by the unit formula)
            try:
                yaw = quat_yaw(float(q.x), float(q.y), float(q.z), float(q.w))
            except ValueError:
                raise ValueError("the path's first pose has a zero quaternion") from None
            if not math.isfinite(yaw):
                raise ValueError("the path's first pose has a non-finite quaternion")
            heading = actions.heading_from_yaw(yaw, grid.origin[2])
        moves = actions.moves_from_cells(cells)
        return actions.plan_steps(cells[0], moves, heading), cells, grid

    def _on_twist(self, msg: Twist, info: dict[str, Any] | None) -> None:
        original = msg
        if not all(math.isfinite(v) for v in (msg.linear.x, msg.angular.z)):
            # inf drove full speed, NaN turned: a commander this broken gets a stop
            self.get_logger().warning(
                f"/cmd_vel with a non-finite value ({msg.linear.x}, {msg.angular.z}) taken as "
                "a stop",
                throttle_duration_sec=2.0,
            )
            msg = Twist()
        self._twist_glitch = msg is not original
        # Its age counts from when it reached this process, not from now: Twists that came
        # while the executor was held up (a long plan read, an old job joined) were read as
        # fresh afterwards, and the chair drove a step on a stream that had already ended.
        # A wall clock stepped forward since makes it older (a stop), never younger.
        received = received_ns(info)
        age_s = max(0.0, (time.time_ns() - received) / 1e9) if received else 0.0
        self._last_twist = msg
        self._last_twist_t = time.monotonic() - age_s

    # ---- jobs ---------------------------------------------------------------------------------

    def _busy(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def _stop_job(self) -> None:
        if self._busy():
            self._abort.set()
            self.link.stop()
            assert self._worker is not None
            self._worker.join(timeout=5.0)

    def _start_job(
        self, name: str, fn: Callable[[threading.Event], None], arrival: Arrival | None = None
    ) -> bool:
        """Start ``fn`` in the worker thread unless an e-stop is latched, or came after the
        input's ``arrival``; return whether it started."""
        self._stop_job()
        with self._gate:  # an e-stop may have come while we waited for the old job
            if self._estop or (arrival is not None and self._estop_since(arrival)):
                return False
            abort = threading.Event()
            self._abort = abort
            self._abort_by = ""
            with self._lock:
                self._job = name

        def body() -> None:
            try:
                fn(abort)
            except Exception as exc:  # never leave the chair moving after a bug
                self.link.stop()
                if name == "plan":
                    self._plan_end = "fault"
                self._set_state(ERROR, f"{name} failed: {exc!r}; chair stopped")
            finally:
                with self._lock:
                    self._job = "idle"

        self._worker = threading.Thread(target=body, name=f"drive-{name}", daemon=True)
        self._worker.start()
        return True

    def _run_plan(
        self,
        steps: list[actions.Step],
        cells: list[tuple[int, int]],
        grid: Grid,
        abort: threading.Event,
    ) -> None:
        self._job_grid = grid
        total = len(steps)
        with self._lock:
            self._progress = (0, total)
        connection = self.link.connection  # before the start checks ask the controller
        try:
            st = self.link.status()
            if st.moving:
                self.link.stop()
                raise LinkError("controller reports a move in progress")
            if self.cfg.set_pose_on_plan:
                if self._moved and grid.cell_of(st.x, st.y) != tuple(cells[0]):
                    # a plan re-sent after the chair drove on: the chair is not where the
                    # pose would be set, and its moves would be driven from elsewhere
                    raise ValueError(
                        f"set_pose_on_plan: the controller reports the chair in cell "
                        f"{grid.cell_of(st.x, st.y)}, not the plan's start {cells[0]}, and it "
                        "has moved since this drive started: its pose is not overwritten"
                    )
                x, y = grid.cell_center(*cells[0])
                yaw = actions.YAW[steps[0].heading] + grid.origin[2]
                self.link.set_pose(float(x), float(y), yaw)
                st = self.link.status()
            if self.cfg.check_start_pose:
                self._check_start(grid, st, cells[0], steps[0].heading)
        except (LinkError, ValueError) as exc:
            self._plan_end = "fault"
            self._set_state(ERROR, f"plan refused: {exc}")
            return
        if abort.is_set():  # an e-stop or a newer job came while the controller was asked
            self._plan_end = self._abort_by or "planner"
            return
        self._set_state(OK, f"driving a plan of {total} step(s) from {cells[0]}")

        def on_step(step: actions.Step, rec: dict[str, Any]) -> None:
            self._publish_record(rec)
            if rec["ack"] == "ACK":
                with self._lock:
                    self._progress = (self._progress[0] + 1, total)

        result: RunResult = run_steps(
            self.link,
            steps,
            distance_m=grid.resolution,
            speed_kmh=self.speed,
            cell_check=self._cell_check(grid),
            abort=abort,
            on_step=on_step,
            on_start=self._on_step_start,
            step_length=controller_step_length(self.link, grid, self.cfg.pose_tolerance)
            if self.cfg.check_start_pose
            else None,
            connection=connection,
        )
        self._entering = None
        if result.ok and self.cfg.check_start_pose:
            short = self._end_problem(grid, cells[-1])
            if short:
                self._plan_end = "fault"
                self._set_state(ERROR, f"plan ended short of its goal: {short}")
                return
        if result.ok:
            self._plan_end = "done"
            self._set_state(OK, f"plan done: {result.done}/{result.total} steps")
        elif result.aborted:
            self._plan_end = self._abort_by or "planner"  # no one named: a newer plan or path
            self._set_state(WARN if not self._estop else ERROR, f"plan aborted: {result.error}")
        else:
            self._plan_end = "fault"
            self._set_state(ERROR, f"plan stopped at step {result.done + 1}: {result.error}")

    def _end_problem(self, grid: Grid, goal: tuple[int, int]) -> str | None:
        """Where the controller says the chair ended, if not within ``pose_tolerance`` of the
        goal cell's centre: a move reported DONE short of its cell (a slipping wheel) was
        "plan done", level OK, on the last step, which no next step's check reads."""
        try:
            st = self.link.status()
        except LinkError as exc:
            return f"no controller pose after the last step: {exc}"
        return off_centre_problem(grid, st.x, st.y, goal, self.cfg.pose_tolerance)

    def _on_step_start(self, step: actions.Step) -> None:
        self._entering = step.dst

    @staticmethod
    def _check_start(grid: Grid, st: proto.Status, cell: tuple[int, int], heading: str) -> None:
        r, c = grid.cell_of(st.x, st.y)
        if (r, c) != tuple(cell):
            raise ValueError(
                f"controller pose ({st.x:.2f}, {st.y:.2f}) is in cell {(r, c)}, "
                f"the plan starts at {cell}"
            )
        here = actions.heading_from_yaw(st.yaw, grid.origin[2])
        if here != heading:
            raise ValueError(f"chair faces {here}, the plan assumes {heading}")

    # ---- /cmd_vel -----------------------------------------------------------------------------

    def _disarm_cmd_vel(self, why: str) -> None:
        """/cmd_vel drives again only after a release; ``why`` is said when it is ignored."""
        with self._gate:
            self._twist_armed = False
            self._disarmed_why = why

    def _arm_if_quiet(self) -> None:
        """/cmd_vel is silent: it may drive again, unless an e-stop is latched or the node is
        too young to have heard a stream already running, or its executor was held up too
        recently for Twists waiting unread to have been read (TICK_LATE_S). Under the gate:
        an e-stop latched between reading ``_estop`` and writing the flag was undone by the
        write."""
        now = time.monotonic()
        settled = (
            now - self._started_mono >= STARTUP_QUIET_S
            and now - self._ticks_on_time_since >= self.cfg.cmd_vel_timeout
        )
        with self._gate:
            self._twist_armed = settled and not self._estop

    def _cmd_vel_tick(self) -> None:
        now = time.monotonic()
        if now - self._last_tick_mono > TICK_LATE_S:
            self._ticks_on_time_since = now  # held up: what came meanwhile is still unread
        self._last_tick_mono = now
        twist = self._last_twist
        if twist is None:
            self._arm_if_quiet()
            return
        if self._twist_stale():
            self._last_twist = None
            self._twist_refused = None  # silence is a release: the next push is asked again
            self._arm_if_quiet()
            if self._twist_running is not None:
                self._twist_running = None
                with self._gate:  # the job and its abort event, as _start_job sets them
                    taken_over = self._job not in ("cmd_vel", "idle")
                    abort = self._abort
                # Only a /cmd_vel step ends with its stream (idle: the e-stop thread's guard
                # stopped it already): a plan that took over from one was stopped here once
                # the joystick fell silent, mid-route.
                if not taken_over:
                    abort.set()
                    self.link.stop()
                    self._set_state(WARN, "no /cmd_vel for too long: chair stopped")
            return
        if self._estop:
            return
        action = self._twist_action(twist)
        moved = action is not None or not self._twist_released(twist)
        if moved:
            with self._gate:  # the stick overrides a plan still waiting for its grid
                self._pending_plan = None
            if self._busy() and self._job == "plan":
                # The stick moved while a plan ran: ignored, it drove the chair the instant
                # the plan ended (two cells backwards, the stick never released). It stops
                # the plan now, armed or not, and drives only after a release.
                self._disarm_cmd_vel("it moved while a plan ran, which it stopped")
                self._abort_if_moving(
                    "/cmd_vel moved while a plan ran (the stick overrides a plan; release it, "
                    "then send the goal again or drive by hand)",
                    by="user",
                )
                return
        if not self._twist_armed:
            if moved:
                self.get_logger().warning(
                    f"/cmd_vel ignored: {self._disarmed_why}; send a zero Twist (or none for "
                    f"{max(self.cfg.cmd_vel_timeout, STARTUP_QUIET_S):g} s) to drive with it",
                    throttle_duration_sec=2.0,
                )
                return
            with self._gate:  # a zero Twist: armed, unless an e-stop came meanwhile
                self._twist_armed = not self._estop
            if not self._twist_armed:
                return
        if self._busy():
            # a released stick leaves a plan alone (a moved one stopped it above); a /cmd_vel
            # step stops at zero velocity or another direction (the joystick reversed), not at
            # the end of the cell, and the next tick starts the new direction
            if self._job != "plan" and action != self._twist_running:
                self._abort.set()
                self.link.stop()
            return
        if action is None:
            # the step is over and the stick let go: nothing is running for the watchdog to
            # stop (it sent a STOP and said "no /cmd_vel for too long" after every release)
            self._twist_running = None
            self._twist_refused = None
            return
        refused = self._twist_refused
        if (
            refused is not None
            and refused[0] == action
            and refused[1] is self._grid  # the same grid object (a Grid's == compares arrays)
            and refused[2] == (self._grid_silence() is None)
        ):
            return  # refused as things stand: asked again for another move, grid or grid state
        self._twist_running = action
        if not self._start_job("cmd_vel", lambda abort: self._run_twist_step(action, twist, abort)):
            self._twist_running = None

    def _refuse_twist(self, action: str, grid: Grid | None) -> None:
        """Not asked again while the stick holds ``action`` and the grid and its node's state
        stay as they are; the step is over (nothing for the watchdog to stop)."""
        self._twist_refused = (action, grid, self._grid_silence() is None)
        self._twist_running = None

    def _twist_stale(self) -> bool:
        return time.monotonic() - self._last_twist_t > self.cfg.cmd_vel_timeout

    def _on_grid_state(self, msg: DiagnosticArray) -> None:
        stalled = busy = 0.0
        for status in msg.status[:1]:
            for kv in status.values:
                try:
                    if kv.key == "stalled_s":
                        stalled = float(kv.value)
                    elif kv.key == "busy_s":
                        busy = float(kv.value)
                except ValueError:
                    pass  # an unreadable figure is no evidence either way
        self._grid_state = (stalled, busy)
        self._grid_state_heard = time.monotonic()

    def _grid_silence(self) -> str | None:
        """Why no step may start now on the grid node's say, else None: it went silent (dead,
        or stopped), its executor has not run for ``grid_state_timeout`` outside a grid or a
        save (hung), or one grid or save has taken over GRID_BUSY_MAX_S (stuck in it)."""
        heard, timeout = self._grid_state_heard, self.cfg.grid_state_timeout
        if heard is None or timeout <= 0.0:
            return None  # never heard: a static grid (map_server, a test) has no heartbeat
        stale = "its grid may be stale (newer maps go ungridded)"
        silent = time.monotonic() - heard
        if silent > timeout:
            return f"the grid node has been silent for {silent:.1f} s: {stale}"
        stalled, busy = self._grid_state
        if busy > GRID_BUSY_MAX_S:
            return f"the grid node has been computing one grid for {busy:.0f} s: {stale}"
        if busy == 0.0 and stalled > timeout:
            return f"the grid node's executor has not run for {stalled:.1f} s (hung): {stale}"
        return None

    def _grid_state_guard(self) -> None:
        """On the e-stop thread: a running move stops when the grid node goes silent."""
        why = self._grid_silence()
        if why is not None:
            self._abort_if_moving(why)

    def _cell_check(self, planned_on: Grid) -> Callable[[tuple[int, int]], str | None]:
        """The check of each step's cell: the grid node alive, then the cell free on the
        latest grid of the geometry the job was planned on."""
        on_grid = planned_grid_check(lambda: self._grid, planned_on)

        def check(cell: tuple[int, int]) -> str | None:
            return self._grid_silence() or on_grid(cell)

        return check

    def _cmd_vel_guard(self) -> None:
        """On the e-stop thread: a /cmd_vel step whose stream went stale is stopped even while
        the executor is held up (reading a long plan), where _cmd_vel_tick cannot run and the
        step would go on blind. The tick does the rest (state, bookkeeping) when it runs."""
        if not self._twist_stale():
            return
        with self._gate:  # the job and its abort event, as _start_job sets them together
            if self._twist_running is None or self._job != "cmd_vel":
                return
            abort = self._abort
        if not abort.is_set():
            abort.set()
            self.link.stop()

    def _twist_action(self, t: Twist) -> str | None:
        """The Table II move of a Twist, or None: no move (released, or one Table II has not).

        A turn is a quarter turn and then a cell forward, so it needs forward speed: a turn
        with none (Nav2's spin, a stick twisted in place) drove a loop of cells, and one with
        the stick pulled back drove forward into the cell on that side. Those are no move."""
        turn = abs(t.angular.z) > self.cfg.angular_deadband
        if t.linear.x > self.cfg.linear_deadband:
            if turn:
                return "LEFT_FORWARD" if t.angular.z > 0 else "RIGHT_FORWARD"
            return "FORWARD"
        if t.linear.x < -self.cfg.linear_deadband and not turn:
            return "BACKWARD"
        if turn or t.linear.x < -self.cfg.linear_deadband:
            self.get_logger().warning(
                f"/cmd_vel ({t.linear.x:g} m/s, {t.angular.z:g} rad/s) is no move the chair "
                "makes (a turn needs forward speed: Table II turns drive forward): chair stays",
                throttle_duration_sec=2.0,
            )
        return None

    def _twist_released(self, t: Twist) -> bool:
        """A finite Twist inside both deadbands: the stick let go (what arms /cmd_vel)."""
        return (
            not self._twist_glitch
            and abs(t.linear.x) <= self.cfg.linear_deadband
            and abs(t.angular.z) <= self.cfg.angular_deadband
        )

    def _run_twist_step(self, action: str, twist: Twist, abort: threading.Event) -> None:
        grid = self._grid
        self._job_grid = grid
        connection = self.link.connection  # before the checks ask the controller
        try:
            st = self.link.status()
            if grid is None:
                raise ValueError("no safe grid: cannot check the cell ahead")
            heading = actions.heading_from_yaw(st.yaw, grid.origin[2])
            here = grid.cell_of(st.x, st.y)
            move = {
                "FORWARD": heading,
                "BACKWARD": actions.opposite(heading),
                "LEFT_FORWARD": actions.turn_left(heading),
                "RIGHT_FORWARD": actions.turn_right(heading),
            }[action]
            (step,) = actions.plan_steps(here, [move], heading)
            distance, problem = step_to_centre(
                grid, st.x, st.y, st.yaw, step, self.cfg.pose_tolerance
            )
            if problem:
                raise ValueError(problem)
        except (LinkError, ValueError) as exc:
            if isinstance(exc, LinkError):  # no controller: not a step a tick later either
                self._disarm_cmd_vel("the controller's link failed under it")
            else:  # a stick held against it asked again every 50 ms: 45 refusals in 2 s
                self._refuse_twist(action, grid)
            self._set_state(ERROR, f"/cmd_vel {action} refused: {exc}")
            self._publish_record(
                {"action": action, "ack": "REFUSED", "reason": str(exc), "t": time.time()}
            )
            return
        speed = min(self.speed, max(abs(twist.linear.x) * 3.6, 0.5))
        result = run_steps(
            self.link,
            [step],
            distance_m=distance,
            speed_kmh=speed,
            cell_check=self._cell_check(grid),
            abort=abort,
            on_step=lambda s, rec: self._publish_record(rec),
            on_start=self._on_step_start,
            connection=connection,
        )
        self._entering = None
        if result.ok:  # its own word: the state read "cmd_vel: plan done" after a plan
            self._set_state(OK, f"/cmd_vel {action}: in cell {step.dst}")
        if not result.ok and not result.aborted:
            if not result.refused:  # the link failed under the step: as a loss of it
                self._disarm_cmd_vel("the controller's link failed under it")
            else:
                self._refuse_twist(action, grid)
            self._set_state(ERROR, f"/cmd_vel {action}: {result.error}")

    # ---- shutdown -----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the chair and the threads; called by spin_node on shutdown."""
        self._abort.set()
        self.link.stop()
        if self._worker is not None:
            self._worker.join(timeout=3.0)
        self.link.close(stop=True)
        side = getattr(self, "_estop_side", None)
        if side is not None:
            side.close()
            self._estop_side = None


def main(argv: list[str] | None = None) -> int:
    return spin_node(lambda: DriveNode(), args=argv)


if __name__ == "__main__":
    sys.exit(main())
