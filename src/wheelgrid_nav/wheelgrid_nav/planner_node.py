"""The planner node: safe grid + start pose + goal pose -> a verified route as nav_msgs/Path.

Subscribes ``/wheelgrid/safe_grid`` (OccupancyGrid, MAP_QOS), ``/goal_pose`` (PoseStamped,
as RViz's 2D Goal Pose sends), and the start from ``/wheelgrid/odometry`` (Odometry),
``/initialpose`` (PoseWithCovarianceStamped) or ``/wheelgrid/chair_pose`` (PoseStamped, the
drive's controller pose) -- whichever arrived last, the chair's pose counting only once it
has moved (it is published at every heartbeat, and would otherwise undo an /initialpose at
once). Without it a second goal, sent after the chair drove, was planned from the first
goal's start, and the drive refused that route. Publishes
``/wheelgrid/plan`` (Path through cell centres, orientation = direction of travel into each
cell; the start cell carries the heading planned from; MAP_QOS) and
``/wheelgrid/plan_markers`` (MarkerArray of arrows, MAP_QOS).

All the planning is in :mod:`wheelgrid_nav.planner`; this module only translates messages.
Safety rules: whenever there is no verified route (unreachable goal, start or goal not free,
training not converged, pose in an unknown frame) an EMPTY Path is published, so a drive that
follows the old route stops, and the goal is dropped. A new grid that blocks any cell of the
current route (or changes the grid's geometry) triggers a replan from the newest start.

A goal lives from its ``/goal_pose`` until the chair stands in its cell, an e-stop, a new goal,
or a planning attempt that finds no route. A goal kept past either of the last two moved the
chair with no command: one refused while the map was still growing was planned to at a later
grid change, minutes on, and a goal reached long ago was planned back to from wherever the
user had driven the chair since, the next time the grid changed under the old route. So the
only goal ever planned to is one the user sent and that has neither failed nor been reached;
send it again after a "no route". A new goal in another cell withdraws the route to the old
one (an empty path) before its own is learned: the drive went on toward the replaced goal for
as long as the learning took.

An e-stop (``/wheelgrid/estop`` true) drops the goal and publishes an empty path, and goals
are refused until it is cleared: nothing the planner does after a clear moves the chair until
a new goal comes. E-stops that arrive while a route is learned are read before it is
published, and a route learned across one is not published.

Parameter ``method`` defaults to ``qlearning-heading`` (the paper uses plain ``qlearning``):
the node always knows the chair's heading from its pose, and costing turns and backing up the
way the chair really drives them picks, among equally short routes, the one with the fewest
manoeuvres -- fewer stops and turns for the person in the chair. Its route is verified against
Dijkstra over (cell, heading) on the same grid.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from wheelgrid_common.fileio import quat_yaw
from wheelgrid_common.frames import CONVENTIONS, convention_for_frame
from wheelgrid_common.map_io import (
    CHAIR_GRID_HINT,
    Grid,
    chair_cell_problem,
    from_occupancy_grid,
    same_geometry,
)
from wheelgrid_common.params import check_no_undeclared, declare_dataclass
from wheelgrid_common.params import field as pfield
from wheelgrid_common.ros_env import sample_key, spin_node, steady_timer, with_message_info
from wheelgrid_nav.actions import cells_to_moves
from wheelgrid_nav.planner import METHODS, PlanInputError, PlannerConfig, check_config, plan

# grid direction -> angle in the grid's own frame (x = col + 1 = "right", y = row - 1 = "up")
_DIR_ANGLE = {"right": 0.0, "up": math.pi / 2, "left": math.pi, "down": -math.pi / 2}
# The chair's pose moves the start only when the chair has moved by this much: the controller's
# dead reckoning at rest stays put, and an /initialpose given since must stand.
CHAIR_MOVED_M = 0.01
CHAIR_TURNED_RAD = math.radians(1.0)
# The route's progress moves on to the chair's cell only within this many cells of it (the
# next cell, and one more should a pose between them be lost): a pose further on is no step
# along the route.
ROUTE_STEP_CELLS = 2
# The drive refuses a chair turned more than this from its plan's start heading
# (wheelgrid_drive.actions.heading_from_yaw): a route for a guessed heading is refused there.
HEADING_TOLERANCE_RAD = math.radians(20.0)
# The drive's state (5 Hz by default) counts as current this long: a drive that died while
# driving must not keep a goal sent again from being planned.
DRIVE_STATE_FRESH_S = 2.0
# A route out this long that the drive (heard, fresh) is not driving was stopped or refused
# there: the drive takes a plan within milliseconds and reports at 5 Hz.
ROUTE_TAKEN_S = 2.0


@dataclass
class PlannerNodeConfig:
    """Node-only settings (the learner's settings are PlannerConfig's, declared alongside)."""

    method: str = pfield(
        "qlearning-heading",
        "qlearning (the paper: cells only) or qlearning-heading (turns/backing up cost extra)",
    )
    goal_wait_s: float = pfield(
        10.0,
        "a goal sent before the first safe grid or start pose is planned if they come within "
        "this time, else dropped (kept, it was planned whenever they came, minutes later, and "
        "the chair set off with no command)",
        "s",
    )
    odometry_convention: str = pfield(
        "auto",
        "axes of the odometry start pose's child frame: auto (REP-103: a frame named "
        "*_optical or *_optical_frame looks along +z, any other along +x, as the mapper reads "
        "it), optical or body; set it as the mapper's mapper.sensor_convention where that is set",
    )
    odometry_max_age_s: float = pfield(
        2.0,
        "a start pose from /wheelgrid/odometry received longer ago than this is as none (the "
        "chair stops, the goal waits goal_wait_s for a fresh start): the mapper publishes a "
        "pose for each frame it maps and none while it is lost or stopped, so an old one is "
        "where the chair was; 0 = no limit (/initialpose and the chair's pose do not age)",
        "s",
    )


def heading_from_yaw(yaw: float, grid_yaw: float) -> str:
    """The grid direction closest to a map-frame yaw, taking the grid's origin yaw into account."""
    rel = yaw - grid_yaw
    return min(_DIR_ANGLE, key=lambda d: abs(math.remainder(rel - _DIR_ANGLE[d], 2 * math.pi)))


