"""Depth images -> 3D points, and ARKit's coordinate conventions -> ROS's (ROS-free).

Every iPhone path into wheelgrid (Stray Scanner exports, the live bridge, any ROS depth camera
through ``depth_to_cloud``) goes through these few functions, so the frame conventions are
decided in exactly one place:

- Camera points are in the OPTICAL convention (x right, y down, z forward), REP-103's
  ``*_optical_frame``. ARKit's own camera axes are x right, y up, z backward
  (:data:`ARKIT_CAMERA_TO_OPTICAL` converts a pose given in those axes).
- ARKit's world is gravity aligned with y up; at session start -z is the camera's viewing
  direction and x its right. A REP-103 world (x forward, y left, z up) is therefore
  ``x_ros = -z_ark, y_ros = -x_ark, z_ros = y_ark`` (:data:`ARKIT_WORLD_TO_ROS`).

Pixels with no return (depth 0 / non-finite) or below the confidence threshold become NaN
points in place, so organised clouds keep their pixel order and nothing downstream can mistake
"no measurement" for "free space".
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

# The deepest depth read as a return: 16-bit millimetres' ceiling, where the bridge's two
# encodings and a 16UC1 image meet. A float depth beyond it is no LiDAR return (a phone's
# LiDAR reaches about 5 m, an indoor depth camera tens of metres at most), and 3e38 m went
# out as finite points, for every consumer of /iphone/points but the mapper (whose range
# filter drops them) to draw or plan with.
MAX_DEPTH_M = 65.535


def metres_to_millimetres(depth_m: np.ndarray) -> np.ndarray:
    """Float metres -> uint16 mm with 0 for "no return": NaN, inf, <= 0 and anything beyond
    :data:`MAX_DEPTH_M`. Clipping there instead turned a 70 m or 3e38 m pixel into 65,535 mm,
    a real-looking point 65.5 m away, where the float path drops it."""
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
    # what rounds to 65,535 mm is kept: float32's 65.535 is 65.53500366 m
    keep = (mm > 0) & (mm <= 65535)  # False for NaN
    return np.where(keep, mm, 0).astype(np.uint16)


# ARKit world (y up, -z initial forward, x right) -> ROS world (x forward, y left, z up).
ARKIT_WORLD_TO_ROS: np.ndarray = np.array(
    [
        [0.0, 0.0, -1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
ARKIT_WORLD_TO_ROS.setflags(write=False)

# ARKit camera axes (x right, y up, z backward) <- optical axes (x right, y down, z forward):
# T_world_optical = T_world_arkitcam @ ARKIT_CAMERA_TO_OPTICAL.
ARKIT_CAMERA_TO_OPTICAL: np.ndarray = np.diag([1.0, -1.0, -1.0, 1.0])
ARKIT_CAMERA_TO_OPTICAL.setflags(write=False)


@lru_cache(maxsize=2)  # one stream's K (two while it changes): 8 held 270 MB of 2048^2 rays
def _rays(h: int, w: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Per-pixel (x/z, y/z) for a pinhole camera; cached because K rarely changes per stream."""
    u = (np.arange(w, dtype=np.float64) - cx) / fx
    v = (np.arange(h, dtype=np.float64) - cy) / fy
    rays = np.empty((h, w, 2), dtype=np.float32)
    rays[:, :, 0] = u[None, :]
    rays[:, :, 1] = v[:, None]
    rays.setflags(write=False)
    return rays


#: The largest focal length (and principal point offset) in pixels: 1e5 px is a 0.6 deg field
#: of view across a 1000 px image, far narrower than any depth camera.
MAX_FOCAL_PX = 1e5


def check_intrinsics(K: np.ndarray) -> np.ndarray:
    """Return K as a (3, 3) float64 array; ValueError if it cannot be a pinhole camera.

    A focal length lies between a pixel and :data:`MAX_FOCAL_PX`, the principal point within
    as many of the image: finite and positive was all depth_to_cloud asked of a CameraInfo,
    and fx = 1e-40 published a cloud of inf, 1e-3 points 64 km away, 1e300 every point on the
    optical axis (a review; the bridge refused them already)."""
    k = np.asarray(K, dtype=np.float64)
    if k.shape != (3, 3):
        raise ValueError(f"intrinsics must be 3x3, got shape {k.shape}")
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    if not (
        np.isfinite(k).all()
        and 1.0 <= fx <= MAX_FOCAL_PX
        and 1.0 <= fy <= MAX_FOCAL_PX
        and abs(cx) <= MAX_FOCAL_PX
        and abs(cy) <= MAX_FOCAL_PX
    ):
        raise ValueError(
            f"intrinsics need fx, fy in [1, {MAX_FOCAL_PX:g}] px and a principal point within "
            f"as many; got fx={fx} fy={fy} cx={cx} cy={cy}"
        )
    return k


