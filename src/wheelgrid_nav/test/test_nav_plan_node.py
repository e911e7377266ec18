"""The planner node over real DDS (loopback): grid + start + goal -> Path; a grid change under
the route -> a new route; an unreachable goal -> an EMPTY path (so the drive stops)."""

import contextlib
import math
import subprocess
import time

import numpy as np
import pytest

from wheelgrid_common.map_io import Grid, to_occupancy_grid
from wheelgrid_common.qos import MAP_QOS, RELIABLE_QOS
from wheelgrid_common.testing import managed_process, python_module, rclpy_context, spin_until

pytestmark = pytest.mark.ros

PAPER_OCCUPIED = [(3, 0), (3, 1), (3, 2), (3, 3), (3, 4), (5, 0), (5, 1), (5, 2), (5, 3), (4, 4)]
PAPER_ROUTE = [(2, 0)] + [(2, c) for c in range(1, 6)] + [(r, 5) for r in range(3, 7)]
RES = 1.2
ORIGIN = (1.0, 2.0, 0.0)


def paper_grid() -> np.ndarray:
    g = np.zeros((8, 8), dtype=np.int8)
    for r, c in [*PAPER_OCCUPIED, (6, 7)]:
        g[r, c] = 100
    return g


def said_by(node) -> list[str]:
    """What ``node`` warns of (and errors), in order, in place of its log; info is dropped."""
    from types import SimpleNamespace as Ns

    said: list[str] = []
    logger = Ns(
        warning=lambda text, **_: said.append(text),
        error=lambda text, **_: said.append(text),
        info=lambda text, **_: None,
    )
    node.get_logger = lambda: logger
    return said


def cells_of(path, grid):
    return [grid.cell_of(p.pose.position.x, p.pose.position.y) for p in path.poses]


def yaw_of(pose):
    q = pose.orientation
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def goal_msg(grid, cell):
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = "map"
    x, y = grid.cell_center(*cell)
    msg.pose.position.x, msg.pose.position.y = float(x), float(y)
    msg.pose.orientation.w = 1.0
    return msg


def start_msg(grid, cell, yaw):
    from geometry_msgs.msg import PoseWithCovarianceStamped

    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = "map"
    x, y = grid.cell_center(*cell)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


class Harness:
    """A test node with the planner's input publishers and output subscriptions."""

    def __init__(self, ctx):
        from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
        from nav_msgs.msg import OccupancyGrid, Odometry, Path
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from visualization_msgs.msg import MarkerArray

        from wheelgrid_common.qos import SENSOR_QOS

        self.node = Node("planner_test", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.grid_pub = self.node.create_publisher(OccupancyGrid, "/wheelgrid/safe_grid", MAP_QOS)
        self.goal_pub = self.node.create_publisher(PoseStamped, "/goal_pose", RELIABLE_QOS)
        self.init_pub = self.node.create_publisher(
            PoseWithCovarianceStamped, "/initialpose", RELIABLE_QOS
        )
        self.odom_pub = self.node.create_publisher(Odometry, "/wheelgrid/odometry", SENSOR_QOS)
        self.paths = []
        self.markers = []
        self.node.create_subscription(Path, "/wheelgrid/plan", self.paths.append, MAP_QOS)
        self.node.create_subscription(
            MarkerArray, "/wheelgrid/plan_markers", self.markers.append, MAP_QOS
        )

    def wait_matched(self, timeout=15.0):
        pubs = (self.grid_pub, self.goal_pub, self.init_pub)
        return spin_until(
            self.ex, lambda: all(p.get_subscription_count() > 0 for p in pubs), timeout
        )

    def next_path(self, count_before, timeout=20.0):
        assert spin_until(self.ex, lambda: len(self.paths) > count_before, timeout)
        return self.paths[-1]

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()


@contextlib.contextmanager
def planner_process(tmp_path, *params):
    """The planner's real entry point as a child process, given ``params`` (``name:=value``)
    and logging to ``tmp_path/planner.log``, and a harness matched to it: yields
    ``(harness, log)``; the process is stopped whatever happens."""
    log = tmp_path / "planner.log"
    args = python_module(
        "wheelgrid_nav.planner_node", "--ros-args", *(a for p in params for a in ("-p", p))
    )
    with (
        open(log, "w") as logf,
        managed_process(args, stdout=logf, stderr=subprocess.STDOUT),
        rclpy_context() as ctx,
    ):
        h = Harness(ctx)
        try:
            assert h.wait_matched(timeout=30.0), log.read_text()
            yield h, log
        finally:
            h.close()


# check_every this large makes the (converging) learning take seconds on the paper grid
SLOW_LEARNING = ("check_every:=20000", "max_episodes:=1000000000000", "max_seconds:=60.0")


def paper_grid_with_the_chair_at_its_start(h) -> Grid:
    """Publish the paper grid and the chair at (2, 0) facing grid "down", and give the planner
    a second to take both; returns the grid."""
    grid = Grid(paper_grid(), RES, ORIGIN)
    h.grid_pub.publish(to_occupancy_grid(grid))
    h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
    spin_until(h.ex, lambda: False, 1.0)
    return grid


def test_planner_node_plans_replans_and_stops(tmp_path):
    from rclpy.parameter import Parameter

    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        planner = make_node(
            context=ctx,
            parameter_overrides=[Parameter("method", value="qlearning-heading")],
        )
        h = Harness(ctx)
        ex = h.ex
        ex.add_node(planner)
        try:
            assert h.wait_matched()
            h.grid_pub.publish(to_occupancy_grid(grid))
            h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))  # facing grid "down"
            assert spin_until(ex, lambda: planner.grid is not None and planner.start, 10.0)
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            path = h.next_path(n)
            assert path.header.frame_id == "map"
            assert cells_of(path, grid) == PAPER_ROUTE
            for pose, cell in zip(path.poses, PAPER_ROUTE, strict=True):
                x, y = grid.cell_center(*cell)
                assert pose.pose.position.x == pytest.approx(x)
                assert pose.pose.position.y == pytest.approx(y)
            # the start cell carries the chair's heading (grid down = -y), so a follower gets
            # Table II's left-forward; then the direction of travel: right (+x), then down
            assert yaw_of(path.poses[0].pose) == pytest.approx(-math.pi / 2)
            assert yaw_of(path.poses[1].pose) == pytest.approx(0.0, abs=1e-9)
            assert yaw_of(path.poses[6].pose) == pytest.approx(-math.pi / 2)
            assert spin_until(ex, lambda: bool(h.markers), 10.0)
            arrows = [m for m in h.markers[-1].markers if m.action == m.ADD]
            assert all(m.type == m.ARROW and len(m.points) == 2 for m in arrows)
            assert h.markers[-1].markers[0].action == h.markers[-1].markers[0].DELETEALL
            assert len(arrows) == len(PAPER_ROUTE) - 1

            # an obstacle appears on the route (4, 5): the node replans around it
            blocked = paper_grid()
            blocked[4, 5] = 100
            grid2 = Grid(blocked, RES, ORIGIN)
            n = len(h.paths)
            h.grid_pub.publish(to_occupancy_grid(grid2))
            path = h.next_path(n)
            cells = cells_of(path, grid2)
            assert cells[0] == (2, 0) and cells[-1] == (6, 5) and (4, 5) not in cells
            assert all(blocked[r, c] == 0 for r, c in cells)
            assert len(cells) - 1 == 11  # via column 6: two moves longer

            # a grid change away from the route does not trigger a replan
            plans = planner.plans
            far = blocked.copy()
            far[0, 0] = 100
            h.grid_pub.publish(to_occupancy_grid(Grid(far, RES, ORIGIN)))
            assert spin_until(ex, lambda: planner.grid.data[0, 0] == 100, 10.0)
            assert planner.plans == plans

            # an unreachable goal: a warning and an EMPTY path, so the drive stops
            walled = far.copy()
            walled[7, 6] = 100  # with the pillar at (6,7) this seals the corner (7,7)
            h.grid_pub.publish(to_occupancy_grid(Grid(walled, RES, ORIGIN)))
            assert spin_until(ex, lambda: planner.grid.data[7, 6] == 100, 10.0)
            assert planner.plans == plans  # (7,6) is not on the route either
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (7, 7)))
            path = h.next_path(n)
            assert path.poses == []
            assert planner.route == []

            # a goal on an occupied cell: also an empty path
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (3, 0)))
            assert h.next_path(n).poses == []

            # a start with a zero quaternion is ignored (the start stays), a goal with NaN
            # gets an empty path and is dropped, so a later grid change does not plan to it
            bad_start = start_msg(grid, (0, 0), 0.0)
            q = bad_start.pose.pose.orientation
            q.x = q.y = q.z = q.w = 0.0
            h.init_pub.publish(bad_start)
            n = len(h.paths)
            bad_goal = goal_msg(grid, (6, 5))
            bad_goal.pose.position.x = float("nan")
            h.goal_pub.publish(bad_goal)
            assert h.next_path(n).poses == [] and planner.goal is None
            assert planner.start[:2] == pytest.approx(grid.cell_center(2, 0))
        finally:
            ex.remove_node(planner)
            planner.destroy_node()
            h.close()


