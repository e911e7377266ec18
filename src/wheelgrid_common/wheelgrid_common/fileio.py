"""Small file formats every stage shares: binary PLY point clouds and TUM trajectories.

PLY is written by hand (float32 x y z, little endian) so files are compact and identical
whatever Open3D version is installed; the reader accepts any binary/ascii PLY with x y z.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

_PLY_TYPES = {
    "char": "i1",
    "uchar": "u1",
    "short": "i2",
    "ushort": "u2",
    "int": "i4",
    "uint": "u4",
    "float": "f4",
    "double": "f8",
    "int8": "i1",
    "uint8": "u1",
    "int16": "i2",
    "uint16": "u2",
    "int32": "i4",
    "uint32": "u4",
    "float32": "f4",
    "float64": "f8",
}


def write_ply(path: str | Path, points: np.ndarray, comment: str = "") -> None:
    """Write ``(N, 3)`` points as binary little-endian PLY with float x y z (metres)."""
    pts = np.ascontiguousarray(np.asarray(points, dtype="<f4").reshape(-1, 3))
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header += [f"comment {line}" for line in comment.splitlines()]
    header += [
        f"element vertex {pts.shape[0]}",
        "property float x",
        "property float y",
        "property float z",
        "end_header",
    ]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(pts.tobytes())


def read_ply(path: str | Path) -> np.ndarray:
    """Read the vertex x y z of a PLY file as ``(N, 3)`` float64; ValueError if unreadable.

    Elements before ``vertex`` (a sensor, a camera) are skipped by their size, not taken for
    vertices, and the vertex count is checked against the body in both formats: a shifted or
    cut-off read is a cloud of garbage or of half a room, and a grid made from either marks
    space free that nobody saw."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    body_start = raw.index(b"\n", end) + 1
    fmt = ""
    # (name, count, scalar properties, has a list property), in file order
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []
    for line in raw[:end].decode("ascii", "replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format" and len(parts) > 1:
            fmt = parts[1]
        elif parts[0] == "element":
            try:
                count = int(parts[2])
            except (IndexError, ValueError) as exc:
                raise ValueError(f"{path}: bad element line {line!r}") from exc
            if count < 0:
                raise ValueError(f"{path}: element {parts[1]} has a negative count {count}")
            elements.append((parts[1], count, [], False))
        elif parts[0] == "property" and elements:
            name, count, props, has_list = elements[-1]
            if parts[1] == "list":
                elements[-1] = (name, count, props, True)
            elif len(parts) < 3 or parts[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: bad property line {line!r}")
            else:
                props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    at = next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)
    if at is None:
        raise ValueError(f"{path}: no vertex element")
    _, count, props, has_list = elements[at]
    if has_list:
        raise ValueError(f"{path}: list properties on vertices are not supported")
    names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(names):
        raise ValueError(f"{path}: vertex element has no x y z")
    cols = [names.index("x"), names.index("y"), names.index("z")]
    before = elements[:at]
    if any(e[3] for e in before):
        raise ValueError(f"{path}: an element with list properties comes before the vertices")
    if fmt == "ascii":
        rows = raw[body_start:].decode("ascii", "replace").splitlines()
        skip = sum(e[1] for e in before)
        body = rows[skip : skip + count]
        if len(body) < count:
            raise ValueError(f"{path}: truncated ({len(body)} of {count} vertex lines)")
        if count == 0:
            return np.empty((0, 3))
        try:
            table = np.loadtxt(body, ndmin=2, dtype=np.float64)
        except ValueError as exc:
            raise ValueError(f"{path}: bad vertex line ({exc})") from exc
        if table.shape[1] != len(props):
            raise ValueError(f"{path}: vertex lines hold {table.shape[1]} values, not {len(props)}")
        return table[:, cols]
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = body_start
    for _, n, before_props, _ in before:
        offset += np.dtype([(q, order + t) for q, t in before_props]).itemsize * n
    dtype = np.dtype([(n, order + t) for n, t in props])
    need = dtype.itemsize * count
    if len(raw) - offset < need:
        raise ValueError(
            f"{path}: truncated ({max(len(raw) - offset, 0)} B of {need} B of vertices)"
        )
    vertices: Any = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)  # structured
    return np.stack([vertices[a] for a in "xyz"], axis=1).astype(np.float64)


