"""Reader for Stray Scanner exports (iPhone LiDAR recordings), ROS-free.

Stray Scanner (https://docs.strayrobots.io/apps/scanner/format.html) writes one folder per
capture: ``depth/NNNNNN.png`` (16-bit millimetres, 0 = no return; older versions ``.npy``),
``confidence/NNNNNN.png`` (ARKit confidence 0/1/2), ``camera_matrix.csv`` (3x3 intrinsics of the
1920x1440 RGB video) and ``odometry.csv`` (``timestamp, frame, x, y, z, qx, qy, qz, qw``: the
ARKit pose of the camera per frame). We keep the exporter's numbers and only convert units and
conventions, so every consumer (mapper tests, ``stream-stray``, ``import-stray``) sees the same
frames:

- depth in metres as float32, NaN where the sensor gave no return (never 0 = "free");
- K scaled from the RGB resolution to the depth resolution;
- pose = ARKit world (y up) <- camera in the OPTICAL convention. Checked on a real capture:
  with the optical convention walls of different frames line up, with ARKit's camera axes
  they smear (see test_mapping_stray.py).
"""

from __future__ import annotations

import bisect
import contextlib
import csv
import math
import sys
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wheelgrid_mapping.bridge_protocol import MAX_STAMP_S
from wheelgrid_mapping.depth import pose_from_xyz_quat

# Stray's camera_matrix.csv describes the RGB video, which is always 1920 x 1440.
RGB_WIDTH = 1920
RGB_HEIGHT = 1440
# How far (a fraction of the image size) camera_matrix.csv's principal point may lie from
# the RGB image's centre: the real capture's is 0.2-0.4 % off; one at the depth resolution
# (256x192) is 87 % off, one of a 3840x2880 video 100 %.
PRINCIPAL_POINT_TOLERANCE = 0.1
# Stray records at 60 Hz; used for stamps only when odometry.csv is missing.
NOMINAL_RATE_HZ = 60.0
# A frame stamped later than any of this many frames after it is stamped ahead (a bad
# timestamp); stamps that jump and stay there are a pause (StrayExport.captured_by).
CAPTURE_ORDER_FRAMES = 3


@dataclass(frozen=True)
class StrayFrame:
    """One depth frame: ``index`` is Stray's frame number, ``stamp`` seconds (ARKit clock)."""

    index: int
    stamp: float
    depth: np.ndarray  # (H, W) float32 metres, NaN = no return
    confidence: np.ndarray | None  # (H, W) uint8 0 low .. 2 high, None if not exported
    K: np.ndarray  # (3, 3) intrinsics at the depth resolution
    pose: np.ndarray | None  # (4, 4) ARKit world (y up) <- optical camera; None if unknown


@contextlib.contextmanager
def _unreadable(path: Path) -> Iterator[None]:
    """A file that does not read as an image (cut off by a full phone, a stray non-image)
    raises ``ValueError`` naming it, the error every reader of an export handles. Whatever
    the reader raised: PIL's UnidentifiedImageError is an OSError, but a header declaring
    30000 x 30000 pixels raised DecompressionBombError, none of OSError, ValueError or
    EOFError, a traceback for the whole export (a review)."""
    try:
        yield
    except Exception as exc:
        raise ValueError(f"{path}: cannot read the image ({exc})") from exc


def _read_image(path: Path) -> np.ndarray:
    """An image as an array (``ValueError`` where it does not read: :func:`_unreadable`)."""
    with _unreadable(path):
        if path.suffix == ".npy":
            return np.load(path, allow_pickle=False)
        from PIL import Image

        with Image.open(path) as im:
            return np.array(im)


def _read_depth(path: Path) -> np.ndarray:
    """A depth image: 16-bit millimetres (PNG) or float metres (.npy). Any other kind raises
    ``ValueError`` naming it: an 8-bit PNG was read as millimetres, 0-255 mm, and its frames
    failed registration as "too few points" with no word of the file."""
    raw = _read_image(path)
    if raw.ndim != 2:
        raise ValueError(f"{path}: depth image must be single-channel, got {raw.shape}")
    if raw.dtype == np.uint16 or np.issubdtype(raw.dtype, np.floating):
        return raw
    # Pillow before 10.3 (Ubuntu 24.04's, under an apt ROS Jazzy) opens a 16-bit PNG as
    # mode I, int32: millimetres all the same, where they fit in 16 bits
    whole = raw.dtype in (np.int32, np.int64, np.uint32) and path.suffix == ".png"
    if whole and (raw.size == 0 or (int(raw.min()) >= 0 and int(raw.max()) <= 0xFFFF)):
        return raw.astype(np.uint16)
    raise ValueError(
        f"{path}: depth must be 16-bit millimetres (or float metres in .npy), not {raw.dtype}"
    )


