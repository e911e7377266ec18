"""Supervised node processes for machines without ``ros2 launch`` (the pip-wheel ROS).

Each node runs as its own process (as under ``ros2 launch``), started through its package's
``main`` so no installed console script or sourced ROS is needed. The supervisor notices a
node that dies, names it, and stops everything else: a half-running chain must never keep
driving a chair.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from wheelgrid_common.ros_env import DIE_WITH_PARENT_CODE, child_env
from wheelgrid_common.testing import stop_process

# A replay maps every frame, as `wheelgrid map` does; live, the mapper keeps only the newest
# (max_queue 1 in wheelgrid.yaml). The launch file's REPLAY_MAPPER must say the same.
REPLAY_MAX_QUEUE = 1000

# node name -> "module:function" of its main(); the same table the launch file mirrors.
NODES: dict[str, str] = {
    "mapper": "wheelgrid_mapping.mapper_node:main",
    "grid": "wheelgrid_nav.grid_node:main",
    "planner": "wheelgrid_nav.planner_node:main",
    "drive": "wheelgrid_drive.drive_node:main",
    "iphone_bridge": "wheelgrid_mapping.iphone_bridge_node:main",
    "depth_to_cloud": "wheelgrid_mapping.depth_to_cloud_node:main",
}


#: The line of :func:`child_code` that lets SIGINT in once its quiet handler is set:
#: :meth:`Supervisor.start` blocks SIGINT for the fork of a child whose code holds it.
_UNBLOCK_SIGINT = "signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})\n"


def child_code(module: str, func: str) -> str:
    """``python -c`` code that runs ``module.func()`` as a supervised child of this process.

    A Ctrl-C while the node's modules are still being imported ends it with status 0: it has
    nothing to save and no chair to stop yet, and a stop half a second after start-up left a
    KeyboardInterrupt traceback in every node's log and "did not stop cleanly", exit 1 (a
    review). Python's own Ctrl-C handling is back before the node's main runs, and rclpy's
    takes over from there. The child starts with SIGINT blocked (:meth:`Supervisor.start`): one
    during the interpreter's own start-up, before this code runs (the venv's site import),
    was a traceback, exit 1, or death by the signal (a review); it waits, pending, for the
    handler here."""
    return (
        "import os, signal, sys\n"
        # a handler, not `except KeyboardInterrupt`: numpy turns one inside its import into an
        # ImportError (rc 1, a traceback; a review); os._exit, as there is nothing to flush
        "signal.signal(signal.SIGINT, lambda *_: os._exit(0))\n"
        + _UNBLOCK_SIGINT
        + f"parent = {os.getpid()}\n"
        + DIE_WITH_PARENT_CODE
        + f"from {module} import {func} as m\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "sys.exit(m() or 0)\n"
    )


def override_text(value: object) -> str:
    """A ``-p name:=value`` value as rcl reads it, a YAML scalar: a string goes single-quoted.
    Unquoted, `--out "scan #2"` became ``scan`` (the rest a YAML comment) and the maps were
    written to a folder nobody named, and a `: ` in a path made rcl refuse the argument."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return str(value)


def node_argv(
    name: str, params_file: Path | None, overrides: dict[str, object], namespace: str = ""
) -> list[str]:
    """argv that runs node ``name`` with a params file and ``-p`` overrides, in ``namespace``
    (absolute, e.g. ``/chair1``) where one is given."""
    module, func = NODES[name].split(":")
    code = child_code(module, func)
    ros_args = ["--ros-args", "-r", f"__node:={name}"]
    if namespace:
        ros_args += ["-r", f"__ns:={namespace}"]
    if params_file is not None:
        ros_args += ["--params-file", str(params_file)]
    for key, value in overrides.items():
        ros_args += ["-p", f"{key}:={override_text(value)}"]
    return [sys.executable, "-c", code, *ros_args]


