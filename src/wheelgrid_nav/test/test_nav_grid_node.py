"""The grid node over real DDS (loopback): both grids transient-local, bad maps keep the previous
grid, ~/save writes the files."""

import contextlib
import math
import subprocess
import time
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from wheelgrid_common.map_io import OCCUPIED, from_occupancy_grid, read_map
from wheelgrid_common.pointcloud2 import to_pointcloud2
from wheelgrid_common.qos import MAP_QOS
from wheelgrid_common.testing import (
    call_service,
    managed_process,
    python_module,
    rclpy_context,
    spin_until,
)
from wheelgrid_nav.grid_synth import paper_like_boxes, paper_like_expected, room_cloud, transform

pytestmark = pytest.mark.ros


def _wait_for_log(path, text: str, count: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.read_text(errors="replace").count(text) >= count:
            return True
        time.sleep(0.05)
    return False


def test_grid_node_publishes_keeps_and_saves(tmp_path):
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    out = tmp_path / "saved"
    log = tmp_path / "node.log"
    cloud = transform(room_cloud(paper_like_boxes(), spacing=0.05), math.radians(4.0), (-0.6, -6.6))
    args = python_module(
        "wheelgrid_nav.grid_node",
        "--ros-args",
        "-p",
        f"output_dir:={out}",
        "-p",
        "max_rate_hz:=10.0",
    )
    with (
        open(log, "w") as logf,
        managed_process(args, stdout=logf, stderr=subprocess.STDOUT) as proc,
        rclpy_context() as ctx,
    ):
        node = Node("grid_node_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        try:
            save = node.create_client(Trigger, "/grid/save")
            assert spin_until(ex, save.service_is_ready, timeout=20.0), log.read_text()

            def call_save():
                answer = call_service(ex, save, Trigger.Request)
                assert answer is not None, log.read_text()
                return answer

            early = call_save()
            assert not early.success and "no grid: nothing received" in early.message

            pub = node.create_publisher(PointCloud2, "/wheelgrid/map_cloud", MAP_QOS)
            pub.publish(to_pointcloud2(cloud, "map"))
            # Subscribers created after the grid was computed must still get it (transient local).
            assert _wait_for_log(log, "grid 8 x 8", 1, 30.0), log.read_text()
            grids: list = []
            fines: list = []
            node.create_subscription(OccupancyGrid, "/wheelgrid/safe_grid", grids.append, MAP_QOS)
            node.create_subscription(OccupancyGrid, "/map", fines.append, MAP_QOS)
            assert spin_until(ex, lambda: grids and fines, timeout=20.0)
            grid = from_occupancy_grid(grids[0])
            np.testing.assert_array_equal(grid.data == OCCUPIED, paper_like_expected())
            assert grid.resolution == pytest.approx(1.2) and grid.frame_id == "map"
            assert grid.origin[2] == pytest.approx(math.radians(4.0), abs=1e-3)
            fine = from_occupancy_grid(fines[0])
            assert fine.resolution == pytest.approx(0.05) and fine.origin[2] == 0.0
            assert set(np.unique(fine.data).tolist()) <= {-1, 0, 100}

            # Bad maps: everything above the safe height, no floor, and the same room
            # flattened to z = 0 (an all-free grid, before it was refused). An empty one is a
            # cleared map, which withdraws the grid (its own test below).
            bad_clouds = [
                np.column_stack([np.arange(50.0), np.zeros(50), np.full(50, 2.2)]),
                np.column_stack([np.arange(500.0) / 50, np.zeros(500), np.full(500, 0.9)]),
                np.column_stack([cloud[:, :2], np.zeros(len(cloud))]),
            ]
            for i, bad in enumerate(bad_clouds, start=1):
                pub.publish(to_pointcloud2(bad, "map"))
                assert _wait_for_log(log, "kept the previous grid", i, 20.0), log.read_text()
            text = log.read_text()
            assert "all_above_band" in text and "no_floor" in text
            assert "only_floor" in text
            spin_until(ex, lambda: len(grids) > 1, timeout=1.0)
            assert len(grids) == 1 and len(fines) == 1  # nothing new was published
            late: list = []
            node.create_subscription(OccupancyGrid, "/wheelgrid/safe_grid", late.append, MAP_QOS)
            assert spin_until(ex, lambda: late, timeout=20.0)
            np.testing.assert_array_equal(from_occupancy_grid(late[0]).data, grid.data)

            saved = call_save()
            assert saved.success, saved.message
            for name in ("grid.yaml", "grid.pgm", "fine.yaml", "fine.pgm", "grid.png"):
                assert (out / name).is_file(), name
            np.testing.assert_array_equal(read_map(out / "grid.yaml").data, grid.data)
            np.testing.assert_array_equal(read_map(out / "fine.yaml").data, fine.data)

            # Parameters at run time: an invalid cell size is refused, a higher safe height
            # recomputes the grid from the last good map (Barrier 2 now blocks its row).
            from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
            from rcl_interfaces.srv import SetParameters

            setp = node.create_client(SetParameters, "/grid/set_parameters")
            assert spin_until(ex, setp.service_is_ready, timeout=20.0)

            def set_double(name: str, value: float):
                def request() -> SetParameters.Request:
                    req = SetParameters.Request()
                    req.parameters = [
                        Parameter(
                            name=name,
                            value=ParameterValue(
                                type=ParameterType.PARAMETER_DOUBLE, double_value=value
                            ),
                        )
                    ]
                    return req

                answer = call_service(ex, setp, request)
                assert answer is not None, log.read_text()
                return answer.results[0]

            refused = set_double("cell_size", 1.23)
            assert not refused.successful and "whole number" in refused.reason
            assert set_double("safe_height", 1.6).successful
            assert spin_until(ex, lambda: len(grids) > 1, timeout=20.0), log.read_text()
            higher = from_occupancy_grid(grids[-1])
            expected = paper_like_expected().copy()
            expected[4, 4:] = True
            np.testing.assert_array_equal(higher.data == OCCUPIED, expected)
            assert proc.poll() is None  # still running after all of it
        finally:
            ex.shutdown()
            node.destroy_node()


@pytest.mark.parametrize(
    "param",
    [
        "max_rate_hz:=1e-12",
        "max_rate_hz:=.nan",
        "pixel_size:=1",
        "floor_clearance:=1.0",
        "output_dir:=~nosuchuser_wg/grid",  # ~/save raised RuntimeError: the node died
    ],
)
def test_bad_parameters_stop_the_grid_node_with_exit_2(param):
    """1e-12 Hz raised inside create_timer (a traceback), NaN meant "no limit" silently, a
    wrongly typed value was a traceback, and a 1 m floor clearance made tables floor."""
    import subprocess

    from wheelgrid_common.ros_env import child_env
    from wheelgrid_common.testing import python_module

    args = python_module("wheelgrid_nav.grid_node", "--ros-args", "-p", param)
    proc = subprocess.run(args, env=child_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "FATAL" in proc.stderr + proc.stdout and "Traceback" not in proc.stderr


def test_a_misspelt_parameter_in_a_params_file_stops_the_node_naming_it(tmp_path):
    """ROS 2 ignores a parameter no node declared: `safe_hieght: 1.4` ran with the default
    safe height, exit 0. Every node refuses what it does not declare, with a suggestion."""
    from wheelgrid_common.ros_env import child_env

    params = tmp_path / "p.yaml"
    params.write_text("grid:\n  ros__parameters:\n    safe_hieght: 1.4\n")
    args = python_module(
        "wheelgrid_nav.grid_node", "--ros-args", "-r", "__node:=grid", "--params-file", str(params)
    )
    proc = subprocess.run(args, env=child_env(), capture_output=True, text=True, timeout=60)
    out = proc.stderr + proc.stdout
    assert proc.returncode == 2, out
    assert "FATAL" in out and "'safe_hieght' (did you mean 'safe_height'?)" in out, out
    assert "Traceback" not in out


def test_a_params_file_that_does_not_parse_stops_the_node_with_exit_2(tmp_path):
    """rclpy's own traceback and exit 1, which a launcher reports as a node that failed."""
    from wheelgrid_common.ros_env import child_env

    params = tmp_path / "p.yaml"
    params.write_text("grid:\n  ros__parameters:\n    safe_height: [1.5\n")
    args = python_module("wheelgrid_nav.grid_node", "--ros-args", "--params-file", str(params))
    proc = subprocess.run(args, env=child_env(), capture_output=True, text=True, timeout=60)
    out = proc.stderr + proc.stdout
    assert proc.returncode == 2, out
    assert "[FATAL] cannot start" in out and "Traceback" not in out, out


@contextlib.contextmanager
def in_process_grid(**params: Any) -> Iterator[SimpleNamespace]:
    """A real GridNode with ``params``, and a test node in the same context that publishes map
    clouds (``pub``, matched) and collects both grids (``grids``, ``fines``); ``ex`` spins both."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2

    from wheelgrid_nav.grid_node import GridNode

    with rclpy_context() as ctx:
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        grid_node = GridNode(context=ctx, parameter_overrides=overrides)
        node = Node("grid_in_process_test", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(grid_node)
        ex.add_node(node)
        try:
            t = SimpleNamespace(grid_node=grid_node, node=node, ex=ex, grids=[], fines=[])
            node.create_subscription(OccupancyGrid, "/wheelgrid/safe_grid", t.grids.append, MAP_QOS)
            node.create_subscription(OccupancyGrid, "/map", t.fines.append, MAP_QOS)
            t.pub = node.create_publisher(PointCloud2, "/wheelgrid/map_cloud", MAP_QOS)
            assert spin_until(ex, lambda: t.pub.get_subscription_count() > 0, 15.0)
            yield t
        finally:
            ex.shutdown()
            grid_node.destroy_node()
            node.destroy_node()


def test_the_grid_node_reports_its_state_twice_a_second_and_how_long_its_executor_stalled():
    """The drive stops the chair when this heartbeat falls silent or says the node is stuck (a
    hung grid node kept its last grid published and the chair drove into an obstacle of a
    newer map). It comes at GRID_STATE_PERIOD_S from a thread of its own, so that a long grid
    does not silence it (a 144 m floor took 2-3 s), and says how long the node's executor
    has not run (stalled_s) and whether a grid is published."""
    import time

    from diagnostic_msgs.msg import DiagnosticArray

    from wheelgrid_common.qos import RELIABLE_QOS
    from wheelgrid_nav.grid_node import GRID_STATE_PERIOD_S

    with in_process_grid(max_rate_hz=100.0) as t:
        states: list[tuple[float, DiagnosticArray]] = []
        t.grid_node.create_subscription(
            DiagnosticArray,
            "/wheelgrid/grid_state",
            lambda m: states.append((time.monotonic(), m)),
            RELIABLE_QOS,
        )
        assert spin_until(t.ex, lambda: len(states) >= 2, 5.0)
        assert states[-1][1].status[0].message.startswith("no grid: nothing received")
        t.pub.publish(to_pointcloud2(room_cloud(paper_like_boxes(), spacing=0.05), "map"))
        assert spin_until(t.ex, lambda: states[-1][1].status[0].message.startswith("grid "), 20.0)
        n = len(states)
        assert spin_until(t.ex, lambda: len(states) >= n + 4, 5.0)
        gaps = np.diff([at for at, _ in states[n - 1 :]])
        assert gaps.max() < 4 * GRID_STATE_PERIOD_S, gaps

        # nothing spins the node's executor (a hung node): the heartbeat, heard here on an
        # executor of another node, says so
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        def value(msg: DiagnosticArray, key: str) -> float:
            return float(next(kv.value for kv in msg.status[0].values if kv.key == key))

        assert value(states[-1][1], "stalled_s") < 4 * GRID_STATE_PERIOD_S
        listener = Node("grid_state_listener", context=t.grid_node.context)
        heard: list[DiagnosticArray] = []
        listener.create_subscription(
            DiagnosticArray, "/wheelgrid/grid_state", heard.append, RELIABLE_QOS
        )
        ex = SingleThreadedExecutor(context=t.grid_node.context)
        ex.add_node(listener)
        try:
            assert spin_until(ex, lambda: bool(heard) and value(heard[-1], "stalled_s") > 2.0, 10.0)
            assert value(heard[-1], "busy_s") == 0.0
        finally:
            ex.shutdown()
            listener.destroy_node()


def test_a_heartbeat_that_fails_once_beats_on_and_a_long_grid_ends_with_a_fresh_tick():
    """A beat that raised (the grid withdrawn by a ~/reset between two of its reads) ended the
    heartbeat's thread for good, and the drive refused every step from then on; and a beat
    between a long grid's end and the executor's next tick said "not busy, stalled for the
    whole grid", which the drive reads as a hung node."""
    import time

    from diagnostic_msgs.msg import DiagnosticArray

    from wheelgrid_common.qos import RELIABLE_QOS

    with in_process_grid(max_rate_hz=100.0) as t:
        node = t.grid_node
        real, calls = node._publish_state, {"n": 0}

        def flaky() -> None:
            calls["n"] += 1
            if calls["n"] == 1:
                raise AttributeError("'NoneType' object has no attribute 'stats'")
            real()

        node._publish_state = flaky
        heard: list[DiagnosticArray] = []
        node.create_subscription(
            DiagnosticArray, "/wheelgrid/grid_state", heard.append, RELIABLE_QOS
        )
        assert spin_until(t.ex, lambda: calls["n"] >= 1 and len(heard) >= 2, 10.0)
        assert node._heartbeat is not None and node._heartbeat.thread.is_alive()
        with node._working():
            time.sleep(0.3)  # the executor's tick cannot run meanwhile
        assert time.monotonic() - node._tick < 0.1 and node._busy_since is None


def test_use_sim_time_is_described_and_cannot_change_live():
    """rclpy's own use_sim_time was the one parameter a running node still took (every other
    is read-only or checked), with no description: set live with no /clock, the node's stamps
    fell to 0 at once. It is set at start only now, in every node (declare_dataclass)."""
    from rclpy.parameter import Parameter

    with in_process_grid(max_rate_hz=100.0) as t:
        [result] = t.grid_node.set_parameters([Parameter("use_sim_time", value=True)])
        assert not result.successful and "read-only" in result.reason
        assert t.grid_node.get_parameter("use_sim_time").value is False
        assert "/clock" in t.grid_node.describe_parameter("use_sim_time").description
        # the node's own parameters still change live
        [result] = t.grid_node.set_parameters([Parameter("safe_height", value=1.6)])
        assert result.successful


def test_the_grid_parameters_declare_their_ranges_and_a_value_outside_is_refused():
    """No parameter carried a range: `ros2 param describe grid density_threshold` showed none
    and rqt's reconfigure could draw no slider for the one node whose parameters change live."""
    from rclpy.parameter import Parameter

    with in_process_grid(max_rate_hz=100.0) as t:
        node = t.grid_node
        (ranged,) = node.describe_parameter("density_threshold").floating_point_range
        assert (ranged.from_value, ranged.to_value) == (0.0, 1.0)
        (height,) = node.describe_parameter("safe_height").floating_point_range
        assert height.from_value == 0.9 and height.to_value == math.inf
        (count,) = node.describe_parameter("min_floor_points").integer_range
        # int64's top for an open end: 2^63 (a float's) killed the node answering a describe
        assert (count.from_value, count.to_value, count.step) == (1, 2**63 - 1, 1)
        # what `ros2 param describe` and rqt ask, over DDS: every parameter described
        from rcl_interfaces.srv import DescribeParameters

        from wheelgrid_common.testing import call_service

        names = [n for n in node._parameters if n != "use_sim_time"]
        ask = t.node.create_client(DescribeParameters, "/grid/describe_parameters")
        got = call_service(t.ex, ask, lambda: DescribeParameters.Request(names=names))
        assert got is not None and [d.name for d in got.descriptors] == names
        assert not node.describe_parameter("alignment").floating_point_range
        [result] = node.set_parameters([Parameter("density_threshold", value=1.5)])
        assert not result.successful and "out of range" in result.reason, result.reason
        assert node.get_parameter("density_threshold").value == 0.05
        assert node.cfg.density_threshold == 0.05
        [result] = node.set_parameters([Parameter("density_threshold", value=0.1)])
        assert result.successful, result.reason
        # a folder no user has (``~maps`` for ``~/maps``): refused, not a node killed at ~/save
        [result] = node.set_parameters([Parameter("output_dir", value="~nosuchuser_wg/g")])
        assert not result.successful and "no user 'nosuchuser_wg'" in result.reason


def test_a_cleared_map_withdraws_the_grid_and_a_parameter_change_does_not_bring_it_back():
    """The mapper's ~/reset publishes an empty map cloud and starts a new map whose frame is
    placed under the next pose: the running grid node kept the old grid, so the planner and the
    drive went on planning and checking routes on cells of a map that no longer exists, in a
    frame the new poses do not share. Now an empty map withdraws it: the same geometry, every
    cell unknown (the planner finds no route, a running move sees its cells change and stops),
    and a later parameter change does not recompute the cleared map."""
    from rclpy.parameter import Parameter

    from wheelgrid_common.map_io import UNKNOWN

    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid(max_rate_hz=100.0) as t:
        grid_node, ex, grids, fines, pub = t.grid_node, t.ex, t.grids, t.fines, t.pub
        pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(ex, lambda: grids and fines, 20.0)
        good = from_occupancy_grid(grids[-1])
        assert (good.data == 0).any()

        pub.publish(to_pointcloud2(np.empty((0, 3)), "map"))  # the mapper's ~/reset
        assert spin_until(ex, lambda: len(grids) > 1 and len(fines) > 1, 10.0), (
            "the grid of the cleared map stayed published"
        )
        gone = from_occupancy_grid(grids[-1])
        assert gone.data.shape == good.data.shape and gone.frame_id == good.frame_id
        assert gone.resolution == good.resolution and gone.origin == good.origin
        assert (gone.data == UNKNOWN).all()
        assert (from_occupancy_grid(fines[-1]).data == UNKNOWN).all()
        # ~/save says why there is nothing to save (it said "nothing received")
        from std_srvs.srv import Trigger

        answer = grid_node._on_save(Trigger.Request(), Trigger.Response())
        assert not answer.success and "the map was cleared" in answer.message
        high = np.column_stack([np.arange(50.0), np.zeros(50), np.full(50, 2.2)])
        pub.publish(to_pointcloud2(high, "map"))  # refused: everything above the band
        assert spin_until(ex, lambda: "refused" in grid_node._no_grid, 10.0)
        answer = grid_node._on_save(Trigger.Request(), Trigger.Response())
        assert "the last map was refused" in answer.message, answer.message

        n = len(grids)
        assert grid_node.set_parameters([Parameter("safe_height", value=1.6)])[0].successful
        spin_until(ex, lambda: len(grids) > n, 1.0)
        assert len(grids) == n, "a parameter change republished the cleared map's grid"


@pytest.mark.parametrize("then", ["a refused map", "a good map", "a parameter change"])
def test_a_reset_within_the_rate_limit_withdraws_the_grid_whatever_comes_next(then: str) -> None:
    """The mapper's ~/reset waited, as any map does, for the rate limit (1 / max_rate_hz after
    the last grid), and the next map cloud replaced it there: with a refused map next (a new
    scan's first frames: only floor) the cleared map's grid stayed published as current; with
    a good one no all-unknown grid ever went out, so the planner kept a goal in the cleared
    map's frame; a parameter change rebuilt the cleared map's grid. The reset now withdraws
    the grid as it comes."""
    from rclpy.parameter import Parameter

    from wheelgrid_common.map_io import UNKNOWN

    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid(max_rate_hz=1.0) as t:
        t.pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(t.ex, lambda: t.grids, 20.0)
        t.pub.publish(to_pointcloud2(np.empty((0, 3)), "map"))  # the mapper's ~/reset
        assert spin_until(t.ex, lambda: len(t.grids) > 1, 1.0), "the reset was held back"
        assert (from_occupancy_grid(t.grids[-1]).data == UNKNOWN).all()
        if then == "a parameter change":
            assert t.grid_node.set_parameters([Parameter("safe_height", value=1.6)])[0].successful
        elif then == "a refused map":
            xy = np.random.default_rng(0).uniform(0, 3, (5000, 2))
            t.pub.publish(to_pointcloud2(np.column_stack([xy, np.zeros(5000)]), "map"))
        else:
            t.pub.publish(
                to_pointcloud2(cloud[::2] + np.array([1.0, 0.5, 0.0]), "map")
            )  # new frame
        # the next map waits for the rate limit (1 s after the first grid, on a 1 s timer)
        spin_until(t.ex, lambda: len(t.grids) > 2, 6.0 if then == "a good map" else 2.5)
        if then == "a good map":
            assert len(t.grids) == 3 and (from_occupancy_grid(t.grids[-1]).data == 0).any()
        else:
            assert len(t.grids) == 2 and t.grid_node.result is None


def test_a_cloud_of_no_points_over_bytes_of_data_keeps_the_grid():
    """A map cloud whose header says 0 points but which carries data does not describe its
    data: it was taken for the mapper's ~/reset (an empty map) and withdrew a good grid (every
    cell unknown, the last good map forgotten). It is malformed, as the same data with a bad
    row_step is: the grid is kept."""
    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid(max_rate_hz=100.0) as t:
        t.pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(t.ex, lambda: t.grids, 20.0)
        rejected: list[str] = []
        reject = t.grid_node._reject
        t.grid_node._reject = lambda why: (rejected.append(why), reject(why))
        bad = to_pointcloud2(cloud[:1000], "map")
        bad.width = 0
        t.pub.publish(bad)
        assert spin_until(t.ex, lambda: rejected, 10.0)
        assert "excess_data" in rejected[0] or "0 points but" in rejected[0], rejected
        spin_until(t.ex, lambda: False, 0.5)
        assert len(t.grids) == 1 and t.grid_node.result is not None


def test_a_map_held_back_by_the_rate_limit_is_computed_under_use_sim_time_with_no_clock():
    """A map cloud that comes within ``1 / max_rate_hz`` of the last grid waits for the node's
    timer. Under ``use_sim_time`` that timer ran on ROS time: with no ``/clock`` (or a replayed
    bag's clock that had stopped) it never fired, and the newest map (here: the room after an
    obstacle appeared) never became a grid, while the old grid stayed published as current.
    The timer now runs on steady time."""
    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid(max_rate_hz=2.0, use_sim_time=True) as t:
        ex, grids, pub = t.ex, t.grids, t.pub
        pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(ex, lambda: grids, 20.0)
        first = from_occupancy_grid(grids[-1])
        # a block filling the free corner cell at the origin, published at once: held back
        # by the rate limit (its row is the last: rows run down from the highest y)
        assert first.data[-1, 0] == 0
        x0 = first.origin[0] + 0.5 * first.resolution
        y0 = first.origin[1] + 0.5 * first.resolution
        g = np.linspace(-0.55, 0.55, 23)
        block = np.array([(x0 + a, y0 + b, z) for a in g for b in g for z in (0.3, 0.6)])
        pub.publish(to_pointcloud2(np.vstack([cloud, block]), "map"))
        assert spin_until(ex, lambda: len(grids) > 1, 10.0), "the held-back map was lost"
        assert from_occupancy_grid(grids[-1]).data[-1, 0] == OCCUPIED


def test_save_puts_a_tilde_output_dir_under_the_users_home(tmp_path, monkeypatch):
    """``output_dir: ~/grids`` reached ~/save as written (no shell expands a ROS parameter)
    and the five files went into a folder literally named ``~``; it now means the home."""
    from std_srvs.srv import Trigger

    home, started = tmp_path / "home", tmp_path / "started_here"
    home.mkdir()
    started.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(started)
    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid(output_dir="~/grids") as t:
        t.pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(t.ex, lambda: t.grids, 20.0)
        answer = t.grid_node._on_save(Trigger.Request(), Trigger.Response())
    assert answer.success, answer.message
    assert (home / "grids" / "grid.yaml").is_file() and (home / "grids" / "grid.pgm").is_file()
    assert not (started / "~").exists()


def test_a_parameter_change_the_current_map_gives_no_grid_with_is_refused():
    """``min_floor_points`` above the map's floor points (or a ``pixel_size`` too fine for its
    floor) was accepted: the recompute failed, the old grid stayed published, and from then
    on the node's parameters said one thing and its grid another -- a later ``cell_size``
    1.0, accepted too, never became a grid (1.2 m cells stayed on the topic) and every new
    map was refused. Now such a change is refused with the reason and leaves the grid and
    the parameters as they were; a good one is applied and published at once."""
    from rclpy.parameter import Parameter

    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid(max_rate_hz=100.0) as t:
        grid_node, ex, grids, pub = t.grid_node, t.ex, t.grids, t.pub
        pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(ex, lambda: grids, 20.0)
        n = len(grids)
        (answer,) = grid_node.set_parameters([Parameter("min_floor_points", value=10**7)])
        assert not answer.successful and "no_floor" in answer.reason, answer.reason
        assert grid_node.get_parameter("min_floor_points").value == 50
        assert grid_node.grid_cfg.min_floor_points == 50
        spin_until(ex, lambda: len(grids) > n, 1.0)
        assert len(grids) == n
        (answer,) = grid_node.set_parameters([Parameter("cell_size", value=1.0)])
        assert answer.successful, answer.reason
        assert spin_until(ex, lambda: len(grids) > n, 10.0)
        assert from_occupancy_grid(grids[-1]).resolution == pytest.approx(1.0)


def test_a_parameter_change_recomputes_a_refused_map():
    """A map refused with "no floor found ... is the map levelled with the floor at z = 0?"
    (here its floor lies 12 cm up) and a ``floor_clearance`` raised to take it in: the change
    was accepted and applied to no map at all, since only a map that once gave a grid was
    recomputed; with the mapper idle (a bag replayed to its end), no grid ever came. Now the
    newest map, refused or not, is recomputed with the new values."""
    from rclpy.parameter import Parameter

    cloud = room_cloud(paper_like_boxes(), spacing=0.05) + np.array([0.0, 0.0, 0.12])
    with in_process_grid(max_rate_hz=100.0) as t:
        grid_node, ex, grids, pub = t.grid_node, t.ex, t.grids, t.pub
        pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(ex, lambda: "refused" in grid_node._no_grid, 20.0)
        assert "no_floor" in grid_node._no_grid and not grids
        (answer,) = grid_node.set_parameters([Parameter("floor_clearance", value=0.15)])
        assert answer.successful, answer.reason
        assert spin_until(ex, lambda: grids, 10.0), "the refused map was not recomputed"
        np.testing.assert_array_equal(
            from_occupancy_grid(grids[-1]).data == OCCUPIED, paper_like_expected()
        )


def test_a_reset_queued_behind_a_busy_node_is_not_replaced_by_the_next_map() -> None:
    """While the node gridded a big map, the mapper's ~/reset (an empty map) and its next map
    came: the subscription kept one message, the next map replaced the reset, and (refused:
    only floor) the cleared map's grid stayed published (a review). Both are read in turn."""
    from wheelgrid_common.map_io import UNKNOWN

    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    with in_process_grid() as t:
        t.pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(t.ex, lambda: t.grids, 20.0)
        # both sent before the node's executor runs again, as while it grids a big map
        t.pub.publish(to_pointcloud2(np.empty((0, 3)), "map"))  # the mapper's ~/reset
        xy = np.random.default_rng(0).uniform(0, 3, (5000, 2))
        t.pub.publish(to_pointcloud2(np.column_stack([xy, np.zeros(5000)]), "map"))
        assert spin_until(t.ex, lambda: len(t.grids) > 1, 5.0), "the reset was lost"
        assert (from_occupancy_grid(t.grids[-1]).data == UNKNOWN).all()


def test_the_heartbeat_says_busy_while_a_map_is_read(monkeypatch) -> None:
    """Reading a map of millions of points took seconds outside the busy mark: the heartbeat
    said "stalled, not busy", which the drive reads as a hung grid node (a review)."""
    from wheelgrid_nav import grid_node as gn

    cloud = room_cloud(paper_like_boxes(), spacing=0.05)
    read = gn.read_xyz
    busy_while_read: list[bool] = []
    with in_process_grid() as t:

        def slow_read(msg):
            busy_while_read.append(t.grid_node._busy_since is not None)
            return read(msg)

        monkeypatch.setattr(gn, "read_xyz", slow_read)
        t.pub.publish(to_pointcloud2(cloud, "map"))
        assert spin_until(t.ex, lambda: t.grids, 20.0)
    assert busy_while_read == [True]


def test_an_empty_output_dir_is_refused() -> None:
    """An empty output_dir named the node's working directory, and ~/save replaced grid files
    there (a review)."""
    from wheelgrid_common.fileio import check_user_folder

    for text in ("", "  "):
        with pytest.raises(ValueError, match="output_dir is empty"):
            check_user_folder(text)
