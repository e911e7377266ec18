"""Service calls that survive a dropped response (ROS-side helper, no node of its own)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def poll_until(predicate: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    """Wait (sleeping, for a node another thread spins) until ``predicate()`` or ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return bool(predicate())


def call_with_retry(
    client: Any,
    request: Callable[[], Any],
    wait: Callable[[Callable[[], bool], float], bool],
    timeout: float,
    attempt: float,
) -> Any:
    """Call an idempotent service, asking again every ``attempt`` seconds while no answer
    comes; the response, or None after ``timeout`` seconds.

    Why: ``service_is_ready()`` turns true once the request path has matched, but the server
    may not have matched this client's response reader yet; rmw_fastrtps then waits 100 ms and
    drops the response (ros2/rmw_fastrtps#390, #467). On a loaded 2-core CI machine one such
    call never returned. A fresh request finds discovery complete; earlier requests stay
    pending, so a server slower than ``attempt`` still answers. ``wait(predicate, seconds)``
    waits for the answer: spinning an executor, or :func:`poll_until` where another thread
    spins the node.
    """
    deadline = time.monotonic() + timeout
    futures: list[Any] = []
    while time.monotonic() < deadline:
        futures.append(client.call_async(request()))  # earlier ones may still answer
        budget = min(attempt, max(deadline - time.monotonic(), 0.0))
        if wait(lambda: any(f.done() for f in futures), budget):
            return next(f for f in futures if f.done()).result()
    return None