@dataclass
class Managed:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    started: float = field(default_factory=time.monotonic)


KEPT_LOGS = 5  # earlier runs' logs kept per node: <name>.log.1 (the last run) .. .5


def rotate_log(path: Path) -> None:
    """Move an earlier run's ``path`` to ``path.1`` (and ``.1`` to ``.2`` ...), as logrotate
    does: a launch truncated the last one's logs, and with them a crashed node's traceback."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    for n in range(KEPT_LOGS - 1, 0, -1):
        older = path.with_name(f"{path.name}.{n}")
        if older.exists():
            older.replace(path.with_name(f"{path.name}.{n + 1}"))
    path.replace(path.with_name(f"{path.name}.1"))


class Supervisor:
    """Start, watch and stop a set of node processes; logs go to ``log_dir/<name>.log``, an
    earlier run's kept as ``<name>.log.1`` (:func:`rotate_log`)."""

    def __init__(self, log_dir: Path, env: dict[str, str] | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = env if env is not None else child_env()
        self.procs: dict[str, Managed] = {}

    def start(self, name: str, argv: Sequence[str]) -> Managed:
        log_path = self.log_dir / f"{name}.log"
        rotate_log(log_path)
        log = open(log_path, "wb")  # noqa: SIM115 - owned by the child for its lifetime
        env = dict(self.env)
        env.setdefault("PYTHONUNBUFFERED", "1")
        # Forked with SIGINT blocked, which the child inherits through exec: child_code
        # unblocks it once its quiet handler is in, and a Ctrl-C before then waits for it.
        # Blocked in this thread only, for the fork: one arriving meanwhile is handled here
        # as ever, once unblocked (or by another thread).
        unblocks = any(_UNBLOCK_SIGINT in a for a in argv)  # only code that lets it in again
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT} if unblocks else set())
        try:
            proc = subprocess.Popen(
                list(argv), env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            log.close()
        managed = Managed(name, proc, log_path)
        self.procs[name] = managed
        return managed

    def start_node(
        self,
        name: str,
        params_file: Path | None,
        overrides: dict[str, object] | None = None,
        namespace: str = "",
    ) -> Managed:
        return self.start(name, node_argv(name, params_file, overrides or {}, namespace))

    def dead(self) -> list[tuple[str, int]]:
        """Processes that exited, with their exit codes."""
        return [(m.name, rc) for m in self.procs.values() if (rc := m.proc.poll()) is not None]

    def tail(self, name: str, lines: int = 15) -> str:
        try:
            text = self.procs[name].log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])

    def stop_all(self) -> dict[str, int | None]:
        """Stop in reverse start order (drive first: the chair stops before its inputs go),
        each node given ``STOP_GRACE_S`` after its SIGINT (5 s where not listed)."""
        codes: dict[str, int | None] = {}
        for name in reversed(list(self.procs)):
            grace = STOP_GRACE_S.get(name, 5.0)
            codes[name] = stop_process(self.procs[name].proc, grace=grace)
        return codes


# Seconds between a node's SIGINT and its SIGTERM (then SIGKILL 2 s on). The mapper saves an
# unsaved map as it stops, after up to 10 s for its worker to let go (a loop closure being
# cancelled) and 5 s for the map's lock: at 5 s, as every node had, a Ctrl-C during a closure
# killed it before the save, and the scan was lost.
STOP_GRACE_S = {"mapper": 25.0}


def default_params_file() -> Path:
    """The bringup package's wheelgrid.yaml (source tree or installed share/)."""
    here = Path(__file__).resolve().parent.parent / "config" / "wheelgrid.yaml"
    if here.exists():
        return here
    prefix = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
    for p in prefix:
        cand = Path(p) / "share" / "wheelgrid_bringup" / "wheelgrid.yaml"
        if cand.exists():
            return cand
    raise FileNotFoundError("wheelgrid.yaml not found (is wheelgrid_bringup built?)")
