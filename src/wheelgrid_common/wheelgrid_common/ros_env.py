"""Running ROS 2 safely from pip wheels, and the same code under a full apt install.

Every process that starts rclpy goes through :func:`configure_ros_env` first, so DDS discovery
stays on this machine unless the user explicitly chose otherwise, large messages (a whole
iPhone cloud) go through shared memory instead of UDP fragments that a loaded machine drops,
and rclpy has a log folder even where ``HOME`` is unset (it refuses to start without one).
"""

from __future__ import annotations

import errno
import fcntl
import os
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, MutableMapping
from contextlib import contextmanager, suppress
from importlib.util import find_spec
from pathlib import Path
from typing import Any, cast


def configure_ros_env(env: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """Fill in safe defaults without overriding what the user set explicitly."""
    env = os.environ if env is None else env
    # Fast DDS multicasts beyond the machine with default discovery; never do that by default.
    # Set but empty (`VAR= cmd`, docker's `-e VAR` with VAR unset on the host) is unset to
    # ROS, which then discovers across the subnet: it multicast onto the LAN.
    if not env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip():
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if "ROS_LOG_DIR" not in env:
        home = env.get("HOME")
        base = (
            os.path.join(home, ".ros", "log")
            if home
            else os.path.join(tempfile.gettempdir(), "wheelgrid-ros-log")
        )
        env["ROS_LOG_DIR"] = base
    os.makedirs(env["ROS_LOG_DIR"], exist_ok=True)
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    profile = fastdds_profile(env)
    if profile is not None:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
    return env


#: The highest ROS_DOMAIN_ID ROS 2 takes (its DDS ports go past 65535 above it).
MAX_DOMAIN_ID = 232


def domain_id_problem(env: Mapping[str, str]) -> str:
    """Why ``env``'s ROS_DOMAIN_ID cannot run ("" where it can, or is unset): "abc" ended the
    launch and `wheelgrid call` in rclpy's traceback, 250 in Fast DDS's "port number is too
    high" with no word of the variable, and -1 ran the chain in domain 0 (a review)."""
    value = env.get("ROS_DOMAIN_ID", "").strip()
    if not value:
        return ""
    if not value.isdigit() or int(value) > MAX_DOMAIN_ID:
        return f"ROS_DOMAIN_ID={value!r} is not a domain: a whole number from 0 to {MAX_DOMAIN_ID}"
    return ""


def rmw_missing(env: Mapping[str, str]) -> str:
    """Why ``env``'s RMW_IMPLEMENTATION cannot run here ("" where it can, or where it is not
    set: Fast DDS then, which the ROS wheels bring). rclpy exits with status 102 at its first
    init when the library is absent, the whole process with it: a shell left with
    rmw_cyclonedds_cpp from another ROS install made the test suite exit 102 with no test
    report (a review). Looked for as rcpputils does: ``lib<name>.so`` on LD_LIBRARY_PATH,
    beside this Python's (the venv's lib, where the wheels put theirs) or under a prefix of
    AMENT_PREFIX_PATH."""
    name = env.get("RMW_IMPLEMENTATION", "").strip()
    if not name or name == "rmw_fastrtps_cpp":
        return ""
    folders = [Path(sys.prefix) / "lib"]
    folders += [Path(d) for d in env.get("LD_LIBRARY_PATH", "").split(os.pathsep) if d]
    folders += [Path(d) / "lib" for d in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if d]
    if any((folder / f"lib{name}.so").exists() for folder in folders):
        return ""
    return (
        f"RMW_IMPLEMENTATION={name} is not installed here (no lib{name}.so on LD_LIBRARY_PATH, "
        f"in {sys.prefix}/lib or under AMENT_PREFIX_PATH): unset it, or set it to "
        "rmw_fastrtps_cpp, which the ROS wheels bring"
    )


#: ``python -c`` code run first in a child that has ``parent`` (the pid that started it)
#: defined: Linux SIGTERMs it when that process dies, however it dies. Children in sessions of
#: their own are reached by nothing else: a supervisor killed outright (SIGKILL, the OOM killer)
#: left every node running, the drive holding the chair's port, and a test node outlived a
#: killed pytest by minutes. SIGTERM is the clean stop every node handles. Plain Python, no
#: wheelgrid import (a child's environment may not reach the packages, and it costs no
#: start-up); where prctl is missing (not Linux), nothing.
DIE_WITH_PARENT_CODE = (
    "import ctypes, os, signal\n"
    "try:\n"
    "    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)\n"
    "except (OSError, AttributeError):\n"
    "    pass\n"
    "else:\n"
    "    if os.getppid() != parent:  # it died before the prctl: nobody would send it\n"
    "        os.kill(os.getpid(), signal.SIGTERM)\n"
)


#: Fast DDS transports for this machine only: shared memory that holds a whole iPhone cloud,
#: UDP on 127.0.0.1 (see the file for what it was measured to change).
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_loopback.xml")
#: ``WHEELGRID_FASTDDS_PROFILE=0`` runs Fast DDS with its own default transports.
PROFILE_SWITCH_ENV = "WHEELGRID_FASTDDS_PROFILE"
#: /dev/shm must have this much free for the profile (16 MB segments, one per participant).
SHM_FREE_NEEDED = 256 * 1024 * 1024


def fastdds_profile(env: Mapping[str, str]) -> Path | None:
    """The profile to run Fast DDS with, or None where it must not be used: another RMW, a
    profile the user set, discovery beyond this machine (a remote RViz would be cut off by a
    loopback-only UDP), or a /dev/shm too small for the segments (a container's 64 MB default):
    Fast DDS's own transports then, as without wheelgrid."""
    if env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    if env.get("FASTRTPS_DEFAULT_PROFILES_FILE") or env.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        return None
    if env.get(PROFILE_SWITCH_ENV, "1") == "0":  # the benchmarks' baseline: Fast DDS defaults
        return None
    if env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") != "LOCALHOST" or env.get("ROS_STATIC_PEERS"):
        return None
    try:
        if shutil.disk_usage("/dev/shm").free < SHM_FREE_NEEDED:
            return None
    except OSError:
        return None
    return FASTDDS_PROFILE if FASTDDS_PROFILE.is_file() else None


def child_env(domain_id: int | None = None, **extra: str) -> dict[str, str]:
    """An environment for a child process that starts ROS: inherits ours, safe defaults set."""
    env = dict(os.environ)
    configure_ros_env(env)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.update(extra)
    return env


#: Where the domain claims' lock files lie: one folder for the machine, since a DDS domain is
#: the machine's, whichever user or checkout runs in it (not $TMPDIR, which one shell may set
#: and another not: two demos then claimed 215 each).
DOMAIN_LOCK_DIR = Path("/tmp") if os.access("/tmp", os.W_OK) else Path(tempfile.gettempdir())


def claim_domain(candidates: Iterable[int], lock_dir: Path | None = None) -> tuple[int, int] | None:
    """The first of ``candidates`` no other wheelgrid process on this machine holds, and the
    file descriptor of its lock (held until it is closed or the process ends, however it
    ends), or None where every one is held.

    Two demos run at once both picked the same domain and each mapped the other's frames (a
    review's two shared 217; the summary could only warn afterwards). A lock file per domain,
    taken with ``flock``, leaves no stale claim behind a killed process. It is opened read-only
    so that another user's demo can lock the same file; a file this user may not open at all
    counts as held. Where the folder takes no locks the candidate tried comes back with -1
    for its descriptor: not claimed, as before there were claims."""
    folder = DOMAIN_LOCK_DIR if lock_dir is None else lock_dir
    for domain in candidates:
        path = folder / f"wheelgrid-ros-domain-{domain}.lock"
        try:
            fd = _open_lock_file(path)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                continue
            return domain, -1  # a folder without locks (ENOLCK): unclaimed, as before
        return domain, fd
    return None


@contextmanager
def held_claims() -> Iterator[list[int]]:
    """A list for :func:`claim_domain`'s lock descriptors (-1 for none), each closed however
    the block ends: a caller run again in the same process (a test) must let go of its
    domain, and the demo's and the launcher's ``main`` both hold one for their run."""
    held: list[int] = []
    try:
        yield held
    finally:
        for fd in held:
            if fd >= 0:
                os.close(fd)


def _open_lock_file(path: Path) -> int:
    """A read-only descriptor of the lock file, made where it is missing. Opened without
    O_CREAT where it exists: Linux's fs.protected_regular refuses O_CREAT on another user's
    file in a sticky folder (/tmp), and that user's old lock would read as held for ever."""
    try:
        return os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        try:
            return os.open(path, os.O_RDONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:  # another process made it just now
            return os.open(path, os.O_RDONLY)


def with_message_info(callback: Callable[[Any, Any], None]) -> Callable[[Any], None]:
    """``callback`` as rclpy's type hints take it. rclpy hands a callback of two parameters
    the message's info as well (its source and receive stamps); its hints know of one."""
    return cast(Callable[[Any], None], callback)


def received_ns(info: dict[str, Any] | None, key: str = "received_timestamp") -> int:
    """The middleware's receive (or with ``key`` "source_timestamp", publication) time from
    rclpy's message info, or 0 where it gives none."""
    if not info:
        return 0
    try:
        return int(info.get(key) or 0)
    except (TypeError, ValueError):
        return 0


def sample_key(info: dict[str, Any] | None) -> tuple[int, int] | None:
    """(publication time, publisher's sequence number) of a sample, the same on every
    subscription that receives it; None where the middleware gives no publication time."""
    published = received_ns(info, "source_timestamp")
    if not published:
        return None
    assert info is not None
    try:
        return published, int(info.get("publication_sequence_number") or 0)
    except (TypeError, ValueError):
        return published, 0


def tf2_problem() -> str | None:
    """Why /tf cannot be published here, or None: tf2_msgs not importable (the pip wheels lack
    it; a full ROS install, or set-up, brings it), or importable without its type support (a
    partial build without its C libraries, where the mapper died creating its publisher)."""
    if find_spec("tf2_msgs") is None:
        return "tf2_msgs is not importable"
    try:
        from tf2_msgs.msg import TFMessage

        TFMessage.__class__.__import_type_support__()  # type: ignore[attr-defined]
    except Exception as exc:
        return f"tf2_msgs is importable but its type support does not load ({exc})"
    return None


def tf2_available() -> bool:
    """True where the mapper can publish /tf (see :func:`tf2_problem`)."""
    return tf2_problem() is None


def side_node(parent: Any, suffix: str) -> Any:
    """A second node of ``parent``'s process, ``<name>_<suffix>`` in its namespace, for work
    that must go on while the parent's executor is held up (the drive's e-stop, the grid's
    heartbeat), on an executor and a thread of the caller's. A launcher names its node with a
    global ``-r __node:=drive``, which renames every node of the process: the side node was a
    second "drive", whose rosout publisher rcl shares and drops with it. A node-local rename
    wins over a global one, and global topic remaps still apply to it."""
    from rclpy.node import Node

    name = f"{parent.get_name()}_{suffix}"
    return Node(
        name,
        namespace=parent.get_namespace(),
        context=parent.context,
        cli_args=["--ros-args", "-r", f"__node:={name}"],
        start_parameter_services=False,
    )


class SideSpinner:
    """A :func:`side_node` spun on an executor and a daemon thread of its own, and stopped
    with it: the drive's e-stop and the grid's heartbeat must go on while their parent's
    executor is held up. ``run(executor)`` is the thread's body (it calls ``executor.spin()``
    and decides what an exception there means); the executor is passed in so the thread never
    reads an attribute its starter has not yet set."""

    def __init__(self, node: Any, thread_name: str, run: Callable[[Any], None]) -> None:
        from rclpy.executors import SingleThreadedExecutor

        self.node = node
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        self.thread = threading.Thread(
            target=run, args=(self.executor,), name=thread_name, daemon=True
        )
        self.thread.start()

    def close(self) -> None:
        """Stop the executor, wait for the thread (1 s at most) and destroy the node."""
        self.executor.shutdown(timeout_sec=1.0)
        self.thread.join(timeout=1.0)
        self.node.destroy_node()


def steady_timer(node: Any, period: float, callback: Callable[[], Any]) -> Any:
    """A timer of ``node`` on steady time, for its housekeeping (publishing at a bounded rate,
    status, watchdogs). On the node's own clock, ``use_sim_time`` (a Nav2 params file's
    ``/**`` section, a replay with a clock) stopped such timers whenever ``/clock`` was absent,
    paused or ended with its bag: a map already made was never published, a grid never
    computed, a status never sent. Messages keep the node's clock in their stamps."""
    from rclpy.clock import Clock, ClockType

    return node.create_timer(period, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


# how often spin_node wakes a node's executor so that a signal handled in Python runs (s)
SIGNAL_POLL_S = 0.5

#: The PyPI name of each module the code imports that a full ROS 2 install does not bring
#: (rosdep has no key for the first three): a module's name is not always its package's.
PIP_NAMES = {
    "kiss_icp": "kiss-icp",
    "open3d": "open3d",
    "rosbags": "rosbags",
    "serial": "pyserial",
    "PIL": "pillow",
    "yaml": "pyyaml",
    "numpy": "numpy",
}


def missing_dependency(exc: ModuleNotFoundError) -> str | None:
    """One line for a dependency that is not installed, or None where the module missing is
    none of them (a module of the project itself: a build problem, said elsewhere). On a full
    ROS 2 the PyPI-only ones are not installed by rosdep, and a node or a command ended in a
    traceback deep in the mapping, exit 1 (a review)."""
    top = (exc.name or "").split(".")[0]
    if top not in PIP_NAMES:
        return None
    return (
        f"the Python package {PIP_NAMES[top]} is not installed (no module {top!r}): "
        f"`pip install {PIP_NAMES[top]}` where the nodes run (requirements.lock pins its "
        "version), or scripts/setup.sh for this checkout's own environment"
    )


def spin_node(factory: Callable[[], Any], args: list[str] | None = None) -> int:
    """Init rclpy, build the node, spin until Ctrl-C/SIGTERM, clean up; return an exit code.

    Node ``main`` functions all go through here so shutdown behaves the same everywhere:
    SIGINT and SIGTERM end the spin, the node is destroyed and the context shut down.
    """
    configure_ros_env()
    try:
        import rclpy
        from rclpy.executors import ExternalShutdownException

        rclpy.init(args=args)
    except KeyboardInterrupt:
        # Ctrl-C while rclpy loads (a launch stopped half a second after its start): nothing
        # has started, nothing is to be saved; it was a traceback, and exit 1 or -2 (a review)
        return 0
    except Exception as exc:  # rclpy's RCLError: a --params-file that does not parse, etc.
        # one line and exit 2, as a bad parameter value: it was rclpy's traceback, exit 1
        import sys

        reason = (str(exc).splitlines() or [""])[0].split(", at /")[0]  # rcl's first line
        print(f"[FATAL] cannot start: {reason}", file=sys.stderr)
        return 2
    # A closed terminal or ssh session (SIGHUP) ended a node at once, without its close(): a
    # mapper's scan was not saved, though save_on_exit promises it. It now ends the spin as
    # Ctrl-C does, with KeyboardInterrupt (re-sent as SIGTERM, it hung wherever SIGTERM was
    # no longer rclpy's: a test process whose earlier test had taken it). Not from another
    # thread: signals are the main thread's, and its caller's. `nohup mapper` ignores it, and
    # goes on doing so.
    old = None
    if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:
        old = _set_signal(signal.SIGHUP, _hang_up)
    node = None
    code = 0
    try:
        node = factory()
        # Python runs a signal handler only once the main thread is back in Python: a node
        # with no timer of its own (depth_to_cloud with its stream stopped) waited in rcl for
        # ever, and SIGHUP, handled in Python above, never stopped it. This wakes it.
        steady_timer(node, SIGNAL_POLL_S, lambda: None)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as exc:  # a node may ask to stop with a code
        code = int(exc.code or 0)
    except ModuleNotFoundError as exc:
        why = missing_dependency(exc)
        if why is None:
            raise
        import sys

        print(f"[FATAL] {why}", file=sys.stderr)
        code = 2
    except Exception:
        # A callback that ran into the context Ctrl-C/SIGTERM had just shut down ("publisher's
        # context is invalid", a take that failed) ended the node with a traceback and exit 1,
        # which the launcher reported as a node that failed. Not so for a running node, nor
        # for one being built when its context went ("error creating node: the given context
        # is not valid": a Ctrl-C during start-up).
        if node.context.ok() if node is not None else rclpy.ok():
            raise
    finally:
        # A second Ctrl-C while the node closes (a mapper waits for its worker and saves the
        # map) raised KeyboardInterrupt out of close(): a traceback, and the save could be
        # skipped. Ignored now; SIGKILL still stops at once.
        old_int = _set_signal(signal.SIGINT, signal.SIG_IGN)
        if old is not None:
            _set_signal(signal.SIGHUP, signal.SIG_IGN)  # a second one, as a second Ctrl-C
        try:
            if node is not None:
                close = getattr(node, "close", None)
                if callable(close):
                    close()
                node.destroy_node()
            # after SIGTERM rclpy's handler has shut the context down, and
            # rclpy.shutdown() was skipped: its default context stayed, and a later
            # rclpy.init() in the same process (a test) raised "must only be called once"
            rclpy.try_shutdown()
        finally:
            for sig, handler in ((signal.SIGINT, old_int), (signal.SIGHUP, old)):
                if handler is not None:
                    _set_signal(sig, handler)
    return code


def _hang_up(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum} (SIGHUP: the terminal closed)")


def _set_signal(sig: signal.Signals, handler: Any) -> Any:
    """``signal.signal``, or None (and nothing set) outside the main thread."""
    with suppress(ValueError):
        return signal.signal(sig, handler)
    return None


def exit_logger(node: Any) -> Any:
    """The node's logger, or after Ctrl-C shut its context down, a logger named after it that
    does not publish to /rosout: the node's own printed "Failed to publish log message to
    rosout" after every line logged on the way out (the map saved on exit, the bridge's
    counts)."""
    if node.context.ok():
        return node.get_logger()
    import rclpy.logging

    return rclpy.logging.get_logger(f"{node.get_name()}.exit")


def check_topic_params(node: Any, topics: dict[str, str], optional: tuple[str, ...] = ()) -> None:
    """``ValueError`` naming the first topic parameter (``{parameter: topic}``) whose name
    rclpy would refuse; an empty name is allowed for the parameters in ``optional`` (that
    input is off)."""
    for what, name in topics.items():
        if what in optional and not name:
            continue
        why = name_problem(name, node.get_name(), node.get_namespace())
        if why:
            raise ValueError(f"{what} {name!r}: {why}")


def rcl_reason(exc: Exception) -> str:
    """rcl's refusal of a name as one line: its first line, without the source location and
    the caret line that follow it, which mean nothing to a user of a command or a node."""
    return str(exc).splitlines()[0].split(", at /")[0].rstrip(": ")


def name_problem(
    name: str, node: str, namespace: str = "/", *, service: bool = False
) -> str | None:
    """Why rclpy would refuse ``name`` as a topic (or service) of node ``node``, or None.

    Checked before ``create_*``, which raises rclpy's own traceback for a bad name; the
    answer is rcl's first line without its source location, for a one-line error."""
    from rclpy.exceptions import InvalidServiceNameException, InvalidTopicNameException
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name

    try:
        validate_full_topic_name(expand_topic_name(name, node, namespace), is_service=service)
    except (InvalidTopicNameException, InvalidServiceNameException, ValueError) as exc:
        why = rcl_reason(exc)
        # rcl expands both kinds by the topic rules and says "topic" either way
        return why.replace("topic name", "service name") if service else why
    return None
