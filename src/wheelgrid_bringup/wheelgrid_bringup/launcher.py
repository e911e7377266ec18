"""``wheelgrid launch``: the chain from one command, where ``ros2 launch`` may not exist.

Starts mapper, grid, planner and drive (and the iPhone bridge with ``--iphone``) as supervised
processes sharing one parameter YAML, optionally replays a bag into them, prints a live status
line, and shuts everything down on Ctrl-C or as soon as any node dies (exit 1, naming it).
``launch/wheelgrid.launch.py`` starts the same nodes with the same file under ``ros2 launch``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from wheelgrid_bringup.chain import Chain, Monitor, NodeDiedError
from wheelgrid_bringup.supervisor import (
    NODES,
    REPLAY_MAX_QUEUE,
    Supervisor,
    default_params_file,
)
from wheelgrid_common.bagio import BagError
from wheelgrid_common.params import read_yaml
from wheelgrid_common.ros_env import (
    child_env,
    claim_domain,
    configure_ros_env,
    domain_id_problem,
    held_claims,
    rcl_reason,
)
from wheelgrid_common.shm import clean_dead_segments


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wheelgrid launch", description=__doc__.splitlines()[0].replace("``", "")
    )
    p.add_argument("--params", type=Path, help="parameter YAML (default: bringup wheelgrid.yaml)")
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--bag",
        type=Path,
        help="rosbag2 folder to replay into the mapper (a ROS 1 .bag: rosbags-convert it first)",
    )
    src.add_argument("--iphone", action="store_true", help="start the iPhone bridge node")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed factor (default 1.0)")
    p.add_argument("--topic", action="append", help="replay only these topics (repeatable)")
    p.add_argument(
        "--clock",
        nargs="?",
        type=float,
        const=40.0,
        metavar="HZ",
        help="with --bag: publish the bag's time on /clock at HZ (default 40, as `ros2 bag "
        "play --clock`) and start every node with use_sim_time, so that what they publish is "
        "stamped on the sensor's clock",
    )
    p.add_argument("--motor-port", help="serial port of the motor controller (drive node)")
    p.add_argument("--no-drive", action="store_true", help="do not start the drive node")
    p.add_argument(
        "--log-dir",
        type=Path,
        default=Path("log/launch"),
        help="node logs, NODE.log (the run before's kept as NODE.log.1, up to .5); with "
        "--namespace NS in LOG_DIR/NS",
    )
    p.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0: never)")
    p.add_argument(
        "--namespace",
        default="",
        metavar="NS",
        help="run the chain in ROS namespace NS (topics /NS/wheelgrid/..., services "
        "/NS/mapper/save_map; a bag's topics are replayed under it too); the params file's "
        "plain node keys (mapper:) are applied to the nodes in NS",
    )
    return p


def check_namespace(text: str) -> str:
    """``NS``, ``/NS`` or ``/a/b`` as rcl's absolute namespace (``""`` for the root), or a
    ``ValueError`` with rcl's reason: a node refused it only in its own log, after start."""
    if not text.strip("/"):
        return ""
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    ns = "/" + text.strip("/")
    try:
        validate_namespace(ns)
    except InvalidNamespaceException as exc:
        raise ValueError(f"--namespace {text!r}: {rcl_reason(exc)}") from None
    return ns