@pytest.mark.parametrize(
    ("child", "params"),
    [
        ("iphone_depth_optical_frame", ()),
        # a camera frame not named optical, which the mapper was told is (sensor_convention):
        # read as a body frame, the start heading came out 90 deg off, "down"
        ("camera", ("odometry_convention:=optical",)),
    ],
)
def test_odometry_start_and_console_entry(tmp_path, child, params):
    """The real entry point as a child process; the start comes from /wheelgrid/odometry in the
    iPhone's optical frame (looking along the grid's "right")."""
    from nav_msgs.msg import Odometry

    grid = Grid(paper_grid(), RES, ORIGIN)
    with planner_process(tmp_path, "method:=qlearning", *params) as (h, log):
        h.grid_pub.publish(to_occupancy_grid(grid))
        odom = Odometry()
        odom.header.frame_id = "map"
        odom.child_frame_id = child
        x, y = grid.cell_center(6, 0)
        odom.pose.pose.position.x, odom.pose.pose.position.y = float(x), float(y)
        q = odom.pose.pose.orientation
        q.x, q.y, q.z, q.w = -0.5, 0.5, -0.5, 0.5  # optical z along map +x
        h.goal_pub.publish(goal_msg(grid, (6, 4)))
        for _ in range(20):  # sensor QoS is best effort: send a few, as a 10 Hz stream would
            h.odom_pub.publish(odom)
            if spin_until(h.ex, lambda: bool(h.paths), 0.25):
                break
        path = h.next_path(0)
        assert cells_of(path, grid) == [(6, c) for c in range(5)], log.read_text()
        q = path.poses[0].pose.orientation  # the start heading: the grid's "right", map +x
        assert math.atan2(2 * q.w * q.z, 1 - 2 * q.z * q.z) == pytest.approx(0.0, abs=1e-6)


def odom_msg(grid, cell):
    """An Odometry pose on ``cell``'s centre in the iPhone's optical frame, looking along the
    grid's "right" (map +x)."""
    from nav_msgs.msg import Odometry

    odom = Odometry()
    odom.header.frame_id = "map"
    odom.child_frame_id = "camera_optical_frame"
    x, y = grid.cell_center(*cell)
    odom.pose.pose.position.x, odom.pose.pose.position.y = float(x), float(y)
    q = odom.pose.pose.orientation
    q.x, q.y, q.z, q.w = -0.5, 0.5, -0.5, 0.5  # optical z along map +x
    return odom


def test_a_start_from_odometry_that_stopped_coming_is_not_planned_from():
    """The mapper publishes /wheelgrid/odometry for each frame it maps and none while it is
    lost or stopped. The planner planned from the last pose it had, wherever the chair had gone
    since. A start from the odometry older than ``odometry_max_age_s`` is now as none: the
    chair stops (an empty path) and the goal waits for a fresh start for ``goal_wait_s``, said
    why; a fresh pose or an /initialpose (the user's word, which does not age) plans it, even
    one read in the same executor pass just after the goal (the demo's sequence: dropped at
    once, the goal was lost and the pose planned nothing, a review)."""
    from rclpy.parameter import Parameter

    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        node = make_node(
            context=ctx,
            parameter_overrides=[
                Parameter("odometry_max_age_s", value=0.3),
                Parameter("goal_wait_s", value=0.5),
                Parameter("method", value="qlearning"),
            ],
        )
        try:
            said = said_by(node)
            paths: list = []
            node._publish_route = lambda grid, cells, *a: paths.append(cells)
            node._on_grid(to_occupancy_grid(grid))
            node._on_odom(odom_msg(grid, (6, 0)))
            node._on_goal(goal_msg(grid, (6, 4)))
            assert node.plans == 1 and paths[-1] == [(6, c) for c in range(5)]
            time.sleep(0.4)  # the odometry stops: the mapper lost its way
            node._on_goal(goal_msg(grid, (6, 3)))
            assert node.plans == 1 and paths[-1] == [] and node.goal is not None
            assert "/wheelgrid/odometry is 0.4 s old (odometry_max_age_s 0.3)" in said[-1], said
            assert "goal kept, not planned yet" in said[-1]
            node._on_odom(odom_msg(grid, (6, 1)))  # mapping again: the waiting goal is planned
            assert node.plans == 2 and paths[-1] == [(6, c) for c in range(1, 4)]
            # the demo's sequence: the replay over, a goal and then the user's start pose
            time.sleep(0.4)
            node._on_goal(goal_msg(grid, (6, 2)))
            assert paths[-1] == [] and node.plans == 2
            node._on_initialpose(start_msg(grid, (6, 0), 0.0))
            assert node.plans == 3 and paths[-1] == [(6, 0), (6, 1), (6, 2)]
            time.sleep(0.4)  # /initialpose does not age
            node._on_goal(goal_msg(grid, (6, 3)))
            assert node.plans == 4 and paths[-1] == [(6, c) for c in range(4)]
            # a fresh start that never comes: the goal is dropped after goal_wait_s, said
            node._on_odom(odom_msg(grid, (6, 0)))
            time.sleep(0.4)
            node._on_goal(goal_msg(grid, (6, 5)))
            assert paths[-1] == [] and node.goal is not None
            time.sleep(0.6)
            node._drop_goal_waited_too_long()
            assert node.goal is None and "odometry is" in said[-1] and "goal_wait_s" in said[-1]
            assert "the mapper has placed no frame since" in said[-1]
            assert node.plans == 4
            # odometry that keeps coming in another frame is named as such, not as a lost mapper
            other = odom_msg(grid, (6, 1))
            other.header.frame_id = "odom"
            node._on_odom(other)
            node._on_goal(goal_msg(grid, (6, 5)))
            assert (
                "poses come but are not used (in frame 'odom' where the grid is in 'map'"
                in (said[-1])
            ), said[-1]
        finally:
            node.destroy_node()
        node = make_node(
            context=ctx, parameter_overrides=[Parameter("odometry_max_age_s", value=0.0)]
        )
        try:
            node._publish_route = lambda grid, cells, *a: None
            node._on_grid(to_occupancy_grid(grid))
            node._on_odom(odom_msg(grid, (6, 0)))
            time.sleep(0.1)
            node._on_goal(goal_msg(grid, (6, 2)))
            assert node.plans == 1  # 0: no limit
        finally:
            node.destroy_node()
        with pytest.raises(SystemExit):
            make_node(
                context=ctx, parameter_overrides=[Parameter("odometry_max_age_s", value=-1.0)]
            )


