"""A mapper stopped while frames are still coming in (Ctrl-C on a live phone stream) saves its
map on exit all the same.

Ctrl-C shuts the node's context down first; a frame the worker was still registering then
published its pose into a dead context, ``RCLError`` killed the worker thread, and the same error
from ``close()``'s last flush skipped the save on exit: the launcher stopped the mapper with exit
1 and the scan was lost without a line saying so (`wheelgrid launch --iphone` stopped while
`wheelgrid stream-stray` streamed).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common.ros_env import configure_ros_env, spin_node
from wheelgrid_common.testing import bag_cloud_odometry, not_installed

BAG = Path(__file__).resolve().parents[3] / "bags" / "paper_room" / "scan"


def _bag_frames(n: int) -> list:
    return bag_cloud_odometry(BAG, n)


@pytest.mark.ros
def test_a_mapper_stopped_with_a_frame_in_flight_still_saves_its_map(tmp_path, monkeypatch):
    if not BAG.exists():
        pytest.skip("bags/paper_room: not present")
    import rclpy

    from wheelgrid_mapping.mapper_node import MapperNode
    from wheelgrid_mapping.pipeline import FrameOutcome

    died: list[BaseException] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: died.append(args.exc_value))
    configure_ros_env()
    rclpy.init(
        args=[
            "--ros-args",
            "-p", f"output_dir:={tmp_path}",
            "-p", "topic:=/exit_mapper/points",
            "-p", "pose_prior_topic:=/exit_mapper/odometry",
        ]
    )  # fmt: skip
    node = None
    closed = False
    try:
        node = MapperNode()
        deadline = time.monotonic() + 60.0

        def taken() -> bool:
            with node._slot_lock:
                return not node._queue

        for msg, odom in _bag_frames(3):  # the node's own callbacks, no DDS needed
            node._on_prior(odom)
            node._on_cloud(msg)
            # the node keeps only the newest frame (max_queue 1): fed all at once, a worker
            # thread slow to wake on a loaded machine took only the third (CI, 1 pose mapped)
            while not taken() and time.monotonic() < deadline:
                time.sleep(0.01)

        # wait until nothing is queued or in preparation (a frame mapped after the count below
        # raced its assertion)
        def settled() -> bool:
            with node._slot_lock:
                idle = not node._queue and not node._pipe.pending
            return idle and len(node.mapper.poses_odom) >= 2

        while not settled() and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.3)  # the worker's report of the last frame
        mapped = len(node.mapper.poses_odom)
        assert mapped >= 2, (
            f"the worker mapped {mapped} of 3 frames: counts {node.counts}, "
            f"failures {node.mapper.failures}"
        )

        rclpy.shutdown()  # what Ctrl-C / SIGTERM does first, before close()
        late = [(9.9, FrameOutcome("used", pose_map=np.eye(4)))]
        node._report(late)  # a frame registered just now: no RCLError into a dead context
        # ... and the frame that was in preparation comes out of close()'s last flush
        monkeypatch.setattr(node._pipe, "flush", lambda: list(late))
        closed = True
        node.close()
        assert not node._worker.is_alive(), "close() left the mapper's worker running"
    finally:
        if node is not None:
            if not closed:  # failed before close(): its worker thread and second process
                node.save_on_exit = False
                node.close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    on_exit = tmp_path / "on_exit"
    assert (on_exit / "map.ply").stat().st_size > 1000
    poses = [ln for ln in (on_exit / "trajectory.tum").read_text().splitlines() if ln[:1] != "#"]
    assert len(poses) == mapped
    assert not died, died


@pytest.mark.ros
def test_spin_node_takes_an_error_raised_by_ctrl_c_s_shutdown_as_a_clean_stop():
    """A callback that ran into the context Ctrl-C had just shut down (rclpy: 'publisher's
    context is invalid', or its take_message failing) ended a node with a traceback and exit 1."""
    import rclpy
    from rclpy.node import Node

    def factory() -> Node:
        node = Node("spin_exit_test")

        def tick() -> None:
            rclpy.shutdown()  # Ctrl-C, as rclpy's signal handler does it
            raise RuntimeError("publisher's context is invalid")

        node.create_timer(0.01, tick)
        return node

    assert spin_node(factory, args=[]) == 0


@pytest.mark.ros
def test_spin_node_still_raises_a_callback_error_of_a_running_node():
    from rclpy.node import Node

    def factory() -> Node:
        node = Node("spin_error_test")

        def tick() -> None:
            raise RuntimeError("a real bug")

        node.create_timer(0.01, tick)
        return node

    with pytest.raises(RuntimeError, match="a real bug"):
        spin_node(factory, args=[])


@pytest.mark.ros
def test_spin_node_closes_a_node_on_sighup_and_a_ctrl_c_while_it_closes_is_ignored():
    """A closed terminal or ssh session (SIGHUP) ended a node at once, without close(): a
    mapper's scan was lost, though save_on_exit promises it. And a second Ctrl-C while a node
    closed raised KeyboardInterrupt out of close() (the mapper's wait for its worker, its
    save): a traceback, and the save could be skipped. The handlers spin_node replaced are
    put back when it returns."""
    import os
    import signal

    from rclpy.node import Node

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals are delivered to the main thread only")
    # run under nohup (CI's runner may be), SIGHUP is inherited ignored, and spin_node keeps
    # ignoring it by design: the test sets the default a terminal gives
    hup = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGHUP)
    closed: list[str] = []

    class Closing(Node):
        def close(self) -> None:
            os.kill(os.getpid(), signal.SIGINT)  # the user's second Ctrl-C
            time.sleep(0.2)  # a handler runs between two bytecodes: here, if at all
            closed.append("done")

    def give_up() -> None:
        raise SystemExit(3)

    def factory() -> Node:
        signal.signal(signal.SIGTERM, lambda *_: None)  # after rclpy.init took it
        node = Closing("spin_hup_test")
        node.create_timer(0.2, lambda: os.kill(os.getpid(), signal.SIGHUP))
        node.create_timer(10.0, give_up)
        return node

    # SIGTERM taken by someone else (in CI an earlier test of the same worker had): SIGHUP
    # re-sent as SIGTERM then reached no rclpy handler, and the spin never ended (here a
    # timer gives up after 10 s instead)
    term = signal.getsignal(signal.SIGTERM)
    try:
        assert spin_node(factory, args=[]) == 0
    finally:
        signal.signal(signal.SIGTERM, term)
    assert closed == ["done"]
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGHUP)) == before
    signal.signal(signal.SIGHUP, hup)