def camera_info_intrinsics(info: Any, width: int, height: int) -> np.ndarray:
    """K of a ``sensor_msgs/CameraInfo`` for a ``width`` x ``height`` image, or ``ValueError``.

    REP-104: K is for the resolution the camera was calibrated at, and ``binning`` and ``roi``
    say how the image published was cut from it. A driver that bins or crops states so there,
    and K projected the smaller image wrongly (a cloud squashed or shifted); that is refused,
    as is a principal point far from the image's centre (K of another resolution)."""
    if (info.width, info.height) != (width, height):
        raise ValueError(f"camera info is {info.width}x{info.height}, depth {width}x{height}")
    binning = (int(info.binning_x), int(info.binning_y))
    roi = info.roi
    full_roi = (roi.x_offset, roi.y_offset) == (0, 0) and (roi.width, roi.height) in (
        (0, 0),
        (width, height),
    )
    if any(b > 1 for b in binning) or not full_roi:
        raise ValueError(
            f"camera info binning {binning[0]}x{binning[1]}, roi {roi.width}x{roi.height} at "
            f"({roi.x_offset}, {roi.y_offset}): a binned or cropped image is not supported "
            "(its K is for the full resolution)"
        )
    K = check_intrinsics(np.asarray(info.k, dtype=np.float64).reshape(3, 3))
    if not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise ValueError(f"camera info: K's last row is {K[2].tolist()}, not a camera's (0, 0, 1)")
    # A rectified image's projection is P's (REP-104; depth_image_proc and image_geometry take
    # P): K alone made clouds of another scale where the two differ. P unset (all 0): K.
    P = np.asarray(info.p, dtype=np.float64).reshape(3, 4)
    if np.isfinite(P).all() and P[0, 0] > 0 and P[1, 1] > 0:
        K = check_intrinsics(P[:, :3])
    problem = principal_point_problem(float(K[0, 2]), float(K[1, 2]), width, height)
    if problem:
        raise ValueError(f"camera info: {problem}")
    return K


def camera_info_doubts(info: Any, depth_frame: str) -> list[tuple[str, str]]:
    """(cause, text) of what a CameraInfo says that the cloud cannot honour, each to be said
    once: distortion coefficients (the image is projected as rectified, as depth_image_proc
    does) and a frame other than the depth image's (the cloud is in the image's). Both went
    unsaid."""
    out = []
    d = np.asarray(info.d, dtype=np.float64)
    if d.size and np.abs(d).max() > 1e-9:
        out.append((
            "distortion",
            f"camera info gives distortion {info.distortion_model} {d.tolist()}: the depth image "
            "is projected as rectified (as depth_image_proc does); give it the rectified image",
        ))  # fmt: skip
    frame = str(info.header.frame_id)
    if frame and depth_frame and frame.lstrip("/") != depth_frame.lstrip("/"):
        out.append((
            "info_frame",
            f"camera info is in frame {frame!r}, the depth image in {depth_frame!r}: the cloud "
            "is published in the depth image's frame (another camera's calibration?)",
        ))  # fmt: skip
    return out


def principal_point_problem(cx: float, cy: float, width: int, height: int) -> str | None:
    """Why intrinsics with this principal point cannot be a ``width`` x ``height`` image's, or
    None: any camera's lies near its image's centre (the iPhone's within 0.5 %). ARKit's K is
    for the 1920 x 1440 RGB image; sent unscaled with a 256 x 192 depth, every cloud came out
    squashed and pushed to one side (a wall 2.7 m wide read 0.36 m)."""
    if abs(cx - width / 2) <= width / 4 and abs(cy - height / 2) <= height / 4:
        return None
    return (
        f"principal point ({cx:g}, {cy:g}) is not near the centre of the {width}x{height} "
        "image: intrinsics of another resolution (not scaled to the depth resolution?)"
    )


