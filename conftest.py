"""Workspace-wide pytest set-up: every test process talks DDS on loopback only, in a ROS domain
no other wheelgrid process on this machine holds.

scripts/test.sh sources scripts/env.sh first; this also covers a bare `pytest` run by a
developer, whose shell may have set other values for a live chain or another machine.
"""

import atexit
import os
import random
import shutil
import tempfile
from pathlib import Path

import pytest

from wheelgrid_common.ros_env import claim_domain, rmw_missing

# Loopback discovery, whatever the shell says: a ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET kept
# from a shell set up for a remote RViz had the test nodes discover across the subnet.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# Each test process (each pytest-xdist worker too) claims its own domain with the demo's
# lock files, never the shell's: scripts/env.sh gives every shell of a checkout its domain, so
# a `wheelgrid launch` in another terminal shares it, and two runs at once that drew the same
# random domain failed each other's node tests (5 of 21 each, a review). The lock is held as
# long as this process lives.
_inherited = os.environ.get("ROS_DOMAIN_ID", "")
_first = random.randint(1, 100)
_order = [(_first - 1 + i) % 100 + 1 for i in range(100)]
_claim = claim_domain(d for d in _order if str(d) != _inherited)
if _claim is None:  # every domain of 1-100 held: share one, as before there were claims
    _claim = (next(d for d in _order if str(d) != _inherited), -1)
os.environ["ROS_DOMAIN_ID"] = str(_claim[0])


def _remove_if_no_file(folder: str) -> None:
    """Every run left its log folder behind, empty (265 in /tmp on a review's machine)."""
    if not any(files for _, _, files in os.walk(folder)):
        shutil.rmtree(folder, ignore_errors=True)


if "ROS_LOG_DIR" not in os.environ:
    os.environ["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix="wheelgrid-test-log.")
    atexit.register(_remove_if_no_file, os.environ["ROS_LOG_DIR"])
try:  # hypothesis keeps its cache in ./.hypothesis: the checkout, 75 files of it (a review)
    from hypothesis.configuration import set_hypothesis_home_dir
except ImportError:
    pass
else:
    _hypothesis_home = tempfile.mkdtemp(prefix="wheelgrid-test-hypothesis.")
    set_hypothesis_home_dir(_hypothesis_home)
    atexit.register(shutil.rmtree, _hypothesis_home, ignore_errors=True)
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
_rmw = rmw_missing(os.environ)
if _rmw:  # rclpy exits 102 at its first init, and the whole run with it
    pytest.exit(_rmw, returncode=2)


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
