"""The whole chain (paper Fig. 13) as supervised processes plus an in-process monitor node.

Shared by ``wheelgrid launch`` and ``wheelgrid demo``: both need the same start order, the
same death detection and the same one-line status.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from wheelgrid_bringup.supervisor import Supervisor
from wheelgrid_common.map_io import Grid, from_occupancy_grid
from wheelgrid_common.qos import MAP_QOS, RELIABLE_QOS
from wheelgrid_common.services import call_with_retry, poll_until


class NodeDiedError(RuntimeError):
    def __init__(self, name: str, code: int, tail: str) -> None:
        super().__init__(f"node '{name}' died (exit code {code})")
        self.name = name
        self.code = code
        self.tail = tail


@dataclass
class ChainState:
    """What the monitor has seen; read under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    mapper: dict[str, str] = field(default_factory=dict)
    last_mapper_t: float = 0.0
    map_points: int = 0
    map_cloud: Any = None
    grid: Grid | None = None
    grid_msg: Any = None
    grid_updates: int = 0
    last_grid_t: float = 0.0
    last_cloud_t: float = 0.0
    plan: list[tuple[float, float]] = field(default_factory=list)
    plan_updates: int = 0
    bridge: dict[str, str] = field(default_factory=dict)
    drive: dict[str, str] = field(default_factory=dict)
    drive_level: int = 0
    drive_message: str = ""
    commands: list[dict[str, Any]] = field(default_factory=list)
    chair_track: list[tuple[float, float, float, float]] = field(default_factory=list)


def _diag_values(msg: Any) -> tuple[dict[str, str], int, str]:
    values: dict[str, str] = {}
    level, message = 0, ""
    for status in msg.status:
        for kv in status.values:
            values[kv.key] = kv.value
        lv = (
            int.from_bytes(status.level, "little")
            if isinstance(status.level, bytes)
            else int(status.level)
        )
        if lv >= level:
            level, message = lv, status.message
    return values, level, message