def _pcd_header(raw: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    """A PCD file's header lines by keyword, and where its body starts; ValueError if none."""
    head: dict[str, list[str]] = {}
    pos = 0
    while pos < len(raw) and len(head) < 20:
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        head[key.upper()] = values
        if key.upper() == "DATA":
            break
    if "DATA" not in head or "FIELDS" not in head:
        raise ValueError(f"{path}: not a PCD file (no FIELDS and DATA header lines)")
    return head, pos


_NOT_SPACE = re.compile(rb"\S")

# PCD's TYPE and SIZE -> numpy's (PCL writes no 1- or 2-byte floats)
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8"} | {
    (t, z): f"{t.lower()}{z}" for t in "IU" for z in (1, 2, 4, 8)
}


def _ascii_problem(body: bytes, n: int, width: int, exc: ValueError) -> str:
    """What is wrong with an ascii PCD body numpy could not read, in the file's own terms
    (numpy's message ends in advice on its own arguments)."""
    lines = [ln.split() for ln in body.splitlines() if ln.strip()]
    if len(lines) != n:
        return f"{len(lines)} point lines, where its header lists {n}"
    for i, values in enumerate(lines):
        if len(values) != width:
            return f"point line {i + 1} holds {len(values)} values, not {width} (cut off?)"
        for v in values:
            try:
                float(v)
            except ValueError:
                return f"point line {i + 1}: {v.decode('ascii', 'replace')!r} is no number"
    return f"bad point line ({exc})"


def read_pcd(path: str | Path) -> np.ndarray:
    """The x y z of a PCL ``.pcd`` file (ascii, binary or binary_compressed) as ``(N, 3)``
    float64, NaN rows kept (an organised cloud marks its pixels without a return so).

    ascii and binary bodies are read here and their length checked against the header: Open3D
    filled the missing points of a cut-off ascii file with whatever its memory held. Only
    binary_compressed goes to Open3D (its decompression checks the size), whose failure is a
    warning on stderr and an empty cloud: the count read is checked against the header.
    """
    path = Path(path)
    raw = path.read_bytes()
    head, body = _pcd_header(raw, path)
    fields = [f.lower() for f in head["FIELDS"]]
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"{path}: PCD fields {' '.join(fields)} hold no x y z")
    kind = (head["DATA"] or ["?"])[0].lower()
    try:
        sizes = [int(v) for v in head.get("SIZE", ["4"] * len(fields))]
        counts = [int(v) for v in head.get("COUNT", ["1"] * len(fields))]
        types = [t.upper() for t in head.get("TYPE", ["F"] * len(fields))]
        width = int((head.get("WIDTH") or ["0"])[0])
        height = int((head.get("HEIGHT") or ["1"])[0])
        n = int((head.get("POINTS") or [str(width * height)])[0])
        if not len(sizes) == len(counts) == len(types) == len(fields) or n < 0:
            raise ValueError("SIZE, TYPE and COUNT must name every field")
        if min(counts) < 1:
            raise ValueError(f"COUNT {' '.join(map(str, counts))}: a field of no values")
        dtype = np.dtype(
            [
                (f"{k}_{f}", _PCD_TYPES[t, z], (c,))
                for k, (f, z, t, c) in enumerate(zip(fields, sizes, types, counts, strict=True))
            ]
        )
    except (ValueError, KeyError) as exc:
        raise ValueError(f"{path}: bad PCD header ({exc})") from exc
    if kind == "binary":
        if len(raw) - body < n * dtype.itemsize:
            raise ValueError(
                f"{path}: cut off ({len(raw) - body} B of the {n * dtype.itemsize} B of points "
                "its header lists)"
            )
        table: Any = np.frombuffer(raw, dtype=dtype, count=n, offset=body)  # structured
        names = [f"{fields.index(a)}_{a}" for a in "xyz"]
        return np.stack([table[name][:, 0] for name in names], axis=1).astype(np.float64)
    if kind == "ascii":
        # Parsed by numpy's C reader, from the bytes read (BytesIO shares them): split into
        # Python lists of strings first, a 36 MB file of a million points peaked at 579 MB of
        # memory and took 3.2 s (now 116 MB, 0.6 s).
        if _NOT_SPACE.search(raw, body) is None:
            table = np.empty((0, sum(counts)))
        else:
            stream = io.BytesIO(raw)
            stream.seek(body)
            try:
                table = np.loadtxt(stream, dtype=np.float64, ndmin=2, comments=None)
            except ValueError as exc:
                raise ValueError(
                    f"{path}: {_ascii_problem(raw[body:], n, sum(counts), exc)}"
                ) from exc
        if table.shape[0] != n:
            raise ValueError(f"{path}: {table.shape[0]} point lines, where its header lists {n}")
        if n == 0:
            return np.empty((0, 3))
        if table.shape[1] != sum(counts):
            raise ValueError(f"{path}: point lines of {table.shape[1]} values, not {sum(counts)}")
        return table[:, [sum(counts[: fields.index(a)]) for a in "xyz"]]
    if kind != "binary_compressed":
        raise ValueError(f"{path}: unknown PCD data kind {kind!r}")
    if n == 0:
        return np.empty((0, 3))
    # The body's own sizes checked first: Open3D sizes its cloud from POINTS before reading,
    # so a header's POINTS 10^12 over a few bytes was std::bad_alloc (or, where the memory was
    # promised, a machine swapping). PCL's body unpacks to exactly POINTS x the point's size,
    # and LZF packs at most 264 bytes into 3.
    if len(raw) - body < 8:
        raise ValueError(f"{path}: cut off (no binary_compressed body)")
    packed, unpacked = (int(v) for v in np.frombuffer(raw, "<u4", 2, body))
    if unpacked != n * dtype.itemsize or unpacked > 88 * packed:
        raise ValueError(
            f"{path}: its header lists {n} points ({n * dtype.itemsize} B), its "
            f"binary_compressed body {unpacked} B packed into {packed} B (damaged?)"
        )
    if packed > len(raw) - body - 8:
        raise ValueError(f"{path}: cut off ({len(raw) - body - 8} B of its {packed} B body)")
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(path, format="pcd", remove_nan_points=False)
    pts = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] != n:
        raise ValueError(
            f"{path}: {pts.shape[0]} of the {n} points its header lists could be read "
            "(a damaged or cut-off binary_compressed body?)"
        )
    return pts