def test_a_goal_read_with_an_estop_after_a_learning_is_dropped_and_said():
    """A route is learned; meanwhile the e-stop is pressed and released, and a new goal sent.
    Read after the learning, the route is not published (it crossed the e-stop), and the new
    goal was kept with no word and no goal_wait_s timer: the next grid the mapper sent planned
    it, and the chair set off with no command (a review: 18 s on). Whether it came before or
    after the clear is lost (each topic is read in turn): it is dropped now, said."""
    from rclpy.parameter import Parameter
    from std_msgs.msg import Bool

    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        node = make_node(context=ctx, parameter_overrides=[Parameter("method", value="qlearning")])
        try:
            said = said_by(node)
            paths: list = []
            node._publish_route = lambda grid, cells, *a: paths.append(cells)
            node._on_grid(to_occupancy_grid(grid))
            node._on_initialpose(start_msg(grid, (2, 0), -math.pi / 2))
            read = {"estops": False, "goal": False}

            def estops() -> None:  # what waited behind the learning: a press and a release
                if not read["estops"]:
                    read["estops"] = True
                    node._on_estop(Bool(data=True))
                    node._on_estop(Bool(data=False))

            def take(sub, handler, with_info=False) -> None:  # and then the user's new goal
                if sub is node._goal_sub and not read["goal"]:
                    read["goal"] = True
                    handler(goal_msg(grid, (0, 7)))

            node._take_waiting_estops, node._take_waiting = estops, take
            node._on_goal(goal_msg(grid, (6, 5)))
            assert node.goal is None and all(p == [] for p in paths), paths
            assert "across an e-stop: not planned" in said[-1], said
            node._on_grid(to_occupancy_grid(grid))  # the mapper's next grid plans nothing
            assert all(p == [] for p in paths) and node.plans == 1
        finally:
            node.destroy_node()


def chair_msg(grid, cell, yaw):
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = "map"
    msg.pose = start_msg(grid, cell, yaw).pose.pose
    return msg


@contextlib.contextmanager
def planner_with_chair(grid):
    """A planner node, the test harness with a /wheelgrid/chair_pose publisher, and ``grid``
    published: yields ``(harness, chair_pub)``."""
    from geometry_msgs.msg import PoseStamped

    from wheelgrid_nav.planner_node import make_node

    with rclpy_context() as ctx:
        planner = make_node(context=ctx)
        h = Harness(ctx)
        chair_pub = h.node.create_publisher(PoseStamped, "/wheelgrid/chair_pose", RELIABLE_QOS)
        h.ex.add_node(planner)
        h.planner = planner
        try:
            assert h.wait_matched()
            assert spin_until(h.ex, lambda: chair_pub.get_subscription_count() > 0, 15.0)
            h.grid_pub.publish(to_occupancy_grid(grid))
            yield h, chair_pub
        finally:
            h.close()
            planner.destroy_node()


def test_the_next_goal_starts_where_the_chair_drove_to(tmp_path):
    """RViz sends goal after goal with no new /initialpose: the second route used to start at
    the first route's start (the drive refused it, the chair stood). The chair's pose moves the
    start when the chair has moved, and only then: at rest it does not undo an /initialpose."""
    grid = Grid(paper_grid(), RES, ORIGIN)
    with planner_with_chair(grid) as (h, chair_pub):
        down = -math.pi / 2
        h.init_pub.publish(start_msg(grid, (2, 0), down))  # the user places the chair
        spin_until(h.ex, lambda: False, 0.3)
        # the controller's power-on pose, heard only now, then again at rest: neither may
        # undo the user's start
        for _ in range(2):
            chair_pub.publish(chair_msg(grid, (0, 0), 0.0))
            spin_until(h.ex, lambda: False, 0.3)
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (2, 5)))
        assert cells_of(h.next_path(n), grid)[0] == (2, 0)
        # the chair drives the route: its pose moves, and the next goal starts there
        for c in range(1, 6):
            chair_pub.publish(chair_msg(grid, (2, c), 0.0))
            spin_until(h.ex, lambda: False, 0.1)
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        assert cells_of(h.next_path(n), grid) == [(r, 5) for r in range(2, 7)]


def test_a_chair_creeping_by_millimetres_a_heartbeat_counts_as_moved(tmp_path):
    """At 0.1 km/h the controller reports 3 mm a heartbeat: compared heartbeat to heartbeat it
    never moved 1 cm, and the start stayed where the user had put it. Measured from the pose
    it last counted, the creep adds up."""
    grid = Grid(paper_grid(), RES, ORIGIN)
    with planner_with_chair(grid) as (h, chair_pub):
        h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
        spin_until(h.ex, lambda: False, 0.3)
        for k in range(5):  # 0, 3, 6, 9, 12 mm along the row of cell (0, 0)
            msg = chair_msg(grid, (0, 0), 0.0)
            msg.pose.position.x += 0.003 * k
            chair_pub.publish(msg)
            spin_until(h.ex, lambda: False, 0.1)
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (0, 3)))
        assert cells_of(h.next_path(n), grid) == [(0, c) for c in range(4)]