def _image_shape(path: Path) -> tuple[int, int]:
    """(height, width) from the file's header, without decoding its pixels; ``ValueError``
    where there is none to read."""
    with _unreadable(path):
        if path.suffix == ".npy":
            shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
        else:
            from PIL import Image

            with Image.open(path) as im:
                shape = (im.height, im.width)
    if len(shape) < 2:
        raise ValueError(f"{path}: not an image (shape {shape})")
    return int(shape[0]), int(shape[1])


def _read_camera_matrix(path: Path) -> np.ndarray:
    try:
        rows = [
            [float(v) for v in line.replace(",", " ").split()]
            for line in path.read_text().splitlines()
            if line.strip()
        ]
        K = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: not a 3x3 camera matrix ({exc})") from exc
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{path}: not a valid 3x3 camera matrix (got shape {K.shape})")
    # It is scaled from the RGB resolution to the depth's; one of another resolution (already
    # at the depth's, a 4K video's) was scaled all the same and stretched every cloud without
    # a word. A real camera's principal point lies within a few % of its image's centre.
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if (
        abs(cx - RGB_WIDTH / 2) > PRINCIPAL_POINT_TOLERANCE * RGB_WIDTH
        or abs(cy - RGB_HEIGHT / 2) > PRINCIPAL_POINT_TOLERANCE * RGB_HEIGHT
    ):
        raise ValueError(
            f"{path}: principal point ({cx:g}, {cy:g}) is not near the centre "
            f"({RGB_WIDTH / 2:g}, {RGB_HEIGHT / 2:g}) of Stray's {RGB_WIDTH}x{RGB_HEIGHT} RGB "
            "image, whose intrinsics this file must hold (they are scaled to the depth "
            "resolution); intrinsics of another resolution would distort every frame"
        )
    return K


def _read_odometry(
    path: Path,
) -> tuple[dict[int, tuple[float, np.ndarray | None]], int, int]:
    """(frame number -> (timestamp s, 4x4 pose or None), rows without a usable pose, frames
    with rows that disagree).

    Two rows for one frame (an export concatenated, an app's retry) that differ leave it no
    pose: which is ARKit's is not known (the last one was taken, silently), and a wrong prior
    moves the frame. Identical repeats are one row.

    A row of numbers whose pose is NaN or has a zero quaternion costs its frame the pose only
    (None; its timestamp is kept where it is one: finite, from 0 to 2^31 s, as a ROS stamp
    holds it; a corrupt 3e9 s went into `import-stray`'s bag as 1928), as a bag's NaN pose
    prior does: it refused the
    whole export. A row that is not 9 numbers, or has no frame number, still raises
    ``ValueError`` naming the line: that file is not odometry. A capture cut short (a full
    phone, the app killed) may leave the file empty (no poses) or its last line cut off (no
    newline after it): that row is left out, costing its frame the pose only; both refused
    the whole export."""
    out: dict[int, tuple[float, np.ndarray | None]] = {}
    unusable = 0
    rows: dict[int, list[float]] = {}  # each frame's first row of numbers
    disagree: set[int] = set()
    text = path.read_text(errors="replace")
    if not text.strip():
        return out, 0, 0
    lines = text.splitlines()
    cut_off = len(lines) if not text.endswith(("\n", "\r")) else -1  # line number, 1-based
    reader = csv.reader(lines)
    header = [h.strip() for h in next(reader, [])]
    need = ["timestamp", "frame", "x", "y", "z", "qx", "qy", "qz", "qw"]
    if [h for h in header if h] != need:
        raise ValueError(f"{path}: header {header} is not {need}")
    for lineno, row in enumerate(reader, start=2):
        if not row or not "".join(row).strip():
            continue
        try:
            t, frame, *v = (float(x) for x in row)
            if len(v) != 7 or not math.isfinite(frame):
                raise ValueError("need 9 numbers and a frame number")
            if frame != int(frame) or frame < 0:  # 1.5 was cut to frame 1's pose, silently
                raise ValueError(f"frame number {frame:g} is no frame's (0, 1, 2, ...)")
        except ValueError as exc:
            if lineno == cut_off:
                break
            raise ValueError(f"{path}:{lineno}: bad odometry row {row!r} ({exc})") from exc
        numbers = [t, *v]
        first = rows.setdefault(int(frame), numbers)
        if first is not numbers:
            if not np.allclose(first, numbers, rtol=0.0, atol=1e-9, equal_nan=True):
                disagree.add(int(frame))
                if int(frame) in out:
                    out[int(frame)] = (out[int(frame)][0], None)
            continue
        pose = None
        if all(math.isfinite(x) for x in v):
            with contextlib.suppress(ValueError):  # a zero quaternion
                pose = pose_from_xyz_quat(*v)
        unusable += pose is None
        if 0 <= t < MAX_STAMP_S:  # False for NaN; past it a ROS stamp's int32 seconds wrap
            out[int(frame)] = (t, pose)
    return out, unusable, len(disagree)