def read_cloud(path: str | Path) -> np.ndarray:
    """A map's points from a PLY (``wheelgrid map``'s, or any with x y z vertices) or a PCD
    file (PCL's, as laser scanners and other mappers export them), by its suffix."""
    path = Path(path)
    if path.is_dir():  # "[Errno 21] Is a directory" said nothing of what to give
        raise ValueError(
            f"{path}: a folder, not a map file (a .ply or .pcd; wheelgrid map writes OUT/map.ply)"
        )
    if path.suffix.lower() == ".pcd":
        return read_pcd(path)
    return read_ply(path)


def pose_or_nan(position: Any, orientation: Any) -> np.ndarray:
    """4x4 pose from a geometry_msgs Pose's ``position`` and ``orientation``; all NaN when the
    quaternion is zero. An ARKit bridge or a bag can carry a zero quaternion before tracking
    starts: as a NaN pose it reaches the mapper, which refuses and counts a pose that is no
    rigid transform, instead of raising inside a subscription callback (which ends the node)
    or ending ``wheelgrid map`` with a traceback."""
    o = orientation
    T = np.eye(4)
    try:
        T[:3, :3] = quat_to_matrix(o.x, o.y, o.z, o.w)
    except ValueError:
        return np.full((4, 4), np.nan)
    T[:3, 3] = [position.x, position.y, position.z]
    return T


