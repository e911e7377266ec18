"""Helpers for tests that run real nodes: an isolated rclpy context, spinning until a condition,
and child processes that are always stopped (SIGINT, then SIGTERM, then SIGKILL).

Tests must stop whatever they start; these helpers make that the default.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.ros_env import DIE_WITH_PARENT_CODE, child_env, configure_ros_env
from wheelgrid_common.services import call_with_retry
from wheelgrid_common.shm import clean_dead_segments


def not_installed(monkeypatch: Any, package: str) -> None:
    """``package`` as if not installed, marked the way Python itself marks a module it must not
    import (None in sys.modules, for its submodules already loaded too): a full ROS 2 where
    rosdep, which has no key for kiss-icp, did not bring it."""
    for name in [n for n in sys.modules if n == package or n.startswith(package + ".")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, package, None)


def box_surface(lo: Sequence[float], hi: Sequence[float], spacing: float, rng: Any) -> np.ndarray:
    """Random points on the six faces of an axis-aligned box, about one per ``spacing**2``."""
    lo_, hi_ = np.asarray(lo, float), np.asarray(hi, float)
    out = []
    for ax in range(3):
        o = [a for a in range(3) if a != ax]
        area = (hi_[o[0]] - lo_[o[0]]) * (hi_[o[1]] - lo_[o[1]])
        n = max(int(area / spacing**2), 4)
        for side in (lo_[ax], hi_[ax]):
            p = np.empty((n, 3))
            p[:, ax] = side
            p[:, o[0]] = lo_[o[0]] + rng.random(n) * (hi_[o[0]] - lo_[o[0]])
            p[:, o[1]] = lo_[o[1]] + rng.random(n) * (hi_[o[1]] - lo_[o[1]])
            out.append(p)
    return np.vstack(out)


def body_frame_room(rng: np.random.Generator, with_floor: bool) -> np.ndarray:
    """Body-convention sensor at 1 m height looking +x into a furnished corner."""
    parts = [
        np.column_stack([np.full(6000, 4.0), rng.random(6000) * 6 - 3, rng.random(6000) * 2.5 - 1]),
        np.column_stack([rng.random(4000) * 4, np.full(4000, 3.0), rng.random(4000) * 2.5 - 1]),
        np.column_stack(
            [2 + rng.random(3000) * 0.5, -1 + rng.random(3000) * 0.5, -1 + rng.random(3000) * 0.8]
        ),
    ]
    if with_floor:
        parts.append(
            np.column_stack([rng.random((15000, 2)) * [4, 6] - [0, 3], np.full(15000, -1.0)])
        )
    return np.vstack(parts) + rng.normal(0, 0.003, (sum(len(p) for p in parts), 3))


def room_world(seed: int) -> np.ndarray:
    """A 6 x 5 x 2.6 m room shell with four boxes (a table, a cupboard, a post, a crate): enough
    structure for ICP in every direction, small enough for unit tests."""
    rng = np.random.default_rng(seed)
    parts = [box_surface([0, 0, 0], [6, 5, 2.6], 0.04, rng)]
    for lo, hi in (
        ([1.0, 3.5, 0], [2.2, 4.3, 0.75]),
        ([4.0, 0.5, 0], [4.5, 1.5, 1.8]),
        ([3.0, 3.0, 0], [3.4, 3.4, 1.2]),
        ([0.5, 0.5, 0], [1.0, 1.2, 0.5]),
    ):
        parts.append(box_surface(lo, hi, 0.03, rng))
    return np.vstack(parts)


def sensor_view(world: np.ndarray, T: np.ndarray, rng: Any) -> np.ndarray:
    """Sensor-frame points (body convention) of ``world`` seen from pose ``T``: within 5 m and
    a 100 deg cone ahead, half of them, with 5 mm noise."""
    inv = np.linalg.inv(T)
    p = world @ inv[:3, :3].T + inv[:3, 3]
    r = np.linalg.norm(p, axis=1)
    p = p[(r < 5.0) & (p[:, 0] > 0.3 * r)]
    p = p[rng.random(len(p)) < 0.5]
    return p + rng.normal(0, 0.005, p.shape)


def check_declared_bounds(
    cls: type, validate: Callable[[Any], None], outside_only: Iterable[str] = ()
) -> list[str]:
    """The fields of config ``cls`` that declare bounds, after checking that ``validate``
    refuses a value just outside each finite bound (or the CLI's YAML takes what the node's
    rclpy refuses) and takes one just inside (or rclpy would pass a value the config then
    refuses, a range that says less than it seems). ``outside_only``: fields whose valid
    values have a gap (0 for off, then from 1) or depend on another field's."""
    import dataclasses
    import math

    import pytest

    from wheelgrid_common.params import bounds_of

    ranged = bounds_of(cls)
    for name, (lo, hi) in ranged.items():
        default = getattr(cls(), name)
        assert lo <= default <= hi, (name, default, lo, hi)
        step = 1 if isinstance(default, int) else 1e-6
        for outside in (lo - step, hi + step):
            if math.isfinite(outside):
                with pytest.raises(ValueError, match=name):
                    validate(dataclasses.replace(cls(), **{name: outside}))
        for inside in (lo + step, hi - step):
            if math.isfinite(inside) and name not in outside_only:
                validate(dataclasses.replace(cls(), **{name: inside}))
    return sorted(ranged)