def pose_problem(pose: Any) -> str | None:
    """Why a geometry_msgs Pose cannot place the chair or its goal, or None. A NaN position
    falls outside every grid, but a NaN or zero quaternion used to give a heading all the
    same (the first direction tried, or +x), and the route's Table II actions follow it."""
    p, q = pose.position, pose.orientation
    values = [float(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w)]
    if not all(math.isfinite(v) for v in values):
        return "a NaN or infinite coordinate"
    if math.hypot(*values[3:]) < 1e-6:
        return "a zero quaternion"
    return None


def forward_yaw(q: Any, child_frame: str = "", convention: str = "auto") -> float:
    """Map-frame yaw of a pose's forward axis, projected onto the floor.

    Optical frames (the iPhone odometry's child frame) look along +z, body frames (RViz poses)
    along +x, by the mapper's own rule (:func:`convention_for_frame`): the planner read only
    ``*_optical_frame`` as optical, and a mapper's ``camera_optical`` poses as 90 deg off. The
    quaternion is normalised first: the unit formula read a 90 deg yaw at a third of unit
    length as 5.6 deg.
    """
    axis = 2 if convention_for_frame(child_frame, convention) == "optical" else 0
    return quat_yaw(float(q.x), float(q.y), float(q.z), float(q.w), axis)


def _quat_from_yaw(yaw: float) -> tuple[float, float]:
    return math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def path_poses(
    grid: Grid, cells: list[tuple[int, int]], start_heading: str | None = None
) -> list[tuple[float, float, float]]:
    """(x, y, yaw) per route cell: the cell centre, and yaw = the direction of travel into it.

    The start cell gets the heading the route was planned from (``start_heading``, a grid
    direction), so a follower (the drive's ``initial_heading: auto``) converts the first move
    with the chair's real heading, as in Table II where (2,0)->(2,1) facing down is
    left-forward; without it the start cell takes the first move's direction.
    """
    if not cells:
        return []
    xy = grid.cell_center(np.array([c[0] for c in cells]), np.array([c[1] for c in cells]))
    moves = cells_to_moves(cells)
    dirs = [start_heading or (moves[0] if moves else "right"), *moves]
    return [
        (
            float(xy[i, 0]),
            float(xy[i, 1]),
            math.remainder(grid.origin[2] + _DIR_ANGLE[dirs[i]], 2 * math.pi),
        )
        for i in range(len(cells))
    ]