def test_a_smaller_grid_a_grid_in_another_frame_and_a_refused_goal(tmp_path):
    """A new grid smaller than the route raised IndexError in the grid callback and ended the
    node; a grid in another frame was planned on with map coordinates; a goal refused for
    its frame left the old goal, planned to at the next start. A grid that leaves no route
    drops the goal: the old grid back plans nothing until the goal is sent again."""
    from rclpy.parameter import Parameter

    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        planner = make_node(
            context=ctx, parameter_overrides=[Parameter("method", value="qlearning")]
        )
        h = Harness(ctx)
        h.ex.add_node(planner)
        try:
            assert h.wait_matched()
            h.grid_pub.publish(to_occupancy_grid(grid))
            h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
            assert spin_until(h.ex, lambda: planner.grid is not None and planner.start, 10.0)
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            assert cells_of(h.next_path(n), grid) == PAPER_ROUTE
            n = len(h.paths)
            small = Grid(np.zeros((3, 3), np.int8), RES, ORIGIN)
            h.grid_pub.publish(to_occupancy_grid(small))
            assert h.next_path(n).poses == []  # (6, 5) is off the 3 x 3 grid: no route
            assert planner.grid.data.shape == (3, 3) and planner.goal is None
            plans = planner.plans
            h.grid_pub.publish(to_occupancy_grid(grid))  # the route is open again
            assert spin_until(h.ex, lambda: planner.grid.data.shape == (8, 8), 10.0)
            spin_until(h.ex, lambda: False, 0.5)
            assert planner.plans == plans  # ... but the goal is gone: nothing planned

            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (6, 5)))  # sent again
            assert cells_of(h.next_path(n), grid) == PAPER_ROUTE
            n = len(h.paths)
            other = to_occupancy_grid(grid)
            other.header.frame_id = "odom"  # start and goal were given in map
            h.grid_pub.publish(other)
            assert h.next_path(n).poses == [] and planner.goal is None

            n = len(h.paths)
            h.grid_pub.publish(to_occupancy_grid(grid))  # back in map
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            assert cells_of(h.next_path(n), grid) == PAPER_ROUTE
            n = len(h.paths)
            refused = goal_msg(grid, (6, 4))
            refused.header.frame_id = "odom"
            h.goal_pub.publish(refused)
            assert h.next_path(n).poses == [] and planner.goal is None
            plans = planner.plans
            h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
            spin_until(h.ex, lambda: False, 0.5)
            assert planner.plans == plans  # no goal any more: nothing planned
        finally:
            h.ex.remove_node(planner)
            planner.destroy_node()
            h.close()


@pytest.mark.parametrize(
    "param",
    [
        "method:=dijkstra",
        "reward_step:=1.0",
        "learning_rate:=1",
        "reward_goal:=.inf",
        "odometry_convention:=sideways",
    ],
)
def test_bad_parameters_stop_the_node_with_exit_2(param):
    from wheelgrid_common.ros_env import child_env

    args = python_module("wheelgrid_nav.planner_node", "--ros-args", "-p", param)
    proc = subprocess.run(args, env=child_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "FATAL" in proc.stderr + proc.stdout


def test_pose_problem_names_what_cannot_place_the_chair():
    from types import SimpleNamespace as Ns

    from wheelgrid_nav.planner_node import pose_problem

    def pose(x=1.0, qw=1.0, qz=0.0):
        return Ns(position=Ns(x=x, y=2.0, z=0.0), orientation=Ns(x=0.0, y=0.0, z=qz, w=qw))

    assert pose_problem(pose()) is None and pose_problem(pose(qw=0.0, qz=2.0)) is None
    assert pose_problem(pose(x=float("nan"))) == "a NaN or infinite coordinate"
    assert pose_problem(pose(qw=float("inf"))) == "a NaN or infinite coordinate"
    assert pose_problem(pose(qw=0.0)) == "a zero quaternion"


@pytest.mark.parametrize("best_effort", [False, True])
def test_an_estop_ends_the_goal_and_nothing_replans_to_it_after_the_clear(tmp_path, best_effort):
    """Through an e-stop the planner kept its goal: cleared, the next grid change (the map
    grows during a scan) gave a new route to it, and the drive drove it with no new command.
    Now the e-stop drops the goal with an empty path, goals wait for the clear, and only a new
    goal after it plans. So does one published best-effort (a joystick, a safety bridge): the
    drive latched it, the planner did not hear it, and after the clear the next grid sent the
    chair 4.8 m on to the goal (a review)."""
    from std_msgs.msg import Bool

    from wheelgrid_common.qos import SENSOR_QOS

    grid = Grid(paper_grid(), RES, ORIGIN)
    with planner_with_chair(grid) as (h, _chair_pub):
        estop = h.node.create_publisher(
            Bool, "/wheelgrid/estop", SENSOR_QOS if best_effort else RELIABLE_QOS
        )
        clear = h.node.create_publisher(Bool, "/wheelgrid/estop", RELIABLE_QOS)
        assert spin_until(h.ex, lambda: estop.get_subscription_count() > 0, 10.0)
        h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
        spin_until(h.ex, lambda: False, 0.3)
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        assert cells_of(h.next_path(n), grid) == PAPER_ROUTE
        n = len(h.paths)
        estop.publish(Bool(data=True))
        assert h.next_path(n).poses == []  # the drive stops and the route is gone
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (2, 5)))  # a goal while latched: refused
        assert h.next_path(n).poses == []
        clear.publish(Bool(data=False))
        spin_until(h.ex, lambda: False, 0.3)
        n = len(h.paths)
        grown = Grid(np.zeros((8, 9), np.int8), RES, ORIGIN)  # the map grows: a new geometry
        grown.data[:, :8] = paper_grid()
        h.grid_pub.publish(to_occupancy_grid(grown))
        spin_until(h.ex, lambda: False, 1.0)
        assert len(h.paths) == n, "a route to the old goal after the clear"
        h.goal_pub.publish(goal_msg(grid, (2, 5)))  # a new goal after the clear plans
        assert cells_of(h.next_path(n), grid) == [(2, c) for c in range(6)]


def test_an_estop_held_by_a_latched_source_before_the_planner_started_refuses_goals():
    """A source that keeps its state (reliable + transient-local) published true before the
    planner started: its volatile subscription never heard it, and a goal was planned while
    the e-stop was held. The kept state is heard now; the source's clear lets a goal plan."""
    from rclpy.node import Node
    from std_msgs.msg import Bool

    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        source = Node("wg_latched_estop", context=ctx)
        pub = source.create_publisher(Bool, "/wheelgrid/estop", MAP_QOS)
        pub.publish(Bool(data=True))
        planner = make_node(context=ctx)
        h = Harness(ctx)
        h.ex.add_node(planner)
        try:
            assert h.wait_matched()
            assert spin_until(h.ex, lambda: planner._estop, 10.0), "the held e-stop was not heard"
            h.grid_pub.publish(to_occupancy_grid(grid))
            h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
            spin_until(h.ex, lambda: False, 0.3)
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            assert h.next_path(n).poses == []
            pub.publish(Bool(data=False))
            assert spin_until(h.ex, lambda: not planner._estop, 10.0)
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            assert cells_of(h.next_path(n), grid) == PAPER_ROUTE
            assert planner._estop_presses == 1  # the kept e-stop, handled once
        finally:
            h.close()
            planner.destroy_node()
            source.destroy_node()


