# Sourced by the Makefile targets: the venv, the colcon install space, and a ROS environment that
# never talks beyond this machine. Safe to source by hand too: `. scripts/env.sh`.
_wg_root=$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)
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
mkdir -p "$ROS_LOG_DIR"
unset _wg_root _wg_u
