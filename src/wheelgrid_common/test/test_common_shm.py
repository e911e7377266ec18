"""Fast DDS segments of dead processes are removed from /dev/shm, and never a live one's."""

from __future__ import annotations

import fcntl
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from wheelgrid_common.shm import SHM_DIR, ShmCleanup, clean_dead_segments


def test_only_the_segments_whose_lock_nobody_holds_are_removed(tmp_path):
    live, dead = "fastrtps_0123456789abcdef", "fastrtps_fedcba9876543210"
    for name in (live, dead):
        (tmp_path / name).write_bytes(b"\0" * 1000)
        (tmp_path / f"{name}_el").touch()
    others = ["fastrtps_port7411", "fastrtps_port7411_el", "sem.fastrtps_port7411_mutex",
              "fastrtps_short_el", "someone_else_el"]  # fmt: skip
    for name in others:
        (tmp_path / name).touch()
    holder = os.open(tmp_path / f"{live}_el", os.O_RDONLY)  # a live participant's lock
    try:
        fcntl.flock(holder, fcntl.LOCK_EX | fcntl.LOCK_NB)
        done = clean_dead_segments(tmp_path)
        assert (done.removed, done.bytes, done.in_use) == (1, 1000, 1)
        left = sorted(p.name for p in tmp_path.iterdir())
        assert left == sorted([live, f"{live}_el", *others])
        # the lock the cleaner took to test the dead one is let go: a new owner can take it
        assert clean_dead_segments(tmp_path).removed == 0
    finally:
        os.close(holder)
    assert clean_dead_segments(tmp_path).removed == 1  # the owner has gone now
    assert clean_dead_segments(tmp_path / "missing") == ShmCleanup(0, 0, 0)


_SEGMENT = re.compile(rf"^{SHM_DIR}/fast(rtps|dds)_[0-9a-z]{{16}}$")


def _segments_of(pid: int) -> set[Path]:
    maps = Path(f"/proc/{pid}/maps").read_text().splitlines()
    files = {ln.split(maxsplit=5)[5] for ln in maps if len(ln.split(maxsplit=5)) == 6}
    # its own segments; the port files it maps are the domain's, shared and reused
    return {Path(f) for f in files if _SEGMENT.match(f)}


def test_a_node_killed_outright_leaves_no_segment_once_it_is_stopped():
    """SIGKILL leaves a participant's segments (17 MB a node with wheelgrid's profile);
    stop_process, which the supervisor and the tests stop every node with, removes them,
    and a participant still running keeps its own."""
    from wheelgrid_common.ros_env import child_env
    from wheelgrid_common.testing import managed_process, stop_process

    if not sys.platform.startswith("linux") or not SHM_DIR.is_dir():
        pytest.skip("Fast DDS keeps its segments in /dev/shm on Linux only")
    code = (
        "import signal; signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from wheelgrid_common.ros_env import configure_ros_env; configure_ros_env()\n"
        "import rclpy, sys; from rclpy.node import Node; from std_msgs.msg import Bool\n"
        "rclpy.init(); n = Node('shm_probe'); n.create_publisher(Bool, '/probe', 1)\n"
        "print('up', flush=True); sys.stdin.readline()\n"
    )
    argv = [sys.executable, "-c", code]
    opts = {"stdin": subprocess.PIPE, "stdout": subprocess.PIPE, "text": True}
    env = child_env()
    if env.get("RMW_IMPLEMENTATION") != "rmw_fastrtps_cpp":
        pytest.skip("another RMW: no Fast DDS segments")
    with managed_process(argv, env=env, **opts) as keeper:
        assert keeper.stdout is not None and keeper.stdout.readline().strip() == "up"
        kept = _segments_of(keeper.pid)
        victim = subprocess.Popen(argv, env=env, start_new_session=True, **opts)
        try:
            assert victim.stdout is not None and victim.stdout.readline().strip() == "up"
            # its own: a reader maps the segments of the writers it hears, the keeper's too
            left = _segments_of(victim.pid) - kept
            assert left, "the probe maps no Fast DDS segment: nothing to test"
            os.killpg(victim.pid, signal.SIGKILL)
            victim.wait(timeout=10)
            assert all(p.exists() for p in left)  # Fast DDS left them
        finally:
            assert stop_process(victim) == -signal.SIGKILL
            victim.stdin.close()  # type: ignore[union-attr]
            victim.stdout.close()  # type: ignore[union-attr]
        assert not any(p.exists() for p in left)
        assert kept and all(p.exists() for p in kept)
