#!/usr/bin/env bash
# The README's test command (`make test`) and CI's: set up, lint, then every test in one pytest run.
# Fails when any test fails. Each run gets its own ROS domain and log folder; DDS stays on loopback.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export ROS_LOG_DIR=$(mktemp -d /tmp/wheelgrid-test-log.XXXXXX)
# the folder goes again where no node wrote a log into it (every run left one, empty)
trap '[ -z "$(find "$ROS_LOG_DIR" -type f -print -quit 2>/dev/null)" ] && rm -rf "$ROS_LOG_DIR"' EXIT
. scripts/env.sh
echo "test: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_LOG_DIR=$ROS_LOG_DIR; each pytest" \
  "process claims a ROS domain no other wheelgrid process here holds (conftest.py)"
ruff check src test bench conftest.py
ruff format --check src test bench conftest.py
mypy  # the packages' type hints (pyproject.toml's [tool.mypy])
# Two workers (pytest-xdist), one per core, each with its own ROS domain (conftest.py); a test
# file runs whole in one worker (--dist loadfile), so a module's nodes and fixtures stay together
# and the live demo runs once. `make test ARGS="-n 0"` runs them in one process, as before.
python -m pytest -p no:dash -p no:cacheprovider -n 2 --dist loadfile --durations=15 "$@"  # the slowest, to keep the suite short