class Monitor:
    """An rclpy node that watches the chain's outputs (and can send goals / poses)."""

    def __init__(
        self, context: Any, name: str = "wheelgrid_monitor", namespace: str | None = None
    ) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
        from nav_msgs.msg import OccupancyGrid
        from nav_msgs.msg import Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String

        self.state = ChainState()
        # in the chain's namespace: its topic names are relative, as the nodes' are
        self.node = Node(name, context=context, namespace=namespace)
        n = self.node
        n.create_subscription(DiagnosticArray, "wheelgrid/mapper_status", self._on_mapper, 10)
        n.create_subscription(PointCloud2, "wheelgrid/map_cloud", self._on_cloud, MAP_QOS)
        n.create_subscription(OccupancyGrid, "wheelgrid/safe_grid", self._on_grid, MAP_QOS)
        n.create_subscription(PathMsg, "wheelgrid/plan", self._on_plan, MAP_QOS)
        n.create_subscription(DiagnosticArray, "wheelgrid/drive_state", self._on_drive, 10)
        n.create_subscription(DiagnosticArray, "iphone/bridge_status", self._on_bridge, 10)
        n.create_subscription(String, "wheelgrid/drive_commands", self._on_command, 50)
        n.create_subscription(PoseStamped, "wheelgrid/chair_pose", self._on_chair, 50)
        self.goal_pub = n.create_publisher(PoseStamped, "goal_pose", RELIABLE_QOS)
        self.initial_pub = n.create_publisher(
            PoseWithCovarianceStamped, "initialpose", RELIABLE_QOS
        )
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(n)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="monitor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:  # context shut down under us while stopping
                if self._stop.is_set():
                    return
                raise

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=3.0)
        self.executor.shutdown()
        self.node.destroy_node()

    # -- callbacks ---------------------------------------------------------------------------
    def _on_mapper(self, msg: Any) -> None:
        values, _, message = _diag_values(msg)
        with self.state.lock:
            self.state.mapper = {**values, "message": message}
            self.state.last_mapper_t = time.monotonic()

    def _on_bridge(self, msg: Any) -> None:
        values, _, _ = _diag_values(msg)
        with self.state.lock:
            self.state.bridge = values

    def _on_cloud(self, msg: Any) -> None:
        with self.state.lock:
            self.state.map_points = int(msg.width) * int(msg.height)
            self.state.map_cloud = msg
            self.state.last_cloud_t = time.monotonic()

    def _on_grid(self, msg: Any) -> None:
        grid = from_occupancy_grid(msg)
        with self.state.lock:
            self.state.grid = grid
            self.state.grid_msg = msg
            self.state.grid_updates += 1
            self.state.last_grid_t = time.monotonic()

    def _on_plan(self, msg: Any) -> None:
        with self.state.lock:
            self.state.plan = [(p.pose.position.x, p.pose.position.y) for p in msg.poses]
            self.state.plan_updates += 1

    def _on_drive(self, msg: Any) -> None:
        values, level, message = _diag_values(msg)
        with self.state.lock:
            self.state.drive = values
            self.state.drive_level = level
            self.state.drive_message = message

    def _on_command(self, msg: Any) -> None:
        try:
            item = json.loads(msg.data)
        except ValueError:
            item = {"raw": msg.data}
        with self.state.lock:
            self.state.commands.append(item)

    def _on_chair(self, msg: Any) -> None:
        q = msg.pose.orientation
        yaw = float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        with self.state.lock:
            self.state.chair_track.append((t, msg.pose.position.x, msg.pose.position.y, yaw))

    def plan_readers(self) -> int:
        """Subscriptions to the plan topic this node's graph knows of (its own included)."""
        return int(self.node.count_subscribers("wheelgrid/plan"))

    # -- actions -----------------------------------------------------------------------------
    def send_initial_pose(self, x: float, y: float, yaw: float, frame: str = "map") -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped

        msg = PoseWithCovarianceStamped()
        msg.header.frame_id = frame
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
        msg.pose.pose.orientation.z = float(np.sin(yaw / 2))
        msg.pose.pose.orientation.w = float(np.cos(yaw / 2))
        self.initial_pub.publish(msg)

    def send_goal(self, x: float, y: float, yaw: float = 0.0, frame: str = "map") -> None:
        from geometry_msgs.msg import PoseStamped

        msg = PoseStamped()
        msg.header.frame_id = frame
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y = float(x), float(y)
        msg.pose.orientation.z = float(np.sin(yaw / 2))
        msg.pose.orientation.w = float(np.cos(yaw / 2))
        self.goal_pub.publish(msg)

    def call_trigger(self, service: str, timeout: float = 10.0) -> tuple[bool, str]:
        """Call a std_srvs/Trigger service (e.g. /mapper/save_map) from the monitor's thread.

        The request is sent again every 5 s while no answer comes (:func:`call_with_retry`: a
        server that has not yet matched this client's response reader drops the response); the
        services called here (save, reset) are idempotent.
        """
        from std_srvs.srv import Trigger

        client = self.node.create_client(Trigger, service)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                return False, f"service {service} not available"
            result = call_with_retry(client, Trigger.Request, poll_until, timeout, 5.0)
            if result is not None:
                return bool(result.success), str(result.message)
            return False, f"service {service} timed out after {timeout:.0f} s"
        finally:
            self.node.destroy_client(client)

    def status_line(self, extra: str = "", drive: bool = True) -> str:
        """One line on the chain: the bridge's frames where a phone bridge runs (the mapper's
        "map 153/779" read as if frames were lost; live, it maps the newest of them and DDS
        may drop some on the way), the map, grid, plan, and the drive where one runs."""
        s = self.state
        with s.lock:
            m, b = s.mapper, s.bridge
            parts = []
            if b:
                clients, frames = b.get("clients", "?"), b.get("frames_published", "?")
                parts.append(f"phone {clients} client(s), {frames} frames published")
            used = m.get("frames_used", m.get("frames_integrated", "?"))
            recv = m.get("frames_received", "?")
            failed = m.get("frames_failed", m.get("registration_failures", "0"))
            mapped = f"map {used}/{recv} frames ({failed} failed), {s.map_points / 1000:.0f}k pts"
            silent = mapper_silence(m, s.last_mapper_t)
            if silent:
                # a frozen mapper's last counts stood on the line as if it were mapping
                mapped += f" (mapper silent for {silent:.0f} s)"
            loops = m.get("loop_closure", "")
            if loops in ("requested", "running"):
                mapped += f", closing loops {m.get('loop_closure_note', '')}".rstrip()
            elif loops in ("closed", "failed"):
                mapped += f", loops {loops}"
            parts.append(mapped)
            if s.grid is not None:
                d = s.grid.data
                parts.append(
                    f"grid {s.grid.rows}x{s.grid.cols} ({int((d == 0).sum())} free, "
                    f"{int((d == 100).sum())} occ, {int((d < 0).sum())} unk)"
                )
            else:
                parts.append("grid -")
            parts.append(f"plan {len(s.plan)} cells" if s.plan else "plan -")
            if drive:
                parts.append(f"drive {s.drive_message or '-'} ({len(s.commands)} cmds)")
        return " | ".join(parts) + (f" | {extra}" if extra else "")


def mapper_silence(status: dict[str, str], last_t: float, now: float | None = None) -> float:
    """Seconds the mapper's status has been overdue by three of its periods (5 s at least),
    or 0: a mapper frozen mid-replay (SIGSTOP, a hang) left "map 28/28" on the status line,
    read as mapping (a review)."""
    if not status or last_t <= 0:
        return 0.0
    try:
        period = float(status.get("status_period_s", "2.0"))
    except ValueError:
        period = 2.0
    age = (time.monotonic() if now is None else now) - last_t
    return age if age > max(3.0 * period, 5.0) else 0.0


class Chain:
    """Supervised nodes + monitor; ``check()`` raises NodeDiedError naming a dead node."""

    def __init__(self, supervisor: Supervisor, monitor: Monitor) -> None:
        self.supervisor = supervisor
        self.monitor = monitor

    def check(self) -> None:
        dead = self.supervisor.dead()
        if dead:
            name, code = dead[0]
            raise NodeDiedError(name, code, self.supervisor.tail(name))

    def wait(self, predicate: Any, timeout: float, what: str, status_every: float = 0.0) -> bool:
        """Wait for ``predicate()`` while watching for dead nodes; prints status lines."""
        deadline = time.monotonic() + timeout
        last = 0.0
        while time.monotonic() < deadline:
            self.check()
            if predicate():
                return True
            now = time.monotonic()
            if status_every and now - last >= status_every:
                print(f"[{what}] {self.monitor.status_line()}", flush=True)
                last = now
            time.sleep(0.1)
        return bool(predicate())