def namespaced_params_file(
    path: Path, namespace: str, out_dir: Path, data: dict[str, Any] | None = None
) -> Path:
    """A copy of the params file whose plain node keys (``mapper:``) name the nodes in
    ``namespace`` (``/chair1/mapper:``): rcl matches a plain key to ``/mapper`` only, and the
    chain's nodes would have run on their defaults. Keys with a ``/`` (``/**``,
    ``/chair1/grid``, ``chair1/grid``) and namespace sections (``chair1: {grid: ...}``) are
    kept as written.
    ``data``: the file as :func:`check_params_file` read it, so that the copy is what was
    checked (read a second time, a file edited in between went unchecked)."""
    import yaml

    if data is None:
        data = read_yaml(path)
    out: dict[Any, Any] = {}
    for key, body in data.items():
        plain = isinstance(body, dict) and "ros__parameters" in body
        # only a bare node name is prefixed: rcl reads ``chair1/grid:`` as ``/chair1/grid``
        # too, and prefixed it became ``/chair1/chair1/grid``, the grid on its defaults
        name = f"{namespace}/{key}" if plain and "/" not in str(key) else key
        if name in out and plain and "ros__parameters" in out[name]:
            # ``grid:`` and ``/chair1/grid:`` both: rcl applies both, the later over the
            # earlier; one dict key for the two kept only the later, and the grid ran on its
            # default safe height where the first section set another
            body = {
                **out[name],
                **body,
                "ros__parameters": _merged(out[name]["ros__parameters"], body["ros__parameters"]),
            }
        out[name] = body
    out_dir.mkdir(parents=True, exist_ok=True)
    copy = out_dir / f"params{namespace.replace('/', '_')}.yaml"
    copy.write_text(yaml.safe_dump(out, sort_keys=False))
    return copy


def _merged(first: dict[str, Any], later: dict[str, Any]) -> dict[str, Any]:
    """``later``'s parameters over ``first``'s, nested groups (``loop_closure:``) merged too."""
    out = dict(first)
    for key, value in later.items():
        both = isinstance(out.get(key), dict) and isinstance(value, dict)
        out[key] = _merged(out[key], value) if both else value
    return out


def node_overrides(name: str, args: argparse.Namespace) -> dict[str, object]:
    """The parameters the command line sets on node ``name``, over the params file's."""
    overrides: dict[str, object] = {}
    if name == "drive" and args.motor_port:
        overrides["port"] = args.motor_port
    if name == "mapper" and args.bag:
        overrides["max_queue"] = REPLAY_MAX_QUEUE
    if args.clock is not None:
        # on the bag's time: without it a node stamps its map, plan and pose with the wall
        # clock of the replay, years after the clouds it made them from
        overrides["use_sim_time"] = True
    return overrides


def section_reaches(pattern: str, node: str) -> bool:
    """Whether a params file's section (``/chair1/grid``, ``/**``, ``/*/grid``) applies to
    the node of fully qualified name ``node``, as rcl matches them: a ``*`` token stands for
    one name token, ``**`` for any number of them (rcl parses no ``*`` inside a token:
    :func:`check_params_file` refuses one). Empty tokens (``/chair1//grid``, a namespace key
    written ``/chair1/``) are none, as in rcl."""

    def match(pat: list[str], name: list[str]) -> bool:
        if not pat:
            return not name
        if pat[0] == "**":
            return any(match(pat[1:], name[i:]) for i in range(len(name) + 1))
        return bool(name) and pat[0] in ("*", name[0]) and match(pat[1:], name[1:])

    def tokens(text: str) -> list[str]:
        return [t for t in text.split("/") if t]

    return match(tokens(pattern), tokens(node))


