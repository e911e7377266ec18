# Sourced by the Makefile targets: the venv, the colcon install space, and a ROS environment that
# never talks beyond this machine. Safe to source by hand too: `. scripts/env.sh`.
_wg_root=$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)
case $_wg_root in
  *[[:space:]]*)
    # colcon's install/setup.sh splits its own path at spaces: nothing of wheelgrid was found
    # ("wheelgrid: command not found", ModuleNotFoundError), after a set-up that went well
    echo "env.sh: the checkout's path has a space in it ($_wg_root), which colcon's setup" \
      "scripts cannot take: move or clone it to a path without one" >&2
    unset _wg_root
    return 1 2>/dev/null || exit 1
    ;;
esac
export PATH="$_wg_root/.venv/bin:$PATH"
# colcon's setup scripts reference unset variables; source them without nounset.
case $- in *u*) _wg_u=1; set +u;; *) _wg_u=0;; esac
# shellcheck disable=SC1091
. "$_wg_root/install/setup.sh"
[ "$_wg_u" = 1 ] && set -u
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_LOG_DIR=${ROS_LOG_DIR:-$_wg_root/log/ros}
# One domain per checkout, the same in every shell that sources this file: a second terminal
# (`wheelgrid call`, RViz) must reach the nodes a first one launched. It was the shell's pid,
# a different domain in every terminal. The tests pick their own (scripts/test.sh).
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( $(printf '%s' "$_wg_root" | cksum | cut -d' ' -f1) % 100 + 1 ))}
export RMW_IMPLEMENTATION=${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}
if [ "$RMW_IMPLEMENTATION" != rmw_fastrtps_cpp ]; then
  # one left from another ROS install (rmw_cyclonedds_cpp) that this one lacks: rclpy exits
  # 102 at its first init, and the test suite and every node with it. The test run's own
  # check (wheelgrid_common.ros_env.rmw_missing) says why.
  _wg_why=$("$_wg_root/.venv/bin/python" -c \
    'import os; from wheelgrid_common.ros_env import rmw_missing; print(rmw_missing(os.environ))' \
    2>/dev/null || true)
  if [ -n "$_wg_why" ]; then
    echo "env.sh: $_wg_why; using rmw_fastrtps_cpp" >&2
    export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
  fi
  unset _wg_why
fi
mkdir -p "$ROS_LOG_DIR"
unset _wg_root _wg_u