def quat_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """Unit quaternion (x, y, z, w) -> 3x3 rotation matrix (normalises first; NaN in, NaN
    out). Scaled by its largest component before the norm: a quaternion of 1e200 (a corrupt
    bag's exponent) overflowed the norm to infinity, divided to zeros, and read as the identity,
    which every rigidity check passes."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    largest = np.max(np.abs(q))
    if largest == 0:
        raise ValueError("zero quaternion")
    if np.isfinite(largest):
        q = q / largest
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_yaw(qx: float, qy: float, qz: float, qw: float, axis: int = 0) -> float:
    """Yaw (rad, about z) of the rotated ``axis`` (0: x, a body frame's forward; 2: z, an
    optical frame's) projected on the floor. Through :func:`quat_to_matrix`, so normalised
    first: the unit formula read a 90 deg yaw at a third of unit length as 5.6 deg."""
    rot = quat_to_matrix(qx, qy, qz, qw)
    return float(np.arctan2(rot[1, axis], rot[0, axis]))


def matrix_to_quat(rot: np.ndarray) -> tuple[float, float, float, float]:
    """3x3 rotation matrix -> unit quaternion (x, y, z, w), w >= 0."""
    m = np.asarray(rot, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        w, x, y, z = (
            0.25 * s,
            (m[2, 1] - m[1, 2]) / s,
            (m[0, 2] - m[2, 0]) / s,
            (m[1, 0] - m[0, 1]) / s,
        )
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x, y, z = (
            (m[2, 1] - m[1, 2]) / s,
            0.25 * s,
            (m[0, 1] + m[1, 0]) / s,
            (m[0, 2] + m[2, 0]) / s,
        )
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x, y, z = (
            (m[0, 2] - m[2, 0]) / s,
            (m[0, 1] + m[1, 0]) / s,
            0.25 * s,
            (m[1, 2] + m[2, 1]) / s,
        )
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x, y, z = (
            (m[1, 0] - m[0, 1]) / s,
            (m[0, 2] + m[2, 0]) / s,
            (m[1, 2] + m[2, 1]) / s,
            0.25 * s,
        )
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def write_tum(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write poses (``(N, 4, 4)``) as TUM lines: ``t x y z qx qy qz qw`` (seconds, metres)."""
    with open(path, "w") as fh:
        for t, pose in zip(np.asarray(stamps, dtype=np.float64), np.asarray(poses), strict=True):
            # rounded first and -0.0 folded into 0.0: a coordinate of -1e-17 is no reason for
            # two replays of one bag to write different files
            x, y, z = (round(float(v), 6) + 0.0 for v in pose[:3, 3])
            qx, qy, qz, qw = (round(v, 9) + 0.0 for v in matrix_to_quat(pose[:3, :3]))
            fh.write(f"{t:.9f} {x:.6f} {y:.6f} {z:.6f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file -> (stamps ``(N,)``, poses ``(N, 4, 4)``); '#' lines are comments."""
    stamps, poses = [], []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        v = [float(x) for x in line.replace(",", " ").split()]
        if len(v) != 8:
            raise ValueError(f"{path}: TUM lines need 8 numbers, got {len(v)}: {line!r}")
        pose = np.eye(4)
        pose[:3, :3] = quat_to_matrix(v[4], v[5], v[6], v[7])
        pose[:3, 3] = v[1:4]
        stamps.append(v[0])
        poses.append(pose)
    return np.asarray(stamps), np.asarray(poses).reshape(-1, 4, 4)


def write_together(writers: dict[Path, Callable[[Path], object]]) -> None:
    """Write a set of files that belong together (a map and its report; a map_server YAML and
    its PGM) so that a failure leaves the old set as it was: each writer fills a temporary
    file beside its target, and the targets are replaced only once every one is complete.
    A write that fails mid-way (a full disk) left a cut-off file beside its old partners:
    a YAML whose origin no longer matches its PGM, a map.ply beside another run's report.

    The replacing is undone too where one target cannot be replaced (a folder in its place,
    another user's file in a sticky /tmp): the targets replaced before it got a new grid.yaml
    and grid.pgm beside the old grid.png, a new map.ply beside no report at all. Each old
    target is kept (a hard link, else a copy) until every one is replaced, and put back
    otherwise."""
    staged = {
        target: target.with_name(f".{target.name}.{os.getpid()}.partial") for target in writers
    }
    kept: dict[Path, Path] = {}
    try:
        for target, write in writers.items():
            write(staged[target])
        for target in writers:
            if target.is_dir() and not target.is_symlink():
                raise IsADirectoryError(errno.EISDIR, "a folder stands in its place", str(target))
        for target in writers:
            if target.is_file():
                old = target.with_name(f".{target.name}.{os.getpid()}.old")
                try:
                    os.link(target, old)
                except OSError:  # a file system without hard links: a copy
                    shutil.copy2(target, old)
                kept[target] = old
        replaced: list[Path] = []
        try:
            for target, tmp in staged.items():
                os.replace(tmp, target)
                replaced.append(target)
        except BaseException:  # a Ctrl-C between two replaces too: a new map, old report
            for target in reversed(replaced):
                with contextlib.suppress(OSError):
                    if target in kept:
                        os.replace(kept.pop(target), target)
                    else:
                        target.unlink()
            raise
    finally:
        for tmp in (*staged.values(), *kept.values()):
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)


def out_folder(text: str) -> Path:
    """argparse ``type`` of an ``--out`` folder: an empty one is refused. ``Path("")`` is the
    current folder, so ``--out ""`` (an unset shell variable) wrote a run's files wherever
    the shell stood, with exit 0. A ``~name`` with no such user is refused too (it was a
    RuntimeError traceback)."""
    import argparse

    if not text.strip():
        raise argparse.ArgumentTypeError("an empty folder name (an unset shell variable?)")
    try:
        return _expand_user(text)
    except FileNotFoundError as exc:
        raise argparse.ArgumentTypeError(str(exc.strerror)) from None


def user_folder(text: str) -> Path:
    """A folder named in a parameter or option, absolute, with ``~`` as the user's home. No
    shell expands a ROS parameter (``output_dir: ~/maps`` in a params file), nor an option
    written ``--out=~/maps``: both made a folder literally named ``~`` beside wherever the
    node was started, and ``rm -rf ~`` is what a user then types to clean it up. Absolute,
    because a service caller may not know where the node was started."""
    return _expand_user(text).absolute()


def check_user_folder(text: str, name: str = "output_dir") -> None:
    """``ValueError`` naming parameter ``name`` where :func:`user_folder` cannot place
    ``text`` (``~maps`` for ``~/maps``): a node checks it at start and on a live change, not
    when a save is asked for (the save raised and the node died). An empty one names no folder:
    it was the node's working directory, and `~/save` replaced grid files there (a review)."""
    if not text.strip():
        raise ValueError(f"{name} is empty: name the folder to save into")
    try:
        user_folder(text)
    except OSError as exc:
        raise ValueError(f"{name}: {exc.strerror}") from None


def _expand_user(text: str) -> Path:
    """``Path(text).expanduser()``. ``~name`` is user name's home: where there is no such user
    (``~maps`` for ``~/maps``) pathlib raises RuntimeError, which no caller caught:
    ``~/save_map`` killed the mapper and the grid node. A FileNotFoundError (an OSError, as
    every unwritable folder is) says so instead."""
    try:
        return Path(text).expanduser()
    except RuntimeError as exc:
        user = text[1:].split("/", 1)[0]
        raise FileNotFoundError(
            errno.ENOENT,
            f"{text!r}: no user {user!r} whose home ~{user} names ({exc}); ~/{user} is a "
            "folder in your home",
            text,
        ) from None


def new_folder(base: Path) -> Path:
    """``base``, made now, or where it exists already ``base_<UTC time>`` (then ``_2``,
    ``_3`` ...): a folder no earlier run wrote into. Claimed by ``mkdir`` alone, so two
    processes saving at the same second (two chains, one ``output_dir``) get one each (an
    empty ``base`` taken for free was another process's, made and not yet written). Used for
    the rescue saves on exit: a second session's scan replaced the first one's there."""
    import time

    base.parent.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    later = [f"{base.name}_{stamp}" + (f"_{n}" if n > 1 else "") for n in range(1, 100)]
    names = [base.name, *later]
    for name in names:
        try:
            (base.parent / name).mkdir()
        except FileExistsError:
            continue
        return base.parent / name
    raise OSError(f"no free folder name beside {base} (100 taken this second)")


def folder_problem(folder: Path) -> str | None:
    """Why ``folder`` cannot be made or written, or None once it exists and is writable. The
    CLIs ask before their first frame: a typo in --out must cost a second, not a run of
    minutes whose result then cannot be saved."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if folder.is_file():  # "(File exists)" said it less plainly
            return f"cannot make the folder {folder}: it is a file"
        return f"cannot make the folder {folder} ({exc.strerror})"
    if not os.access(folder, os.W_OK):
        return f"the folder {folder} is not writable"
    return None
