"""The ``wheelgrid`` command: one entry point, subcommands implemented by each package.

Subcommands are imported lazily so ``wheelgrid --help`` is instant and a missing optional
piece only affects its own subcommand. Each target is ``module:function`` taking ``argv`` and
returning an exit code (0 ok, 2 bad input, 1 failure).
"""

from __future__ import annotations

import importlib
import os
import sys

# name -> (module:function, one-line help). Order is the order of the paper's pipeline.
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": (
        "wheelgrid_sim.cli:main",
        "write a synthetic iPhone-LiDAR room scan (rosbag2) with exact ground truth",
    ),
    "bag-recover": (
        "wheelgrid_common.bag_recover:main",
        "copy the complete messages of a recording that was cut off into a bag that opens",
    ),
    "map": (
        "wheelgrid_mapping.cli_map:main",
        "filter and register a bag or Stray Scanner export into a levelled 3D map (map.ply)",
    ),
    "measure": (
        "wheelgrid_mapping.cli_measure:main",
        "measure distances between surfaces of a map (the paper's Table I)",
    ),
    "import-stray": (
        "wheelgrid_mapping.cli_stray:import_main",
        "convert a Stray Scanner export into a rosbag2 bag with the bridge's topics",
    ),
    "stream-stray": (
        "wheelgrid_mapping.cli_stray:stream_main",
        "play a Stray Scanner export to an iphone_bridge in real time (stands in for the phone)",
    ),
    "grid": (
        "wheelgrid_nav.cli_grid:main",
        "turn a map into the safe 2D grid (grid.yaml/pgm for Nav2, fine map, grid.png)",
    ),
    "plan": (
        "wheelgrid_nav.cli_plan:main",
        "plan up/down/left/right moves on a safe grid with Q-learning",
    ),
    "drive": (
        "wheelgrid_drive.cli:main",
        "send a plan to the motor controller over serial (Table II actions)",
    ),
    "motor-sim": (
        "wheelgrid_drive.motor_sim:main",
        "run the simulated motor controller on a pty "
        "(`ros2 run wheelgrid_drive wheelgrid-motor-sim` on a full ROS 2)",
    ),
    "launch": (
        "wheelgrid_bringup.launcher:main",
        "start mapper, grid, planner and drive nodes (and a bag replay or the iPhone bridge)",
    ),
    "call": (
        "wheelgrid_bringup.call:main",
        "call a node's Trigger service (e.g. /mapper/close_loops, /mapper/save_map): no ros2 CLI",
    ),
    "demo": (
        "wheelgrid_bringup.demo:main",
        "the whole chain on the bundled bag: map, grid, plan, drive a simulated chair; out/",
    ),
}


def usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = [
        "usage: wheelgrid <command> [options]",
        "",
        "A safe 2D grid map for indoor wheelchair navigation from iPhone LiDAR scans (ROS 2).",
        "",
        "commands:",
    ]
    lines += [f"  {name.ljust(width)}  {helptext}" for name, (_, helptext) in COMMANDS.items()]
    lines += ["", "Run 'wheelgrid <command> --help' for a command's options."]
    return "\n".join(lines)


def _missing(command: str, exc: ModuleNotFoundError) -> int:
    """A dependency not installed is one line and exit 2; any other missing module is ours to
    see whole (raised again)."""
    from wheelgrid_common.ros_env import missing_dependency

    why = missing_dependency(exc)
    if why is None:
        raise exc
    print(f"wheelgrid {command}: {why}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"wheelgrid: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    target, _ = COMMANDS[name]
    module_name, func_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] == module_name.split(".")[0]:
            print(
                f"wheelgrid {name}: not available ({exc}); is the workspace built? (make setup)",
                file=sys.stderr,
            )
            return 2
        return _missing(name, exc)
    func = getattr(module, func_name)
    try:
        return int(func(rest) or 0)
    except ModuleNotFoundError as exc:  # imported where it is first needed (kiss_icp, open3d)
        return _missing(name, exc)
    except KeyboardInterrupt:
        print(f"wheelgrid {name}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # `wheelgrid plan --json | head`: the reader left; not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