def check_params_file(path: Path, namespace: str = "") -> dict[str, Any]:
    """The ROS 2 parameter file at ``path`` (``node: {ros__parameters: {...}}`` per node), or
    ``ValueError`` where it is not one: rcl would refuse it only inside each node, as a
    traceback in that node's log after the chain had started, and the launch would end with
    exit 1 naming a dead node instead of the file's line.

    Every section must also reach a node of the chain in ``namespace`` (a plain ``mapper:`` is
    given to the namespace's mapper, see :func:`namespaced_params_file`). rcl ignores a section
    that names no node, so ``gird:`` (or ``chair2:`` under ``--namespace chair1``) ran the grid
    on its defaults, its safe height among them, with exit 0."""
    import difflib

    data = read_yaml(path)
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{path}: expected a mapping of node name: {{ros__parameters: ...}}")
    chain = [f"{namespace}/{name}" for name in NODES]

    def check(name: str, body: object) -> None:  # a node, or a namespace holding nodes
        if isinstance(body, dict) and "ros__parameters" in body:
            if not isinstance(body["ros__parameters"], dict):
                raise ValueError(f"{path}: {name}'s ros__parameters must be a mapping")
            if name.endswith("/"):
                raise ValueError(
                    f"{path}: section {name!r}: a node's key must not end in '/' (rcl refuses "
                    "the file in every node: node name must not be empty)"
                )
            # a plain top-level key is the namespace's node; anything else is as written
            fqn = f"{namespace}/{name}" if "/" not in name else "/" + name.lstrip("/")
            if any("*" in t and t not in ("*", "**") for t in fqn.split("/")):
                raise ValueError(
                    f"{path}: section {name!r}: rcl reads * and ** only as whole name tokens "
                    "(/*/grid, /**), and refuses this file in every node"
                )
            if not any(section_reaches(fqn, node) for node in chain):
                close = difflib.get_close_matches(fqn, chain, n=1)
                raise ValueError(
                    f"{path}: section {name!r} (node {fqn}) reaches no node of the chain "
                    f"({', '.join(chain)})"
                    + (f": did you mean {close[0]!r}?" if close else "")
                    + "; its parameters would apply to nothing, and the node meant would run "
                    "on its defaults"
                )
            return
        if not isinstance(body, dict) or not body:
            raise ValueError(
                f"{path}: {name!r} must hold a ros__parameters mapping (or nodes under a "
                "namespace), as a ROS 2 params file does"
            )
        for key, inner in body.items():
            check(f"{name}/{key}", inner)

    for node, body in data.items():
        check(str(node), body)
    _rcl_reads(path)
    return data


def _rcl_reads(path: Path) -> None:
    """``ValueError`` where rcl's own parser refuses the file: a parameter with no value, a
    key beside ``ros__parameters``, a list of mixed types or of lists, a YAML alias. Each
    passed the checks above, every node then died reading it, and the launch ended with exit 1
    naming the first node to die (a review). rcl parses ``--params-file`` as a context starts:
    one that makes no node opens no DDS participant. Domain 0 and no logging, so that only the
    file can fail it (not a ROS_DOMAIN_ID of "abc") and no log file is left per check; rcl's
    own "Failed to parse global arguments" line is kept off stderr, said here in one line."""
    from rclpy.context import Context

    ctx = Context()
    err = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            try:
                ctx.init(
                    args=["--ros-args", "--params-file", str(path)],
                    initialize_logging=False,
                    domain_id=0,
                )
            finally:
                os.dup2(err, 2)
    except Exception as exc:  # rclpy's RCLError: "... Error: No value at line 3, at ..."
        text = str(exc)
        why = text.split("Error: ", 1)[1].split(", at ", 1)[0] if "Error: " in text else text
        raise ValueError(f"{path}: rcl cannot read it: {why.strip()}") from None
    finally:
        os.close(err)
    ctx.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    with held_claims() as held:  # the domain's lock, let go however the launch ends
        return _main(argv, held)