ARKIT_CONFIDENCE_LEVELS = (0, 1, 2)  # low, medium, high


def check_min_confidence(value: int, name: str = "min_confidence") -> None:
    """``ValueError`` unless ``value`` is one of ARKit's confidence levels: above 2 drops every
    pixel and below 0 none, both without a word."""
    if value not in ARKIT_CONFIDENCE_LEVELS:
        raise ValueError(f"{name} must be 0, 1 or 2 (ARKit's levels), not {value}")


def confidence_loss(min_confidence: int) -> str | None:
    """What ARKit's confidence threshold costs thin obstacles, where it costs them nearly all;
    None otherwise. The thin-obstacle check's room has no confidence channel, so it cannot say:
    on the real capture (95 frames, a review) ARKit rates high only 0.5 % of the pixels of a
    3-pixel-wide thing standing 15 cm or more in front of its background (56 % of all pixels),
    and a 5 cm bar 3-4.5 m ahead is 2.5-3.8 pixels wide. ``min_confidence 2`` emptied a table's
    middle in the real capture's map, its floor read free beneath (3.1 m^2 of fine pixels)."""
    if min_confidence < 2:
        return None
    return (
        f"min_confidence {min_confidence} keeps only ARKit's high-confidence pixels, and ARKit "
        "rates high 0.5 % of the pixels of a thin object 3 pixels wide (on the real capture): "
        "thin obstacles vanish from the map"
    )


