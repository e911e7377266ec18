"""``wheelgrid call``: a Trigger call from a shell (its success path runs in the mapper node
test, against a real node)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest

from wheelgrid_common.ros_env import child_env


@contextlib.contextmanager
def serving(srv_type: Any, name: str, handler: Any) -> Iterator[None]:
    """A service ``name`` of ``srv_type`` answered by ``handler`` in this process, spun on a
    thread of its own while the block runs (a `wheelgrid call` child process calls it)."""
    import threading

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from wheelgrid_common.testing import rclpy_context

    with rclpy_context() as ctx:
        node = Node("wg_call_server", context=ctx)
        node.create_service(srv_type, name, handler)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        spinner = threading.Thread(target=ex.spin, daemon=True)
        spinner.start()
        try:
            yield
        finally:
            ex.shutdown()
            spinner.join(timeout=10.0)
            node.destroy_node()


def wheelgrid_call(service: str, timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wheelgrid_bringup.cli", "call", service, "--timeout", str(timeout)],
        env=child_env(), capture_output=True, text=True, timeout=60,
    )  # fmt: skip


@pytest.mark.ros
def test_call_without_such_a_service_says_so_and_exits_2() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "wheelgrid_bringup.cli", "call", "/nobody/close_loops",
         "--timeout", "1"],
        env=child_env(), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "no service /nobody/close_loops" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.ros
def test_a_service_of_another_type_is_named_as_such() -> None:
    """A node's parameter service (or any non-Trigger one) was reported as "no service"."""
    from std_srvs.srv import SetBool

    with serving(SetBool, "/wg_test/set_flag", lambda _q, r: r):
        # the call's new participant must discover this one within its timeout: 3 s was too
        # short once in a loaded two-worker run ("no service")
        proc = wheelgrid_call("/wg_test/set_flag", 10)
    assert proc.returncode == 2 and proc.stdout == "", proc.stdout + proc.stderr
    assert "is a std_srvs/srv/SetBool service, not std_srvs/srv/Trigger" in proc.stderr


@pytest.mark.parametrize("name", ["", "1abc", "bad//name", "bad name!"])
def test_a_service_name_rclpy_refuses_is_one_line_and_exit_2(name: str, capsys) -> None:
    """rclpy raised its own traceback for these, after DDS had started."""
    from wheelgrid_bringup.call import main

    assert main([name, "--timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"wheelgrid call: {name!r}: ") and ", at /" not in err, err
    assert "topic" not in err, err  # it is a service name, whatever rcl's rules call it


@pytest.mark.ros
def test_a_service_slower_than_five_seconds_is_called_once() -> None:
    """The request went out again every 5 s while no answer came: a Trigger service that took
    6 s ran twice (a /mapper/reset would clear what was mapped between the two)."""
    import time

    from std_srvs.srv import Trigger

    calls: list[float] = []

    def slow(_request, response):
        calls.append(time.monotonic())
        time.sleep(5.5)
        response.success, response.message = True, f"handled request #{len(calls)}"
        return response

    with serving(Trigger, "/wg_test/slow", slow):
        proc = wheelgrid_call("/wg_test/slow", 30)
        time.sleep(1.0)  # a second request, had one gone out, would be served meanwhile
    assert proc.returncode == 0 and "ok: handled request #1" in proc.stdout, proc.stderr
    assert len(calls) == 1, calls
