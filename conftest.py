"""Workspace-wide pytest set-up: every test process talks DDS on loopback only, in its own domain.

scripts/test.sh already exports these; this also covers a bare `pytest` run by a developer.
"""

import os
import random
import tempfile

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="wheelgrid-test-log."))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
