"""Benchmark of the drive stage: the serial link to the (simulated) motor controller over a pty.

    python bench/bench_drive.py [--quick] [--json FILE] [--no-ros]

Figures (all over a real pty, pyserial on the host side, the simulator thread on the other):

* round-trip latency of a HEARTBEAT -> STATUS exchange through MotorLink (p50, p95), against a
  baseline measured in the same process: a raw 6-byte write/read echo on the same kind of pty
  (no framing, no CRC, no threads) -- the ratio is the cost of the protocol and the link;
* commands per second: MOVE (ACKed) + STOP (ACKed) pairs, each command a full round trip;
* e-stop latency at the link: ``link.stop()`` from another thread while a move runs and the
  host polls the controller -> the simulator has the STOP frame (target 100 ms), against the
  raw pty echo;
* e-stop latency through ROS: a std_msgs/Bool on /wheelgrid/estop -> STOP frame at the
  simulator, drive node in the same process over DDS loopback (target 100 ms), against a Bool
  to a bare subscriber over the same loopback (the floor); and the same while the drive node
  reads a 9,999-pose plan (0.3-0.5 s of its executor's time), against a bare subscriber that
  takes the plan on the same executor (what a drive node without a thread of its own for the
  e-stop would do);
* watchdog: how long after the host's last frame the controller stops the motors by itself
  (configured timeout 500 ms).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from wheelgrid_drive import protocol as proto
from wheelgrid_drive.link import MotorLink
from wheelgrid_drive.motor_sim import MotorSim, MotorSimConfig

LONG_PLAN = 9_999  # poses: the drive node refuses more than 10,000


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def raw_echo_rtt(n: int) -> list[float]:
    """Baseline: 6 bytes out through pyserial, echoed by a thread on the master, read back."""
    import serial

    master, slave = os.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def echo() -> None:
        import select

        while not stop.is_set():
            r, _, _ = select.select([master], [], [], 0.05)
            if r:
                os.write(master, os.read(master, 4096))

    th = threading.Thread(target=echo, daemon=True)
    th.start()
    ser = serial.Serial(os.ttyname(slave), 115200, timeout=1.0)
    out = []
    msg = bytes([0xA5, 0, 1, 1, 0x12, 0x34])
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            ser.write(msg)
            got = ser.read(len(msg))
            out.append(time.perf_counter() - t0)
            assert got == msg
    finally:
        stop.set()
        th.join(1.0)
        ser.close()
        os.close(master)
        os.close(slave)
    return out


def link_rtt(link: MotorLink, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        link.request(proto.MsgType.HEARTBEAT)
        out.append(time.perf_counter() - t0)
    return out


def commands_per_s(link: MotorLink, pairs: int) -> float:
    t0 = time.perf_counter()
    for _ in range(pairs):
        link.move("FORWARD", 1.2, 3.0)
        if not link.stop():
            raise RuntimeError("STOP not acknowledged")
    return 2 * pairs / (time.perf_counter() - t0)


def estop_link(sim: MotorSim, link: MotorLink, n: int) -> list[float]:
    """link.stop() from this thread while another thread runs a move and polls STATUS."""
    out = []
    for _ in range(n):
        abort = threading.Event()
        th = threading.Thread(
            target=lambda a=abort: _swallow(lambda: link.execute("FORWARD", 1.2, 3.0, abort=a)),
            daemon=True,
        )
        th.start()
        while sim.state == proto.State.IDLE:
            time.sleep(0.005)
        time.sleep(0.05)
        t0 = time.monotonic()
        link.stop()
        stop = next(e for e in reversed(sim.events) if e.what == "stop")
        out.append(stop.t - t0)
        abort.set()
        th.join(5.0)
    return out


def _swallow(fn) -> None:  # type: ignore[no-untyped-def]
    """The aborted move's thread ends in LinkError by design; the figure is the stop time."""
    with contextlib.suppress(Exception):
        fn()


def watchdog(n: int, timeout: float) -> list[float]:
    out = []
    for _ in range(n):
        sim = MotorSim(MotorSimConfig(heartbeat_timeout=timeout)).start()
        try:
            link = MotorLink(sim.slave_path).open()
            link.start_heartbeat()
            link.move("FORWARD", 2.0, 0.5)
            time.sleep(0.3)
            link.close(stop=False)  # the host goes silent mid-move
            deadline = time.monotonic() + 3.0
            while sim.state != proto.State.IDLE and time.monotonic() < deadline:
                time.sleep(0.01)
            dog = [e for e in sim.events if e.what == "watchdog"]
            if not dog:
                raise RuntimeError("the controller did not stop by itself")
            out.append(float(dog[0].detail))
        finally:
            sim.stop()
    return out


