"""The grid node: /wheelgrid/map_cloud -> /wheelgrid/safe_grid (cells) and /map (fine map).

Thin by design: the grid itself is :func:`wheelgrid_nav.grid.build_grid`. Both outputs are
MAP_QOS (reliable, transient local) so RViz, Nav2 and the planner get the current grid whenever
they start. The grid is recomputed at most ``max_rate_hz`` times a second while the map keeps
changing (the newest cloud wins). A cloud that cannot give a safe grid (empty, no floor, all
points above the safe height, malformed) is reported with a warning and the previous grid stays
published: an all-free grid from a bad map would send the chair into walls. An empty map is the
exception: it is the mapper's ``~/reset``, whose next map lies in a new frame, so the previous
grid is withdrawn (republished with every cell unknown).

``~/save`` (std_srvs/Trigger) writes grid.yaml/pgm, fine.yaml/pgm and grid.png into the
``output_dir`` parameter. Parameters may be changed at run time (``set_parameters``): invalid
values are refused, valid ones recompute the grid at once (from the newest map, even a refused
one the new values make good, else the last good map), and a change the last good map gives
no grid with is refused too (the grid and the parameters stay as they were).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import fields, replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from wheelgrid_common import params
from wheelgrid_common.fileio import check_user_folder, user_folder
from wheelgrid_common.map_io import UNKNOWN, to_occupancy_grid
from wheelgrid_common.pointcloud2 import CloudError, read_xyz
from wheelgrid_common.qos import MAP_QOS, MAP_QUEUE_QOS, RELIABLE_QOS
from wheelgrid_common.ros_env import SideSpinner, side_node, spin_node, steady_timer
from wheelgrid_nav.grid import GridError, GridNodeConfig, GridResult, build_grid, grid_config

# Relative names: in the root namespace they are /wheelgrid/..., and a node started
# in a namespace (`--ros-args -r __ns:=/chair1`, a launch file's namespace) keeps to it.
MAP_CLOUD_TOPIC = "wheelgrid/map_cloud"
SAFE_GRID_TOPIC = "wheelgrid/safe_grid"
FINE_MAP_TOPIC = "map"
# The node's heartbeat: the drive stops the chair when it falls silent or says the node is
# stuck (a hung node keeps its last grid published while newer maps go ungridded, and the
# chair drove into a new obstacle). It is sent from a thread of its own, so that a long grid
# (a 144 m floor: 2-3 s) or a ~/save does not silence it; it says how long the node's executor
# has not run (stalled_s) and how long its current grid or save has taken (busy_s).
GRID_STATE_TOPIC = "wheelgrid/grid_state"
GRID_STATE_PERIOD_S = 0.5
_TICK_S = 0.1


def check_rate(hz: float) -> None:
    """``ValueError`` unless ``max_rate_hz`` is a rate a timer can run: NaN and negatives
    meant "no limit" silently, and 1e-12 raised inside create_timer, after the old timer was
    gone, ending the node."""
    if not (math.isfinite(hz) and 0.001 <= hz <= 100.0):
        raise ValueError(f"max_rate_hz must be in [0.001, 100] Hz, not {hz}")


class GridNode(Node):
    """Subscribes the map cloud, publishes the safe grid and the fine map, saves on request."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("grid", **kwargs)
        try:  # a wrongly typed value comes out of declare_dataclass as ValueError too
            self.cfg = params.declare_dataclass(self, GridNodeConfig(), read_only=False)
            params.check_no_undeclared(self)
            self.grid_cfg = grid_config(self.cfg)
            self.grid_cfg.validate()
            check_rate(self.cfg.max_rate_hz)
            check_user_folder(self.cfg.output_dir)
        except ValueError as exc:
            self.get_logger().fatal(f"invalid parameters: {exc}")
            raise SystemExit(2) from exc
        self.period = 1.0 / self.cfg.max_rate_hz if self.cfg.max_rate_hz > 0 else 0.0
        self.result: GridResult | None = None
        self._pending: tuple[Any, str] | None = None
        self._last_good: tuple[Any, str] | None = None
        # the newest map, when it was refused after the last good one: a parameter change
        # may make it good (a floor_clearance raised for a floor that lies 12 cm up)
        self._refused: tuple[Any, str] | None = None
        self._last_compute = -float("inf")
        # why there is no grid, for ~/save's answer: "nothing received" was said too after
        # the map was cleared (~/reset) or when every map so far was refused
        self.grid_pub = self.create_publisher(OccupancyGrid, SAFE_GRID_TOPIC, MAP_QOS)
        self.fine_pub = self.create_publisher(OccupancyGrid, FINE_MAP_TOPIC, MAP_QOS)
        self.create_subscription(PointCloud2, MAP_CLOUD_TOPIC, self._on_cloud, MAP_QUEUE_QOS)
        self._no_grid = f"nothing received on {self.resolve_topic_name(MAP_CLOUD_TOPIC)}"
        self.create_service(Trigger, "~/save", self._on_save)
        self._timer = steady_timer(self, max(self.period, 0.05), self._maybe_compute)
        self._tick = time.monotonic()  # the executor's last run (a timer on it)
        self._busy_since: float | None = None  # a grid or a save under way since
        steady_timer(self, _TICK_S, self._on_tick)
        self._start_heartbeat()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f"waiting for {self.resolve_topic_name(MAP_CLOUD_TOPIC)}; safe_height "
            f"{self.cfg.safe_height} m, cell {self.cfg.cell_size} m, density_threshold "
            f"{self.cfg.density_threshold}"
        )

    def _start_heartbeat(self) -> None:
        """The heartbeat's node, on an executor and a thread of its own."""
        beat = side_node(self, "heartbeat")
        self.state_pub = beat.create_publisher(DiagnosticArray, GRID_STATE_TOPIC, RELIABLE_QOS)
        steady_timer(beat, GRID_STATE_PERIOD_S, self._beat)
        self._heartbeat: SideSpinner | None = SideSpinner(
            beat, "grid-heartbeat", self._spin_heartbeat
        )

    @staticmethod
    def _spin_heartbeat(executor: Any) -> None:
        # at shutdown it falls silent, which is what the drive reads as a dead node
        with suppress(ExternalShutdownException):
            executor.spin()

    def _on_tick(self) -> None:
        self._tick = time.monotonic()

    @contextmanager
    def _working(self) -> Iterator[None]:
        """A grid or a save under way: the heartbeat says so, so a long one is not a hang."""
        self._busy_since = time.monotonic()
        try:
            yield
        finally:
            # the executor runs again from now: set before the busy flag is cleared, or a beat
            # between the two sent "not busy, stalled for the whole grid", read as a hang
            self._tick = time.monotonic()
            self._busy_since = None

    def close(self) -> None:
        """Stop the heartbeat's thread (spin_node calls it before destroying the node)."""
        heartbeat = getattr(self, "_heartbeat", None)
        if heartbeat is not None:
            heartbeat.close()
            self._heartbeat = None

    def destroy_node(self) -> None:
        self.close()  # a caller that only destroys the node stops its heartbeat's thread too
        super().destroy_node()

    def _beat(self) -> None:
        """One heartbeat. Nothing may end the heartbeat's thread: a beat that raised (the
        grid withdrawn by a ~/reset between two reads of it) ended it for good, and the drive
        then refused every step for the rest of the session."""
        try:
            self._publish_state()
        except Exception as exc:
            if self.context.ok():  # at shutdown a publish fails: not worth a word
                self.get_logger().error(f"grid_state not sent: {exc!r}", throttle_duration_sec=10.0)

    def _publish_state(self) -> None:
        # each field read once: the executor's thread changes them meanwhile (busy first, then
        # the tick: see _working)
        now = time.monotonic()
        busy_since = self._busy_since
        tick = self._tick
        result = self.result
        st = DiagnosticStatus(name="grid", hardware_id="wheelgrid")
        if result is not None:
            g = result.stats
            st.level = DiagnosticStatus.OK
            st.message = (
                f"grid {result.grid.rows}x{result.grid.cols} ({g['free']} free, "
                f"{g['occupied']} occ, {g['unknown']} unk)"
            )
        else:
            st.level, st.message = DiagnosticStatus.WARN, f"no grid: {self._no_grid}"
        st.values = [
            KeyValue(key="map_waiting", value=str(self._pending is not None).lower()),
            KeyValue(key="stalled_s", value=f"{now - tick:.2f}"),
            KeyValue(key="busy_s", value=f"{0.0 if busy_since is None else now - busy_since:.2f}"),
        ]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.state_pub.publish(arr)

    def _on_cloud(self, msg: PointCloud2) -> None:
        try:
            # a map of millions of points takes a second or more to read: said busy, or the
            # heartbeat read "stalled, not busy" and the drive stopped for a hung grid node
            with self._working():
                points = read_xyz(msg)
        except CloudError as exc:
            if exc.cause != "empty":
                self._reject(f"unusable map cloud ({exc})")
                return
            # The mapper's ~/reset (a 1 x 0 cloud): the map is gone, at once. It waited as the
            # next map to build at the rate limit, where the next map cloud replaced it, so
            # the cleared map's grid stayed published (and a parameter change rebuilt it). A
            # map still waiting was made before the reset, in the cleared map's frame: gone too.
            self._pending = None
            why = "an empty map cloud: the mapper's ~/reset, or a mapper started anew"
            self._withdraw(GridError("empty", why))
            return
        self._pending = (points, msg.header.frame_id or "map")
        self._maybe_compute()

    def _reject(self, why: str) -> None:
        kept = "kept the previous grid" if self.result is not None else "no grid published yet"
        if self.result is None:
            self._no_grid = f"the last map was refused: {why}"
        self.get_logger().warning(f"{why}; {kept}")

    def _maybe_compute(self) -> None:
        if self._pending is None or time.monotonic() - self._last_compute < self.period:
            return
        points, frame_id = self._pending
        self._pending = None
        self._last_compute = time.monotonic()
        with self._working():
            try:
                result = build_grid(points, self.grid_cfg, frame_id=frame_id)
            except GridError as exc:
                if exc.cause == "empty":  # no finite point: a cleared map as well
                    self._withdraw(exc)
                    return
                self._refused = (points, frame_id)
                self._reject(f"bad map ({exc.cause}): {exc}")
                return
            self._refused = None
            self._publish(result, points, frame_id)

    def _publish(self, result: GridResult, points: Any, frame_id: str) -> None:
        """Make ``result`` (built from ``points``) the node's grid and publish both grids."""
        self.result = result
        self._last_good = (points, frame_id)
        stamp = self.get_clock().now().to_msg()
        self.grid_pub.publish(to_occupancy_grid(result.grid, stamp))
        self.fine_pub.publish(to_occupancy_grid(result.fine, stamp))
        st = result.stats
        for doubt in st["warnings"]:
            self.get_logger().warning(doubt, throttle_duration_sec=60.0)
        self.get_logger().info(
            f"grid {result.grid.rows} x {result.grid.cols} from {st['map_points']} map points "
            f"(yaw {st['yaw_deg']:.2f} deg): {st['occupied']} occupied, {st['free']} free, "
            f"{st['unknown']} unknown, {1000 * (time.monotonic() - self._last_compute):.0f} ms"
        )

    def _withdraw(self, exc: GridError) -> None:
        """An empty map is the mapper's ~/reset (or a map with no finite point): the map the
        grid was made of no longer exists, and the next map's frame is placed under its first
        pose, so the old cells no longer lie where the new poses are. Kept, the planner and the
        drive went on using them. Both grids are replaced by their geometry with every cell
        unknown (no route; a running move sees its cells change and stops), and the map is
        forgotten, so a parameter change cannot bring the old grid back (nor a refused map:
        with no grid yet, there is nothing to withdraw but the maps are forgotten all the same)."""
        old = self.result
        self.result = None
        self._last_good = self._refused = None
        self._no_grid = "the map was cleared (the mapper's ~/reset); no grid until a new map"
        if old is None:
            self.get_logger().info(f"the map was cleared ({exc}): no grid until a new map")
            return
        stamp = self.get_clock().now().to_msg()
        for grid, pub in ((old.grid, self.grid_pub), (old.fine, self.fine_pub)):
            unknown = replace(grid, data=np.full_like(grid.data, UNKNOWN))
            pub.publish(to_occupancy_grid(unknown, stamp))
        self.get_logger().warning(
            f"the map was cleared ({exc}): grid withdrawn, every cell unknown until a new map"
        )

    def _on_set_parameters(self, changed: list[Any]) -> SetParametersResult:
        """Validate the new values as a whole and build the grid with them before accepting.

        The newest map, where it was refused, is tried first: the new values may make it good
        (a map refused for its floor 12 cm up, and ``floor_clearance`` raised: with the mapper
        idle, no new map came and no grid ever did). Then the last good map: a change it gives
        no grid with (``min_floor_points`` above its floor points, a ``pixel_size`` too fine for
        its floor) is refused with the reason. It was accepted, the old grid stayed published,
        and the parameters no longer said what the grid was made with (a later ``cell_size``,
        accepted too, never became a grid)."""
        values = {f.name: getattr(self.cfg, f.name) for f in fields(GridNodeConfig)}
        values.update({p.name: p.value for p in changed if p.name in values})
        try:
            cfg = params.from_mapping(GridNodeConfig, values)
            grid_cfg = grid_config(cfg)
            grid_cfg.validate()
            check_rate(cfg.max_rate_hz)  # 1e-12 killed the node: its timer went first
            check_user_folder(cfg.output_dir)
        except (TypeError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        with self._working():
            return self._apply(changed, cfg, grid_cfg)

    def _apply(self, changed: list[Any], cfg: GridNodeConfig, grid_cfg: Any) -> SetParametersResult:
        """The grid built with checked new values (see _on_set_parameters), then theirs."""
        result, held, still = None, None, None
        if self._refused is not None:
            # the newest map, refused with the old values, may give a grid with the new ones
            # (only a map that once gave a grid was recomputed: with the mapper idle, none came)
            self._last_compute = time.monotonic()
            try:
                result = build_grid(self._refused[0], grid_cfg, frame_id=self._refused[1])
                held, self._refused = self._refused, None
            except GridError as exc:
                still = exc
        if result is None and self._last_good is not None:
            self._last_compute = time.monotonic()
            held = self._last_good
            try:
                result = build_grid(held[0], grid_cfg, frame_id=held[1])
            except GridError as exc:
                return SetParametersResult(
                    successful=False,
                    reason=f"the current map gives no grid with it ({exc.cause}): {exc}",
                )
        self.cfg, self.grid_cfg = cfg, grid_cfg
        self.period = 1.0 / cfg.max_rate_hz if cfg.max_rate_hz > 0 else 0.0
        self.destroy_timer(self._timer)
        self._timer = steady_timer(self, max(self.period, 0.05), self._maybe_compute)
        self.get_logger().info("parameters changed: " + ", ".join(p.name for p in changed))
        if result is not None and held is not None:
            self._publish(result, *held)
        elif still is not None:
            self._reject(f"the newest map still gives no grid ({still.cause}): {still}")
        return SetParametersResult(successful=True)

    def _on_save(self, _req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        if self.result is None:
            resp.success = False
            resp.message = "no grid: " + self._no_grid
            return resp
        try:
            from wheelgrid_nav.grid_png import write_outputs

            with self._working():
                files = write_outputs(self.result, user_folder(self.cfg.output_dir))
        except OSError as exc:
            resp.success = False
            resp.message = f"cannot write {self.cfg.output_dir}: {exc}"
            return resp
        resp.success = True
        resp.message = "wrote " + " ".join(str(p) for p in files.values())
        self.get_logger().info(resp.message)
        return resp


def main(args: list[str] | None = None) -> None:
    sys.exit(spin_node(lambda: GridNode(), args))


if __name__ == "__main__":
    main()