def shared_data(name: str, repo_root: Path) -> Path:
    """Where a real data set lives: ``$WHEELGRID_SHARED/data/NAME``, else the checkout's sibling
    ``../shared/data/NAME``. It may be absent: callers skip with a reason (never copy it in)."""
    base = os.environ.get("WHEELGRID_SHARED")
    return (Path(base) if base else repo_root.parent / "shared") / "data" / name


def free_port() -> int:
    """A TCP port on loopback that nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def rclpy_context() -> Iterator[Any]:
    """An rclpy Context of its own (init + shutdown), so tests never leak a global init."""
    configure_ros_env()
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


def spin_until(
    executor: Any, predicate: Callable[[], bool], timeout: float, step: float = 0.05
) -> bool:
    """Spin ``executor`` until ``predicate()`` is true or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step)
    return bool(predicate())


def diagnostics_log(node: Any, topic: str) -> list[dict[str, str]]:
    """A list that ``node`` fills with the key/values of the first status of every
    DiagnosticArray on ``topic`` (a bridge's or a drive's state, as a test waits on it)."""
    from diagnostic_msgs.msg import DiagnosticArray

    from wheelgrid_common.qos import RELIABLE_QOS

    log: list[dict[str, str]] = []
    node.create_subscription(
        DiagnosticArray,
        topic,
        lambda m: log.append({kv.key: kv.value for kv in m.status[0].values}),
        RELIABLE_QOS,
    )
    return log


def call_service(
    executor: Any,
    client: Any,
    request: Callable[[], Any],
    timeout: float = 20.0,
    attempt: float = 4.0,
) -> Any:
    """:func:`~wheelgrid_common.services.call_with_retry`, spinning ``executor`` while waiting."""
    return call_with_retry(
        client, request, lambda done, wait: spin_until(executor, done, wait), timeout, attempt
    )


def stop_process(proc: subprocess.Popen[Any], grace: float = 5.0) -> int | None:
    """SIGINT (clean rclpy shutdown), then SIGTERM, then SIGKILL the whole process group.

    A process that did not exit cleanly (killed, crashed, or ended by a signal before this was
    called) leaves its Fast DDS segments in /dev/shm, about 17 MB a node: removed here."""
    rc = _stop(proc, grace)
    if rc is not None and rc != 0:
        clean_dead_segments()
    return rc


def _stop(proc: subprocess.Popen[Any], grace: float) -> int | None:
    if proc.poll() is not None:
        return proc.returncode
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        try:
            os.killpg(proc.pid, sig)
            # and SIGCONT, as systemd does: a stopped (SIGSTOP, Ctrl-Z) process handles no
            # signal, and a frozen mapper waited out the grace, was SIGKILLed, and its scan was
            # never saved on exit (a review)
            os.killpg(proc.pid, signal.SIGCONT)
        except ProcessLookupError:
            break
        try:
            return proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


#: ``python -c`` code: :data:`DIE_WITH_PARENT_CODE`, then exec ``argv[2:]`` (the same pid, so
#: the caller's handle stays the child's).
_DIE_WITH_PARENT_THEN_EXEC = (
    "import sys\nparent = int(sys.argv[1])\n"
    + DIE_WITH_PARENT_CODE
    + "os.execvp(sys.argv[2], sys.argv[2:])\n"
)


def dying_with_this_process(args: Sequence[str]) -> list[str]:
    """argv that runs ``args`` (the same pid) SIGTERMed by Linux when this process's thread
    that starts it ends, however it ends: for a child in a session of its own, which nothing
    else reaches when a test process is killed outright."""
    return [sys.executable, "-c", _DIE_WITH_PARENT_THEN_EXEC, str(os.getpid()), *args]