def test_a_start_turned_between_two_grid_directions_gets_no_route(tmp_path):
    """A start facing 45 deg went to "right" by a tie: the route was published, and the drive
    (which accepts 20 deg at most) refused it. Now the planner says why, with an empty path;
    18 deg off still plans, as the drive still drives it (the goal sent again: a goal with no
    route is dropped)."""
    grid = Grid(paper_grid(), RES, ORIGIN)
    with planner_with_chair(grid) as (h, _chair_pub):
        h.init_pub.publish(start_msg(grid, (2, 0), math.radians(45.0)))
        spin_until(h.ex, lambda: False, 0.3)
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        assert h.next_path(n).poses == []
        n = len(h.paths)
        h.init_pub.publish(start_msg(grid, (2, 0), math.radians(-72.0)))  # 18 deg off "down"
        turned = math.radians(-72.0)  # two topics: the start must be in first
        assert spin_until(h.ex, lambda: h.planner.start[2] == pytest.approx(turned), 10.0)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        assert cells_of(h.next_path(n), grid) == PAPER_ROUTE


@pytest.mark.parametrize("best_effort", [False, True])
def test_an_estop_pressed_and_released_while_a_route_is_learned_leaves_no_route(
    tmp_path, best_effort
):
    """The e-stop shares the planner's executor with the learning: pressed and released while a
    route was learned (up to max_seconds), both waited behind it, so the route to the goal of
    before the e-stop was published first -- after the drive had seen the clear, so it drove it
    with no new command -- and only then the e-stop's empty path. Now e-stops that came during
    the learning are read before a route is published: none is, and the path is empty. A
    best-effort press (a joystick) was read after the reliable clear that followed it: the
    route went out, and the planner stayed latched after the user's clear, refusing the next
    goal (a review). Samples are handled in the order they were published."""
    from std_msgs.msg import Bool

    from wheelgrid_common.qos import SENSOR_QOS

    with planner_process(tmp_path, *SLOW_LEARNING) as (h, log):
        estop = h.node.create_publisher(
            Bool, "/wheelgrid/estop", SENSOR_QOS if best_effort else RELIABLE_QOS
        )
        clear = h.node.create_publisher(Bool, "/wheelgrid/estop", RELIABLE_QOS)
        assert spin_until(h.ex, lambda: estop.get_subscription_count() > 0, 15.0)
        assert spin_until(h.ex, lambda: clear.get_subscription_count() > 0, 15.0)
        grid = paper_grid_with_the_chair_at_its_start(h)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        spin_until(h.ex, lambda: False, 1.0)  # the route is being learned
        estop.publish(Bool(data=True))
        spin_until(h.ex, lambda: False, 0.2)
        clear.publish(Bool(data=False))
        assert spin_until(h.ex, lambda: "e-stop" in log.read_text(), 60.0), log.read_text()
        spin_until(h.ex, lambda: False, 1.0)
        assert h.paths, log.read_text()
        assert all(p.poses == [] for p in h.paths), (
            "a route to the goal of before the e-stop was published\n" + log.read_text()
        )
        n = len(h.paths)
        h.goal_pub.publish(goal_msg(grid, (2, 5)))  # after the clear: planned
        assert h.next_path(n, timeout=60.0).poses, log.read_text()


@pytest.mark.parametrize("start", ["initialpose", "odometry"])
@pytest.mark.parametrize("change", ["goal", "grid"])
def test_a_goal_or_grid_that_came_while_a_route_was_learned_voids_it(tmp_path, change, start):
    """A new goal or grid waited behind the learning, as e-stops did: the route to the old goal
    went out after the new goal was sent (and stayed the plan while the new one was learned),
    and a route through a cell the new grid had closed went out before the replan. Both are
    read before a route is published: the first route out is the one for the newest inputs.

    ``start`` "odometry": the start streams on /wheelgrid/odometry at 10 Hz, and the learning
    takes longer than odometry_max_age_s (0.5 s here). The replan judged the start's age by the
    last pose read before the learning: the chair stopped and its goal was dropped while the
    mapper worked (a review, a 2.8 s learning). The odometry that waited behind the learning
    is read first now: the first path out is a route."""
    closed = paper_grid()
    closed[2, 3] = 100  # on the route to (6, 5) along row 2
    params = (*SLOW_LEARNING, "odometry_max_age_s:=0.5")
    with planner_process(tmp_path, *params) as (h, log):
        if start == "initialpose":
            grid = paper_grid_with_the_chair_at_its_start(h)
        else:
            grid = Grid(paper_grid(), RES, ORIGIN)
            h.grid_pub.publish(to_occupancy_grid(grid))
            odom = odom_msg(grid, (2, 0))
            h.node.create_timer(0.1, lambda: h.odom_pub.publish(odom))
            spin_until(h.ex, lambda: False, 1.0)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        spin_until(h.ex, lambda: False, 1.0)  # the route is being learned
        if change == "goal":
            h.goal_pub.publish(goal_msg(grid, (0, 7)))
        else:
            h.grid_pub.publish(to_occupancy_grid(Grid(closed, RES, ORIGIN)))
        assert spin_until(h.ex, lambda: h.paths, 120.0), log.read_text()
        spin_until(h.ex, lambda: False, 1.0)
        assert h.paths[0].poses, log.read_text()  # a route, not the empty path of a stale start
        first = cells_of(h.paths[0], grid)
        if change == "goal":
            assert first[-1] == (0, 7), (first, log.read_text())
        else:
            assert first[-1] == (6, 5) and (2, 3) not in first, (first, log.read_text())
        assert "was learned: replanning" in log.read_text(), log.read_text()
        assert "odometry is" not in log.read_text(), log.read_text()


def test_a_new_goal_withdraws_the_route_to_the_old_one_while_it_is_learned(tmp_path):
    """The route to a goal the user had replaced stayed the plan while the new one was learned
    (up to max_seconds), and the drive went on along it. Now a new goal in another cell
    publishes an empty path at once, before its own route; the same goal sent again, with no
    drive driving it (none runs here), is planned again and keeps the route meanwhile. The learning is made to take seconds: the plan topic keeps one message
    (MAP_QOS), so paths published milliseconds apart may reach a subscriber as the last one
    alone, and the withdrawal matters where the learning is long."""
    with planner_process(tmp_path, *SLOW_LEARNING) as (h, log):
        grid = paper_grid_with_the_chair_at_its_start(h)
        h.goal_pub.publish(goal_msg(grid, (6, 5)))
        first = h.next_path(0, timeout=120.0)
        assert cells_of(first, grid)[-1] == (6, 5), log.read_text()
        h.goal_pub.publish(goal_msg(grid, (6, 5)))  # the same goal again: its route stands
        h.next_path(1, timeout=120.0)
        h.goal_pub.publish(goal_msg(grid, (0, 7)))
        assert spin_until(h.ex, lambda: len(h.paths) >= 4, 120.0), log.read_text()
        spin_until(h.ex, lambda: False, 0.5)
        ends = [cells_of(p, grid)[-1] if p.poses else None for p in h.paths]
        # the first goal, the same goal again (learned again, the route kept meanwhile), then
        # the new goal: the old route withdrawn while its own route is learned
        assert ends == [(6, 5), (6, 5), None, (0, 7)], (ends, log.read_text())
        assert log.read_text().count("withdrawn") == 1, log.read_text()


