"""Workspace-wide pytest set-up: every test process talks DDS on loopback only, in its own domain.

scripts/test.sh already exports these; this also covers a bare `pytest` run by a developer.
"""

import os
import random
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
if os.environ.get("PYTEST_XDIST_WORKER", "").startswith("gw"):
    # pytest -n: every worker inherits the run's domain, and two workers' nodes of one name
    # (/mapper, /planner) would hear each other. Each worker takes its own, spread over 1-100.
    _worker = int(os.environ["PYTEST_XDIST_WORKER"][2:])
    _workers = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), 1)
    _base = int(os.environ["ROS_DOMAIN_ID"])
    os.environ["ROS_DOMAIN_ID"] = str((_base - 1 + _worker * (100 // _workers)) % 100 + 1)
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="wheelgrid-test-log."))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


@pytest.fixture
def stray_capture() -> Path:
    """The real iPhone capture (../shared/data/stray-iphone-room); skips when it is absent."""
    from wheelgrid_common.testing import shared_data

    path = shared_data("stray-iphone-room", Path(__file__).resolve().parent)
    if not (path / "depth").is_dir():
        pytest.skip(f"{path}: the real Stray capture is not present")
    return path


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Tests that kill a node outright (the chain's node-killed test, the launcher's SIGKILL
    tests) leave its Fast DDS segments in /dev/shm, about 17 MB a node, and a test must stop what it
    started: the segments of dead processes go here (never one a live process holds)."""
    from wheelgrid_common.shm import clean_dead_segments

    clean_dead_segments()