@pytest.mark.ros
def test_frames_still_queued_at_exit_are_counted(tmp_path):
    """A bag replayed faster than the node maps it (max_queue large) left frames queued at
    Ctrl-C: dropped without a trace, and the saved report read 19 frames of the 40 received.
    They are counted now (node_counts unmapped_at_exit) and said."""
    if not BAG.exists():
        pytest.skip("bags/paper_room: not present")
    import json

    import rclpy

    from wheelgrid_mapping.mapper_node import MapperNode

    configure_ros_env()
    rclpy.init(
        args=[
            "--ros-args",
            "-p", f"output_dir:={tmp_path}",
            "-p", "topic:=/queued_mapper/points",
            "-p", "pose_prior_topic:=/queued_mapper/odometry",
            "-p", "max_queue:=100",
        ]
    )  # fmt: skip
    node = None
    try:
        node = MapperNode()
        frames = _bag_frames(6)
        with node._lock:  # the worker takes a frame and waits here: the rest stay queued
            for msg, odom in frames:
                node._on_prior(odom)
                node._on_cloud(msg)
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                with node._slot_lock:
                    if len(node._queue) < len(frames):
                        break  # the worker has taken its frame
                time.sleep(0.01)
            with node._slot_lock:
                queued = len(node._queue)
            assert 0 < queued < len(frames)
            rclpy.shutdown()
            closer = threading.Thread(target=node.close)
            closer.start()
            while not node._stop and closer.is_alive():
                time.sleep(0.01)
        closer.join(timeout=30.0)
        assert not closer.is_alive()
        assert node.counts["unmapped_at_exit"] == queued
        report = json.loads((tmp_path / "on_exit_unlevelled" / "report.json").read_text())
        assert report["node_counts"]["unmapped_at_exit"] == queued
        assert report["frames"]["read"] + queued == node.counts["received"] == len(frames)
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


@pytest.mark.ros
def test_an_empty_cloud_does_not_silence_the_warning_for_frames_without_valid_points(tmp_path):
    """Malformed clouds are logged once per cause, and a 0 x 0 cloud's cause is "empty": the
    same key the node gave frames whose points were all NaN, whose warning it then never
    logged (frames_empty 3, not a word of why)."""
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from wheelgrid_mapping.mapper_node import MapperNode
    from wheelgrid_mapping.pipeline import FrameOutcome

    configure_ros_env()
    rclpy.init(args=["--ros-args", "-p", f"output_dir:={tmp_path}", "-p", "save_on_exit:=false"])
    node = None
    try:
        node = MapperNode()
        node._on_cloud(PointCloud2())  # 0 x 0: malformed, cause "empty"
        assert node.counts["malformed"] == 1
        node._report([(1.0, FrameOutcome("empty", "no valid points (all NaN or out of range)"))])
        assert {"empty", "no_valid_points"} <= node._logged
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


@pytest.mark.ros
def test_a_node_with_no_timer_of_its_own_stops_on_sighup():
    """SIGHUP is handled in Python, which runs a handler only once the main thread is back in
    Python: depth_to_cloud, waiting in rcl for a stream that had stopped, never was, and went
    on running after its terminal closed."""
    import os
    import signal
    import subprocess

    from wheelgrid_common.testing import child_env, managed_process, python_module

    args = python_module("wheelgrid_mapping.depth_to_cloud_node")
    with managed_process(
        args,
        env=child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        # a terminal's default, where the runner itself was started under nohup
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL),  # type: ignore[arg-type]
    ) as proc:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # its start-up line: spinning from here on
        assert "depth_to_cloud" in line, line
        time.sleep(1.5)  # idle in rcl, no message to wake it
        os.kill(proc.pid, signal.SIGHUP)
        assert proc.wait(timeout=10.0) == 0


@pytest.mark.ros
@pytest.mark.parametrize(("module", "pip"), [("kiss_icp", "kiss-icp"), ("open3d", "open3d")])
def test_a_mapper_without_kiss_icp_or_open3d_is_one_fatal_line(module, pip, monkeypatch, capfd):
    """On a full ROS 2 rosdep brings no kiss-icp or open3d (no keys): the mapper died at its
    start with a traceback through the registration, exit 1, where a bad parameter is one
    line, exit 2; without open3d it started, took frames and died at the first floor search,
    the scan lost (a review). Both are looked for as it starts."""
    from wheelgrid_mapping.mapper_node import MapperNode

    not_installed(monkeypatch, module)
    assert spin_node(MapperNode, args=[]) == 2
    err = capfd.readouterr().err
    assert f"[FATAL] the Python package {pip} is not installed" in err, err
    assert "Traceback" not in err