def test_no_route_goes_out_where_the_estops_that_came_while_it_was_learned_cannot_be_read():
    """The check for e-stops that came during the learning uses rclpy's take_message, which is
    not public API: if a later rclpy broke it, the route learned meanwhile was published
    unchecked (or the node died); it must publish an empty path instead."""
    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), 1.2)
    with rclpy_context() as ctx:
        node = make_node(context=ctx)
        try:
            node.grid = grid
            x, y = grid.cell_center(2, 0)
            node.start = (float(x), float(y), -math.pi / 2)  # facing down the grid
            gx, gy = grid.cell_center(6, 5)
            node.goal = (float(gx), float(gy))
            published: list[list] = []
            node._publish_route = lambda g, cells, heading=None: published.append(list(cells))

            def broken() -> None:
                raise AttributeError("'Subscription' object has no attribute 'take_message'")

            node._take_waiting_estops = broken
            node._plan()
            assert published == [[]], published
            assert node.goal is None  # dropped with the route: nothing plans to it later
            node._take_waiting_estops = lambda: None  # readable again: the goal sent again
            node.goal = (float(gx), float(gy))
            node._plan()
            assert len(published) == 2 and published[1][0] == (2, 0) and published[1][-1] == (6, 5)
        finally:
            node.destroy_node()


def test_a_goal_refused_or_reached_is_never_planned_to_again(tmp_path):
    """A goal kept past its end moved the chair with no command: one with no route when sent
    (a cell the growing map had not reached yet) was planned to at a later grid change, and a
    goal reached long ago was planned back to from wherever the chair had been driven since,
    once the grid changed under the old route."""
    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    walled = paper_grid()
    walled[2, 5] = walled[2, 6] = walled[2, 7] = 100  # with row 3 this seals the south half
    with rclpy_context() as ctx:
        planner = make_node(context=ctx)
        h = Harness(ctx)
        h.ex.add_node(planner)
        try:
            assert h.wait_matched()
            h.grid_pub.publish(to_occupancy_grid(Grid(walled, RES, ORIGIN)))
            h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
            assert spin_until(h.ex, lambda: planner.grid is not None and planner.start, 10.0)
            n = len(h.paths)
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            assert h.next_path(n).poses == [] and planner.goal is None
            # the wall opens: the old goal is not planned to
            plans = planner.plans
            h.grid_pub.publish(to_occupancy_grid(grid))
            assert spin_until(h.ex, lambda: planner.grid.data[2, 5] == 0, 10.0)
            h.init_pub.publish(start_msg(grid, (2, 0), -math.pi / 2))
            spin_until(h.ex, lambda: False, 0.5)
            assert planner.plans == plans and len(h.paths) == n + 1

            # sent again it is planned, then reached: the chair's pose in the goal cell ends it
            h.goal_pub.publish(goal_msg(grid, (6, 5)))
            assert cells_of(h.next_path(n + 1), grid) == PAPER_ROUTE
            assert planner.goal is not None
            h.init_pub.publish(start_msg(grid, (6, 5), -math.pi / 2))
            assert spin_until(h.ex, lambda: planner.goal is None, 10.0)
            # driven away by hand, then the grid grows under the old route: nothing planned
            plans, n = planner.plans, len(h.paths)
            h.init_pub.publish(start_msg(grid, (0, 0), 0.0))
            assert spin_until(
                h.ex, lambda: planner.start[:2] == pytest.approx(grid.cell_center(0, 0)), 10.0
            )
            bigger = np.zeros((9, 8), np.int8)
            bigger[:8] = paper_grid()
            h.grid_pub.publish(to_occupancy_grid(Grid(bigger, RES, ORIGIN)))
            assert spin_until(h.ex, lambda: planner.grid.data.shape == (9, 8), 10.0)
            spin_until(h.ex, lambda: False, 0.5)
            assert planner.plans == plans and len(h.paths) == n

            # a goal in the chair's own cell: a one-cell route, and done at once
            h.goal_pub.publish(goal_msg(grid, (0, 0)))
            path = h.next_path(n)
            assert cells_of(path, grid) == [(0, 0)] and planner.goal is None
        finally:
            h.ex.remove_node(planner)
            planner.destroy_node()
            h.close()


@contextlib.contextmanager
def recording_planner():
    """A planner node, in process, whose published routes are also kept: (node, published)."""
    from wheelgrid_nav.planner_node import make_node

    with rclpy_context() as ctx:
        node = make_node(context=ctx)
        try:
            published: list[list] = []
            publish = node._publish_route

            def record(g, cells, heading=None):
                published.append(list(cells))
                publish(g, cells, heading)

            node._publish_route = record
            yield node, published
        finally:
            node.destroy_node()


def row_2_goal(node, grid):
    """Give ``node`` ``grid``, the chair at (2, 0) facing right and a goal at (2, 4)."""
    node._on_grid(to_occupancy_grid(grid))
    node._on_initialpose(start_msg(grid, (2, 0), 0.0))
    node._on_goal(goal_msg(grid, (2, 4)))


def test_a_grid_that_leaves_the_route_open_is_not_a_change_under_it_when_the_start_was_unknown():
    """The chair's own cell may be unknown (a sensor on the chair never sees the floor under
    it), and the route starts there. Every new grid -- the grid node republishes at each map
    update -- found that cell "not free" and replanned: the same route went out again, and the
    drive stopped the running move for it (then refused it, the chair between two cells). Only
    an occupied start cell, or any other route cell not free, is a change under the route."""
    data = np.zeros((6, 6), np.int8)
    data[2, 0] = -1  # the chair's cell, never seen
    grid = Grid(data, 1.0)
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        assert published == [[(2, c) for c in range(5)]]
        node._on_grid(to_occupancy_grid(grid))  # the same grid again
        assert len(published) == 1 and node.plans == 1
        occupied = data.copy()
        occupied[2, 0] = 100  # the start cell turns occupied: that is a change
        node._on_grid(to_occupancy_grid(Grid(occupied, 1.0)))
        assert node.plans == 2 and published[-1] == []


def test_a_grid_of_cells_smaller_than_the_chair_withdraws_the_route_and_the_goal():
    """A grid of 0.6 m cells (or the 5 cm /map sent as the safe grid) planned a route through
    a gap narrower than the chair. It is refused: the route before it withdrawn (the map it
    was planned on is gone) and its goal dropped. Kept, the next good grid planned it and the
    chair drove on with no command (a review); a new goal is planned."""
    data = np.zeros((6, 6), np.int8)
    grid = Grid(data, 1.0)
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        assert published == [[(2, c) for c in range(5)]] and node.plans == 1
        node._on_grid(to_occupancy_grid(Grid(data, 0.6)))
        assert published[-1] == [] and node.grid is None and node.goal is None
        node._on_grid(to_occupancy_grid(grid))  # chair-sized again: nothing planned by itself
        assert node.plans == 1 and published[-1] == []
        node._on_goal(goal_msg(grid, (2, 4)))  # sent again: planned
        assert node.plans == 2 and published[-1] == [(2, c) for c in range(5)]