def depth_to_points(
    depth: np.ndarray,
    K: np.ndarray,
    confidence: np.ndarray | None = None,
    min_confidence: int = 0,
) -> np.ndarray:
    """Back-project a depth image (metres) into ``(H*W, 3)`` float32 optical-frame points.

    Row-major pixel order is kept (point ``r*W + c`` is pixel (r, c)) so the result can be
    published as an organised cloud. Pixels whose depth is 0, negative or non-finite, or whose
    confidence is below ``min_confidence``, become NaN rows: unknown, never free.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be a 2-D image, got shape {d.shape}")
    h, w = d.shape
    k = check_intrinsics(K)
    rays = _rays(h, w, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    z = d.astype(np.float32, copy=False)
    valid = np.isfinite(z) & (z > 0)
    if confidence is not None and min_confidence > 0:
        c = np.asarray(confidence)
        if c.shape != d.shape:
            raise ValueError(f"confidence shape {c.shape} differs from depth shape {d.shape}")
        valid &= c >= min_confidence
    zz = np.where(valid, z, np.float32(np.nan))
    out = np.empty((h, w, 3), dtype=np.float32)
    out[:, :, 0] = rays[:, :, 0] * zz
    out[:, :, 1] = rays[:, :, 1] * zz
    out[:, :, 2] = zz
    return out.reshape(-1, 3)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to ``(N, 3)`` points (NaN rows stay NaN)."""
    t = np.asarray(T, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    return p @ t[:3, :3].T + t[:3, 3]


def pose_from_xyz_quat(
    x: float, y: float, z: float, qx: float, qy: float, qz: float, qw: float
) -> np.ndarray:
    """4x4 pose from a translation and a unit quaternion (x, y, z, w)."""
    from wheelgrid_common.fileio import quat_to_matrix

    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(qx, qy, qz, qw)
    T[:3, 3] = (x, y, z)
    return T


def arkit_pose_to_ros(T_ark_world_optical: np.ndarray) -> np.ndarray:
    """ARKit world (y up) <- optical camera  ->  ROS ``odom`` (z up) <- optical camera.

    Only the world side changes: the camera side is already optical. For a pose in ARKit's own
    camera axes, right-multiply by :data:`ARKIT_CAMERA_TO_OPTICAL` first.
    """
    T = np.asarray(T_ark_world_optical, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"pose must be 4x4, got shape {T.shape}")
    return ARKIT_WORLD_TO_ROS @ T


# ---- sensor_msgs/Image payloads, without cv_bridge (not in the ROS wheels) ----------------

_IMAGE_DTYPES: dict[str, str] = {
    "32FC1": "f4",
    "16UC1": "u2",
    "mono16": "u2",
    "8UC1": "u1",
    "mono8": "u1",
}


def image_array(
    encoding: str, height: int, width: int, step: int, is_bigendian: bool, data: bytes
) -> np.ndarray:
    """A single-channel sensor_msgs/Image payload as a native-endian ``(H, W)`` array.

    Row padding (``step > width * bytes``) and big-endian data are honoured; anything that does
    not add up raises ValueError naming the field, so a node can log it instead of crashing.
    """
    if encoding not in _IMAGE_DTYPES:
        raise ValueError(f"image encoding {encoding!r} not supported (use {sorted(_IMAGE_DTYPES)})")
    dt = np.dtype((">" if is_bigendian else "<") + _IMAGE_DTYPES[encoding])
    if height <= 0 or width <= 0:
        raise ValueError(f"image is {width}x{height}")
    if step < width * dt.itemsize:
        raise ValueError(f"step {step} < width {width} x {dt.itemsize} B")
    raw = np.frombuffer(data, dtype=np.uint8)
    if raw.size < step * height:
        raise ValueError(f"image data has {raw.size} B, needs step {step} x height {height}")
    rows = raw[: step * height].reshape(height, step)[:, : width * dt.itemsize]
    return np.ascontiguousarray(rows).view(dt).reshape(height, width).astype(dt.newbyteorder("="))


def depth_image_to_metres(
    encoding: str,
    height: int,
    width: int,
    step: int,
    is_bigendian: bool,
    data: bytes,
    mm_scale: float = 0.001,
) -> np.ndarray:
    """Depth Image (32FC1 metres, or 16UC1/mono16 scaled by ``mm_scale``) -> float32 metres.

    0 and non-finite values become NaN: REP-118 uses 0 (16UC1) and NaN (32FC1) for "no return";
    so does a 32FC1 depth beyond :data:`MAX_DEPTH_M` (a 16UC1 one is scaled as configured).
    """
    if encoding not in ("32FC1", "16UC1", "mono16"):
        raise ValueError(f"depth encoding {encoding!r} not supported (32FC1 m or 16UC1 mm)")
    arr = image_array(encoding, height, width, step, is_bigendian, data)
    if encoding == "32FC1":
        d = arr.astype(np.float32)
        d[~((d > 0) & (d <= np.float32(MAX_DEPTH_M)))] = np.nan
    else:
        d = arr.astype(np.float32) * np.float32(mm_scale)
        d[~(np.isfinite(d) & (d > 0))] = np.nan
    return d


class StampSync:
    """Group messages of several streams that carry the same stamp (message_filters stand-in).

    ``add(stream, stamp, item)`` returns ``{stream: item}`` once every required stream has an item
    within ``tolerance`` seconds of each other, else None. Each stream keeps at most ``queue``
    items, so a stream that stops never grows memory; items older than a completed set are
    dropped (they can no longer be matched in order).
    """

    def __init__(self, streams: list[str], tolerance: float = 0.001, queue: int = 10) -> None:
        if not streams:
            raise ValueError("StampSync needs at least one stream")
        self.streams = list(streams)
        self.tolerance = float(tolerance)
        self.queue = int(queue)
        self._items: dict[str, list[tuple[float, object]]] = {s: [] for s in self.streams}
        self.dropped = 0
        # per stream too: a node tells "depth images go unmatched" (it says why) from the
        # harmless leftovers of the other streams
        self.dropped_by_stream: dict[str, int] = dict.fromkeys(self.streams, 0)

    def add(self, stream: str, stamp: float, item: object) -> dict[str, object] | None:
        if stream not in self._items:
            raise KeyError(f"unknown stream {stream!r}")
        q = self._items[stream]
        q.append((stamp, item))
        if len(q) > self.queue:
            q.pop(0)
            self.dropped += 1
            self.dropped_by_stream[stream] += 1
        return self._match(stamp)

    def _match(self, stamp: float) -> dict[str, object] | None:
        found: dict[str, tuple[int, object]] = {}
        for s, q in self._items.items():
            best = None
            for i, (t, item) in enumerate(q):
                if abs(t - stamp) <= self.tolerance and (
                    best is None or abs(t - stamp) < abs(q[best[0]][0] - stamp)
                ):
                    best = (i, item)
            if best is None:
                return None
            found[s] = best
        for s, (i, _) in found.items():
            self.dropped += i  # older unmatched items of this stream are abandoned
            self.dropped_by_stream[s] += i
            del self._items[s][: i + 1]
        return {s: item for s, (_, item) in found.items()}
