#!/usr/bin/env bash
# One-shot, idempotent set-up: system libraries Open3D needs, .venv from the pinned lock file,
# then a colcon build of src/. Fast (a few seconds) when everything is already in place.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
case $ROOT in
  *[[:space:]]*)
    # colcon's install/setup.sh splits its own path at spaces: the set-up went well, and then
    # nothing of wheelgrid could be found
    echo "setup: the checkout's path has a space in it ($ROOT), which colcon's setup" \
      "scripts cannot take: move or clone it to a path without one" >&2
    exit 2
    ;;
esac
PY=${PYTHON:-python3}

# Open3D's wheel links against a few Debian libraries; a bare image may lack them.
missing=()
# read once: `ldconfig -p | grep -q` under pipefail failed when grep quit first (SIGPIPE),
# and about one set-up in ten said a library was missing that was there
libs=$(ldconfig -p)
for lib in libusb-1.0.so.0 libEGL.so.1 libGL.so.1 libX11.so.6 libudev.so.1 libgomp.so.1; do
  grep -qF "$lib" <<<"$libs" || missing+=("$lib")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: missing system libraries: ${missing[*]}" >&2
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get install -y -q libusb-1.0-0 libegl1 libgl1 libx11-6 libudev1 libgomp1 >/dev/null \
      || { apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 libegl1 libgl1 libx11-6 libudev1 libgomp1 >/dev/null; }
  else
    echo "setup: install them with: sudo apt-get install libusb-1.0-0 libegl1 libgl1 libx11-6 libudev1 libgomp1" >&2
    exit 1
  fi
fi

mkdir -p .stamps log
# pip too: a set-up killed between the venv's python and ensurepip's pip left a venv every
# later run failed on (".venv/bin/pip: No such file or directory")
if [ ! -x .venv/bin/python ] || ! .venv/bin/python -m pip --version >/dev/null 2>&1; then
  rm -rf .venv .stamps/lock
  "$PY" -m venv .venv
fi
if [ ! -f .stamps/lock ] || ! cmp -s requirements.lock .stamps/lock; then
  echo "setup: installing pinned dependencies into .venv (about a minute the first time)" >&2
  .venv/bin/pip install -q --disable-pip-version-check -r requirements.lock
  cp requirements.lock .stamps/lock
fi

# tf2_msgs (the /tf message), which the ROS wheels lack, from vendor/tf2_msgs into .venv: only
# where it is not importable (a full ROS install has its own) and once. Without CMake or a
# compiler the set-up goes on and says so: the mapper then publishes no /tf, as before.
# importable is not enough: a partial build without its C type support imports, and the
# mapper's /tf publisher then fails; the check loads the type support too
TF2_CHECK="import tf2_msgs.msg; tf2_msgs.msg.TFMessage.__class__.__import_type_support__()"
if ! .venv/bin/python -c "$TF2_CHECK" 2>/dev/null; then
  echo "setup: building tf2_msgs (the /tf message) from vendor/tf2_msgs into .venv" >&2
  if (
    export PATH="$ROOT/.venv/bin:$PATH" AMENT_PREFIX_PATH="$ROOT/.venv"
    rm -rf build/vendor_tf2_msgs
    cmake -S vendor/tf2_msgs -B build/vendor_tf2_msgs -DCMAKE_BUILD_TYPE=Release \
      -DBUILD_TESTING=OFF -DCMAKE_PREFIX_PATH="$ROOT/.venv" -DCMAKE_INSTALL_PREFIX="$ROOT/.venv" \
      -DPython3_EXECUTABLE="$ROOT/.venv/bin/python" \
      && cmake --build build/vendor_tf2_msgs -j 2 && cmake --install build/vendor_tf2_msgs
  ) >log/tf2_msgs-build.log 2>&1 && .venv/bin/python -c "$TF2_CHECK" 2>/dev/null; then
    echo "setup: tf2_msgs built: the mapper publishes /tf" >&2
  else
    echo "setup: WARNING: tf2_msgs could not be built (see log/tf2_msgs-build.log; it needs" \
      "cmake and a C/C++ compiler): the mapper runs without /tf" >&2
  fi
fi

# colcon from the venv, never a system ROS: build every package of src/ (ament_python).
export PATH="$ROOT/.venv/bin:$PATH"
mkdir -p log
colcon --log-base log build --symlink-install --base-paths src \
  --event-handlers console_cohesion- summary- status- >/dev/null 2>log/colcon-build.err \
  || { cat log/colcon-build.err >&2; colcon --log-base log build --symlink-install --base-paths src; exit 1; }
echo "setup: ready (.venv + install/)" >&2