def test_a_route_the_drive_stopped_or_refused_is_not_planned_again_at_the_next_grid():
    """The drive stopped the route (the controller went silent) and said so; the planner kept
    it, and the next grid of another geometry (the map growing) planned it again: the chair
    set off 3 s after an ERROR with no command (a review). A route the drive stopped for the
    user (the stick, an e-stop) or a fault ends its goal at once, as the drive says it
    (drive_state's plan_end); one the planner's own grid change stopped is planned again; and
    a route the drive has not taken ROUTE_TAKEN_S after it went out ends its goal at the next
    grid. Counted from the newest route, a drive that never took any was sent one again at
    every grid for ever (a review: a restarted drive drove it 4.8 m)."""
    data = np.zeros((6, 6), np.int8)
    grid, grown = Grid(data, 1.0), Grid(np.zeros((6, 7), np.int8), 1.0)
    route = [(2, c) for c in range(5)]
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        node._on_drive_state(drive_state("plan"))  # driving it: a grown map replans
        node._on_grid(to_occupancy_grid(grown))
        assert node.plans == 2 and published[-1] == route
        node._on_drive_state(drive_state("idle", "planner"))  # the grid change stopped it
        assert node.goal is not None
        node._on_grid(to_occupancy_grid(grid))
        assert node.plans == 3 and published[-1] == route
        node._on_drive_state(drive_state("plan"))
        node._on_drive_state(drive_state("idle", "fault"))  # stopped: the controller silent
        assert node.goal is None and published[-1] == [], published[-2:]
        node._on_grid(to_occupancy_grid(grown))
        assert node.plans == 3
    # the stick or an e-stop the planner did not hear; a drive restarted (it never ended a
    # plan) within the 2 s its silence takes to count
    for end in ("user", ""):
        with recording_planner() as (node, published):
            row_2_goal(node, grid)
            node._on_drive_state(drive_state("plan"))
            node._on_drive_state(drive_state("cmd_vel", end))
            assert node.goal is None and published[-1] == []
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        node._on_drive_state(drive_state("idle"))  # it never takes the route (refused it)
        node._on_grid(to_occupancy_grid(grown))  # just out: the drive may not have it yet
        assert node.plans == 2 and node.goal is not None
        node._untaken_since -= 10.0  # replanned since, but not taken since the first
        node._on_grid(to_occupancy_grid(grid))
        assert node.plans == 2 and node.goal is None and published[-1] == []


