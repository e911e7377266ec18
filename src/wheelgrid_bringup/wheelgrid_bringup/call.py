"""``wheelgrid call SERVICE``: call a std_srvs/Trigger service of a running node.

The pip-installed ROS 2 has no ``ros2`` command, yet a live session needs a few calls from a
shell: ``/mapper/close_loops`` at the end of a scan, ``/mapper/save_map``, ``/grid/save``,
``/mapper/reset``. Where ``ros2 service call`` exists it does the same. Exit 0 when the service
answered success, 1 when it refused or never answered, 2 when no such service appeared.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from wheelgrid_common.ros_env import configure_ros_env, domain_id_problem, name_problem
from wheelgrid_common.testing import spin_until

# How long the call waits, once the service is ready, before it sends its one request.
RESPONSE_MATCH_S = 1.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="wheelgrid call",
        description="Call a std_srvs/Trigger service (e.g. /mapper/close_loops, "
        "/mapper/save_map, /mapper/reset, /grid/save) and print its answer.",
    )
    p.add_argument("service", help="service name, e.g. /mapper/save_map")
    p.add_argument(
        "--timeout", type=float, default=30.0, help="seconds to wait in all (default 30)"
    )
    args = p.parse_args(argv)
    if not args.timeout > 0:
        print(f"wheelgrid call: --timeout must be > 0, not {args.timeout}", file=sys.stderr)
        return 2
    why = name_problem(args.service, "wheelgrid_call", service=True)  # before DDS starts
    if why:
        print(f"wheelgrid call: {args.service!r}: {why}", file=sys.stderr)
        return 2
    configure_ros_env()
    if why := domain_id_problem(os.environ):
        print(f"wheelgrid call: {why}", file=sys.stderr)
        return 2
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger

    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("wheelgrid_call", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    deadline = time.monotonic() + args.timeout
    try:
        client = node.create_client(Trigger, args.service)
        if not spin_until(ex, client.service_is_ready, args.timeout):
            print(
                f"wheelgrid call: {_not_ready(node, args.service, args.timeout)}", file=sys.stderr
            )
            return 2
        # One request: it was sent again every 5 s while no answer came, and a service
        # slower than that ran twice (a /mapper/reset then cleared what was mapped between).
        # The resending covered rmw_fastrtps dropping the response to a reader the server has
        # not matched yet (ros2/rmw_fastrtps#390): "ready" means the request path matched.
        # A short wait after "ready" lets the server match the response reader too.
        remaining = max(deadline - time.monotonic(), 0.1)
        spin_until(ex, lambda: False, min(RESPONSE_MATCH_S, remaining / 4))
        future = client.call_async(Trigger.Request())
        if not spin_until(ex, future.done, max(deadline - time.monotonic(), 0.1)):
            print(
                f"wheelgrid call: {args.service} did not answer within {args.timeout:.0f} s "
                "(the request was sent once: the node may still carry it out; see its log)",
                file=sys.stderr,
            )
            return 1
        result = future.result()
        print(("ok: " if result.success else "refused: ") + str(result.message))
        return 0 if result.success else 1
    finally:
        ex.shutdown()
        node.destroy_node()
        if ctx.ok():
            rclpy.shutdown(context=ctx)


def _not_ready(node: object, service: str, timeout: float) -> str:
    """Why no Trigger service answered: one of another type by that name (it said "no service"
    for /planner/describe_parameters), or none at all."""
    wanted = service if service.startswith("/") else "/" + service
    try:
        found = dict(node.get_service_names_and_types())  # type: ignore[attr-defined]
    except Exception:  # the graph could not be read: say what is known
        found = {}
    # the graph lists this command's own Trigger client under the name too
    types = [t for t in found.get(wanted, []) if t != "std_srvs/srv/Trigger"]
    if types:
        return (
            f"{service} is a {', '.join(types)} service, not std_srvs/srv/Trigger: this command "
            "calls Trigger services only (/mapper/close_loops, /mapper/save_map, /grid/save ...)"
        )
    return (
        f"no service {service} within {timeout:.0f} s (is the node running, with the same "
        "ROS_DOMAIN_ID?)"
    )