def _main(argv: list[str] | None, held: list[int]) -> int:
    args = build_parser().parse_args(argv)
    if not (math.isfinite(args.rate) and args.rate > 0):  # NaN: a replay that spun, silent
        print(f"wheelgrid launch: --rate must be > 0, not {args.rate}", file=sys.stderr)
        return 2
    if not (math.isfinite(args.duration) and args.duration >= 0):
        # NaN never stopped, and -1 stopped at once with exit 0
        print(
            f"wheelgrid launch: --duration must be >= 0 s (0: never), not {args.duration}",
            file=sys.stderr,
        )
        return 2
    if args.clock is not None and not args.bag:
        # live, time is the sensor's own: there is no bag time to send
        print("wheelgrid launch: --clock needs --bag (it sends the bag's time)", file=sys.stderr)
        return 2
    if args.clock is not None and not (math.isfinite(args.clock) and args.clock > 0):
        print(f"wheelgrid launch: --clock must be > 0 Hz, not {args.clock}", file=sys.stderr)
        return 2
    try:
        namespace = check_namespace(args.namespace)
    except ValueError as exc:
        print(f"wheelgrid launch: {exc}", file=sys.stderr)
        return 2
    configure_ros_env()
    if why := domain_id_problem(os.environ):
        print(f"wheelgrid launch: {why}", file=sys.stderr)
        return 2
    try:
        params = args.params or default_params_file()
    except FileNotFoundError as exc:
        print(f"wheelgrid launch: {exc}", file=sys.stderr)
        return 2
    if not params.exists():
        print(f"wheelgrid launch: no such params file {params}", file=sys.stderr)
        return 2
    try:
        checked = check_params_file(params, namespace)
        if namespace:
            params = namespaced_params_file(params, namespace, args.log_dir, checked)
    except (OSError, ValueError) as exc:
        print(f"wheelgrid launch: {exc}", file=sys.stderr)
        return 2
    names = ["mapper", "grid", "planner"]
    if not args.no_drive:
        names.append("drive")
    if args.iphone:
        names.insert(0, "iphone_bridge")

    import rclpy
    from rclpy.context import Context

    from wheelgrid_bringup.replay import BagPlayer, not_replayed_note

    stop = {"flag": False}

    def on_signal(signum: int, _frame: object) -> None:
        stop["flag"] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    # A closed terminal or a dropped ssh session: Python's default for SIGHUP ended the
    # launcher at once, skipping the clean-up below, and the nodes (in sessions of their own)
    # ran on, orphaned. It stops the chain like Ctrl-C.
    if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:  # `nohup wheelgrid launch`
        signal.signal(signal.SIGHUP, on_signal)

    env = child_env()
    # a chain killed outright before this one (kill -9, the OOM killer, a power cut of the
    # process, not of the machine) left its nodes' shared memory behind: about 17 MB a node
    freed = clean_dead_segments()
    if freed.removed:
        print(
            f"launch: removed {freed.removed} Fast DDS segments of dead processes from "
            f"/dev/shm ({freed.bytes / 2**20:.0f} MiB)",
            flush=True,
        )
    # a second terminal (`wheelgrid call`, RViz) reaches these nodes only on this domain
    print(
        f"launch: ROS_DOMAIN_ID={env.get('ROS_DOMAIN_ID', '0')} "
        f"ROS_AUTOMATIC_DISCOVERY_RANGE={env['ROS_AUTOMATIC_DISCOVERY_RANGE']}"
        + (f" namespace {namespace}" if namespace else ""),
        flush=True,
    )
    # held while the chain runs, so that a test process, which claims a domain no other
    # wheelgrid process holds (conftest.py), never lands on it: only demos held theirs, and a
    # test run beside a launch could join its graph, drive included (a review). Held already
    # (the test or demo that started this launch, a second launch of this checkout): as before.
    with contextlib.suppress(ValueError):
        claim = claim_domain([int(env.get("ROS_DOMAIN_ID", "0"))])
        if claim is not None:
            held.append(claim[1])
    try:
        # a chain in a namespace logs in a folder of its own: two chains on one --log-dir
        # wrote into the same files, and each launcher read the other's mapper log
        sup = Supervisor(args.log_dir / namespace.strip("/") if namespace else args.log_dir, env)
    except OSError as exc:  # a --log-dir below a file: a traceback, exit 1
        print(f"wheelgrid launch: --log-dir {args.log_dir}: {exc.strerror}", file=sys.stderr)
        return 2
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    monitor = Monitor(ctx, "wheelgrid_launch", namespace or None)
    chain = Chain(sup, monitor)
    player = None
    code = 0
    replay_failed = False
    try:
        if args.bag:  # opened before any node starts: a wrong path costs no node start-up
            try:
                player = BagPlayer(
                    monitor.node,
                    args.bag,
                    args.topic,
                    args.rate,
                    clock_hz=args.clock or 0.0,
                    clock_readers=len(names),
                    namespace=namespace,
                )
            except BagError as exc:
                print(f"wheelgrid launch: {exc}", file=sys.stderr)
                return 2
            if player.left_out:
                print(f"launch: {not_replayed_note(player)}", flush=True)
        for name in names:
            sup.start_node(name, params, node_overrides(name, args), namespace)
            print(
                f"launch: started {name} (pid {sup.procs[name].proc.pid}, log "
                f"{sup.procs[name].log_path})",
                flush=True,
            )
        if player is not None:
            # let the nodes' subscriptions match first: a frame sent before is lost
            deadline = time.monotonic() + 30.0
            while player.unsubscribed() and time.monotonic() < deadline and not stop["flag"]:
                chain.check()
                time.sleep(0.1)
            # stopped while the nodes started (a review: "replaying anyway", then the
            # replay started on the way out): nothing is replayed
            if not stop["flag"]:
                if player.unsubscribed():
                    print(
                        f"launch: no subscriber for {', '.join(player.unsubscribed())}; "
                        "replaying anyway",
                        flush=True,
                    )
                player.start(delay=0.5)
        t0 = time.monotonic()
        last = 0.0
        while not stop["flag"]:
            chain.check()
            now = time.monotonic()
            if player is not None and player.error and not replay_failed:
                # said once, where a script reads it, and the exit says it too: a status line
                # alone scrolled by, and the launch ended 0 on a map of half the bag
                replay_failed = True
                say_replay_failed(player)
            if now - last >= 1.0:
                extra = ""
                if player is not None:
                    extra = f"replay {player.published}/{player.total}"
                    if player.error:
                        extra += f" ERROR {player.error}"
                line = monitor.status_line(extra, drive="drive" in names)
                print(f"[{now - t0:6.1f} s] {line}", flush=True)
                last = now
            if args.duration and now - t0 >= args.duration:
                break
            time.sleep(0.1)
    except NodeDiedError as exc:
        print(
            f"wheelgrid launch: {exc}; stopping the chain\n--- last lines of {exc.name} ---\n"
            f"{exc.tail}",
            file=sys.stderr,
        )
        code = 1
    finally:
        if player is not None:
            player.stop()
        codes = sup.stop_all()
        monitor.close()
        if ctx.ok():
            rclpy.shutdown(context=ctx)
        if codes:
            print(
                "launch: stopped " + ", ".join(f"{n} ({c})" for n, c in codes.items()), flush=True
            )
        if "mapper" in sup.procs:
            for line in save_on_exit_lines(sup.procs["mapper"].log_path):
                print(f"launch: mapper: {line}", flush=True)
        if player is not None and player.error:  # a replay stopped early sets no error
            if not replay_failed:
                say_replay_failed(player)
            code = code or 1
        unclean = {n: c for n, c in codes.items() if c != 0}
        if unclean and code == 0:
            # A node that had to be killed may have lost what it does on its way out (the
            # mapper's save, the drive's last STOP): exit 0 told a script all was well.
            print(
                "wheelgrid launch: "
                + ", ".join(f"{n} (exit {c})" for n, c in unclean.items())
                + " did not stop cleanly: see "
                + ", ".join(str(sup.procs[n].log_path) for n in unclean),
                file=sys.stderr,
            )
            code = 1
    return code


def say_replay_failed(player: Any) -> None:
    print(
        f"wheelgrid launch: the replay failed after {player.published} of {player.total} "
        f"messages ({player.error}); the map holds only the messages before it",
        file=sys.stderr,
        flush=True,
    )


SAVE_ON_EXIT = ("map saved on exit", "map NOT saved on exit", "cannot save the map")


def save_on_exit_lines(log_path: Path) -> list[str]:
    """What the mapper did with an unsaved map as it stopped, from its log: the node writes it
    to ``<output_dir>/on_exit`` (relative to where the chain was started) or a temporary
    folder, and a user watching the console would otherwise never learn where."""
    try:
        text = log_path.read_text(errors="replace")
    except OSError:
        return []
    lines = [line.strip() for line in text.splitlines()]
    return [
        line[line.find("]: ") + 3 :] if "]: " in line else line
        for line in lines
        if any(key in line for key in SAVE_ON_EXIT)
    ]


if __name__ == "__main__":
    sys.exit(main())