def drive_state(job, plan_end=""):
    """The drive's state as it publishes it (wheelgrid/drive_state), its job ``job`` and who
    ended its last plan."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    values = [KeyValue(key="job", value=job), KeyValue(key="plan_end", value=plan_end)]
    return DiagnosticArray(status=[DiagnosticStatus(name="wheelgrid/drive", values=values)])


def test_the_same_goal_again_and_a_cell_behind_the_chair_leave_the_route_as_it_is():
    """Three things made the planner send a route anew, each stopping the drive's running move
    (and a chair half-way through a quarter turn then got "heading off the grid", its goal
    dropped): the same goal sent again while the drive drives it (relearned; with the drive
    not driving it, having refused or dropped the plan, it is planned again, as the drive's
    "send the goal again" asks); a cell the chair has already driven over
    turning unknown or occupied in a new grid (the chair's own trace); and a cell ahead that
    closed kept the old route published for the whole relearning. Now the first two change
    nothing, and the third withdraws the route at once, before the new one."""
    data = np.zeros((6, 6), np.int8)
    grid = Grid(data, 1.0)
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        route = [(2, c) for c in range(5)]
        assert published == [route] and node.plans == 1
        node._on_goal(goal_msg(grid, (2, 4)))  # again, no drive driving it: planned again
        assert published == [route, route] and node.plans == 2
        del published[1:]
        node._on_drive_state(drive_state("plan"))  # the drive on its way there
        node._on_goal(goal_msg(grid, (2, 4)))  # the same goal again: nothing
        assert published == [route] and node.plans == 2
        node._drive_job = ("plan", time.monotonic() - 10.0, "")  # a drive silent since: died
        node._on_goal(goal_msg(grid, (2, 4)))
        assert published == [route, route] and node.plans == 3
        del published[1:]
        node.plans = 2
        node._on_drive_state(drive_state("plan"))
        x, y = grid.cell_center(2, 2)
        node.start = (float(x), float(y), 0.0)  # the chair drove on to (2, 2)
        behind = data.copy()
        behind[2, 0] = 100  # where the chair started: behind it now
        behind[2, 1] = -1
        node._on_grid(to_occupancy_grid(Grid(behind, 1.0)))
        assert published == [route] and node.plans == 2
        ahead = behind.copy()
        ahead[2, 3] = 100  # ahead: withdrawn at once, then the way round
        node._on_grid(to_occupancy_grid(Grid(ahead, 1.0)))
        assert node.plans == 3 and published[1] == [], published
        assert published[2][0] == (2, 2) and published[2][-1] == (2, 4)
        assert (2, 3) not in published[2]


def test_a_goal_that_cannot_be_planned_yet_says_what_it_waits_for():
    """A goal sent before the first safe grid or start pose got no path and no log line: the
    user heard nothing, and the chair set off whenever the grid or start came. It is still
    planned then, but the planner says so when the goal comes."""
    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        node = make_node(context=ctx)
        try:
            said = said_by(node)
            node._on_goal(goal_msg(grid, (6, 5)))
            assert node.plans == 0 and len(said) == 1
            assert "/wheelgrid/safe_grid" in said[0] and "start pose" in said[0]
            node._on_grid(to_occupancy_grid(grid))
            node._on_goal(goal_msg(grid, (6, 5)))
            assert len(said) == 2 and "/wheelgrid/safe_grid" not in said[1]
            assert "/initialpose" in said[1]
            node._on_initialpose(start_msg(grid, (2, 0), -math.pi / 2))  # planned now
            assert node.plans == 1 and node.route == PAPER_ROUTE
        finally:
            node.destroy_node()


def test_a_goal_that_waits_longer_than_goal_wait_s_is_dropped():
    """A goal waiting for the first grid or start pose was planned whenever they came, maybe
    minutes later, and the chair set off with no command. After ``goal_wait_s`` it is dropped,
    said, and answered with an empty path; a grid and a start after that plan nothing."""
    from rclpy.parameter import Parameter

    from wheelgrid_nav.planner_node import make_node

    grid = Grid(paper_grid(), RES, ORIGIN)
    with rclpy_context() as ctx:
        node = make_node(context=ctx, parameter_overrides=[Parameter("goal_wait_s", value=0.2)])
        try:
            said = said_by(node)
            paths: list = []
            node._publish_route = lambda grid, cells, *a: paths.append(cells)
            node._on_goal(goal_msg(grid, (6, 5)))
            node._drop_goal_waited_too_long()  # not yet
            assert node.goal is not None and paths == []
            time.sleep(0.3)
            node._drop_goal_waited_too_long()
            assert node.goal is None and paths == [[]]
            assert "goal_wait_s (0.2 s)" in said[-1] and "send it again" in said[-1]
            node._on_grid(to_occupancy_grid(grid))
            node._on_initialpose(start_msg(grid, (2, 0), -math.pi / 2))
            assert node.plans == 0
            # a goal sent once grid and start are there is planned at once: nothing waits
            node._on_goal(goal_msg(grid, (6, 5)))
            assert node.plans == 1 and node._goal_waits_since is None
        finally:
            node.destroy_node()


def test_a_grid_of_another_size_or_origin_withdraws_the_route_at_once():
    """A grid that grew (the map growing) and closed a cell on the route only said
    "replanning": the old route stayed the plan for the whole learning, through the closed
    cell (a review: 3.7 s; 20 s while grids kept coming). It is withdrawn first now, as a
    closed cell on a grid of the same geometry is."""
    data = np.zeros((6, 6), np.int8)
    grid = Grid(data, 1.0)
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        node._on_drive_state(drive_state("plan"))
        grown = np.zeros((6, 7), np.int8)
        grown[2, 3] = 100  # on the route
        node._on_grid(to_occupancy_grid(Grid(grown, 1.0)))
        assert published[1] == [], published
        assert published[2][-1] == (2, 4) and (2, 3) not in published[2]


def test_grids_that_keep_coming_while_routes_are_learned_replan_in_a_loop_not_a_recursion():
    """Each grid of a new geometry read after a learning voided its route, and the replan was
    called from within the plan: as long as grids came faster than a learning took (1 Hz
    against 2.8 s on a big grid) the stack grew, eleven deep in a review's 20 s. Here 150 such
    grids come, one during each learning, under a stack limit 100 frames above this test's:
    a replan per frame ran out of stack; a loop does not."""
    import inspect
    import sys

    data = np.zeros((6, 6), np.int8)
    grid = Grid(data, 1.0)
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        assert node.plans == 1
        node._on_drive_state(drive_state("plan"))
        take = node._take_waiting
        shifts = iter(range(1, 151))

        def a_grid_came(sub, handler, with_info=False):
            if sub is node._grid_sub and (k := next(shifts, None)) is not None:
                handler(to_occupancy_grid(Grid(data, 1.0, origin=(0.0, 1e-3 * k, 0.0))))
            take(sub, handler, with_info)

        node._take_waiting = a_grid_came
        limit = sys.getrecursionlimit()
        sys.setrecursionlimit(len(inspect.stack()) + 100)
        try:
            node._on_goal(goal_msg(grid, (2, 5)))
        finally:
            sys.setrecursionlimit(limit)
        assert node.plans == 152
        assert published[-1] and published[-1][-1] == (2, 5)


def test_a_cell_left_behind_on_a_route_that_comes_back_through_it_is_behind():
    """A route that turns in a side pocket comes back through the cell before it. The cells
    ahead were counted from the chair's cell's first visit on the route, so the pocket, left
    already, was still ahead, and a grid calling it unknown (the chair's own trace) withdrew
    the route and stopped the chair (a review). The chair's progress along the route counts."""
    from geometry_msgs.msg import PoseStamped

    data = np.full((3, 10), 100, np.int8)
    data[1, :] = 0
    data[0, 5] = 0  # the pocket
    grid = Grid(data, 1.0)
    with recording_planner() as (node, published):
        node._on_grid(to_occupancy_grid(grid))
        node._on_initialpose(start_msg(grid, (1, 5), 0.0))
        node._on_goal(goal_msg(grid, (1, 0)))
        route = published[-1]
        assert route[:3] == [(1, 5), (0, 5), (1, 5)] and route[-1] == (1, 0), route
        node._on_drive_state(drive_state("plan"))
        plans = node.plans
        # the controller's pose: the first only sets the reference, then into the pocket and
        # backed out of it
        for cell, yaw in (((1, 5), 0.0), ((0, 5), math.pi / 2), ((1, 5), math.pi / 2)):
            pose = PoseStamped()
            pose.header.frame_id = "map"
            x, y = grid.cell_center(*cell)
            pose.pose.position.x, pose.pose.position.y = float(x), float(y)
            pose.pose.orientation.z, pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
            node._on_chair_pose(pose)
        left = data.copy()
        left[0, 5] = -1  # the pocket the chair has left
        node._on_grid(to_occupancy_grid(Grid(left, 1.0)))
        assert node.plans == plans and published[-1] == route, published[-2:]


def test_one_stray_pose_far_along_a_route_does_not_pass_the_cells_between():
    """On a U-shaped route one pose at its far leg (odometry jitter, a relocalisation, a wrong
    /initialpose put right) moved the route's progress past every cell between for good: a
    cell still ahead of the chair closing then withdrew nothing (a review). Progress moves
    only to the next cells; a pose further on counts for one check alone."""
    data = np.full((3, 6), 100, np.int8)
    data[0, :] = 0
    data[2, :] = 0
    data[:, 5] = 0  # a U-shaped corridor
    grid = Grid(data, 1.0)

    with recording_planner() as (node, published):
        node._on_grid(to_occupancy_grid(grid))
        node._on_initialpose(start_msg(grid, (0, 0), 0.0))
        node._on_goal(goal_msg(grid, (2, 1)))
        assert published[-1][-1] == (2, 1) and (0, 3) in published[-1]
        node._on_drive_state(drive_state("plan"))
        for cell in [(0, 0), (0, 1), (2, 2), (0, 1)]:  # (2, 2): one stray pose
            node._on_chair_pose(goal_msg(grid, cell))  # a PoseStamped at the cell's centre
        closed = data.copy()
        closed[0, 3] = 100  # still ahead of the chair at (0, 1)
        n = len(published)
        node._on_grid(to_occupancy_grid(Grid(closed, 1.0)))
        assert published[n] == [], published[n:]


def test_a_drive_that_falls_silent_while_it_drives_the_route_ends_the_goal():
    """A drive last heard driving the route was stopped (killed, restarted): the planner sent
    the route again at every grid meanwhile, and the restarted drive drove it 4.8 m with no
    command (a review). Silent for DRIVE_STATE_FRESH_S, it ends the goal, said once."""
    grid = Grid(np.zeros((6, 6), np.int8), 1.0)
    with recording_planner() as (node, published):
        row_2_goal(node, grid)
        node._on_drive_state(drive_state("plan"))
        node._drop_goal_of_a_silent_drive()
        assert node.goal is not None  # heard just now
        job, _heard, said = node._drive_job
        node._drive_job = (job, time.monotonic() - 10.0, said)
        node._drop_goal_of_a_silent_drive()
        assert node.goal is None and published[-1] == []
        node._on_grid(to_occupancy_grid(Grid(np.zeros((6, 7), np.int8), 1.0)))
        assert node.plans == 1  # nothing to plan to