class StrayExport:
    """A Stray Scanner export folder; ``len()``, iteration and ``frame(i)`` give StrayFrames.

    ``frame(i)`` takes the position ``0 <= i < len()`` in capture order (normally equal to
    Stray's frame number, which is ``StrayFrame.index``).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise ValueError(f"{self.path}: not a folder (expected a Stray Scanner export)")
        depth_dir = self.path / "depth"
        cam = self.path / "camera_matrix.csv"
        missing = [p.name for p in (depth_dir, cam) if not p.exists()]
        if missing:
            raise ValueError(
                f"{self.path}: not a Stray Scanner export (missing {', '.join(missing)})"
            )
        files = [
            p for p in depth_dir.iterdir() if p.suffix in (".png", ".npy") and p.stem.isdigit()
        ]
        if not files:
            raise ValueError(f"{depth_dir}: no depth frames (NNNNNN.png or .npy)")
        files.sort(key=lambda p: int(p.stem))
        self._depth_files = files
        odo = self.path / "odometry.csv"
        try:
            self._K_rgb = _read_camera_matrix(cam)
            self._odometry, self._unusable_poses, self._disagreeing_poses = (
                _read_odometry(odo) if odo.exists() else ({}, 0, 0)
            )
        except OSError as exc:  # no permission, a folder in its place: no command caught it
            raise ValueError(f"{exc.filename}: cannot read it ({exc.strerror})") from exc
        self._known: list[int] | None = None  # odometry's frame numbers, sorted when needed
        self._conf_dir = self.path / "confidence"
        self.height, self.width = self._resolution(files)
        K = self._K_rgb.copy()
        K[0, :] *= self.width / RGB_WIDTH
        K[1, :] *= self.height / RGB_HEIGHT
        self.K = K
        self.K.setflags(write=False)

    @staticmethod
    def _resolution(files: list[Path]) -> tuple[int, int]:
        """(height, width) of the export's depth: the most common shape among all its depth
        images, read from their headers (the earliest on a tie). One broken file at the start
        must not refuse a capture whose other frames read (each frame that does not is skipped
        when it is read), nor one of another size: the first image alone set the resolution,
        and one 512 x 384 first frame made all 119 others "differ from the first frame's", the
        whole capture unreadable; the first five that read then outvoted 35 others with three
        (a review)."""
        shapes: list[tuple[int, int]] = []
        first_error: ValueError | None = None
        for f in files:
            try:
                shapes.append(_image_shape(f))
            except ValueError as exc:
                first_error = first_error or exc
        if not shapes:
            raise ValueError(
                f"none of the {len(files)} depth images reads; the first: {first_error}"
            )
        counts = Counter(shapes)
        return max(counts, key=counts.__getitem__)  # max keeps the first of equal counts

    @property
    def has_poses(self) -> bool:
        return any(pose is not None for _, pose in self._odometry.values())

    @property
    def frames_without_pose(self) -> int:
        """Depth frames that odometry.csv has no usable pose for (no row: a capture cut short
        writes depth first; or a NaN / zero-quaternion row): with ``--prior arkit`` those
        frames fail once a frame before them had a prior (before that, register without one)."""
        return sum(
            self._odometry.get(int(p.stem), (0.0, None))[1] is None for p in self._depth_files
        )

    def missing_poses_note(self) -> str:
        """What odometry.csv lacks, for a warning each command ends with its own consequence;
        '' when every depth frame has its pose."""
        missing = self.frames_without_pose
        if not missing:
            return ""
        bad, twice = self._unusable_poses, self._disagreeing_poses
        whys = [f"{bad} of its rows NaN or a zero quaternion"] if bad else []
        if twice:
            whys.append(f"{twice} frame{'s' if twice > 1 else ''} with rows that disagree")
        why = f" ({'; '.join(whys)})" if whys else ""
        return f"odometry.csv has no pose for {missing} of {len(self)} depth frames{why}"

    def __len__(self) -> int:
        return len(self._depth_files)

    def __iter__(self) -> Iterator[StrayFrame]:
        for i in range(len(self)):
            yield self.frame(i)

    def stamp(self, i: int) -> float:
        """Capture time of position ``i`` without reading its images (for real-time playback)."""
        return self._stamp_of(int(self._depth_files[i].stem))

    def captured_by(self, i: int) -> float:
        """The latest time position ``i`` can have been captured: Stray numbers frames in
        capture order, so no later than the stamps of the :data:`CAPTURE_ORDER_FRAMES` frames
        after it where most of them are stamped before it (else its own: one of them stamped
        behind is that frame's fault). An export has no arrival times, so a
        frame stamped far in the future (one bad timestamp in odometry.csv) read as a pause in
        the capture: it was registered as after a dropout, and every later stamp in
        trajectory.tum came shifted by its lead. Given as the frame's arrival, this holds such
        a frame back (:mod:`.frame_clock`), while a real pause (the app stalled: the stamps
        jump and go on from there) stays a pause."""
        end = min(len(self), i + 1 + CAPTURE_ORDER_FRAMES)
        # Only where most of the frames after it are stamped before it: one of them stamped
        # behind (a bad row) pulled the frames before it down with it, and taken for stamped
        # ahead they were skipped while the bad one began the map (a review).
        later = sorted(self.stamp(j) for j in range(i + 1, end))
        own = self.stamp(i)
        if not later or later[(len(later) - 1) // 2] >= own:
            return own
        return min(own, later[0])

    def _stamp_of(self, index: int) -> float:
        """Odometry time of frame ``index``; else extrapolated at 60 Hz on the same clock from
        the nearest row before it (the first row for frames before every row). Extrapolated
        from the first row, the frames after a short odometry.csv came stamped before the
        last row's frame (a capture runs a little under 60 Hz): a clock that went back."""
        if index in self._odometry:
            return self._odometry[index][0]
        if self._odometry:
            if self._known is None:
                self._known = sorted(self._odometry)
            k = bisect.bisect_left(self._known, index)
            ref = self._known[k - 1] if k > 0 else self._known[0]
            return self._odometry[ref][0] + (index - ref) / NOMINAL_RATE_HZ
        return index / NOMINAL_RATE_HZ

    def frame(self, i: int) -> StrayFrame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range: export has {len(self)} frames")
        path = self._depth_files[i]
        index = int(path.stem)
        raw = _read_depth(path)
        if raw.shape != (self.height, self.width):
            raise ValueError(
                f"{path}: shape {raw.shape} differs from the export's depth resolution "
                f"({self.height}, {self.width})"
            )
        if np.issubdtype(raw.dtype, np.integer):
            depth = raw.astype(np.float32) * np.float32(0.001)  # millimetres
        else:
            depth = raw.astype(np.float32)  # float exports are already metres
        depth[~(depth > 0)] = np.nan
        confidence = None
        for ext in (".png", ".npy"):
            cpath = self._conf_dir / f"{path.stem}{ext}"
            if cpath.exists():
                confidence = _read_image(cpath).astype(np.uint8)
                if confidence.shape != depth.shape:
                    raise ValueError(
                        f"{cpath}: shape {confidence.shape} differs from depth {depth.shape}"
                    )
                break
        stamp = self._stamp_of(index)
        if not 0.0 <= stamp < MAX_STAMP_S:
            # a frame before odometry.csv's first row, its time extrapolated back past the
            # clock's start: import-stray failed whole on it, the bridge dropped it quietly
            raise ValueError(
                f"{path}: its time, {stamp:.3f} s, extrapolated from odometry.csv's first row "
                f"at 60 Hz, is no time a ROS stamp holds (0 .. 2^31 s)"
            )
        odo = self._odometry.get(index)
        return StrayFrame(
            index=index,
            stamp=stamp,
            depth=depth,
            confidence=confidence,
            K=self.K.copy(),
            pose=odo[1] if odo else None,
        )

    def frame_or_warn(self, i: int) -> StrayFrame | None:
        """Frame ``i``, or None with a warning on stderr when its images do not read: one
        broken file in a long capture skips that frame (the mapper copes with a gap, as with a
        dropped one) and does not end a map, a stream or an import at that point."""
        try:
            return self.frame(i)
        except ValueError as exc:
            print(f"\nwheelgrid: warning: frame {i} skipped: {exc}", file=sys.stderr)
            return None
