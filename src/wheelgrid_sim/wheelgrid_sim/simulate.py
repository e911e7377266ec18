"""Render a scan along a trajectory into a rosbag2 bag, next to its exact ground truth.

Output folder layout (fixed; other stages and tests read it)::

    DIR/scan/               rosbag2 bag: /iphone/points (sensor_msgs/PointCloud2, organised)
                            and /iphone/odometry (nav_msgs/Odometry, ARKit-like, drifting)
    DIR/scene.json          room, boxes, barrier heights, seed, scene name
    DIR/poses.tum           room_from_optical per frame, stamps = message stamps
    DIR/poses_map.tum       the same poses in the levelled MAP frame convention
    DIR/truth.json          map_from_room, frames, rate, stride, camera, grid parameters
    DIR/expected_grid.yaml  the exact safe grid (+ .pgm), ROOM frame, origin at the room corner
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.bagio import POINTCLOUD2, BagError, BagWriter
from wheelgrid_common.fileio import read_tum, write_tum
from wheelgrid_common.map_io import OCCUPIED, Grid, read_map, write_map
from wheelgrid_common.pointcloud2 import to_pointcloud2
from wheelgrid_sim.camera import DepthCamera, depth_to_points
from wheelgrid_sim.odometry import arkit_like_odometry
from wheelgrid_sim.scene import Scene, paper_scene, random_scene
from wheelgrid_sim.trajectory import STAMP_EPOCH, make_trajectory

TOPIC = "/iphone/points"
FRAME_ID = "iphone_depth_optical_frame"
ODOM_TOPIC = "/iphone/odometry"
ODOM_FRAME = "odom"
ODOMETRY = "nav_msgs/msg/Odometry"
SAFE_HEIGHT = 1.5
FLOOR_CLEARANCE = 0.05
CELL_SIZE = 1.2
PAPER_START = (2, 0)
PAPER_GOAL = (6, 5)


def make_scene(name: str, seed: int) -> Scene:
    """``paper`` (the paper's experiment, seed only drives noise/trajectory) or ``random``."""
    if name == "paper":
        return paper_scene()
    if name == "random":
        return random_scene(seed)
    raise ValueError(f"scene must be 'paper' or 'random', not {name!r}")


def map_from_room(first_pose: np.ndarray) -> np.ndarray:
    """4x4 MAP <- ROOM: map origin on the floor below the first camera pose, x along its
    viewing direction projected on the floor, z up (the convention of CONVENTIONS.md)."""
    fwd = first_pose[:3, 2]
    yaw = math.atan2(fwd[1], fwd[0])
    room_from_map = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    room_from_map[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    room_from_map[:2, 3] = first_pose[:2, 3]
    return np.linalg.inv(room_from_map)


def frame_stamp_ns(index: int, rate: float) -> int:
    """Message stamp of frame ``index``: a fixed epoch + index / rate, in integer ns."""
    return STAMP_EPOCH * 1_000_000_000 + round(index * 1e9 / rate)


def start_goal(scene: Scene, grid: Grid) -> tuple[list[int], list[int]]:
    """The paper's start/goal cells; for random scenes two opposite corners of the free ring
    of cells along the walls (the ring lap starts in the bottom-left one)."""
    if scene.name == "paper":
        return list(PAPER_START), list(PAPER_GOAL)
    return [grid.rows - 1, 0], [0, grid.cols - 1]


def canonical_cdr(msg: Any, msgtype: str) -> bytes:
    """CDR bytes of an rclpy message with ZEROED alignment padding.

    rclpy's ``serialize_message`` leaves the padding bytes after strings uninitialised (seen
    here: two runs of the same frame differ only at the bytes after ``frame_id`` and the field
    names), so bags would not be reproducible bit for bit. A round trip through rosbags'
    serialiser, whose output is otherwise byte-identical, writes zeros there.
    """
    from rclpy.serialization import serialize_message

    from wheelgrid_common.bagio import typestore

    store = _STORE.get("store")
    if store is None:
        store = _STORE["store"] = typestore()
    raw = serialize_message(msg)
    return bytes(store.serialize_cdr(store.deserialize_cdr(raw, msgtype), msgtype))


_STORE: dict[str, Any] = {}


def odometry_msg(stamp: Any, T_odom_optical: np.ndarray) -> Any:
    """nav_msgs/Odometry laid out like the iPhone bridge's: ARKit gives no covariance and no
    twist, so both covariances carry -1 in element 0 ("unknown"), never a false zero."""
    from nav_msgs.msg import Odometry

    from wheelgrid_common.fileio import matrix_to_quat

    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = ODOM_FRAME
    msg.child_frame_id = FRAME_ID
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in T_odom_optical[:3, 3])
    q = matrix_to_quat(T_odom_optical[:3, :3])
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
    cov = [0.0] * 36
    cov[0] = -1.0
    msg.pose.covariance = cov
    msg.twist.covariance = cov
    return msg


@dataclass
class SimResult:
    """What :func:`simulate` wrote, with counts a summary line can report."""

    out_dir: Path
    bag: Path
    scene_json: Path
    poses_tum: Path
    poses_map_tum: Path
    truth_json: Path
    expected_grid: Path
    frames: int
    points_per_frame: int
    valid_points: int
    bag_bytes: int
    seconds: float
    occupied_cells: int
    grid_shape: tuple[int, int]

    @property
    def valid_fraction(self) -> float:
        return self.valid_points / max(1, self.frames * self.points_per_frame)


def simulate(
    out_dir: str | Path,
    *,
    seed: int = 7,
    frames: int = 120,
    rate: float = 5.0,
    scene: str | Scene = "paper",
    stride: int = 1,
    storage: str = "sqlite3",
    noise: bool = True,
    odometry: bool = True,
    on_frame: Callable[[int], None] | None = None,
    back_to_start: bool = False,
) -> SimResult:
    """Render ``frames`` depth frames and write the bag plus ground truth under ``out_dir``.

    Raises ``ValueError`` for bad arguments and ``BagError`` when ``out_dir/scan`` exists
    (never overwrite a recording). ``on_frame(i)`` is called after each frame (progress bars).
    ``odometry`` adds ``/iphone/odometry``: the ARKit-like pose with drift, as a phone gives it.
    ``back_to_start``: the path goes on to where it began (:func:`make_trajectory`).
    """
    t0 = time.monotonic()
    if frames < 1:
        raise ValueError("frames must be >= 1")
    if not rate > 0:
        raise ValueError("rate must be > 0 Hz")
    if storage not in ("sqlite3", "mcap"):
        raise ValueError(f"storage must be sqlite3 or mcap, not {storage!r}")
    sc = scene if isinstance(scene, Scene) else make_scene(scene, seed)
    cam = DepthCamera(stride=stride)
    out = Path(out_dir)
    bag = out / "scan"
    if bag.exists():
        raise BagError(f"{bag}: already exists; choose a new --out or remove it")
    before = set(out.iterdir()) if out.is_dir() else None
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _simulate(out, bag, sc, cam, frames, rate, seed, stride, storage, noise,
                         odometry, on_frame, back_to_start, t0)  # fmt: skip
    except BaseException:
        # Ctrl-C or a full disk: the bag, closed as it was, opened as a complete recording of
        # fewer frames than the ground truth beside it described, and a second run into the
        # same --out was refused. What this run wrote goes; the cause goes on.
        if before is None:  # the folder is this run's
            shutil.rmtree(out, ignore_errors=True)
            raise
        for path in set(out.iterdir()) - before:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        raise


def _simulate(
    out: Path,
    bag: Path,
    sc: Scene,
    cam: DepthCamera,
    frames: int,
    rate: float,
    seed: int,
    stride: int,
    storage: str,
    noise: bool,
    odometry: bool,
    on_frame: Callable[[int], None] | None,
    back_to_start: bool,
    t0: float,
) -> SimResult:
    """:func:`simulate`'s work, once its arguments are checked and ``out`` exists."""

    _, poses = make_trajectory(sc, frames, rate, seed, back_to_start)
    stamps_ns = [frame_stamp_ns(i, rate) for i in range(frames)]
    stamps_s = np.array([ns / 1e9 for ns in stamps_ns])
    m_from_r = map_from_room(poses[0])

    grid = sc.expected_grid(SAFE_HEIGHT, FLOOR_CLEARANCE, CELL_SIZE)
    grid.frame_id = "room"
    odom_poses, o_from_r = arkit_like_odometry(poses, seed)
    files = _write_truth(out, sc, cam, grid, stamps_s, poses, m_from_r, frames, rate, seed)
    truth = json.loads(files["truth"].read_text())
    truth["odometry_topic"] = ODOM_TOPIC if odometry else None
    truth["odom_from_room"] = o_from_r.tolist()
    truth["back_to_start"] = bool(back_to_start)
    files["truth"].write_text(json.dumps(truth, indent=1) + "\n")

    from builtin_interfaces.msg import Time

    K = cam.intrinsics()
    rng = np.random.default_rng([seed, 0x51])
    valid = 0
    with BagWriter(bag, storage=storage) as writer:
        for i in range(frames):
            depth = cam.render(sc, poses[i], rng, noise=noise)
            pts = depth_to_points(depth, K)
            valid += int(np.isfinite(depth).sum())
            ns = stamps_ns[i]
            msg = to_pointcloud2(
                pts,
                FRAME_ID,
                Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
                height=cam.rows,
            )
            msg.is_dense = False  # organised: NaN pixels may appear in any frame
            writer.write(TOPIC, POINTCLOUD2, ns, canonical_cdr(msg, POINTCLOUD2))
            if odometry:
                odom = odometry_msg(msg.header.stamp, odom_poses[i])
                writer.write(ODOM_TOPIC, ODOMETRY, ns, canonical_cdr(odom, ODOMETRY))
            if on_frame is not None:
                on_frame(i)
    bag_bytes = sum(p.stat().st_size for p in bag.rglob("*") if p.is_file())
    return SimResult(
        out_dir=out,
        bag=bag,
        scene_json=files["scene"],
        poses_tum=files["poses"],
        poses_map_tum=files["poses_map"],
        truth_json=files["truth"],
        expected_grid=files["grid"],
        frames=frames,
        points_per_frame=cam.rows * cam.cols,
        valid_points=valid,
        bag_bytes=bag_bytes,
        seconds=time.monotonic() - t0,
        occupied_cells=int((grid.data == OCCUPIED).sum()),
        grid_shape=(grid.rows, grid.cols),
    )


def _write_truth(
    out: Path,
    sc: Scene,
    cam: DepthCamera,
    grid: Grid,
    stamps: np.ndarray,
    poses: np.ndarray,
    m_from_r: np.ndarray,
    frames: int,
    rate: float,
    seed: int,
) -> dict[str, Path]:
    scene_doc = sc.to_json()
    scene_doc["seed"] = int(seed)
    (out / "scene.json").write_text(json.dumps(scene_doc, indent=1) + "\n")
    write_tum(out / "poses.tum", stamps, poses)
    write_tum(out / "poses_map.tum", stamps, m_from_r @ poses)
    grid_yaml = write_map(out / "expected_grid.yaml", grid)
    start, goal = start_goal(sc, grid)
    truth = {
        "map_from_room": m_from_r.tolist(),
        "frames": int(frames),
        "rate": float(rate),
        "stride": int(cam.stride),
        "seed": int(seed),
        "scene": sc.name,
        "topic": TOPIC,
        "frame_id": FRAME_ID,
        "stamp_epoch": STAMP_EPOCH,
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "hfov_deg": cam.hfov_deg,
            "rows": cam.rows,
            "cols": cam.cols,
            "min_range": cam.min_range,
            "max_range": cam.max_range,
            "stride": cam.stride,
            "K": cam.intrinsics().tolist(),
            "noise_base": cam.noise_base,
            "noise_quad": cam.noise_quad,
            "outlier_fraction": cam.outlier_fraction,
            "depth": "z-depth along the optical axis, NaN = no return",
        },
        "safe_height": SAFE_HEIGHT,
        "floor_clearance": FLOOR_CLEARANCE,
        "cell_size": CELL_SIZE,
        "expected_grid": "expected_grid.yaml",
        "expected_grid_frame": "room",
        "start_cell": start,
        "goal_cell": goal,
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    return {
        "scene": out / "scene.json",
        "poses": out / "poses.tum",
        "poses_map": out / "poses_map.tum",
        "truth": out / "truth.json",
        "grid": grid_yaml,
    }


@dataclass
class GroundTruth:
    """Everything a test needs to judge a pipeline run on a simulated scan."""

    root: Path
    scene: Scene
    stamps: np.ndarray  # (N,) s
    poses: np.ndarray  # (N, 4, 4) room_from_optical
    poses_map: np.ndarray  # (N, 4, 4) map_from_optical
    map_from_room: np.ndarray  # (4, 4)
    expected_grid: Grid  # room frame
    camera: DepthCamera
    truth: dict[str, Any] = field(default_factory=dict)

    @property
    def bag(self) -> Path:
        return self.root / "scan"

    def expected_grid_for(
        self,
        safe_height: float = SAFE_HEIGHT,
        floor_clearance: float = FLOOR_CLEARANCE,
        cell_size: float = CELL_SIZE,
    ) -> Grid:
        """The exact grid for other parameters (room frame)."""
        return self.scene.expected_grid(safe_height, floor_clearance, cell_size)

    def room_to_map(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return p @ self.map_from_room[:3, :3].T + self.map_from_room[:3, 3]


def load_ground_truth(out_dir: str | Path) -> GroundTruth:
    """Read a ``simulate`` output folder back (the bag itself stays on disk: ``.bag``)."""
    root = Path(out_dir)
    for name in ("scene.json", "truth.json", "poses.tum", "poses_map.tum", "expected_grid.yaml"):
        if not (root / name).exists():
            raise FileNotFoundError(f"{root / name}: missing; is {root} a simulate output?")
    truth = json.loads((root / "truth.json").read_text())
    scene = Scene.from_json(json.loads((root / "scene.json").read_text()))
    stamps, poses = read_tum(root / "poses.tum")
    _, poses_map = read_tum(root / "poses_map.tum")
    grid = read_map(root / truth.get("expected_grid", "expected_grid.yaml"))
    grid.frame_id = "room"
    c = truth["camera"]
    cam = DepthCamera(
        width=int(c["width"]),
        height=int(c["height"]),
        hfov_deg=float(c["hfov_deg"]),
        min_range=float(c["min_range"]),
        max_range=float(c["max_range"]),
        stride=int(c["stride"]),
    )
    return GroundTruth(
        root=root,
        scene=scene,
        stamps=stamps,
        poses=poses,
        poses_map=poses_map,
        map_from_room=np.asarray(truth["map_from_room"], dtype=np.float64),
        expected_grid=grid,
        camera=cam,
        truth=truth,
    )