def plan_msg(n: int, places: list[tuple[float, float]]) -> Any:
    """A nav_msgs/Path of ``n`` poses going back and forth between ``places`` (frame map)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg

    plan = PathMsg()
    plan.header.frame_id = "map"
    for i in range(n):
        ps = PoseStamped()
        ps.header.frame_id = "map"
        x, y = places[i % len(places)]
        ps.pose.position.x, ps.pose.position.y = float(x), float(y)
        ps.pose.orientation.w = 1.0
        plan.poses.append(ps)
    return plan


def estop_ros(n: int, long_plan: int = 0) -> list[float]:
    """/wheelgrid/estop (Bool) -> STOP frame at the simulator, drive node over DDS loopback.

    ``long_plan`` > 0: 30 ms before each e-stop, a plan of that many poses is published, so
    that the drive node's executor is reading it when the e-stop comes.
    """
    import numpy as np
    from nav_msgs.msg import OccupancyGrid
    from nav_msgs.msg import Path as PathMsg
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from std_msgs.msg import Bool

    from wheelgrid_common.map_io import Grid, to_occupancy_grid
    from wheelgrid_common.qos import MAP_QOS, RELIABLE_QOS
    from wheelgrid_common.testing import rclpy_context, spin_until
    from wheelgrid_drive.drive_node import DriveNode

    out = []
    grid = Grid(np.zeros((6, 6), np.int8), 1.2)
    sim = MotorSim(MotorSimConfig()).start()
    try:
        with rclpy_context() as ctx:
            drive = DriveNode(
                context=ctx, parameter_overrides=[Parameter("port", value=sim.slave_path)]
            )
            node = Node("bench_drive", context=ctx)
            ex = SingleThreadedExecutor(context=ctx)
            ex.add_node(drive)
            ex.add_node(node)
            pub = node.create_publisher(Bool, "/wheelgrid/estop", RELIABLE_QOS)
            gpub = node.create_publisher(OccupancyGrid, "/wheelgrid/safe_grid", MAP_QOS)
            ppub = node.create_publisher(PathMsg, "/wheelgrid/plan", MAP_QOS)
            plan = plan_msg(long_plan, [grid.cell_center(2, 2), grid.cell_center(2, 3)])
            gpub.publish(to_occupancy_grid(grid))
            # the drive reads plans volatile: a plan published before its reader matched is
            # never sent to it, and the round would time an e-stop with no plan being read
            spin_until(
                ex,
                lambda: pub.get_subscription_count() > 0 and ppub.get_subscription_count() > 0,
                10.0,
            )
            try:
                for _ in range(n):
                    pub.publish(Bool(data=False))
                    spin_until(ex, lambda: not drive._estop, 2.0, step=0.005)
                    drive.link.move("FORWARD", 1.2, 3.0)
                    spin_until(ex, lambda: sim.state != proto.State.IDLE, 2.0, step=0.005)
                    if long_plan:
                        ppub.publish(plan)
                        time.sleep(0.03)
                    t0 = time.monotonic()
                    pub.publish(Bool(data=True))

                    def stopped(t0: float = t0) -> bool:
                        return any(e.what == "stop" and e.t >= t0 for e in sim.events)

                    if not spin_until(ex, stopped, 3.0, step=0.001):
                        raise RuntimeError("e-stop never reached the controller")
                    stop = next(e for e in sim.events if e.what == "stop" and e.t >= t0)
                    out.append(stop.t - t0)
            finally:
                drive.close()
                ex.shutdown()
                drive.destroy_node()
                node.destroy_node()
    finally:
        sim.stop()
    return out


def bare_bool_ros(n: int, long_plan: int = 0) -> list[float]:
    """Baseline for the DDS e-stop rows: a std_msgs/Bool to a bare subscriber over the same
    loopback, its node spun by a single-threaded executor of its own -- the floor any drive
    node has. ``long_plan`` > 0: the same node also takes the plan, published 30 ms before the
    Bool as in :func:`estop_ros`, as a drive node without a thread of its own for the e-stop
    would."""
    from nav_msgs.msg import Path as PathMsg
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import Bool

    from wheelgrid_common.qos import MAP_QOS, RELIABLE_QOS
    from wheelgrid_common.testing import rclpy_context

    out = []
    got: list[float] = []
    read: list[int] = []
    with rclpy_context() as ctx:
        sub_node = Node("bench_bare_estop", context=ctx)
        node = Node("bench_bare_pub", context=ctx)
        sub_node.create_subscription(
            PathMsg,
            "/bench/plan",
            lambda m: read.append(sum(1 for p in m.poses if p.pose.orientation.w)),
            MAP_QOS,
        )
        sub_node.create_subscription(
            Bool, "/bench/estop", lambda m: got.append(time.monotonic()), RELIABLE_QOS
        )
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(sub_node)
        spinner = threading.Thread(target=ex.spin, daemon=True)
        spinner.start()
        pub = node.create_publisher(Bool, "/bench/estop", RELIABLE_QOS)
        ppub = node.create_publisher(PathMsg, "/bench/plan", MAP_QOS)
        plan = plan_msg(long_plan, [(0.0, 0.0), (1.0, 0.0)])

        def wait(pred: Callable[[], bool], timeout: float) -> bool:
            deadline = time.monotonic() + timeout
            while not pred() and time.monotonic() < deadline:
                time.sleep(0.0005)
            return pred()

        try:
            wait(lambda: pub.get_subscription_count() > 0 and ppub.get_subscription_count() > 0, 10)
            for _ in range(n):
                got.clear()
                read.clear()
                if long_plan:
                    ppub.publish(plan)
                    time.sleep(0.03)
                t0 = time.monotonic()
                pub.publish(Bool(data=True))
                if not wait(lambda: bool(got), 3.0):
                    raise RuntimeError("the bare subscriber never got the Bool")
                out.append(got[0] - t0)
                if long_plan and not wait(lambda: bool(read), 5.0):
                    raise RuntimeError("the bare subscriber never read the plan")
        finally:
            ex.shutdown()
            spinner.join(5.0)
            sub_node.destroy_node()
            node.destroy_node()
    return out


def estop_row(
    figure: str, stops: list[float], note: str = "", base: list[float] | None = None, what=""
) -> dict:
    """A row of e-stop latencies (s): the worst against ``base``'s worst, measured beside it
    (``what`` says what it is), else against the 100 ms target; the median beside."""
    worst = max(stops) * 1000.0
    ref = max(base) * 1000.0 if base else 100.0
    said = (
        f"baseline: {what}, max (p50 {statistics.median(base) * 1000.0:.2f} ms)"
        if base
        else ("baseline: 100 ms target")
    )
    return dict(
        figure=figure,
        value=worst,
        unit="ms",
        baseline=ref,
        ratio=worst / ref,
        note=f"p50 {statistics.median(stops) * 1000.0:.2f} ms, n={len(stops)}{note}; {said}"
        + ("; target 100 ms" if base else ""),
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI-size run")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--no-ros", action="store_true", help="skip the DDS e-stop figure")
    args = ap.parse_args()
    n_rtt = 200 if args.quick else 2000
    n_pairs = 50 if args.quick else 500
    n_stop = 5 if args.quick else 20
    n_dog = 2 if args.quick else 5

    base = raw_echo_rtt(n_rtt)
    sim = MotorSim(MotorSimConfig(time_scale=1.0)).start()
    link = MotorLink(sim.slave_path, retries=0).open()
    try:
        rtt = link_rtt(link, n_rtt)
        cps = commands_per_s(link, n_pairs)
        link.start_heartbeat()
        stops = estop_link(sim, link, n_stop)
        stats = link.stats
    finally:
        link.close()
        sim.stop()
    dog = watchdog(n_dog, 0.5)
    ros_stops = [] if args.no_ros else estop_ros(n_stop)
    bare = [] if args.no_ros else bare_bool_ros(n_stop)
    busy_stops = [] if args.no_ros else estop_ros(n_stop, long_plan=LONG_PLAN)
    bare_busy = [] if args.no_ros else bare_bool_ros(n_stop, long_plan=LONG_PLAN)

    b50 = statistics.median(base)
    ms = 1000.0
    rows = [
        dict(
            figure="link round trip p50 (HEARTBEAT->STATUS)",
            value=statistics.median(rtt) * ms,
            unit="ms",
            baseline=b50 * ms,
            ratio=statistics.median(rtt) / b50,
            note=f"baseline: raw pty echo p50, n={n_rtt}",
        ),
        dict(
            figure="link round trip p95",
            value=pct(rtt, 0.95) * ms,
            unit="ms",
            baseline=pct(base, 0.95) * ms,
            ratio=pct(rtt, 0.95) / pct(base, 0.95),
            note="baseline: raw pty echo p95",
        ),
        dict(
            figure="commands per second (MOVE+STOP, each ACKed)",
            value=cps,
            unit="cmd/s",
            baseline=1.0 / b50,
            ratio=cps * b50,
            note=f"baseline: raw pty echoes/s; {n_pairs} pairs",
        ),
        estop_row("e-stop latency at the link, max", stops, "", base, "raw pty echo"),
        dict(
            figure="watchdog stop after host silence, max",
            value=max(dog) * ms,
            unit="ms",
            baseline=500.0,
            ratio=max(dog) * ms / 500.0,
            note=f"n={n_dog}; baseline: configured timeout",
        ),
    ]
    if ros_stops:
        rows.append(
            estop_row(
                "e-stop latency /wheelgrid/estop -> controller, max",
                ros_stops,
                ", DDS loopback",
                bare,
                "a Bool to a bare subscriber",
            )
        )
    if busy_stops:
        rows.append(
            estop_row(
                f"the same while a {LONG_PLAN:,}-pose plan is read, max",
                busy_stops,
                "; the e-stop has a thread of its own",
                bare_busy,
                "the bare subscriber taking the plan too, on one executor",
            )
        )
    for r in rows:
        print(
            f"{r['figure']:<52} {r['value']:10.3f} {r['unit']:<6} "
            f"(baseline {r['baseline']:.3f}, ratio {r['ratio']:.2f}) {r['note']}"
        )
    print(f"link stats during the run: {stats}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