@contextmanager
def managed_process(
    args: Sequence[str], env: dict[str, str] | None = None, **popen: Any
) -> Iterator[subprocess.Popen[Any]]:
    """Start a child in its own process group and always stop it on exit, and where the test
    process is killed outright (SIGKILL, the OOM killer, a CI timeout) too: it runs in a
    session of its own, so nothing else reached it, and a grid node outlived a killed pytest
    by minutes (a review). Linux SIGTERMs it when the thread that started it ends: start it
    from the test's own thread."""
    proc = subprocess.Popen(
        dying_with_this_process(args),
        env=env if env is not None else child_env(),
        start_new_session=True,
        **popen,
    )
    try:
        yield proc
    finally:
        stop_process(proc)


def python_module(module: str, *args: str) -> list[str]:
    """argv that runs ``python -m module args`` with this interpreter (the venv's)."""
    return [sys.executable, "-m", module, *args]


def wheelgrid_command(*args: str) -> list[str]:
    """argv that runs ``wheelgrid args`` with this interpreter (no console script needed)."""
    return [
        sys.executable,
        "-c",
        "import sys; from wheelgrid_bringup.cli import main; sys.exit(main())",
        *args,
    ]


def chain_params(tmp_path: Path, output_dir: Path, **sections: dict[str, Any]) -> Path:
    """The bundled params file (``wheelgrid launch``'s default) with the mapper's output_dir
    (and here the grid's) set to ``output_dir`` and each ``sections`` node's parameters
    updated, written to ``tmp_path/params.yaml``: a test's chain saves nothing in the
    checkout."""
    import yaml

    from wheelgrid_bringup.supervisor import default_params_file

    params = yaml.safe_load(default_params_file().read_text())
    for node in ("mapper", "grid"):
        params[node]["ros__parameters"]["output_dir"] = str(output_dir)
    for node, values in sections.items():
        params[node]["ros__parameters"].update(values)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def bag_cloud_odometry(bag: Any, n: int) -> list:
    """The first ``n`` (PointCloud2, Odometry) pairs of a bridge-like bag (``/iphone/points``,
    ``/iphone/odometry``) as rclpy messages, for tests that publish them to a live mapper."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from wheelgrid_common.bagio import BagReader

    clouds, odoms = [], []
    with BagReader(bag) as reader:
        for topic, _, _, raw in reader.raw(["/iphone/points", "/iphone/odometry"]):
            if topic == "/iphone/points":
                clouds.append(deserialize_message(raw, PointCloud2))
            else:
                odoms.append(deserialize_message(raw, Odometry))
            if len(clouds) >= n and len(odoms) >= n:
                break
    return list(zip(clouds[:n], odoms[:n], strict=True))


def ros1_cloud_bag(src: Any, dst: Path, n: int) -> Path:
    """The first ``n`` /iphone/points clouds of the rosbag2 ``src`` written as a ROS 1 .bag at
    ``dst`` (ROS 1 serialisation, with Header.seq): what older iPhone tools record."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from wheelgrid_common.bagio import BagReader

    ts = get_typestore(Stores.ROS1_NOETIC)
    PC2 = ts.types["sensor_msgs/msg/PointCloud2"]
    PF = ts.types["sensor_msgs/msg/PointField"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    with BagReader(src) as reader, Writer(dst) as w:
        conn = w.add_connection("/iphone/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for k, (_, t_ns, m) in enumerate(reader.messages(["/iphone/points"])):
            if k >= n:
                break
            fields = [PF(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                      for f in m.fields]  # fmt: skip
            stamp = Time(sec=m.header.stamp.sec, nanosec=m.header.stamp.nanosec)
            msg = PC2(header=Header(seq=k, stamp=stamp, frame_id=m.header.frame_id),
                      height=m.height, width=m.width, fields=fields,
                      is_bigendian=m.is_bigendian, point_step=m.point_step,
                      row_step=m.row_step, data=m.data, is_dense=m.is_dense)  # fmt: skip
            w.write(conn, t_ns, ts.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))
    return dst


def edit_bag(
    src: Path,
    out: Path,
    *,
    topics: Iterable[str] | None = None,
    keep: Callable[[str, int], bool] | None = None,
    until: Callable[[str, int], bool] | None = None,
    edits: Mapping[str, Callable[[int, Any], bytes | None]] | None = None,
    storage: str = "sqlite3",
) -> Path:
    """A copy of the rosbag2 bag ``src`` at ``out``, message by message in log-time order, for
    tests that need a bag broken or bent one way: every such test had its own copy loop.

    ``k`` counts each topic's messages from 0. ``topics`` (default all) are copied;
    ``until(topic, k)`` true ends the copy before that message; ``keep(topic, k)`` false
    leaves a message out; ``edits[topic](k, msg)`` gets each kept message of its topic decoded
    (a rosbags message), changes it in place, or returns the raw bytes to write instead (a
    message that does not deserialise). Others are copied byte for byte."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    from wheelgrid_common.bagio import typestore

    store = typestore()
    edits = edits or {}
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Reader(src) as reader:
        names = None if topics is None else set(topics)
        wanted = [c for c in reader.connections if names is None or c.topic in names]
        writer = Writer(out, version=9, storage_plugin=plugin)
        writer.open()
        conns = {}
        for c in wanted:
            if c.topic not in conns:
                conns[c.topic] = writer.add_connection(c.topic, c.msgtype, typestore=store)
        seen: dict[str, int] = {}
        try:
            for conn, t_ns, raw in reader.messages(connections=wanted):
                k = seen.get(conn.topic, 0)
                seen[conn.topic] = k + 1
                if until is not None and until(conn.topic, k):
                    break
                if keep is not None and not keep(conn.topic, k):
                    continue
                data = bytes(raw)
                edit = edits.get(conn.topic)
                if edit is not None:
                    msg = store.deserialize_cdr(data, conn.msgtype)
                    replaced = edit(k, msg)
                    data = (
                        replaced
                        if replaced is not None
                        else bytes(store.serialize_cdr(msg, conn.msgtype))
                    )
                writer.write(conns[conn.topic], t_ns, data)
        finally:
            writer.close()
    return out


def _lost_and_moved(
    src: Path,
    out: Path,
    lost: str,
    first: int,
    last: int,
    shift: tuple[float, float],
    clouds: str,
    odometry: str,
) -> Path:
    """A copy of ``src`` (clouds and odometry) with messages ``first``-``last`` of the topic
    ``lost`` left out and the odometry's world moved by ``shift`` from the message after them."""

    def move(k: int, msg: Any) -> None:
        if k > last:
            msg.pose.pose.position.x += shift[0]
            msg.pose.pose.position.y += shift[1]

    return edit_bag(
        src,
        out,
        topics=[clouds, odometry],
        keep=lambda topic, k: not (topic == lost and first <= k <= last),
        edits={odometry: move},
    )


def dropout_bag(
    src: Path,
    out: Path,
    first: int,
    last: int,
    shift: tuple[float, float] = (0.0, 0.0),
    clouds: str = "/iphone/points",
    odometry: str = "/iphone/odometry",
) -> Path:
    """A copy of the bag ``src`` (clouds and odometry) at ``out`` with clouds ``first``-``last``
    lost, the odometry going on, and the odometry's world moved by ``shift`` (x, y in metres)
    from the message after them: ARKit re-anchoring while the stream was down. The tests and
    bench/dropouts.py build their dropouts this one way."""
    return _lost_and_moved(src, out, clouds, first, last, shift, clouds, odometry)


def prior_pause_bag(
    src: Path,
    out: Path,
    first: int,
    last: int,
    shift: tuple[float, float] = (0.0, 0.0),
    clouds: str = "/iphone/points",
    odometry: str = "/iphone/odometry",
) -> Path:
    """A copy of the bag ``src`` (clouds and odometry) at ``out`` with odometry messages
    ``first``-``last`` lost, every cloud kept (the pose prior pauses while the clouds go on),
    and the odometry's world moved by ``shift`` (x, y in metres) from the message after them.
    The tests and bench/prior_pauses.py build their pauses this one way."""
    return _lost_and_moved(src, out, odometry, first, last, shift, clouds, odometry)


def poses_by_stamp(path: Path) -> dict[float, np.ndarray]:
    """A TUM file's poses by stamp, rounded to the 10 ms that tell a 5 Hz bag's frames apart
    (a trajectory and the bag's true poses are compared frame by frame)."""
    from wheelgrid_common.fileio import read_tum

    stamps, poses = read_tum(path)
    return {round(float(t), 2): pose for t, pose in zip(stamps, poses, strict=True)}