def _make_node_class() -> type:
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from nav_msgs.msg import OccupancyGrid, Odometry, Path
    from rclpy.node import Node
    from std_msgs.msg import Bool
    from visualization_msgs.msg import Marker, MarkerArray

    from wheelgrid_common.qos import (
        MAP_QOS,
        RELIABLE_QOS,
        SENSOR_QOS,
        volatile_writers_expected,
    )

    class PlannerNode(Node):
        """Thin ROS wrapper around :func:`wheelgrid_nav.planner.plan`."""

        def __init__(self, **kwargs: Any) -> None:
            super().__init__("planner", **kwargs)
            try:  # a wrongly typed value comes out of declare_dataclass as ValueError too
                self.node_cfg = declare_dataclass(self, PlannerNodeConfig())
                self.cfg = declare_dataclass(self, PlannerConfig())
                check_no_undeclared(self)
                check_config(self.cfg, self.node_cfg.method)
            except ValueError as exc:  # PlanInputError included
                self.get_logger().fatal(f"bad planner parameters: {exc}")
                raise SystemExit(2) from None
            wait = self.node_cfg.goal_wait_s
            if not (math.isfinite(wait) and wait > 0):
                self.get_logger().fatal(f"goal_wait_s must be > 0 s, not {wait}")
                raise SystemExit(2)
            age = self.node_cfg.odometry_max_age_s
            if not (math.isfinite(age) and age >= 0):
                self.get_logger().fatal(f"odometry_max_age_s must be >= 0 s, not {age}")
                raise SystemExit(2)
            if self.node_cfg.odometry_convention not in CONVENTIONS:
                self.get_logger().fatal(
                    f"odometry_convention must be one of {', '.join(CONVENTIONS)}, not "
                    f"{self.node_cfg.odometry_convention!r}"
                )
                raise SystemExit(2)
            if self.node_cfg.method not in METHODS:
                self.get_logger().fatal(
                    f"unknown method {self.node_cfg.method!r} (use {' or '.join(METHODS)})"
                )
                raise SystemExit(2)
            self.grid: Grid | None = None
            self.start: tuple[float, float, float] | None = None  # x, y, yaw in map
            self.goal: tuple[float, float] | None = None
            # monotonic time a goal began to wait for the first grid or start (None: planned)
            self._goal_waits_since: float | None = None
            # the frames start and goal were given in ("" = the grid's): a grid that comes in
            # another frame must not turn their coordinates into cells
            self.start_frame = ""
            self.goal_frame = ""
            # monotonic time the start came from /wheelgrid/odometry (None: it came from
            # /initialpose or the chair's pose, which do not age)
            self._start_from_odometry_at: float | None = None
            # the frame of the odometry last refused since the last one used (None: none was)
            self._odometry_refused: str | None = None
            self.route: list[tuple[int, int]] = []
            self._route_at = 0  # the route's cell the chair has got to (_advance_on_route)
            self.plans = 0  # planning attempts (for tests and diagnostics)
            self.path_pub = self.create_publisher(Path, "wheelgrid/plan", MAP_QOS)
            self.marker_pub = self.create_publisher(MarkerArray, "wheelgrid/plan_markers", MAP_QOS)
            self._grid_sub = self.create_subscription(
                OccupancyGrid, "wheelgrid/safe_grid", self._on_grid, MAP_QOS
            )
            self._goal_sub = self.create_subscription(
                PoseStamped, "goal_pose", self._on_goal, RELIABLE_QOS
            )
            # while the inputs that waited behind a learning are read, they plan nothing: the
            # learning's end decides whether to publish its route or plan again
            self._draining = False
            self._odom_sub = self.create_subscription(
                Odometry, "wheelgrid/odometry", self._on_odom, SENSOR_QOS
            )
            self.create_subscription(
                PoseWithCovarianceStamped, "initialpose", self._on_initialpose, RELIABLE_QOS
            )
            self.create_subscription(
                PoseStamped, "wheelgrid/chair_pose", self._on_chair_pose, RELIABLE_QOS
            )
            self._last_chair: tuple[float, float, float] | None = None
            # whether the drive is driving a plan (its state's job, and when that was heard):
            # the same goal sent again leaves a route being driven alone
            # the drive's job, when it was heard and its state's message
            self._drive_job: tuple[str, float, str] = ("", -math.inf, "")
            # when the oldest route the drive has not driven since went out (None: it drives
            # the newest, or none went out): replans (each grid of another size, the map
            # growing) send a route anew, and counted from each new one a drive that took
            # none was sent one again for ever (a review: a refused route)
            self._untaken_since: float | None = None
            self.create_subscription(
                DiagnosticArray, "wheelgrid/drive_state", self._on_drive_state, RELIABLE_QOS
            )
            # An e-stop ends the goal: cleared, the chair drove on to it at the next grid change
            # (the map grows during a scan) with no new command. A goal during one is refused.
            self._estop = False
            self._estop_presses = 0  # e-stops (true) received: a route learned across one is void
            self._estop_sub = self.create_subscription(
                Bool, "wheelgrid/estop", with_message_info(self._on_estop_reliable), RELIABLE_QOS
            )
            # A latched source's kept state (reliable + transient-local) reaches only a
            # transient-local reader: an e-stop held before this node started was ignored and
            # the goal planned. This copy may only latch; each sample is handled once.
            self._estop_seen: deque[tuple[int, int]] = deque(maxlen=64)
            self._estop_latched_sub = self.create_subscription(
                Bool,
                "wheelgrid/estop",
                with_message_info(self._on_estop_latched),
                MAP_QOS,
                event_callbacks=volatile_writers_expected(),
            )
            # An e-stop published best-effort (a joystick, a safety bridge) matches neither
            # subscription above: the drive latched it, the planner kept the goal, and the
            # next grid sent the chair on to it after the clear (a review). This copy latches
            # only, as the latched one does.
            self._estop_best_effort_sub = self.create_subscription(
                Bool, "wheelgrid/estop", with_message_info(self._on_estop_latched), SENSOR_QOS
            )
            steady_timer(self, 0.5, self._drop_goal_waited_too_long)
            steady_timer(self, 0.5, self._drop_goal_of_a_silent_drive)
            self.get_logger().info(f"planner ready (method {self.node_cfg.method})")

        # ---- inputs ---------------------------------------------------------------------
        def _frame_ok(self, frame: str, what: str) -> bool:
            expected = self.grid.frame_id if self.grid is not None else "map"
            if frame and frame != expected:
                self.get_logger().warning(
                    f"{what} is in frame {frame!r}, the grid in {expected!r}: ignored (no tf)",
                    throttle_duration_sec=2.0,  # odometry at 100 Hz in another frame
                )
                return False
            return True

        def _on_grid(self, msg: Any) -> None:
            try:
                grid = from_occupancy_grid(msg)
            except ValueError as exc:
                self.get_logger().error(f"bad safe grid ignored: {exc}")
                return
            if problem := chair_cell_problem(grid.resolution):
                # no route on it, nor on the grid before it: that one is no longer the map's.
                # The goal goes too: kept, the next good grid planned it and the chair drove
                # on with no command (a review)
                self.get_logger().error(f"safe grid refused: {problem}; {CHAIR_GRID_HINT}")
                self.grid = None
                if self.route or self.goal is not None:
                    self._no_route(grid, "safe grid refused")
                return
            old = self.grid
            self.grid = grid
            if self.goal is None or self.start is None:
                return
            if why := self._drive_left_the_route():
                self._no_route(grid, why)
                return
            # the route's cells are only indices of the old grid: read on a smaller new one
            # they raised IndexError and ended the node
            if not self.route or not same_geometry(grid, old):
                if self.route:
                    # Withdrawn at once, as for a closed cell (the drive stops its move at a
                    # grid of another geometry anyway): kept, it stayed the plan for the whole
                    # learning, through a cell the new grid had closed (a review).
                    self.get_logger().info(
                        "safe grid changed its size or origin under the route: the route is "
                        "withdrawn (an empty path) while a new one is learned"
                    )
                    self._publish_route(grid, [])
                else:
                    self.get_logger().info("safe grid changed under the route: replanning")
                self._plan()
            elif self._route_blocked(grid, self._route_ahead(grid)):
                # Withdrawn at once: the route through the closed cell stayed the plan for
                # as long as the new one was learned (seconds). Only the cells still ahead
                # count: one driven over going unknown (the chair's own trace, a person
                # behind it) replanned, and the drive stopped a move for nothing.
                self.get_logger().info(
                    "safe grid closed a cell ahead on the route: the route is withdrawn (an "
                    "empty path) while a new one is learned"
                )
                self._publish_route(grid, [])
                self._plan()

        def _route_ahead(self, grid: Grid) -> list[tuple[int, int]]:
            """The route from the chair's cell on, counted from where the chair has got to
            along it (all of that where the chair is off it). A pose further on than the
            next few cells (a stray pose, a relocalisation) moves no progress: it counts for
            this check alone, as every pose did before progress was kept."""
            self._advance_on_route(grid)
            ahead = self.route[self._route_at :]
            here = grid.cell_of(self.start[0], self.start[1]) if self.start else None
            return ahead[ahead.index(here) :] if here in ahead else ahead

        def _advance_on_route(self, grid: Grid | None) -> None:
            """Moves the route's progress on to the chair's cell where it is the cell of the
            progress or one of the next ROUTE_STEP_CELLS. Taken from the route's start, a
            route that comes back through a cell (a three-point turn into a side pocket) kept
            the pocket, already left, ahead of the chair, and a grid closing it stopped the
            chair for nothing (a review). Any cell further on: one stray pose at the far leg
            of a U-shaped route passed the cells between for good, and a cell closing there
            withdrew nothing (a review)."""
            if grid is None or self.start is None or not self.route:
                return
            here = grid.cell_of(self.start[0], self.start[1])
            near = self.route[self._route_at : self._route_at + ROUTE_STEP_CELLS + 1]
            if here in near:
                self._route_at += near.index(here)

        def _route_blocked(self, grid: Grid, route: list[tuple[int, int]]) -> bool:
            """Whether ``grid`` (same geometry as the route's) closes a cell of ``route``, by
            the rule the route was planned under: its first cell, the chair's own, may be
            unknown (``allow_unknown_start``). Judged "not free" like the rest, an unknown start
            cell replanned at every new grid (each map update), and the drive stopped the
            running move for the same route sent again."""
            (r0, c0), rest = route[0], route[1:]
            first = int(grid.data[r0, c0])
            first_ok = first == 0 or (self.cfg.allow_unknown_start and first < 0)
            return not first_ok or any(grid.data[r, c] != 0 for r, c in rest)

        def _first_time(self, info: dict[str, Any] | None) -> bool:
            """Whether no e-stop subscription handled this sample before (a latched source's
            live samples reach both)."""
            key = sample_key(info)
            if key is None:
                return True
            if key in self._estop_seen:
                return False
            self._estop_seen.append(key)
            return True

        def _on_estop_reliable(self, msg: Any, info: dict[str, Any] | None) -> None:
            if self._first_time(info):
                self._on_estop(msg)

        def _on_estop_latched(self, msg: Any, info: dict[str, Any] | None) -> None:
            if msg.data and not self._estop and self._first_time(info):
                self._on_estop(msg)

        def _on_estop(self, msg: Any) -> None:
            if not msg.data:
                if self._estop:
                    self.get_logger().info("e-stop cleared: send a new goal to drive on")
                self._estop = False
                return
            self._estop = True
            self._estop_presses += 1
            if self.goal is not None:
                self.get_logger().warning("e-stop: goal dropped; publishing an empty path")
                self.goal = None
                self._publish_route(self.grid, [])

        def _on_goal(self, msg: Any) -> None:
            if self._estop:
                self.get_logger().warning("goal refused: e-stop latched; publishing an empty path")
                self.goal = None
                self._publish_route(self.grid, [])
                return
            if not self._frame_ok(msg.header.frame_id, "goal"):
                self.goal = None  # refused: a later start or grid must not plan to the old one
                self._publish_route(None, [])
                return
            problem = pose_problem(msg.pose)
            if problem:  # the chair stops: an empty path, as for an unreachable goal
                self.get_logger().warning(f"goal refused: {problem}; publishing an empty path")
                self.goal = None
                self._publish_route(self.grid, [])
                return
            goal = (float(msg.pose.position.x), float(msg.pose.position.y))
            same = self._same_goal_cell(goal, msg.header.frame_id)
            if same and (self._draining or (self.route and self._drive_runs_a_plan())):
                # RViz's goal tool pressed again while the chair drives there: relearned, the
                # same route went out anew and the drive stopped its running move for it
                # (mid-turn, the heading check then refused the route and dropped the goal).
                # Where the drive is not driving it (it refused or dropped the plan, and says
                # "send the goal again"), the goal is planned again from where the chair is.
                self.get_logger().info(
                    f"goal {goal} again: the drive is on its way there; the route stands"
                )
                return
            if self.route and not self._same_goal_cell(goal, msg.header.frame_id):
                # The route to the goal of before is withdrawn while the new one is learned
                # (up to max_seconds): kept, the drive went on toward a goal the user had
                # just replaced, for as long as the learning took.
                self.get_logger().info(
                    "new goal: the route to the previous one is withdrawn (an empty path) "
                    "while the new one is learned"
                )
                self._publish_route(self.grid, [])
            self.goal = goal
            self.goal_frame = msg.header.frame_id
            self._untaken_since = None  # the user's own goal: its routes counted anew
            self._goal_waits_since = None
            if self._say_what_the_goal_waits_for():
                self._goal_waits_since = time.monotonic()
            self._plan()

        def _on_drive_state(self, msg: Any) -> None:
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                if "job" not in values:
                    continue
                was = self._drive_job[0]
                job = values["job"]
                self._drive_job = (job, time.monotonic(), str(status.message))
                if job == "plan":
                    self._untaken_since = None
                elif (
                    was == "plan"
                    and values.get("plan_end", "") in ("user", "fault", "")
                    and (self.route or self.goal is not None)
                ):
                    # the stick, an e-stop, a refusal or a fault ended it, or a drive that
                    # never ended a plan ("": restarted) now speaks: sent again at the next
                    # grid (the map growing), the chair drove 4.8 m on to a goal its user had
                    # stopped (a review); "done" and the planner's own withdrawals ("planner")
                    # keep the goal
                    self._no_route(self.grid, f"the drive stopped the route ({status.message})")

        def _drop_goal_of_a_silent_drive(self) -> None:
            """A drive last heard driving the route that falls silent (stopped, killed) ends
            the goal: the planner sent the route again at every grid meanwhile, and a drive
            restarted on the port drove it 4.8 m with no command (a review)."""
            job, heard, _ = self._drive_job
            if job != "plan" or time.monotonic() - heard <= DRIVE_STATE_FRESH_S:
                return
            self._drive_job = ("", heard, "")  # said once
            if self.route or self.goal is not None:
                self._no_route(self.grid, "the drive went silent while it drove the route")

        def _drive_left_the_route(self) -> str | None:
            """Why the route held is no longer the drive's, or None: a drive is heard, it is
            not driving a plan, and the route went out long enough ago for it to have taken
            it. The drive stopped it (the controller went silent, a step refused, an e-stop
            it heard first) or refused it, and says "send the goal again"; replanned at the
            next grid change (the map growing), the chair set off with no command (a
            review: 3 s after an ERROR, and after a grid of too small cells)."""
            job, heard, said = self._drive_job
            now = time.monotonic()
            if not self.route or not job or now - heard > DRIVE_STATE_FRESH_S:
                return None
            since = self._untaken_since
            if job == "plan" or since is None or now - since < ROUTE_TAKEN_S:
                return None
            return f"the drive is not driving the route ({said})"

        def _drive_runs_a_plan(self) -> bool:
            job, heard, _ = self._drive_job
            return job == "plan" and time.monotonic() - heard <= DRIVE_STATE_FRESH_S

        def _same_goal_cell(self, goal: tuple[float, float], frame: str) -> bool:
            """Whether ``goal`` lies in the cell of the goal being planned or driven to: a goal
            sent again keeps its route (a second press of RViz's tool must not stop the
            chair)."""
            if self.goal is None or self.grid is None or frame != self.goal_frame:
                return False
            return self.grid.cell_of(*goal) == self.grid.cell_of(*self.goal)

        def _missing_for_a_goal(self) -> list[str]:
            missing = []
            if self.grid is None:
                missing.append(f"safe grid on {self.resolve_topic_name('wheelgrid/safe_grid')}")
            stale = self._stale_start()
            if self.start is None or stale:
                starts = [
                    self.resolve_topic_name(t)
                    for t in ("initialpose", "wheelgrid/odometry", "wheelgrid/chair_pose")
                ]
                missing.append(
                    f"start pose ({starts[0]}, {starts[1]}, or {starts[2]} once the chair moves"
                    + (f"; {stale}" if stale else "")
                    + ")"
                )
            return missing

        def _say_what_the_goal_waits_for(self) -> bool:
            """Name what a goal that cannot be planned yet waits for (True where it waits): it
            got no path and no word, and the chair set off when the first grid or start came,
            maybe minutes on."""
            missing = self._missing_for_a_goal()
            if missing:
                self.get_logger().warning(
                    f"goal kept, not planned yet: no {' and no '.join(missing)}; it is planned "
                    f"if that comes within goal_wait_s ({self.node_cfg.goal_wait_s:g} s), "
                    "else dropped"
                )
            return bool(missing)

        def _drop_goal_waited_too_long(self) -> None:
            """A goal still waiting for the first grid or start after ``goal_wait_s`` ends:
            planned whenever they came, the chair set off minutes after its goal, with no
            command, as a goal with no route once did (both are dropped, said, and the chair
            stopped with an empty path)."""
            since = self._goal_waits_since
            if since is None or self.goal is None:
                return
            if time.monotonic() - since < self.node_cfg.goal_wait_s:
                return
            self._goal_waits_since = None
            missing = self._missing_for_a_goal()
            self._no_route(
                self.grid,
                f"goal not planned within goal_wait_s ({self.node_cfg.goal_wait_s:g} s): "
                f"still no {' and no '.join(missing) or 'grid or start'}",
            )

        def _set_start(self, pose: Any, frame: str, child: str, convention: str = "auto") -> bool:
            if not self._frame_ok(frame, "start pose"):
                return False
            problem = pose_problem(pose)
            if problem:
                self.get_logger().warning(
                    f"start pose ignored: {problem}", throttle_duration_sec=2.0
                )
                return False
            self.start = (
                float(pose.position.x),
                float(pose.position.y),
                forward_yaw(pose.orientation, child, convention),
            )
            self.start_frame = frame
            self._start_from_odometry_at = None  # the odometry's own call sets it after this
            self._advance_on_route(self.grid)  # at every pose: a grid may come cells later
            self._drop_if_reached()
            return True

        def _drop_if_reached(self) -> None:
            """Forget the goal once the chair stands in its cell. Nothing is published: the
            drive finishes its last move to the cell's centre on its own."""
            grid = self.grid
            if grid is None or self.goal is None or self.start is None:
                return
            if {self.start_frame, self.goal_frame} - {"", grid.frame_id}:
                return  # _plan says why it cannot place them
            here = grid.cell_of(self.start[0], self.start[1])
            if here == grid.cell_of(self.goal[0], self.goal[1]):
                self.get_logger().info(f"goal {here} reached: goal done")
                self.goal = None

        def _follow_start(
            self,
            pose: Any,
            frame: str,
            child: str,
            convention: str = "auto",
            from_odometry: bool = False,
        ) -> None:
            """A start from a stream (odometry, the chair's pose): planned from at once only
            when it is the first start and a goal waits; later ones move the start that the
            next goal or grid change plans from."""
            had_start = self.start is not None
            started = self._set_start(pose, frame, child, convention)
            if started and from_odometry:
                self._start_from_odometry_at = time.monotonic()
                self._odometry_refused = None
            # a goal waits for it: the first start, or one that had gone stale
            waits = not had_start or self._goal_waits_since is not None
            if started and waits and self.goal is not None:
                self._plan()

        def _on_odom(self, msg: Any) -> None:
            at = self._start_from_odometry_at
            self._follow_start(
                msg.pose.pose,
                msg.header.frame_id,
                msg.child_frame_id,
                self.node_cfg.odometry_convention,
                from_odometry=True,
            )
            if self._start_from_odometry_at == at:  # refused: its frame, or a bad pose
                self._odometry_refused = msg.header.frame_id

        def _stale_start(self) -> str:
            """Why the start cannot be planned from now, or "": one from the mapper's odometry
            that has not come again for odometry_max_age_s. The mapper publishes no pose while
            it is lost (relocalising) or stopped; before, the planner planned from the last
            one, wherever the chair had gone since, and only the drive's pose check (30 cm)
            stood between that route and the chair. Such a start is as none: a goal waits
            for a fresh one (goal_wait_s)."""
            limit, at = self.node_cfg.odometry_max_age_s, self._start_from_odometry_at
            if limit <= 0 or at is None:
                return ""
            age = time.monotonic() - at
            if age <= limit:
                return ""
            topic = self.resolve_topic_name("wheelgrid/odometry")
            why = "the mapper has placed no frame since (lost, or stopped)"
            if self._odometry_refused is not None:
                grid_frame = self.grid.frame_id if self.grid is not None else "map"
                why = (
                    f"poses come but are not used (in frame {self._odometry_refused!r} where "
                    f"the grid is in {grid_frame!r}: no tf; or a NaN pose)"
                )
            return (
                f"the start pose from {topic} is {age:.1f} s old (odometry_max_age_s {limit:g}): "
                + why
            )

        def _on_chair_pose(self, msg: Any) -> None:
            pose = msg.pose
            if pose_problem(pose):
                return  # _set_start would say so at every heartbeat; the drive reports it
            now = (
                float(pose.position.x),
                float(pose.position.y),
                forward_yaw(pose.orientation, ""),
            )
            ref = self._last_chair
            if ref is None:
                # The first pose only sets the reference: the controller's power-on pose is no
                # place the user chose, and it may arrive after their /initialpose.
                self._last_chair = now
                return
            # Measured from the pose last counted, not the last heartbeat's: a chair creeping a
            # few millimetres a heartbeat would otherwise never have moved.
            moved = (
                math.hypot(now[0] - ref[0], now[1] - ref[1]) >= CHAIR_MOVED_M
                or abs(math.remainder(now[2] - ref[2], math.tau)) >= CHAIR_TURNED_RAD
            )
            if moved:
                self._last_chair = now
                self._follow_start(pose, msg.header.frame_id, "")

        def _on_initialpose(self, msg: Any) -> None:
            # an explicit start from the user (RViz 2D Pose Estimate): plan from it at once
            if self._set_start(msg.pose.pose, msg.header.frame_id, "") and self.goal is not None:
                self._plan()

        # ---- planning -------------------------------------------------------------------
        def _plan(self) -> None:
            # Learned again in a loop while a goal or grid that came during a learning voids
            # it: called from itself, the stack grew for as long as grids came faster than
            # one learning took (a review: eleven deep in 20 s).
            while self._plan_once():
                pass

        def _plan_once(self) -> bool:
            """Plan once; True where what came while the route was learned voids it and it
            must be learned again."""
            if self._draining:  # an input read after a learning: judged once it is done
                return False
            if self.grid is None or self.start is None or self.goal is None:
                return False
            stale = self._stale_start()
            if stale:
                # Where the chair is, is not known now: it stops (an empty path), and the goal
                # waits for a fresh start, as for a first one (goal_wait_s). Dropped at once,
                # a goal judged just before an /initialpose in the same executor pass was
                # lost, and the pose then planned nothing (the demo's sequence, a review).
                if self._goal_waits_since is None:  # (a new goal has said so already)
                    self._goal_waits_since = time.monotonic()
                    self.get_logger().warning(
                        f"{stale}; publishing an empty path; the goal waits up to goal_wait_s "
                        f"({self.node_cfg.goal_wait_s:g} s) for a start pose"
                    )
                self._publish_route(self.grid, [])
                return False
            self._goal_waits_since = None  # planned (or refused) now: it waits no more
            grid = self.grid
            for what, frame in (("start", self.start_frame), ("goal", self.goal_frame)):
                if frame and frame != grid.frame_id:
                    self._no_route(
                        grid,
                        f"the grid is in frame {grid.frame_id!r}, the {what} in {frame!r}: "
                        "no route (no tf)",
                    )
                    return False
            self.plans += 1
            start = grid.cell_of(self.start[0], self.start[1])
            goal = grid.cell_of(self.goal[0], self.goal[1])
            heading = heading_from_yaw(self.start[2], grid.origin[2])
            off = math.remainder(self.start[2] - grid.origin[2] - _DIR_ANGLE[heading], math.tau)
            if abs(off) > HEADING_TOLERANCE_RAD:
                # 45 deg went to "right" by a tie: a route was published and the drive refused it
                self._no_route(
                    grid,
                    f"no route: the chair's heading is {math.degrees(abs(off)):.0f} deg off the "
                    f"grid's nearest direction ({heading}), more than "
                    f"{math.degrees(HEADING_TOLERANCE_RAD):.0f}: which way each move turns is "
                    "a guess; turn the chair along the grid",
                )
                return False
            method = self.node_cfg.method
            try:
                res = plan(grid.data, start, goal, self.cfg, method=method, heading=heading)
            except PlanInputError as exc:
                self._no_route(grid, f"no route: {exc}")
                return False
            if not res.ok:
                self._no_route(grid, f"no route from {start} to {goal}: {res.reason}")
                return False
            presses, goal_before = self._estop_presses, self.goal
            self._draining = True
            try:
                self._take_waiting_estops()
                # the odometry that came meanwhile, first: a replan for a goal or grid read
                # here judged the start's age by the last pose read before the learning, and
                # a learning over odometry_max_age_s stopped the chair (a review, 2.8 s)
                self._take_waiting(self._odom_sub, self._on_odom)
                self._take_waiting(self._goal_sub, self._on_goal)
                self._take_waiting(self._grid_sub, self._on_grid)
            except Exception as exc:  # rclpy's take_message is not public API: fail safe
                self.get_logger().error(
                    f"cannot read the inputs that came while the route was learned ({exc!r}); "
                    "route not published, an empty path instead; goal dropped, send it again"
                )
                self.goal = None
                self._publish_route(grid, [])
                return False
            finally:
                self._draining = False
            if self._estop_presses != presses:
                # the e-stop has dropped the goal and published an empty path: this route
                # leads to the goal of before it
                self.get_logger().warning("route learned across an e-stop: not published")
                if self.goal is not None:
                    # A goal read with the e-stop's inputs: whether it came before or after
                    # the clear is lost (each topic is read in turn). Kept, it waited with no
                    # word and no timer, and the next grid planned it, the chair setting off
                    # with no command (a review: 18 s on). Dropped, said: send it again.
                    self._no_route(
                        grid,
                        "a goal came while a route was learned across an e-stop: not planned "
                        "(whether it came before or after the clear is not known)",
                    )
                return False
            if self.goal != goal_before:
                # a new goal came while this one was learned (or was refused, and published
                # its empty path): the route to the old goal went out after it, and stayed
                # the plan while the new one was learned
                self.get_logger().info("a new goal came while the route was learned: replanning")
                return self.goal is not None
            if self.grid is not grid:
                newest = self.grid
                if not same_geometry(newest, grid) or self._route_blocked(newest, res.cells):
                    # a route through a cell the newest grid closes went out before the replan
                    self.get_logger().info(
                        "the safe grid changed under the route while it was learned: replanning"
                    )
                    return True
                grid = newest
            self.get_logger().info(
                f"route {start} -> {goal} facing {heading}: {len(res.moves)} moves "
                f"({res.episodes} episodes, {res.seconds * 1000:.0f} ms)"
            )
            self._publish_route(grid, res.cells, heading)
            self._drop_if_reached()  # a goal in the chair's own cell: a one-cell route, done
            return False

        def _no_route(self, grid: Grid | None, why: str) -> None:
            """The chair stops (an empty path) and the goal is dropped: kept, it was planned
            to at whatever later grid change let a route through, with no command."""
            dropped = "; goal dropped, send it again" if self.goal is not None else ""
            self.get_logger().warning(f"{why}; publishing an empty path{dropped}")
            self.goal = None
            self._publish_route(grid, [])

        def _take_waiting(self, sub: Any, handler: Any, with_info: bool = False) -> None:
            """Hand ``handler`` the messages waiting on ``sub`` (see _take_waiting_estops),
            and their info where it takes it."""
            with sub.handle:
                while True:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    if taken is None:
                        return
                    handler(*taken) if with_info else handler(taken[0])

        def _take_waiting_estops(self) -> None:
            """Handle the e-stops that arrived while a route was learned, before it goes out.

            The learning holds this node's executor for up to ``max_seconds``: an e-stop
            pressed and released meanwhile waited behind it, the route to the goal of before
            the press was published after the drive had seen the release (and it drove it with
            no new command), and only then came the e-stop's empty path. ``take_message`` is
            what rclpy's own executor calls, but not public API: where it fails, the caller
            publishes no route rather than one an e-stop may have voided.

            All three subscriptions' samples are handled in the order they were published: a
            best-effort press read after the reliable clear that followed it latched the
            planner after the user's clear, and the route learned across it went out first (a
            review)."""
            waiting: list[tuple[Any, Any, dict[str, Any] | None]] = []
            for sub, handler in (
                (self._estop_sub, self._on_estop_reliable),
                (self._estop_latched_sub, self._on_estop_latched),
                (self._estop_best_effort_sub, self._on_estop_latched),
            ):
                self._take_waiting(sub, lambda msg, info, h=handler: waiting.append((h, msg, info)),
                                   with_info=True)  # fmt: skip
            # (a sample without a publication time goes first: no time to order it by)
            waiting.sort(key=lambda w: sample_key(w[2]) or (0, 0))
            for handler, msg, info in waiting:
                handler(msg, info)

        def _publish_route(
            self, grid: Grid | None, cells: list[tuple[int, int]], heading: str | None = None
        ) -> None:
            self.route = list(cells)
            self._route_at = 0
            if cells and self._untaken_since is None:
                self._untaken_since = time.monotonic()
            stamp = self.get_clock().now().to_msg()
            frame = grid.frame_id if grid is not None else "map"
            path = Path()
            path.header.frame_id = frame
            path.header.stamp = stamp
            poses = path_poses(grid, cells, heading) if grid is not None else []
            for x, y, yaw in poses:
                ps = PoseStamped()
                ps.header = path.header
                ps.pose.position.x, ps.pose.position.y = x, y
                ps.pose.orientation.z, ps.pose.orientation.w = _quat_from_yaw(yaw)
                path.poses.append(ps)
            self.path_pub.publish(path)
            markers = MarkerArray()
            clear = Marker()
            clear.header = path.header
            clear.ns = "wheelgrid_plan"
            clear.action = Marker.DELETEALL
            markers.markers.append(clear)
            res = grid.resolution if grid is not None else 1.0
            for i in range(len(poses) - 1):
                m = Marker()
                m.header = path.header
                m.ns, m.id = "wheelgrid_plan", i
                m.type, m.action = Marker.ARROW, Marker.ADD
                for x, y, _ in poses[i : i + 2]:
                    m.points.append(_point(x, y, 0.05))
                m.pose.orientation.w = 1.0
                m.scale.x, m.scale.y, m.scale.z = 0.08 * res, 0.25 * res, 0.3 * res
                m.color.r, m.color.g, m.color.b, m.color.a = 0.1, 0.3, 0.9, 1.0
                markers.markers.append(m)
            self.marker_pub.publish(markers)

    def _point(x: float, y: float, z: float) -> Any:
        from geometry_msgs.msg import Point

        return Point(x=x, y=y, z=z)

    return PlannerNode


def make_node(**kwargs: Any) -> Any:
    """Build the planner node (after rclpy.init); kwargs go to rclpy's Node (context, ...)."""
    return _make_node_class()(**kwargs)


def main(argv: list[str] | None = None) -> None:
    sys.exit(spin_node(make_node, argv))


if __name__ == "__main__":
    main()
