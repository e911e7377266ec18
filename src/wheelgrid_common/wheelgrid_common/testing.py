"""Helpers for tests that run real nodes: an isolated rclpy context, spinning until a condition,
and child processes that are always stopped (SIGINT, then SIGTERM, then SIGKILL).

Tests must stop whatever they start; these helpers make that the default.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from wheelgrid_common.ros_env import child_env, configure_ros_env


def shared_data(name: str, repo_root: Path) -> Path:
    """Where a real data set lives: ``$WHEELGRID_SHARED/data/NAME``, else the checkout's sibling
    ``../shared/data/NAME``. It may be absent: callers skip with a reason (never copy it in)."""
    base = os.environ.get("WHEELGRID_SHARED")
    return (Path(base) if base else repo_root.parent / "shared") / "data" / name


def free_port() -> int:
    """A TCP port on loopback that nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def rclpy_context() -> Iterator[Any]:
    """An rclpy Context of its own (init + shutdown), so tests never leak a global init."""
    configure_ros_env()
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


def spin_until(
    executor: Any, predicate: Callable[[], bool], timeout: float, step: float = 0.05
) -> bool:
    """Spin ``executor`` until ``predicate()`` is true or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step)
    return bool(predicate())


def stop_process(proc: subprocess.Popen[Any], grace: float = 5.0) -> int | None:
    """SIGINT (clean rclpy shutdown), then SIGTERM, then SIGKILL the whole process group."""
    if proc.poll() is not None:
        return proc.returncode
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            return proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


@contextmanager
def managed_process(
    args: Sequence[str], env: dict[str, str] | None = None, **popen: Any
) -> Iterator[subprocess.Popen[Any]]:
    """Start a child in its own process group and always stop it on exit."""
    proc = subprocess.Popen(
        list(args), env=env if env is not None else child_env(), start_new_session=True, **popen
    )
    try:
        yield proc
    finally:
        stop_process(proc)


def python_module(module: str, *args: str) -> list[str]:
    """argv that runs ``python -m module args`` with this interpreter (the venv's)."""
    return [sys.executable, "-m", module, *args]
